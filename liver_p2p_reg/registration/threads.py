"""One torch thread count for every registration, whoever changed it before and whichever thread registers."""

from __future__ import annotations

import os
import sys


def default_threads() -> int:
    """The process default: OMP_NUM_THREADS when it is a positive integer, else the CPUs this process may use.

    Computed, not read back from torch: torch's count is process-wide state any earlier caller
    (a training run, a benchmark worker, a test) may have changed.
    """
    value = os.environ.get("OMP_NUM_THREADS", "").strip()
    if value.isdigit() and int(value) > 0:
        return int(value)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def pin_threads(num_threads: int) -> int:
    """Set torch's intra-op threads for the calling thread to `num_threads` (0: default_threads()); returns it.

    Why per registration: reductions split over threads sum in another order, so 1 and 2 threads
    differ in the last bits (up to ~1e-4 mm on the bundled bags), and OpenMP keeps the count per
    calling thread (the node registers on a worker thread). Setting it each time costs ~6 us and
    makes a pose independent of what ran earlier in the process. When torch is not imported yet
    and the default is wanted, nothing is done: torch then starts at that same default.
    """
    want = num_threads if num_threads > 0 else default_threads()
    torch = sys.modules.get("torch")
    if torch is None and num_threads <= 0:
        return want
    if torch is None:
        import torch
    torch.set_num_threads(want)
    return want
