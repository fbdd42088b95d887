"""Apply the deformed-screening rule (docs/benchmark_real/RULE_deformed_screening.md) on the three validation sets.

    .venv/bin/python scripts/select_deformed_screening.py [--out out/select_deformed] \
        [--report docs/benchmark_real/selection_deformed_screening.md] [--check-run] \
        [--test-report docs/benchmark_real/judgement_deformed_screening.md]

`learned-p2p-ransac-icp` at `ransac_candidate_visibility` 0.2 on every case below visibility 0.2 and its 2 mm noise
copy; per close contender its error and residuals after the full ICP and the elastic stage
(liver_p2p_reg/bench/deformed_screening.py). Rows kept in OUT/SET.json. Each judge's poses are composed from them;
the screening's own choice must give the method's own pose in every case, or there is no verdict.

`--check-run` (rule 3): the judge built in (`contender_judge_ratio`) on every such case of real-val-v2 must give
the composed pose. `--test-report`: the four real test sets' views below 0.3, the method's own poses beside the
judged ones and the rigid bound (rows kept in OUT/test/SET.json below 0.2 and OUT/test_020/SET.json from 0.2).
`--margin-report`: RULE_judge_margin.md composed from the kept rows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.candidate_runs import publish_report
from liver_p2p_reg.bench.case_runs import set_rows
from liver_p2p_reg.bench.deformed_screening import (
    CHECK_SET,
    SETS,
    SETTINGS,
    TAG,
    TEST_SETS,
    check_mismatches,
    collect_case,
    judged_case,
    judgement_table,
    margin_verdict,
    noisy,
    reproduction_mismatches,
    verdict,
)
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import LiverP2PError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/select_deformed")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", help="write the table and verdict here (markdown)")
    parser.add_argument("--check-run", action="store_true", help="run the built-in judge on real-val-v2 (rule 3)")
    parser.add_argument("--test-report", help="judge it on the four real test sets; the table goes here (markdown)")
    parser.add_argument("--margin-report", help="apply RULE_judge_margin.md to the kept rows; the table goes here")
    args = parser.parse_args(argv)
    settings = Config.from_dict(SETTINGS).to_dict()
    out = Path(args.out)
    try:
        rows = {
            name: set_rows(name, collect_case, settings, out, below_visibility=0.2, workers=args.workers, tag=TAG)
            for name in SETS
        }
        check = (
            set_rows(CHECK_SET, judged_case, settings, out / "check", below_visibility=0.2, workers=args.workers)
            if args.check_run
            else None
        )
        # from 0.2 up the judge runs only where a view's estimated visibility is below 0.2: kept apart, so that the
        # small views' rows stand alone
        tested = (
            {
                name: set_rows(name, judged_case, settings, out / "test", below_visibility=0.2, workers=args.workers)
                + set_rows(
                    name,
                    judged_case,
                    settings,
                    out / "test_020",
                    from_visibility=0.2,
                    below_visibility=0.3,
                    workers=args.workers,
                )
                for name in TEST_SETS
            }
            if args.test_report
            else None
        )
    except LiverP2PError as exc:  # a set's cases could not be read, or a registration raised: nothing is kept
        parser.exit(2, f"error: {exc}\n")
    table, line, _ = verdict(rows)
    bad = {name: reproduction_mismatches(set_) for name, set_ in rows.items()}
    judged = [r for set_ in rows.values() for r in set_ if r["screened"]]
    added = np.array([r["added_ms"] for r in judged]) if judged else np.zeros(1)
    table += [
        "",
        f"Cases with two or more screened candidates: {len(judged)}; the screening's own choice differs from the "
        f"method's own pose in {sum(map(len, bad.values()))}"
        + "".join(f"; {n}: {', '.join(b[:3])}" for n, b in bad.items() if b)
        + ".",
        f"Time this collection added per such case (the other contenders' full ICP and every contender's whole elastic "
        f"stage, one thread): median {np.median(added):.0f} ms, 90th percentile {np.percentile(added, 90):.0f} ms; the "
        "built-in judge skips the stage's held-out check (its time: docs/results/speed.md, SPEED-JUDGE).",
    ]
    if any(bad.values()):
        line = "The screening's own choice does not reproduce the method's poses: no verdict."
    if check is not None:
        off = check_mismatches(check, rows[CHECK_SET])
        table.append(
            f"Rule 3's check (`--check-run`): the judge built in (`contender_judge_ratio` 1.5) on the {len(check)} "
            f"poses of {CHECK_SET} gives the composed pose (RMS-TRE within 0.01 mm) in {len(check) - len(off)}"
            + (f"; not in {', '.join(off[:5])}" if off else "")
            + "."
        )
    command = f"python scripts/select_deformed_screening.py --out {args.out}" + (
        f" --report {args.report}" if args.report else ""
    )
    title = "Close contenders judged after the full ICP and the elastic stage, on the validation sets (rule: RULE_deformed_screening.md)"
    publish_report(title, table, line, command + (" --check-run" if check is not None else ""), args.report)
    if args.margin_report:
        m_table, m_line, _ = margin_verdict(rows)
        title = "A margin before the contenders' judge overrules the screening, on the validation sets (rule: RULE_judge_margin.md)"
        m_command = f"python scripts/select_deformed_screening.py --out {args.out} --margin-report {args.margin_report}"
        publish_report(title, m_table, m_line, m_command, args.margin_report)
    if tested is not None:
        small = {name: [r for r in noisy(rs) if 0.05 <= r["visibility"] < 0.2] for name, rs in tested.items()}
        pooled = {
            name: (np.mean([r["own_mm"] for r in rs]), np.mean([r["judged_mm"] for r in rs]))
            for name, rs in small.items()
        }
        summary = (
            "2 mm noise, pooled over [0.05, 0.2), own -> judged mean: "
            + "; ".join(f"{name} {a:.2f} -> {b:.2f} mm" for name, (a, b) in pooled.items())
            + f". Judged lower on {sum(b < a for a, b in pooled.values())} of {len(pooled)} sets."
        )
        title = "The contenders' judge (elastic stage's residual, r 1.5) on the real test sets' small views"
        publish_report(
            title,
            judgement_table(tested),
            summary,
            f"python scripts/select_deformed_screening.py --out {args.out} --test-report {args.test_report}",
            args.test_report,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
