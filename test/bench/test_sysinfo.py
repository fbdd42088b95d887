"""The machine line of the benchmark reports tells two hosts that share one CPU name apart."""

from __future__ import annotations

import platform

from liver_p2p_reg.bench.sysinfo import cpu_model

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 167
model name\t: Intel(R) Xeon(R) Processor
stepping\t: 1

processor\t: 1
cpu family\t: 6
model\t\t: 106
model name\t: Another name
stepping\t: 6
"""


def test_name_with_family_model_and_stepping_of_the_first_processor(tmp_path) -> None:
    path = tmp_path / "cpuinfo"
    path.write_text(CPUINFO)
    assert cpu_model(path) == "Intel(R) Xeon(R) Processor (cpu family 6, model 167, stepping 1)"


def test_a_name_without_numbers_and_no_name_at_all(tmp_path) -> None:
    named = tmp_path / "named"
    named.write_text("processor\t: 0\nmodel name\t: Some CPU\n")
    assert cpu_model(named) == "Some CPU"
    arm = tmp_path / "arm"  # aarch64 kernels give no model name: the platform's guess
    arm.write_text("processor\t: 0\nBogoMIPS\t: 50.00\nCPU implementer\t: 0x41\n")
    fallback = platform.processor() or platform.machine() or "unknown"
    assert cpu_model(arm) == fallback
    assert cpu_model(tmp_path / "missing") == fallback
