"""Shared pytest fixtures: small deterministic clouds and a temp working dir."""

from __future__ import annotations

import os

import numpy as np
import pytest

# Tests must be deterministic and light on the 2-core CI machine.
os.environ.setdefault("OMP_NUM_THREADS", "2")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
