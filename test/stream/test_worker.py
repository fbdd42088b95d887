"""The node's worker thread: jobs in order, keyed jobs collapsed, a job that raises drops no other, a stopped worker
ends after its step and never takes the next worker's jobs."""

from __future__ import annotations

import threading
import time

from liver_p2p_reg.stream.worker import Worker, current_worker


def wait_for(condition, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.005)
    return condition()


def test_jobs_run_in_order_keyed_ones_collapse_and_errors_drop_nothing() -> None:
    done, errors, gate = [], [], threading.Event()
    worker = Worker(lambda: done.append("step"), lambda: None, errors.append).start()
    worker.submit(gate.wait)  # held: what follows queues up behind it
    assert wait_for(lambda: not worker._jobs)  # taken
    for i in range(50):  # a flood of models: one warm-up waits, the latest
        worker.submit(lambda i=i: done.append(f"warm {i}"), key="warm_up")
    worker.submit(lambda: 1 / 0)
    worker.submit(lambda: done.append("service"))
    worker.submit(lambda: done.append("reconfigure a"), key="reconfigure")
    worker.submit(lambda: done.append("reconfigure b"), key="reconfigure")  # replaces a, in a's place
    gate.set()
    assert wait_for(lambda: done.count("step") == 2)
    assert done == ["step", "warm 49", "service", "reconfigure b", "step"]  # a step after each batch of jobs
    assert len(errors) == 1 and isinstance(errors[0], ZeroDivisionError)
    assert worker.stop(1.0) and not worker.is_alive()


def test_a_stopped_worker_ends_after_its_step_and_takes_no_other_work() -> None:
    gate, ran = threading.Event(), []
    old = Worker(lambda: None, lambda: None, lambda exc: None).start()
    old.submit(gate.wait)
    old.submit(lambda: ran.append("old's next job"))
    assert wait_for(lambda: not old._jobs)  # taken: it is in gate.wait now
    assert not old.stop(0.05)  # abandoned in its job, as a registration at cleanup
    new = Worker(lambda: None, lambda: None, lambda exc: None).start()
    new.submit(lambda: ran.append("new's job"))
    assert wait_for(lambda: ran == ["new's job"])
    gate.set()
    old.join(2.0)
    assert not old.is_alive() and ran == ["new's job"]  # it ended without its queued job, and took none of new's
    assert new.stop(1.0)


def test_a_due_registration_wakes_the_worker_without_a_job() -> None:
    steps = []
    due = [time.monotonic() + 0.05]
    worker = Worker(lambda: (steps.append(1), due.clear()), lambda: due[0] if due else None, lambda exc: None).start()
    assert wait_for(lambda: steps == [1], 2.0)
    assert worker.stop(1.0)


def test_a_stopped_worker_takes_no_job_and_each_thread_knows_its_worker() -> None:
    seen = []
    worker = Worker(lambda: None, lambda: None, lambda exc: None).start()
    assert worker.submit(lambda: seen.append(current_worker()))
    assert wait_for(lambda: seen == [worker]) and current_worker() is None  # this thread runs no worker
    assert worker.stop(1.0)
    assert not worker.submit(lambda: seen.append("late"))  # never runs: whoever queued it must answer it
    time.sleep(0.05)
    assert seen == [worker]
