"""The node's one worker thread: submitted jobs in order, then the due registration; woken by events, never polling."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

MAX_WAIT_S = 60.0  # it wakes at least this often, however far the next due registration lies
_running = threading.local()  # the Worker whose thread this is (none in other threads)


def current_worker() -> Worker | None:
    """The Worker running on this thread, None elsewhere (an abandoned one's outputs must not go out)."""
    return getattr(_running, "worker", None)


class Worker:
    """One thread running submitted jobs in order, then `step` (a registration when one is due).

    Each worker owns its queue, its wake-up and its stop flag: a worker abandoned in a long registration (a
    managed node cleaned up and configured again) ends after that step and never takes the next worker's jobs.
    A job submitted under a `key` replaces a job of that key still waiting (one model warm-up, one reconfigure):
    a flood of models or parameter sets queues one job, not one each.
    """

    def __init__(
        self,
        step: Callable[[], None],
        next_due_s: Callable[[], float | None],
        on_error: Callable[[Exception], None],
        name: str = "registration",
    ) -> None:
        self._step, self._next_due_s, self._on_error = step, next_due_s, on_error
        self._wake = threading.Condition()
        self._jobs: list[tuple[str | None, Callable[[], None]]] = []
        self.stopping = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> Worker:
        self._thread.start()
        return self

    def submit(self, job: Callable[[], None] | None = None, key: str | None = None) -> bool:
        """Queue `job` (None: only wake up, a cloud may be due); a waiting job of the same `key` is replaced in place.
        False once stopped: the job will never run (a request must then be answered by whoever queued it)."""
        with self._wake:
            if self.stopping:
                return False
            if job is not None:
                at = next((i for i, (k, _) in enumerate(self._jobs) if key is not None and k == key), None)
                if at is None:
                    self._jobs.append((key, job))
                else:
                    self._jobs[at] = (key, job)
            self._wake.notify_all()
        return True

    def stop(self, join_s: float) -> bool:
        """Stop taking work and wait up to `join_s` for the step in progress; False when it is still running."""
        with self._wake:
            self.stopping = True
            self._jobs.clear()
            self._wake.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(join_s)
        return not self._thread.is_alive()

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def join(self, timeout_s: float) -> None:
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def _run(self) -> None:
        _running.worker = self
        while True:
            with self._wake:
                while not self.stopping and not self._jobs:
                    due_s = self._next_due_s()
                    wait_s = None if due_s is None else due_s - time.monotonic()
                    if wait_s is not None and wait_s <= 0:
                        break
                    # bounded: a wait beyond threading.TIMEOUT_MAX (max_rate_hz 1e-10) raised and ended the thread
                    self._wake.wait(None if wait_s is None else min(wait_s, MAX_WAIT_S))
                if self.stopping:
                    return
                jobs, self._jobs = [job for _, job in self._jobs], []
            # each job alone: one that raises must not drop the next (a service's job left unanswered hangs it)
            for job in [*jobs, self._step]:
                if self.stopping:  # stopped meanwhile: the rest is not this worker's to do
                    return
                try:
                    job()
                except Exception as exc:  # the worker must outlive anything; once stopped, stay silent
                    if self.stopping:
                        return
                    self._on_error(exc)
