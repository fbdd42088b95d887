"""Apply the feature-agreement rule (docs/benchmark_real/RULE_feature_agreement.md) on the three validation sets.

    .venv/bin/python scripts/select_feature_agreement.py [--out out/select_agreement] \
        [--report docs/benchmark_real/selection_feature_agreement.md]

`learned-p2p-ransac-icp` at `ransac_candidate_visibility` 0.2 on every case below visibility 0.2 and its 2 mm noise
copy; per screened candidate its short residual, its learned matches' agreement and the error after the full ICP
from it (liver_p2p_reg/bench/agreement_rule.py). Rows kept in OUT/SET.json. Each lambda's poses are composed from
them; lambda 0 must give the method's own pose in every case, or there is no verdict.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from liver_p2p_reg.bench.agreement_rule import SETS, SETTINGS, TAG, collect_case, reproduction_mismatches, verdict
from liver_p2p_reg.bench.candidate_runs import publish_report
from liver_p2p_reg.bench.case_runs import set_rows
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import LiverP2PError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/select_agreement")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", help="write the table and verdict here (markdown)")
    args = parser.parse_args(argv)
    settings = Config.from_dict(SETTINGS).to_dict()
    try:
        rows = {
            name: set_rows(
                name, collect_case, settings, Path(args.out), below_visibility=0.2, workers=args.workers, tag=TAG
            )
            for name in SETS
        }
    except LiverP2PError as exc:  # a set's cases could not be read, or a registration raised: nothing is kept
        parser.exit(2, f"error: {exc}\n")
    table, line, _ = verdict(rows)
    bad = {name: reproduction_mismatches(set_) for name, set_ in rows.items()}
    screened = sum(bool(r["screened"]) for set_ in rows.values() for r in set_)
    table += [
        "",
        f"Cases with two or more screened candidates: {screened}; lambda 0 differs from the method's own pose "
        f"in {sum(map(len, bad.values()))}" + "".join(f"; {n}: {', '.join(b[:3])}" for n, b in bad.items() if b) + ".",
    ]
    if any(bad.values()):
        line = "Lambda 0 does not reproduce the method's poses: no verdict."
    command = f"python scripts/select_feature_agreement.py --out {args.out}" + (
        f" --report {args.report}" if args.report else ""
    )
    title = "The learned matches' agreement in the screening, on the validation sets (rule: RULE_feature_agreement.md)"
    publish_report(title, table, line, command, args.report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
