"""The tables of a benchmark report (paper Table I-III form), computed from the rows of cases.csv."""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np

from liver_p2p_reg.bench.cases import BIN_LABELS, PAPER_FIRST_BIN, visibility_bin
from liver_p2p_reg.bench.jobs import BOUND, ORACLE
from liver_p2p_reg.bench.markdown import DASH, fmt, md_table, pct, pm
from liver_p2p_reg.bench.stats import (
    ALPHA,
    SAFETY_TAU_MM,
    SUCCESS_TAU_MM,
    Row,
    by_bin,
    in_bin,
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
from liver_p2p_reg.registration.confidence import pose_warnings

SLOW_MEDIAN_MS = 5000.0  # methods slower than this per case (median) are marked "slow"
LOW_DEFORMATION_MM = (0.0, 6.0)  # the paper's Table III deformation ranges (fiducial RMS, mm)
HIGH_DEFORMATION_MM = (6.0, 12.0)
GOOD_POSE_MM = 10.0  # the confidence table counts warnings on poses within this RMS-TRE as false alarms


def _density(row: dict) -> str:
    """A row's target density; rows written before the column existed (empty) were uniform."""
    return str(row.get("density") or "uniform")


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


class Tables:
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
        label = {ORACLE: f"{method} (oracle)", BOUND: f"{method} (ICP from the true pose)"}.get(method, method)
        return f"{label} (slow)" if method in self.slow else label

    def n_cases(self) -> int:
        return len({r["case_id"] for r in self.main})

    # --- tables ------------------------------------------------------------------------
    def table_tre(self, rows: list[Row] | None = None) -> list[str]:
        rows = self.main if rows is None else rows
        header = ["method", *(BIN_LABELS[i] for i in self.bins), "all"]
        counts = [len({r["case_id"] for r in rows if in_bin(i)(r)}) for i in self.bins]
        table = [["*cases*", *(str(c) for c in counts), str(len({r["case_id"] for r in rows}))]]
        for m in self.methods:
            groups = by_bin(select(rows, method=m))
            everything = np.array([r["rms_tre_mm"] for r in select(rows, method=m)], float)
            table.append([self.name(m), *(pm(groups[i]) for i in self.bins), pm(everything)])
        return md_table(header, table)

    def table_ratio(self) -> list[str]:
        """Mean RMS-TRE over the oracle's, and over the rigid bound's where the bound was run, in the
        lowest and highest bins that hold cases."""
        if ORACLE not in self.methods or not self.bins:
            return [f"*No `{ORACLE}` rows: ratios to the oracle need the oracle.*"]
        lo, hi = self.bins[0], self.bins[-1]
        ends = (lo, hi) if hi != lo else (lo,)  # one bin (camera crops): one column
        references = [
            (title, by_bin(select(self.main, method=name)))
            for name, title in ((ORACLE, "oracle"), (BOUND, "bound"))
            if name in self.methods
        ]
        header = ["method", *(f"mean / {name} {BIN_LABELS[i]}" for name, _ in references for i in ends)]
        rows = []
        for m in self.methods:
            if m == ORACLE:
                continue
            groups = by_bin(select(self.main, method=m))
            cells = []
            for _, reference in references:
                for i in ends:
                    ratio = (
                        mean_std(groups[i])[0] / mean_std(reference[i])[0]
                        if groups[i].size and reference[i].size
                        else math.nan
                    )
                    cells.append(fmt(ratio))
            rows.append([self.name(m), *cells])
        return md_table(header, rows)

    def table_success(self, tau_mm: float = SUCCESS_TAU_MM, rows: list[Row] | None = None) -> list[str]:
        rows = self.main if rows is None else rows
        header = ["method", *(BIN_LABELS[i] for i in self.bins), "all"]
        table = []
        for m in self.methods:
            mine = select(rows, method=m)
            cells = [pct(success_rate(where(mine, in_bin(i)), tau_mm)) for i in self.bins]
            table.append([self.name(m), *cells, pct(success_rate(mine, tau_mm))])
        return md_table(header, table)

    def noise_sections(self) -> list[str]:
        """Per-bin tables of the rows with benchmark-added noise, when it was added to more than the lowest bin."""
        noisy = [r for r in main_rows(self.rows, with_added_noise=True) if r.get("added_noise_mm", 0.0) > 0]
        if not any(visibility_bin(r["visibility"]) not in (PAPER_FIRST_BIN, None) for r in noisy):
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
            cells = [pm(np.array([r["rms_tre_mm"] for r in by_density[d]], float)) for d in densities]
            cells += [fmt(means[d] / means["uniform"]) for d in densities if d != "uniform"]
            cells += [pct(success_rate(by_density[d], SAFETY_TAU_MM)) for d in densities]
            table.append([self.name(m), *cells])
        return md_table(header, table)

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
        return md_table(["method", "failed", "flagged ambiguous", "most common failure"], rows)

    def table_confidence(self, rows: list[Row]) -> list[str]:
        """Per method: how many bad poses the node's WARN/ERROR rules would have flagged, and good ones needlessly."""
        cfg = Config.from_dict(self.settings.get("config", {}))

        def reasons_for(row: Row) -> set[str]:
            if row["failed"]:
                return {"error"}
            uncertainty = row.get("uncertainty_mm", 0.0)  # absent from runs before the column existed
            violation = row.get("free_space_violation", math.nan)  # NaN: no sensor origin given
            bound = row.get("error_bound_mm", math.nan)  # absent from runs before the error bound
            return set(pose_warnings(row["residual_mm"], row["ambiguous"], uncertainty, cfg, violation, bound))

        kinds = ["residual", "ambiguous", "uncertainty"]
        if any(math.isfinite(r.get("free_space_violation", math.nan)) for r in rows):
            kinds.append("free_space")  # only runs with the sensor origin (`--sensor-aware`) can warn by it
        if any(math.isfinite(r.get("error_bound_mm", math.nan)) for r in rows):
            kinds.append("error_bound")
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
        return md_table(header, table)

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
        return md_table(header, rows)

    def table_noise(self) -> list[str] | None:
        noisy = main_rows(self.rows, with_added_noise=True)
        levels = sorted({r["noise_mm"] for r in noisy if math.isfinite(r["noise_mm"])})
        if len(levels) < 2:
            return None
        low = where(noisy, in_bin(PAPER_FIRST_BIN))
        header = ["method", *(f"noise {lv:g} mm" for lv in levels)]
        rows = []
        for m in self.methods:
            mine = select(low, method=m)
            cells = []
            for lv in levels:
                vals = np.array([r["rms_tre_mm"] for r in mine if r["noise_mm"] == lv], float)
                cells.append(f"{pm(vals)} (n={vals.size})")
            rows.append([self.name(m), *cells])
        return md_table(header, rows)

    def table_deformation(self) -> list[str] | None:
        def in_range(rng: tuple[float, float]):
            return lambda r: rng[0] <= r["deformation_rms_mm"] < rng[1]

        mild, large = in_range(LOW_DEFORMATION_MM), in_range(HIGH_DEFORMATION_MM)
        if not where(self.main, mild) or not where(self.main, large):
            return None
        lowbin = in_bin(PAPER_FIRST_BIN)
        header = [
            "method",
            f"0–6 mm {BIN_LABELS[PAPER_FIRST_BIN]}",
            f"6–12 mm {BIN_LABELS[PAPER_FIRST_BIN]}",
            "0–6 mm all",
            "6–12 mm all",
            f"success 0–6 / 6–12 mm {BIN_LABELS[PAPER_FIRST_BIN]}",
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
            cells = [f"{pm(np.array([r['rms_tre_mm'] for r in p], float))} (n={len(p)})" for p in parts]
            cells.append(f"{pct(success_rate(parts[0]))} / {pct(success_rate(parts[1]))}")
            rows.append([self.name(m), *cells])
        return md_table(header, rows)

    # --- runtime + machine ------------------------------------------------------
    def table_runtime(self) -> list[str]:
        rows = []
        for m in self.methods:
            t = np.array([r["runtime_ms"] for r in select(self.main, method=m)], float)
            rows.append([self.name(m), fmt(percentile(t, 50), 1), fmt(percentile(t, 95), 1), str(t.size)])
        return md_table(["method", "median total (ms)", "p95 total (ms)", "runs"], rows)

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
        return md_table(["method (median / p95 ms)", *names], rows)

    def machine_lines(self) -> list[str]:
        return [f"- {k}: {v}" for k, v in self.machine.items()]
