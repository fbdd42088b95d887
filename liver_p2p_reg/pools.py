"""Process pools for the parallel commands: their workers are spawned, never forked."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from typing import Any


def spawn_pool(workers: int, **kwargs: Any) -> ProcessPoolExecutor:
    """A pool of `workers` fresh interpreter processes; other keywords as ProcessPoolExecutor's.

    Why spawn: torch's, Open3D's and pykdtree's OpenMP (libgomp) threads do not survive a fork, and
    a forked child blocks forever in its first parallel region of a runtime its parent has used.
    """
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), **kwargs)
