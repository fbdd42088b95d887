"""Apply the surface search's rule (docs/benchmark_real/RULE_surface_search.md).

    python scripts/select_surface_search.py [--out-root out/select_search] [--check-run] \
        [--report docs/benchmark_real/selection_surface_search.md]
    python scripts/select_surface_search.py --test T [--test-report docs/benchmark_real/judgement_surface_search.md]

Runs (resumable: rows already in a run's cases.csv are kept) the default with the search off and at 0.20 on the
three validation sets, composes each threshold's rows by the cases' M/N, checks the two runs agree where they
must, and writes the table and verdict. `--check-run` runs the chosen threshold for real on real-val-v2 and
requires its RMS-TRE to equal the composed rows case by case. The time rule is read from the SPEED-SEARCH block
of docs/results/speed.md, written by `scripts/bench_paths.py --methods
fpfh-ransac-icp,learned-p2p-icp,learned-p2p-icp:surface_search_visibility=T --block SPEED-SEARCH`.
`--test T` runs the default without the search and at T on the four test sets and judges T against the former (the
published rows were made on another CPU: they are compared too, not used).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from liver_p2p_reg.bench.candidate_runs import publish_report, run_candidate
from liver_p2p_reg.bench.ransac_candidate_rule import median_ms
from liver_p2p_reg.bench.ransac_threshold_rule import run_differences
from liver_p2p_reg.bench.surface_search_rule import (
    CANDIDATE_RUN,
    METHOD,
    REFERENCE_RUN,
    RUN_THRESHOLD,
    SETTING,
    TEST_REFERENCE_RUN,
    TEST_SETS,
    TIME_LIMIT_MS,
    VAL_SETS,
    compose,
    judged_on_test_sets,
    method_rows,
    validation_verdict,
)

CHECK_SET = "real-val-v2"
SPEED_BLOCK = "SPEED-SEARCH"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-root", default="out/select_search")
    parser.add_argument("--data-root", help="named sets' root (default: $LIVER_P2P_DATA or ./data)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--check-run", action="store_true", help="run the chosen threshold on real-val-v2 and compare")
    parser.add_argument("--speed", default="docs/results/speed.md", help=f"markdown holding the {SPEED_BLOCK} block")
    parser.add_argument("--report", help="write the validation table and verdict here (markdown)")
    parser.add_argument("--test", type=float, help="judge this threshold on the test sets (after the validation)")
    parser.add_argument("--test-report", help="write the test table and verdict here (markdown)")
    args = parser.parse_args()
    runs = dict(workers=args.workers, data_root=args.data_root, threads=1)
    if args.test is not None:
        name = f"test-{args.test:.2f}"
        run_candidate(TEST_REFERENCE_RUN, "", TEST_SETS, [METHOD], args.out_root, **runs)
        run_candidate(name, "", TEST_SETS, [METHOD], args.out_root, settings={SETTING: args.test}, **runs)
        table, line, _, published = judged_on_test_sets(args.out_root, args.test, name, TEST_REFERENCE_RUN)
        table += ["", "The default's rows of this run beside the published ones (made on another CPU):", ""]
        table += [f"- {row}" for row in published]
        title = "The surface search on the real test sets (rule: RULE_surface_search.md)"
        command = f"python scripts/select_surface_search.py --out-root {args.out_root} --test {args.test:.2f}"
        publish_report(title, table, line, command, args.test_report)
        return 0
    run_candidate(REFERENCE_RUN, "", VAL_SETS, [METHOD], args.out_root, **runs)
    run_candidate(CANDIDATE_RUN, "", VAL_SETS, [METHOD], args.out_root, settings={SETTING: RUN_THRESHOLD}, **runs)
    table, line, chosen = validation_verdict(args.out_root)
    if chosen is not None and args.check_run:
        name = f"threshold-{chosen:.2f}"
        check = {CHECK_SET: VAL_SETS[CHECK_SET]}
        run_candidate(name, "", check, [METHOD], args.out_root, settings={SETTING: chosen}, **runs)
        root = Path(args.out_root)
        composed = compose(
            method_rows(root / REFERENCE_RUN / CHECK_SET), method_rows(root / CANDIDATE_RUN / CHECK_SET), chosen
        )
        real = method_rows(root / name / CHECK_SET)
        bad = run_differences(composed, real)
        table += [
            "",
            f"Real run at {chosen:.2f} on {CHECK_SET}: {len(real)} rows, {len(bad)} differing from the "
            "composed rows" + (": " + ", ".join(bad[:5]) if bad else "."),
        ]
        if bad:
            line, chosen = "The real run differs from the composed rows: no verdict.", None
    if chosen is not None:
        spec = f"{METHOD}:{SETTING}={chosen:g}"
        ms = median_ms(Path(args.speed), spec, SPEED_BLOCK)
        fast = ms <= TIME_LIMIT_MS
        table += [
            "",
            f"Time: median {ms:.1f} ms per registration (limit {TIME_LIMIT_MS:.0f} ms), "
            f"{'met' if fast else 'missed'}; the default without the search "
            f"{median_ms(Path(args.speed), METHOD, SPEED_BLOCK):.1f} ms in the same run "
            f"(`scripts/bench_paths.py --methods ...,{spec} --block {SPEED_BLOCK}`).",
        ]
        line = (
            f"Threshold {chosen:.2f} passes rules 1-3 and the time: it goes to the test sets."
            if fast
            else f"Threshold {chosen:.2f} passes rules 1-3 but not the time: not chosen (the rule times the next "
            "threshold that passes 1-3, if the pooled line above names one; otherwise the search stays off, opt-in)."
        )
    title = "The surface search's threshold on the validation sets (rule: RULE_surface_search.md)"
    command = f"python scripts/select_surface_search.py --out-root {args.out_root}" + (
        " --check-run" if args.check_run else ""
    )
    publish_report(title, table, line, command, args.report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
