"""Choose the error bound's rival classes on the validation collections (docs/benchmark_real/RULE_bound_rival_groups.md).

    .venv/bin/python scripts/select_bound_rival_groups.py [--cache out/bound] \
        [--out docs/benchmark_real/selection_bound_rival_groups.md]

The rigid validation poses `liver-p2p calibrate-bound` calibrates on (collected into its --cache: run it first), each
candidate calibrated by 2-fold cross-fitting over the calibration's liver split (seed 0) and judged on the half it
did not calibrate its quantiles on; the table, the rule's verdict and the chosen edge are written to --out.
"""

from __future__ import annotations

import argparse
from datetime import datetime, timezone
from pathlib import Path

from liver_p2p_reg.bench.bound_report import TRUE_BINS
from liver_p2p_reg.bench.bound_select import cross_fitted, rule_failures
from liver_p2p_reg.cli.calibrate_cmd import DEFAULT_VAL, validation_collections

CANDIDATES = (None, 1.25, 1.5, 2.0)  # the rule's r; None: today's calibration (visibility groups only)
MIN_GAIN = 0.02  # (b) at least 2 points below none's
TIE = 0.005  # within 0.5 points: the larger r
COVERAGE_FLOOR = 0.85


def choose(rows: dict) -> tuple[float | None, list[str]]:
    """The rule's choice and, per candidate, why it qualifies or not."""
    none = rows[None]
    why, qualified = [], []
    for r, row in rows.items():
        if r is None:
            continue
        fails = rule_failures(row, none, MIN_GAIN, COVERAGE_FLOOR)
        why.append(f"- r = {r:g}: " + ("qualifies" if not fails else "; ".join(fails)))
        if not fails:
            qualified.append(r)
    if not qualified:
        return None, why
    best = min(rows[r]["good_warned"] for r in qualified)
    return max(r for r in qualified if rows[r]["good_warned"] <= best + TIE), why


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="out/bound", help="calibrate-bound's --cache (default: out/bound)")
    ap.add_argument("--out", default="docs/benchmark_real/selection_bound_rival_groups.md")
    args = ap.parse_args()
    data, config = validation_collections(args.cache, deformed=False)
    # the scale's features as calibrate-bound fits them (the rule compared the seven, before log_halves existed)
    rows = {r: cross_fitted(data, config, rival_edges=() if r is None else (r,), n_features=7) for r in CANDIDATES}
    chosen, why = choose(rows)
    bins = list(TRUE_BINS)
    lines = [
        "# Selection of the error bound's rival classes (validation collections)",
        "",
        f"Generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC by `.venv/bin/python "
        "scripts/select_bound_rival_groups.py`; rule: [RULE_bound_rival_groups.md](RULE_bound_rival_groups.md). "
        f"{len(data['count'])} rigid validation poses ({', '.join(Path(d).name for d in DEFAULT_VAL)}, 2 mm noise), "
        "2-fold cross-fitting over the calibration's liver split (seed 0), judged at true visibility [0.05, 0.3) on "
        "the half that did not make the quantiles (its livers fitted the scale model, the same in every candidate); "
        "WARN above 10 mm or for any other reason.",
        "",
        "| r (contested below) | bad poses with OK | good poses warned | "
        + " | ".join(f"coverage [{lo:.2f}, {hi:.2f})" for lo, hi in bins)
        + " |",
        "|---|---|---|" + "---|" * len(bins),
    ]
    for r, row in rows.items():
        cov = " | ".join(f"{row['coverage'][b]:.1%}" for b in bins)
        name = "none (today)" if r is None else f"{r:g}"
        lines.append(f"| {name} | {row['bad_ok']} | {row['good_warned']:.1%} | {cov} |")
    lines += ["", *why, "", f"**Chosen: {'none (today stays)' if chosen is None else f'r = {chosen:g}'}.**", ""]
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
