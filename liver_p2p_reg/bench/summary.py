"""summary.md of a benchmark run (paper Table I-III, VI form), and the README block regenerated from it."""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from liver_p2p_reg.bench import plots
from liver_p2p_reg.bench.ablation_report import ablation_section
from liver_p2p_reg.bench.cases import BIN_LABELS, PAPER_FIRST_BIN
from liver_p2p_reg.bench.headline import headline_sections
from liver_p2p_reg.bench.jobs import ORACLE
from liver_p2p_reg.bench.stats import ALPHA, SAFETY_TAU_MM, SUCCESS_TAU_MM, Row, main_rows
from liver_p2p_reg.bench.tables import GOOD_POSE_MM, SLOW_MEDIAN_MS, Tables
from liver_p2p_reg.errors import InputError


class Summary(Tables):
    """The documents of a run, built from its tables: summary.md and the README block."""

    def header_lines(self) -> list[str]:
        s = self.settings
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        lines = [
            f"Dataset `{s['dataset']}` ({self.n_cases()} cases, preset `{s['preset']}`"
            + (f", limit {s['limit']}" if s.get("limit") else "")
            + f"), methods: {', '.join(f'`{m}`' for m in self.methods)}; generated {stamp}.",
        ]
        selected = s.get("n_cases")
        if self.incomplete or (isinstance(selected, int) and self.n_cases() < selected):
            lines += [
                "",
                f"**Partial run:** the tables cover the {self.n_cases()} cases that every method ran on, of the "
                f"{selected if isinstance(selected, int) else '?'} selected ({self.incomplete} more ran for some methods only); rerun the same command to "
                "finish: it resumes.",
            ]
        if self.command:
            lines += ["", f"Command: `{self.command}`"]
        return lines

    def markdown(self, out: Path) -> str:
        plots.success_vs_tau(self.rows, out / "success_vs_tau.png")
        plots.tre_vs_visibility(self.rows, out / "tre_vs_visibility.png")
        lines = ["# Benchmark summary", "", *self.header_lines(), ""]
        lines += ["## RMS-TRE (mm) per visibility bin, mean ± std (Table I form)", "", *self.table_tre(), ""]
        lines += ["## Mean RMS-TRE relative to the oracle", "", *self.table_ratio(), ""]
        lines += [f"## Success rate (RMS-TRE < {SUCCESS_TAU_MM:g} mm)", "", *self.table_success(), ""]
        lines += [
            f"## Success rate at the laparoscopic safety margin (RMS-TRE < {SAFETY_TAU_MM:g} mm)",
            "",
            *self.table_success(SAFETY_TAU_MM),
            "",
        ]
        lines += headline_sections(self)
        lines += [
            "![success rate vs tau](success_vs_tau.png)",
            "",
            "![RMS-TRE vs visibility](tre_vs_visibility.png)",
            "",
        ]
        lines += ["## Failures and ambiguity flags", "", *self.table_failures(), ""]
        lines += [
            "## Confidence: would the node have warned? (WARN or ERROR by the configured thresholds)",
            "",
            f"Cases as stored (no benchmark-added noise). A pose is warned when the method failed, or it is ambiguous, or its residual is above "
            f"`residual_warn_mm`, or its uncertainty above `uncertainty_warn_mm`, or (rows with the sensor origin, `[fs]`) its "
            f"free-space violation above `free_space_warn`; a safe method warns on every pose off by "
            f"{SUCCESS_TAU_MM:g} mm or more and on few within {GOOD_POSE_MM:g} mm.",
            "",
            *self.table_confidence(self.main),
            "",
        ]
        noisy = [r for r in main_rows(self.rows, with_added_noise=True) if r.get("added_noise_mm", 0.0) > 0]
        if noisy:
            lines += [
                "With benchmark-added sensor noise (the noise rows below):",
                "",
                *self.table_confidence(noisy),
                "",
            ]
        lines += [
            f"## Wilcoxon rank-sum tests, with vs without P2P (two-sided; **\\*** = p < {ALPHA:g}; Δ = difference of means)",
            "",
            *self.table_wilcoxon(),
            "",
        ]
        lines += self.noise_sections()
        density = self.table_density()
        if density:
            lines += [
                "## Target density (the same crops and poses sampled three ways)",
                "",
                "uniform: area-uniform samples; mesh-vertices: the vertices of the liver's own decimated mesh "
                "(deformed with it); depth-falloff: a depth camera's cos(incidence) / depth² density. Bins and "
                "twins share the crop, pose and fiducials.",
                "",
                *density,
                "",
            ]
        noise = self.table_noise()
        if noise:
            lines += [
                f"## Sensor noise at visibility {BIN_LABELS[PAPER_FIRST_BIN]} (Table II form), RMS-TRE mm",
                "",
                *noise,
                "",
            ]
        lines += _deform_section("## ", self.rows)
        deformation = self.table_deformation()
        if deformation:
            lines += ["## Deformation range (fiducial RMS after rigid removal; Table III form), RMS-TRE mm", ""]
            lines += [*deformation, ""]
        lines += ablation_section(self, out)
        lines += [
            "## Runtime per case (wall clock, all stages through `Registrar.register`)",
            "",
            *self.table_runtime(),
            "",
        ]
        lines += ["### Per stage", "", *self.table_stages(), ""]
        lines += ["## Machine", "", *self.machine_lines(), ""]
        lines += [
            "## Rules",
            "",
            f"- Visibility bins use the case's stored visibility ratio; the last bin is closed. Success: no failure and RMS-TRE < {SUCCESS_TAU_MM:g} mm.",
            "- A method that raises (RegistrationError / InputError / an internal error) or returns a non-finite transform is a *failure*: "
            "it keeps the initial (identity) pose, so its RMS-TRE is the initial misalignment, and it never counts as a success. "
            "A method that returns a transform but reports ok=False is also a failure, with the TRE of its transform.",
            f"- *slow*: median runtime above {SLOW_MEDIAN_MS / 1000:g} s per case. std is the population standard deviation.",
            "- Runtimes are wall clock on the machine below, including preprocessing; they vary with machine load.",
            "",
        ]
        return "\n".join(lines)

    def readme_block(self, summary_link: str) -> str:
        lines = [*self.header_lines(), ""]
        lines += ["RMS-TRE (mm) per visibility bin, mean ± std:", "", *self.table_tre(), ""]
        if ORACLE in self.methods:
            lines += ["Mean RMS-TRE relative to the oracle:", "", *self.table_ratio(), ""]
        lines += [f"Success rate (RMS-TRE < {SUCCESS_TAU_MM:g} mm):", "", *self.table_success(), ""]
        lines += [
            f"Success rate at the laparoscopic safety margin (RMS-TRE < {SAFETY_TAU_MM:g} mm):",
            "",
            *self.table_success(SAFETY_TAU_MM),
            "",
        ]
        lines += headline_sections(self, heading="")
        lines += [
            f"Would the node have warned (failed, ambiguous, residual or uncertainty above its threshold)? "
            f"Poses off by {SUCCESS_TAU_MM:g} mm or more should all be warned, few within {GOOD_POSE_MM:g} mm:",
            "",
            *self.table_confidence(self.main),
            "",
        ]
        lines += [line.replace("## ", "") for line in self.noise_sections()]
        density = self.table_density()
        if density:
            lines += ["Target density (the same crops and poses sampled three ways):", "", *density, ""]
        lines += _deform_section("", self.rows)
        lines += ["Runtime per case:", "", *self.table_runtime(), ""]
        cpu = self.machine.get("cpu", "")
        lines += [
            f"Machine: {cpu}, {self.machine.get('usable_cores', '?')} usable cores, torch {self.machine.get('torch', '?')}, "
            f"device {self.machine.get('device', '?')}. Full report with curves, statistics and ablations: [{summary_link}]({summary_link}).",
        ]
        return "\n".join(lines)


def _deform_section(heading: str, rows: list) -> list[str]:
    """The non-rigid stage against its own rigid poses (bench/deform_table.py), when the run has `+deform` rows."""
    from liver_p2p_reg.bench.deform_table import table_deform

    table = table_deform(rows)
    if table is None:
        return []
    title = "The non-rigid stage: interior RMS-TRE of each `+deform` row against its own rigid pose"
    note = (
        "(rows with the benchmark's added noise when the run has them; harm: a pose within 10 mm made worse by > 1 mm)"
    )
    return [f"{heading}{title}" + ("" if heading else ":"), "", note, "", *table, ""]


def write_summary(
    out: Path, rows: list[Row], settings: dict[str, Any], machine: dict[str, Any], command: str = ""
) -> Summary:
    """Write OUT/summary.md and its PNGs; return the Summary (for the README block)."""
    if not rows:
        raise InputError(f"no benchmark rows in {out}")
    summary = Summary(rows, settings, machine, command)
    (out / "summary.md").write_text(summary.markdown(out))
    return summary
