"""The small-view matcher shipping rule of docs/benchmark_real/RULE_small_views.md, on the candidates' validation runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.cases_csv import CASES_CSV, read_rows

NOISE = ["--noise-levels", "2", "--noise-bins", "all"]
SETS = {"real-val-v2": NOISE, "real-val-camera-v2": NOISE, "insilico-val-v2": NOISE}  # name -> benchmark args
REAL, INSILICO = ("real-val-v2", "real-val-camera-v2"), ("insilico-val-v2",)
METHOD = "learned-p2p-icp"
SMALL = 0.2  # the bins below this visibility are "where the laparoscope looks"
GROSS_MM, SUCCESS_MM, SLACK_MM = 20.0, 10.0, 0.10


def group_stats(out_root: str, name: str, datasets: tuple[str, ...], lo: float, hi: float) -> dict[str, float]:
    """Mean RMS-TRE, success@10 mm, poses off by >= 20 mm (failures included) and cases at visibility [lo, hi)."""
    rows = []
    for dataset in datasets:
        rows += [
            r
            for r in read_rows(Path(out_root) / name / dataset / CASES_CSV)
            if r["method"] == METHOD and lo <= r["visibility"] < hi
        ]
    return tre_stats(rows)


def tre_stats(rows: list[dict]) -> dict[str, float]:
    """Mean RMS-TRE, success@10 mm, poses off by >= 20 mm and count of benchmark rows (a failure: 1 m, gross)."""
    tre = np.array([np.inf if r["failed"] else r["rms_tre_mm"] for r in rows])
    finite = np.where(np.isfinite(tre), tre, 1e3)  # a failure counts as 1 m in the mean
    return {
        "mean": float(finite.mean()) if len(rows) else float("nan"),
        "s10": float(np.mean(tre < SUCCESS_MM)) if len(rows) else float("nan"),
        "gross": int(np.sum(tre >= GROSS_MM)),
        "n": len(rows),
    }


def verdict(reference: str, candidate: str, out_root: str) -> tuple[list[str], str]:
    """The rule's table (reference first) and its verdict line."""
    groups = {
        "real, < 0.2": (REAL, 0.0, SMALL),
        "real, >= 0.2": (REAL, SMALL, 1.01),
        "insilico, all": (INSILICO, 0.0, 1.01),
    }
    stats = {c: {g: group_stats(out_root, c, *spec) for g, spec in groups.items()} for c in (reference, candidate)}
    ref, cand = stats[reference], stats[candidate]
    checks = [
        cand["real, < 0.2"]["mean"] < ref["real, < 0.2"]["mean"]
        and cand["real, < 0.2"]["s10"] >= ref["real, < 0.2"]["s10"],
        cand["real, >= 0.2"]["mean"] <= ref["real, >= 0.2"]["mean"] + SLACK_MM
        and cand["real, >= 0.2"]["gross"] <= ref["real, >= 0.2"]["gross"],
        cand["insilico, all"]["mean"] <= ref["insilico, all"]["mean"] + SLACK_MM
        and cand["insilico, all"]["gross"] <= ref["insilico, all"]["gross"],
    ]
    table = ["| weights | group | cases | mean RMS-TRE (mm) | success@10 mm | >= 20 mm |", "|---|---|---|---|---|---|"]
    for c in (reference, candidate):
        for g, s in stats[c].items():
            table.append(f"| {c} | {g} | {s['n']} | {s['mean']:.2f} | {100 * s['s10']:.1f} % | {s['gross']} |")
    table += ["", "| rule | " + " | ".join(f"{i}" for i in (1, 2, 3)) + " |", "|---|---|---|---|"]
    table.append(f"| {candidate} passes | " + " | ".join("yes" if ok else "no" for ok in checks) + " |")
    if all(checks):
        return table, f"{candidate} passes every rule: it ships."
    failed = ", ".join(str(i + 1) for i, ok in enumerate(checks) if not ok)
    return table, f"{candidate} fails rule {failed}: {reference} stays."
