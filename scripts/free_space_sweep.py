"""Choose free_space_weight and free_space_warn on validation camera crops by docs/freespace/rule.md.

    LIVER_P2P_DATA=/work/data nice -n 10 .venv/bin/python scripts/free_space_sweep.py --out OUT

Runs, through the benchmark harness's own `run_one` (as `liver-p2p benchmark --sensor-aware`
does), every method once without the sensor origin and once per candidate weight with it, on
every case of the validation set; resumable (OUT/cases.csv). Then applies the rule and writes
OUT/README.md with the numbers and the choice. Never run it on a test set.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from liver_p2p_reg.bench.cases import case_info, list_case_paths, resolve_dataset
from liver_p2p_reg.bench.harness import CASES_CSV, Variant, read_rows, run_one, write_rows
from liver_p2p_reg.config import Config
from liver_p2p_reg.phantom.testset import TESTSETS

WEIGHTS = (0.5, 1.0, 2.0, 4.0, 8.0)
WARN_GRID = (0.10, 0.15, 0.20, 0.25, 0.30, 0.40)
METHODS = ("learned-p2p-icp", "learned-p2p", "fpfh-p2p-icp")
GROSS_MM = 20.0
GOOD_MM = 10.0
TIE_MM = 0.02
FALSE_ALARM_SHARE = 0.02


def variants(methods: list[str], weights: list[float]) -> list[Variant]:
    plain = [Variant(m) for m in methods]
    aware = [Variant(m, (("free_space_weight", w),), sensor_aware=True) for w in weights for m in methods]
    return plain + aware


def choose(rows: list[dict], methods: list[str], weights: list[float]) -> tuple[list[str], float, float]:
    """The rule: report lines, the chosen weight and warn threshold."""
    lines = ["| setting | " + " | ".join(f"{m} mean mm" for m in methods) + " | S mm | poses >= 20 mm |", ""]
    lines[1] = "|" + "---|" * (len(methods) + 3)

    def stats(label_of) -> tuple[list[float], float, int]:
        means, gross = [], 0
        for m in methods:
            tre = np.array([r["rms_tre_mm"] for r in rows if r["method"] == label_of(m)], float)
            means.append(float(tre.mean()))
            gross += int((tre >= GROSS_MM).sum())
        return means, float(np.mean(means)), gross

    base_means, base_s, base_gross = stats(lambda m: m)
    lines.append(f"| no origin | {' | '.join(f'{v:.3f}' for v in base_means)} | {base_s:.3f} | {base_gross} |")
    scores = {}
    for w in weights:
        means, s, gross = stats(lambda m, w=w: Variant(m, (("free_space_weight", w),), sensor_aware=True).label)
        lines.append(f"| weight {w:g} | {' | '.join(f'{v:.3f}' for v in means)} | {s:.3f} | {gross} |")
        if gross <= base_gross:
            scores[w] = s
    if not scores:
        return (
            [*lines, "", "No weight keeps the gross poses at the baseline's count: free space stays off."],
            0.0,
            math.inf,
        )
    lowest = min(scores.values())
    weight = min(w for w, s in scores.items() if s <= lowest + TIE_MM)
    chosen = [
        r
        for m in methods
        for r in rows
        if r["method"] == Variant(m, (("free_space_weight", weight),), sensor_aware=True).label
    ]
    good = np.array([r["free_space_violation"] for r in chosen if r["rms_tre_mm"] <= GOOD_MM], float)
    warn = next((t for t in WARN_GRID if np.mean(good > t) <= FALSE_ALARM_SHARE), WARN_GRID[-1])
    lines += [
        "",
        f"Admissible weights (poses >= {GROSS_MM:g} mm not above the baseline's {base_gross}): "
        f"{', '.join(f'{w:g}' for w in scores)}; lowest S {lowest:.3f} mm; chosen weight **{weight:g}** "
        f"(the smallest within {TIE_MM} mm of the lowest).",
        "",
        f"Violation of the chosen weight's poses within {GOOD_MM:g} mm (n = {good.size}): "
        + ", ".join(f"{q}th pct {np.percentile(good, q):.3f}" for q in (50, 90, 95, 98, 99)),
        "",
        "| warn threshold | "
        + " | ".join(f"{t:.2f}" for t in WARN_GRID)
        + " |\n|"
        + "---|" * (len(WARN_GRID) + 1)
        + "\n| share of good poses warned | "
        + " | ".join(f"{100 * np.mean(good > t):.1f} %" for t in WARN_GRID)
        + " |",
        "",
        f"Chosen warn threshold **{warn:.2f}** (the smallest warning at most {100 * FALSE_ALARM_SHARE:g} % of them).",
    ]
    return lines, weight, warn


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="insilico-val-camera-v1")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--weights", default=",".join(f"{w:g}" for w in WEIGHTS))
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.dataset in TESTSETS and TESTSETS[args.dataset].split != "val":
        raise SystemExit("the free-space settings are chosen on validation sets only")
    methods = [m for m in args.methods.split(",") if m]
    weights = [float(w) for w in args.weights.split(",") if w]
    folder, _ = resolve_dataset(args.dataset, None)
    cases = [case_info(p) for p in list_case_paths(folder)]
    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = args.out / CASES_CSV
    rows = read_rows(csv_path) if csv_path.exists() else []
    done = {(r["case_id"], r["method"]) for r in rows}
    config = Config().to_dict()
    todo = [(c, v) for c in cases for v in variants(methods, weights) if (c.case_id, v.label) not in done]
    for k, (case, variant) in enumerate(tqdm(todo, desc="sweep", unit="run")):
        rows.append(run_one(case, variant, config))
        if k % 50 == 49:
            write_rows(csv_path, rows)  # resumable
    write_rows(csv_path, rows)
    rows = read_rows(csv_path)
    lines, weight, warn = choose(rows, methods, weights)
    text = "\n".join(
        [
            "# Free-space settings on the validation camera crops",
            "",
            f"Dataset `{args.dataset}` ({len(cases)} cases), methods {', '.join(f'`{m}`' for m in methods)}; "
            "rule: [rule.md](rule.md). Command: `LIVER_P2P_DATA=... python scripts/free_space_sweep.py "
            f"--dataset {args.dataset} --out {args.out}`.",
            "",
            *lines,
            "",
        ]
    )
    (args.out / "README.md").write_text(text)
    print(text)
    print(f"free_space_weight={weight:g} free_space_warn={warn:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
