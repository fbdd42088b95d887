"""The matcher shipping rule of docs/benchmark_real/RULE.md, applied to the candidates' validation benchmark runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.cases_csv import CASES_CSV, read_rows

SETS = {  # name -> extra benchmark arguments
    "real-val-v1": ["--noise-levels", "2", "--noise-bins", "all"],
    "insilico-val-v1": ["--noise-levels", "2,4"],
    "insilico-val-camera-v1": [],
    "real-val-camera-v1": ["--noise-levels", "2", "--noise-bins", "all"],
}
REAL, INSILICO = ("real-val-v1", "real-val-camera-v1"), ("insilico-val-v1", "insilico-val-camera-v1")
METHODS = ("learned-p2p", "learned-p2p-icp")
GROSS_MM = 20.0  # a candidate may leave no more poses off by this than the shipped matcher


def _rows(out_root: str, name: str, datasets: tuple[str, ...], method: str) -> list[dict]:
    """The rows of `method` in candidate `name`'s runs on these datasets (OUT_ROOT/NAME/DATASET/cases.csv)."""
    out = []
    for dataset in datasets:
        out += [r for r in read_rows(Path(out_root) / name / dataset / CASES_CSV) if r["method"] == method]
    return out


def pooled(out_root: str, name: str, datasets: tuple[str, ...], method: str) -> tuple[float, int, int]:
    """Mean RMS-TRE, poses off by >= 20 mm (failures included) and cases."""
    rs = _rows(out_root, name, datasets, method)
    tre = np.array([r["rms_tre_mm"] for r in rs])
    gross = sum(r["rms_tre_mm"] >= GROSS_MM or r["failed"] for r in rs)
    return float(tre.mean()), int(gross), len(rs)


def verdict(candidates: list[str], out_root: str) -> tuple[list[str], str]:
    """The rule's table (one line per candidate, the first the shipped reference) and its verdict line."""
    ref = candidates[0]
    table = [
        "| candidate | real-val default mean mm | real-val default >= 20 mm | insilico-val default mean mm "
        "| insilico-val default >= 20 mm | real-val learned-p2p mean mm | rule 1 | rule 2 | rule 3 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    stats = {
        c: (
            pooled(out_root, c, REAL, "learned-p2p-icp"),
            pooled(out_root, c, INSILICO, "learned-p2p-icp"),
            pooled(out_root, c, REAL, "learned-p2p"),
        )
        for c in candidates
    }
    (r_ref, i_ref, p_ref) = stats[ref]
    passing = []
    for c in candidates:
        (r, i, p) = stats[c]
        ok1 = r[1] <= r_ref[1] and r[0] < r_ref[0]
        ok2 = i[1] <= i_ref[1] and i[0] <= i_ref[0] + 0.10
        ok3 = p[0] < p_ref[0]
        if c != ref and ok1 and ok2 and ok3:
            passing.append(c)
        marks = ["–" if c == ref else ("yes" if ok else "no") for ok in (ok1, ok2, ok3)]
        table.append(
            f"| {c}{' (shipped)' if c == ref else ''} | {r[0]:.2f} (n={r[2]}) | {r[1]} | {i[0]:.2f} (n={i[2]}) "
            f"| {i[1]} | {p[0]:.2f} | {' | '.join(marks)} |"
        )
    if not passing:
        return table, f"No candidate passes: {ref} stays."
    best = min(passing, key=lambda c: stats[c][0][0])
    close = [c for c in passing if stats[c][0][0] <= stats[best][0][0] + 0.05]
    best = min(close, key=lambda c: stats[c][2][0])
    return table, f"Passing: {', '.join(passing)}. Ships: **{best}**."
