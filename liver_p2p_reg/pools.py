"""Process pools and worker processes for the parallel commands: spawned, never forked."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from typing import Any


def spawn_context() -> multiprocessing.context.SpawnContext:
    """The start method of every worker process the package starts (pools, the training loader's workers).

    Why spawn: torch's, Open3D's and pykdtree's OpenMP (libgomp) threads do not survive a fork, and
    a forked child blocks forever in its first parallel region of a runtime its parent has used.
    """
    return multiprocessing.get_context("spawn")


def spawn_pool(workers: int, **kwargs: Any) -> ProcessPoolExecutor:
    """A pool of `workers` fresh interpreter processes (spawn_context); other keywords as ProcessPoolExecutor's."""
    return ProcessPoolExecutor(workers, mp_context=spawn_context(), **kwargs)
