"""summary.md of a benchmark run (paper Table I-III, VI form), and the README block regenerated from it."""

from __future__ import annotations

import math
import os
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.bench import plots
from liver_p2p_reg.bench.cases import BIN_EDGES, BIN_LABELS, visibility_bin
from liver_p2p_reg.bench.harness import ABLATION_K, ORACLE
from liver_p2p_reg.bench.stats import (
    ALPHA,
    SAFETY_TAU_MM,
    SUCCESS_TAU_MM,
    Row,
    by_bin,
    main_rows,
    mean_std,
    order_methods,
    p2p_pairs,
    percentile,
    rank_sum,
    select,
    stage_columns,
    success_rate,
    where,
)
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.confidence import pose_warnings

SLOW_MEDIAN_MS = 5000.0  # methods slower than this per case (median) are marked "slow"
LOW_DEFORMATION_MM = (0.0, 6.0)  # the paper's Table III deformation ranges (fiducial RMS, mm)
HIGH_DEFORMATION_MM = (6.0, 12.0)
DASH = "–"
GOOD_POSE_MM = 10.0  # the confidence table counts warnings on poses within this RMS-TRE as false alarms


def _fmt(value: float, digits: int = 2) -> str:
    return DASH if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _density(row: dict) -> str:
    """A row's target density; rows written before the column existed (empty) were uniform."""
    return str(row.get("density") or "uniform")


def _pm(values: np.ndarray) -> str:
    mean, std = mean_std(values)
    return DASH if not math.isfinite(mean) else f"{mean:.2f} ± {std:.2f}"


def _pct(value: float) -> str:
    return DASH if not math.isfinite(value) else f"{100 * value:.1f} %"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def _in_bin(index: int):
    lo, hi = BIN_EDGES[index], BIN_EDGES[index + 1]
    last = index == len(BIN_LABELS) - 1
    return lambda r: lo <= r["visibility"] < hi or (last and r["visibility"] == hi)


def complete_cases(rows: list[Row]) -> tuple[list[Row], int]:
    """Rows of the cases that every method ran on (a fair comparison), and how many cases were left out.

    An interrupted or extended run can hold some cases for only some methods; those are left out.
    """
    methods = {r["method"] for r in rows}
    by_case: dict[str, set[str]] = {}
    for r in rows:
        by_case.setdefault(r["case_id"], set()).add(r["method"])
    done = {c for c, ms in by_case.items() if ms == methods}
    return [r for r in rows if r["case_id"] in done], len(by_case) - len(done)


class Summary:
    """Computes every table of the report from the rows of cases.csv."""

    def __init__(self, rows: list[Row], settings: dict[str, Any], machine: dict[str, Any], command: str = "") -> None:
        self.rows = rows
        self.main, self.incomplete = complete_cases(main_rows(rows))
        self.settings = settings
        self.machine = machine
        self.command = command
        self.methods = order_methods({r["method"] for r in self.main})
        counts = by_bin(select(self.main, method=self.methods[0])) if self.methods else []
        self.bins = [i for i, g in enumerate(counts) if g.size]  # bins that hold cases
        self.slow = {
            m
            for m in self.methods
            if np.median([r["runtime_ms"] for r in select(self.main, method=m)]) > SLOW_MEDIAN_MS
        }

    def name(self, method: str) -> str:
        label = f"{method} (oracle)" if method == ORACLE else method
        return f"{label} (slow)" if method in self.slow else label

    def n_cases(self) -> int:
        return len({r["case_id"] for r in self.main})

    # --- tables ------------------------------------------------------------------------
    def table_tre(self, rows: list[Row] | None = None) -> list[str]:
        rows = self.main if rows is None else rows
        header = ["method", *(BIN_LABELS[i] for i in self.bins), "all"]
        counts = [len({r["case_id"] for r in rows if _in_bin(i)(r)}) for i in self.bins]
        table = [["*cases*", *(str(c) for c in counts), str(len({r["case_id"] for r in rows}))]]
        for m in self.methods:
            groups = by_bin(select(rows, method=m))
            everything = np.array([r["rms_tre_mm"] for r in select(rows, method=m)], float)
            table.append([self.name(m), *(_pm(groups[i]) for i in self.bins), _pm(everything)])
        return _table(header, table)

    def table_ratio(self) -> list[str]:
        if ORACLE not in self.methods or not self.bins:
            return [f"*No `{ORACLE}` rows: ratios to the oracle need the oracle.*"]
        lo, hi = self.bins[0], self.bins[-1]
        ends = (lo, hi) if hi != lo else (lo,)  # one bin (camera crops): one column
        oracle = by_bin(select(self.main, method=ORACLE))
        header = ["method", *(f"mean / oracle {BIN_LABELS[i]}" for i in ends)]
        rows = []
        for m in self.methods:
            if m == ORACLE:
                continue
            groups = by_bin(select(self.main, method=m))
            cells = []
            for i in ends:
                ratio = (
                    mean_std(groups[i])[0] / mean_std(oracle[i])[0] if groups[i].size and oracle[i].size else math.nan
                )
                cells.append(_fmt(ratio))
            rows.append([self.name(m), *cells])
        return _table(header, rows)

    def table_success(self, tau_mm: float = SUCCESS_TAU_MM, rows: list[Row] | None = None) -> list[str]:
        rows = self.main if rows is None else rows
        header = ["method", *(BIN_LABELS[i] for i in self.bins), "all"]
        table = []
        for m in self.methods:
            mine = select(rows, method=m)
            cells = [_pct(success_rate(where(mine, _in_bin(i)), tau_mm)) for i in self.bins]
            table.append([self.name(m), *cells, _pct(success_rate(mine, tau_mm))])
        return _table(header, table)

    def noise_sections(self) -> list[str]:
        """Per-bin tables of the rows with benchmark-added noise, when it was added to more than the lowest bin."""
        noisy = [r for r in main_rows(self.rows, with_added_noise=True) if r.get("added_noise_mm", 0.0) > 0]
        if not any(visibility_bin(r["visibility"]) not in (0, None) for r in noisy):
            return []
        lines = []
        for level in sorted({r["added_noise_mm"] for r in noisy}):
            rows, _ = complete_cases([r for r in noisy if r["added_noise_mm"] == level])
            lines += [f"## With {level:g} mm added sensor noise, per visibility bin", ""]
            lines += ["RMS-TRE (mm), mean ± std:", "", *self.table_tre(rows), ""]
            for tau in (SAFETY_TAU_MM, SUCCESS_TAU_MM):
                lines += [f"Success rate (RMS-TRE < {tau:g} mm):", "", *self.table_success(tau, rows), ""]
        return lines

    def table_density(self) -> list[str] | None:
        """Mean RMS-TRE per target density on the same crops and poses (density twins)."""
        densities = sorted({_density(r) for r in self.main})
        if len(densities) < 2 or "uniform" not in densities:
            return None
        header = ["method", *(f"{d}" for d in densities), *(f"{d} / uniform" for d in densities if d != "uniform")]
        header += [f"success < {SAFETY_TAU_MM:g} mm {d}" for d in densities]
        table = []
        for m in self.methods:
            mine = select(self.main, method=m)
            by_density = {d: [r for r in mine if _density(r) == d] for d in densities}
            means = {d: mean_std(np.array([r["rms_tre_mm"] for r in v], float))[0] for d, v in by_density.items()}
            cells = [_pm(np.array([r["rms_tre_mm"] for r in by_density[d]], float)) for d in densities]
            cells += [_fmt(means[d] / means["uniform"]) for d in densities if d != "uniform"]
            cells += [_pct(success_rate(by_density[d], SAFETY_TAU_MM)) for d in densities]
            table.append([self.name(m), *cells])
        return _table(header, table)

    def table_failures(self) -> list[str]:
        rows = []
        for m in self.methods:
            mine = select(self.main, method=m)
            failed = [r for r in mine if r["failed"]]
            ambiguous = sum(bool(r["ambiguous"]) for r in mine)
            reason = Counter(r["reason"] for r in failed).most_common(1)
            rows.append(
                [self.name(m), f"{len(failed)} / {len(mine)}", str(ambiguous), reason[0][0][:80] if reason else ""]
            )
        return _table(["method", "failed", "flagged ambiguous", "most common failure"], rows)

    def table_confidence(self, rows: list[Row]) -> list[str]:
        """Per method: how many bad poses the node's WARN/ERROR rules would have flagged, and good ones needlessly."""
        cfg = Config.from_dict(self.settings.get("config", {}))

        def reasons_for(row: Row) -> set[str]:
            if row["failed"]:
                return {"error"}
            uncertainty = row.get("uncertainty_mm", 0.0)  # absent from runs before the column existed
            violation = row.get("free_space_violation", math.nan)  # NaN: no sensor origin given
            return set(pose_warnings(row["residual_mm"], row["ambiguous"], uncertainty, cfg, violation))

        kinds = ["residual", "ambiguous", "uncertainty"]
        if any(math.isfinite(r.get("free_space_violation", math.nan)) for r in rows):
            kinds.append("free_space")  # only runs with the sensor origin (`--sensor-aware`) can warn by it
        header = [
            "method",
            f"poses off by ≥ {SUCCESS_TAU_MM:g} mm",
            "of them warned",
            f"poses within {GOOD_POSE_MM:g} mm warned",
            "warned in all",
            "by " + " / ".join(k.replace("ambiguous", "ambiguity").replace("_", " ") for k in kinds),
        ]
        table = []
        for m in self.methods:
            if m == ORACLE:
                continue
            mine = select(rows, method=m)
            reasons = [reasons_for(r) for r in mine]
            bad = [bool(w) for r, w in zip(mine, reasons, strict=True) if r["rms_tre_mm"] >= SUCCESS_TAU_MM]
            good = [bool(w) for r, w in zip(mine, reasons, strict=True) if r["rms_tre_mm"] <= GOOD_POSE_MM]
            counts = [sum(k in w for w in reasons) for k in kinds]
            table.append(
                [
                    self.name(m),
                    str(len(bad)),
                    f"{sum(bad)}" if bad else DASH,
                    f"{sum(good)} / {len(good)}",
                    f"{sum(bool(w) for w in reasons)} / {len(mine)}",
                    " / ".join(str(c) for c in counts),
                ]
            )
        return _table(header, table)

    def table_wilcoxon(self) -> list[str]:
        pairs = p2p_pairs(self.methods)
        if not pairs:
            return ["*No method pairs with and without P2P in this run.*"]
        header = ["comparison", *(BIN_LABELS[i] for i in self.bins)]
        rows = []
        for a, b in pairs:
            ga, gb = by_bin(select(self.main, method=a)), by_bin(select(self.main, method=b))
            cells = []
            for i in self.bins:
                p = rank_sum(ga[i], gb[i])
                if not math.isfinite(p):
                    cells.append(DASH)
                    continue
                diff = mean_std(ga[i])[0] - mean_std(gb[i])[0]
                mark = " **\\***" if p < ALPHA else ""
                cells.append(f"p={p:.3g}{mark} (Δ {diff:+.2f} mm)")
            rows.append([f"{a} vs {b}", *cells])
        return _table(header, rows)

    def table_noise(self) -> list[str] | None:
        noisy = main_rows(self.rows, with_added_noise=True)
        levels = sorted({r["noise_mm"] for r in noisy if math.isfinite(r["noise_mm"])})
        if len(levels) < 2:
            return None
        low = where(noisy, _in_bin(0))
        header = ["method", *(f"noise {lv:g} mm" for lv in levels)]
        rows = []
        for m in self.methods:
            mine = select(low, method=m)
            cells = []
            for lv in levels:
                vals = np.array([r["rms_tre_mm"] for r in mine if r["noise_mm"] == lv], float)
                cells.append(f"{_pm(vals)} (n={vals.size})")
            rows.append([self.name(m), *cells])
        return _table(header, rows)

    def table_deformation(self) -> list[str] | None:
        def in_range(rng: tuple[float, float]):
            return lambda r: rng[0] <= r["deformation_rms_mm"] < rng[1]

        mild, large = in_range(LOW_DEFORMATION_MM), in_range(HIGH_DEFORMATION_MM)
        if not where(self.main, mild) or not where(self.main, large):
            return None
        lowbin = _in_bin(0)
        header = [
            "method",
            f"0–6 mm {BIN_LABELS[0]}",
            f"6–12 mm {BIN_LABELS[0]}",
            "0–6 mm all",
            "6–12 mm all",
            f"success 0–6 / 6–12 mm {BIN_LABELS[0]}",
        ]
        rows = []
        for m in self.methods:
            mine = select(self.main, method=m)
            parts = [
                where(mine, lambda r: mild(r) and lowbin(r)),
                where(mine, lambda r: large(r) and lowbin(r)),
                where(mine, mild),
                where(mine, large),
            ]
            cells = [f"{_pm(np.array([r['rms_tre_mm'] for r in p], float))} (n={len(p)})" for p in parts]
            cells.append(f"{_pct(success_rate(parts[0]))} / {_pct(success_rate(parts[1]))}")
            rows.append([self.name(m), *cells])
        return _table(header, rows)

    # --- ablations -----------------------------------------------------------------
    def ablation_cases(self, method: str) -> set[str]:
        return {r["case_id"] for r in self.rows if r["base_method"] == method and r["variant"]}

    def _variant_rows(self, method: str, variant: str) -> list[Row]:
        """Rows of `method` with `variant` on the ablation cases; the default setting is the main run."""
        ids = self.ablation_cases(method)
        if variant == "":
            return [r for r in self.main if r["method"] == method and r["case_id"] in ids]
        return [r for r in self.rows if r["base_method"] == method and r["variant"] == variant]

    def k_curves(self) -> dict[str, dict[int, tuple[float, float]]]:
        k_default = int(self.settings["config"]["k"])
        curves: dict[str, dict[int, tuple[float, float]]] = {}
        for m in self.methods:
            if not m.endswith("-p2p") or not self.ablation_cases(m):
                continue
            per_k = {}
            for k in ABLATION_K:
                rows = self._variant_rows(m, "" if k == k_default else f"k={k}")
                if rows:
                    low = [r["rms_tre_mm"] for r in rows if _in_bin(0)(r)]
                    per_k[k] = (
                        float(np.mean(low)) if low else math.nan,
                        float(np.mean([r["rms_tre_mm"] for r in rows])),
                    )
            curves[m] = per_k
        return curves

    def ablation_section(self, out: Path) -> list[str]:
        curves = self.k_curves()
        screened = [m for m in self.methods if m.endswith("-p2p-icp") and self.ablation_cases(m)]
        if not curves and not screened:
            return []
        cfg = self.settings["config"]
        ids = set().union(*(self.ablation_cases(m) for m in [*curves, *screened]))
        counts = by_bin([r for r in self.main if r["case_id"] in ids and r["method"] == self.methods[0]])
        sizes = sorted({g.size for g in counts if g.size})
        per_bin = str(sizes[0]) if len(sizes) == 1 else f"{sizes[0]}–{sizes[-1]}" if sizes else "0"
        lines = [
            "## P2P ablations (Fig. 8, Table VI form)",
            "",
            f"On {len(ids)} noise-free cases ({per_bin} per visibility bin, spread over livers); "
            f"every other setting as in the main run (K={cfg['k']}, selection {cfg['selection']}, "
            f"candidate proposal {cfg['candidate_proposal']}). Mean RMS-TRE (mm): lowest bin / all ablation cases.",
            "",
        ]
        if curves:
            header = ["method", *(f"K={k}" for k in ABLATION_K)]
            rows = [
                [m, *(f"{_fmt(per_k[k][0])} / {_fmt(per_k[k][1])}" if k in per_k else DASH for k in ABLATION_K)]
                for m, per_k in curves.items()
            ]
            lines += _table(header, rows)
            plots.k_ablation(curves, out / "ablation_k.png")
            lines += ["", "![mean RMS-TRE vs K](ablation_k.png)", ""]
        refit_values = (cfg["refit_iterations"], 0) if cfg["refit_iterations"] else (0, 6)
        seeds = cfg.get("consensus_seeds", 0)  # absent from runs made before the option existed
        consensus_values = (seeds, 0) if seeds else (0, 64)
        screen_values = (cfg.get("refine_candidates", 1), 1) if cfg.get("refine_candidates", 1) > 1 else (1, 6)
        for field, values, methods in (
            ("selection", ("closest-point", "inlier-count"), list(curves)),
            ("candidate_proposal", (True, False), list(curves)),
            ("mutual_only", (False, True), list(curves)),  # True: the paper's strict mutual nearest neighbours
            ("refit_iterations", refit_values, list(curves)),  # 0: the paper's single weighted Procrustes fit
            ("consensus_seeds", consensus_values, list(curves)),  # 0: no consensus-started twin candidates
            ("refine_candidates", screen_values, screened),  # 1: ICP refines only P2P's choice
        ):
            if not methods:
                continue
            header = ["method"]
            for v in values:
                header += [f"{field}={v} {BIN_LABELS[0]}", f"{field}={v} all", f"success {field}={v}"]
            rows = []
            for m in methods:
                cells = []
                for v in values:
                    variant = "" if str(cfg.get(field)) == str(v) else f"{field}={v}"
                    sub = self._variant_rows(m, variant)
                    low = np.array([r["rms_tre_mm"] for r in sub if _in_bin(0)(r)], float)
                    cells += [_pm(low), _pm(np.array([r["rms_tre_mm"] for r in sub], float)), _pct(success_rate(sub))]
                rows.append([m, *cells])
            lines += _table(header, rows) + [""]
        return lines

    # --- runtime + machine ------------------------------------------------------
    def table_runtime(self) -> list[str]:
        rows = []
        for m in self.methods:
            t = np.array([r["runtime_ms"] for r in select(self.main, method=m)], float)
            rows.append([self.name(m), _fmt(percentile(t, 50), 1), _fmt(percentile(t, 95), 1), str(t.size)])
        return _table(["method", "median total (ms)", "p95 total (ms)", "runs"], rows)

    def table_stages(self) -> list[str]:
        stages = stage_columns(self.main)
        if not stages:
            return ["*No method reported per-stage runtimes.*"]
        names = [s[len("runtime_") : -len("_ms")] for s in stages]
        rows = []
        for m in self.methods:
            mine = select(self.main, method=m)
            cells = []
            for s in stages:
                t = np.array([r.get(s, math.nan) for r in mine], float)
                cells.append(DASH if not np.isfinite(t).any() else f"{percentile(t, 50):.1f} / {percentile(t, 95):.1f}")
            rows.append([self.name(m), *cells])
        return _table(["method (median / p95 ms)", *names], rows)

    def machine_lines(self) -> list[str]:
        return [f"- {k}: {v}" for k, v in self.machine.items()]

    # --- documents ----------------------------------------------------------------
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
            lines += [f"## Sensor noise at visibility {BIN_LABELS[0]} (Table II form), RMS-TRE mm", "", *noise, ""]
        deformation = self.table_deformation()
        if deformation:
            lines += ["## Deformation range (fiducial RMS after rigid removal; Table III form), RMS-TRE mm", ""]
            lines += [*deformation, ""]
        lines += self.ablation_section(out)
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
        lines += ["Runtime per case:", "", *self.table_runtime(), ""]
        cpu = self.machine.get("cpu", "")
        lines += [
            f"Machine: {cpu}, {self.machine.get('usable_cores', '?')} usable cores, torch {self.machine.get('torch', '?')}, "
            f"device {self.machine.get('device', '?')}. Full report with curves, statistics and ablations: [{summary_link}]({summary_link}).",
        ]
        return "\n".join(lines)


def write_summary(
    out: Path, rows: list[Row], settings: dict[str, Any], machine: dict[str, Any], command: str = ""
) -> Summary:
    """Write OUT/summary.md and its PNGs; return the Summary (for the README block)."""
    if not rows:
        raise InputError(f"no benchmark rows in {out}")
    summary = Summary(rows, settings, machine, command)
    (out / "summary.md").write_text(summary.markdown(out))
    return summary


def readme_markers(name: str = "BENCHMARK") -> tuple[str, str]:
    """The comment lines around a generated README block."""
    return f"<!-- {name}:START -->", f"<!-- {name}:END -->"


def replace_readme_block(readme: Path, block: str, name: str = "BENCHMARK") -> None:
    """Replace the text between the `name` markers of `readme` with `block`."""
    start_marker, end_marker = readme_markers(name)
    try:
        text = readme.read_text()
    except OSError as exc:
        raise InputError(f"cannot read {readme}: {exc.strerror or exc}") from None
    start, end = text.find(start_marker), text.find(end_marker)
    if start < 0 or end < 0 or end < start:
        raise InputError(f"{readme} lacks the {start_marker} ... {end_marker} markers")
    new = text[: start + len(start_marker)] + "\n" + block.strip() + "\n" + text[end:]
    tmp = readme.with_name(readme.name + ".tmp")
    tmp.write_text(new)
    os.replace(tmp, readme)


def relative_link(target: Path, start_dir: Path) -> str:
    """A POSIX relative link from `start_dir` to `target` (for the README)."""
    return Path(os.path.relpath(target.resolve(), start_dir.resolve())).as_posix()
