"""Choose free_space_weight and free_space_warn on validation camera crops by docs/freespace/rule.md.

    LIVER_P2P_DATA=/work/data nice -n 10 .venv/bin/python scripts/free_space_sweep.py --out OUT

Runs, through the benchmark harness's own `run_one` (as `liver-p2p benchmark --sensor-aware`
does), every method once without the sensor origin and once per candidate weight with it, on
every case of the validation set; resumable (OUT/cases.csv). Then applies the rule and writes
OUT/README.md with the numbers and the choice. Never run it on a test set.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from liver_p2p_reg.bench.cases import case_info, list_case_paths, resolve_dataset
from liver_p2p_reg.bench.cases_csv import CASES_CSV, read_rows, write_rows
from liver_p2p_reg.bench.free_space_rule import METHODS, WEIGHTS, choose, variants
from liver_p2p_reg.bench.harness import run_one
from liver_p2p_reg.config import Config
from liver_p2p_reg.phantom.testset import TESTSETS


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
