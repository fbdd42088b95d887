"""alloc.reuse_freed_memory: a freed large buffer is reused without new page faults (Linux/glibc)."""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import resource, sys
import numpy as np
from liver_p2p_reg.alloc import reuse_freed_memory
applied = reuse_freed_memory() if sys.argv[1] == "on" else False
def cycle():
    buffer = np.empty(48 * 1024 * 1024 // 8)  # 48 MiB, the size of a large view's score matrix
    buffer.fill(1.0)
    del buffer
cycle()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
cycle()
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _second_cycle_faults(mode: str) -> tuple[bool, int]:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
    applied, faults = out.stdout.split()
    return applied == "True", int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_large_buffer_is_reused_without_page_faults() -> None:
    applied, faults_on = _second_cycle_faults("on")
    _, faults_off = _second_cycle_faults("off")
    assert applied
    assert faults_off > 50  # glibc's default: the buffer is mapped afresh and faulted in again
    assert faults_on < faults_off / 10
