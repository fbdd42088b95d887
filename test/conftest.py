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


def require_rclpy():
    """Import rclpy for a test module: skip without it, but fail under CI (CI=true must run the ROS tests)."""
    try:
        import rclpy
    except ImportError as exc:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(
                f"CI=true but rclpy is not importable ({exc}); `make setup` installs the ros extra", pytrace=False
            )
        pytest.skip(
            f"rclpy not importable ({exc}); install the ros extra: pip install -e '.[ros]'", allow_module_level=True
        )
    return rclpy
