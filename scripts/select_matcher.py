"""Apply the matcher shipping rule (docs/benchmark_real/RULE.md) to candidate weights on the validation sets.

    python scripts/select_matcher.py --candidate v2= --candidate v3s1=RUN1/best.safetensors \
        --candidate v3s2=RUN2/best.safetensors --out-root out/select --report docs/benchmark_real/selection.md

Runs `liver-p2p benchmark` (resumable) for every candidate on real-val-v1 and real-val-camera-v1
(clean + 2 mm noise on every case), insilico-val-v1 (+ 2 and 4 mm on its lowest bin) and
insilico-val-camera-v1 with `learned-p2p,learned-p2p-icp`, then writes the rule's table and
verdict. An empty path is the bundled weights. The first candidate is the reference (shipped).
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

import numpy as np

SETS = {  # name -> extra benchmark arguments
    "real-val-v1": ["--noise-levels", "2", "--noise-bins", "all"],
    "insilico-val-v1": ["--noise-levels", "2,4"],
    "insilico-val-camera-v1": [],
    "real-val-camera-v1": ["--noise-levels", "2", "--noise-bins", "all"],
}
REAL, INSILICO = ("real-val-v1", "real-val-camera-v1"), ("insilico-val-v1", "insilico-val-camera-v1")
METHODS = ("learned-p2p", "learned-p2p-icp")
GROSS_MM = 20.0


def run_benchmarks(name: str, weights: str, args: argparse.Namespace) -> None:
    config = Path(args.out_root) / f"{name}.yaml"
    config.parent.mkdir(parents=True, exist_ok=True)
    config.write_text(f"weights_path: '{Path(weights).resolve() if weights else ''}'\n")
    for dataset, extra in SETS.items():
        cmd = [sys.executable, "-m", "liver_p2p_reg", "-q", "benchmark", "--dataset", dataset]
        cmd += ["--methods", ",".join(METHODS), "--out", str(Path(args.out_root) / name / dataset)]
        cmd += ["--workers", str(args.workers), "--config", str(config), *extra]
        if args.data_root:
            cmd += ["--data-root", args.data_root]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)


def rows(out_root: str, name: str, datasets: tuple[str, ...], method: str) -> list[dict]:
    out = []
    for dataset in datasets:
        with open(Path(out_root) / name / dataset / "cases.csv", newline="") as fh:
            out += [r for r in csv.DictReader(fh) if r["method"] == method]
    return out


def pooled(out_root: str, name: str, datasets: tuple[str, ...], method: str) -> tuple[float, int, int]:
    """Mean RMS-TRE, poses off by >= 20 mm (failures included) and cases."""
    rs = rows(out_root, name, datasets, method)
    tre = np.array([float(r["rms_tre_mm"]) for r in rs])
    gross = sum(float(r["rms_tre_mm"]) >= GROSS_MM or r["failed"] == "true" for r in rs)
    return float(tre.mean()), int(gross), len(rs)


def verdict(candidates: list[str], out_root: str) -> tuple[list[str], str]:
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--candidate", action="append", required=True, help="NAME=WEIGHTS (empty: bundled)")
    parser.add_argument("--out-root", default="out/select")
    parser.add_argument("--data-root", help="named sets' root (default: $LIVER_P2P_DATA or ./data)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", help="write the table and verdict here (markdown)")
    parser.add_argument("--no-run", action="store_true", help="only apply the rule to existing runs")
    args = parser.parse_args()
    candidates = []
    for item in args.candidate:
        name, _, weights = item.partition("=")
        candidates.append(name)
        if not args.no_run:
            run_benchmarks(name, weights, args)
    table, text = verdict(candidates, args.out_root)
    report = ["# Matcher selection on the validation sets (rule: RULE.md)", "", *table, "", text, ""]
    report += [
        "Command: `python scripts/select_matcher.py " + " ".join(f"--candidate {c}" for c in args.candidate) + "`"
    ]
    print("\n".join(report))
    if args.report:
        Path(args.report).write_text("\n".join(report) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
