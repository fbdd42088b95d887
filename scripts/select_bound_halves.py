"""Choose whether the error bound's scale takes the half-view feature (docs/benchmark_real/RULE_bound_halves.md).

    .venv/bin/python scripts/select_bound_halves.py [--cache out/bound] \
        [--out docs/benchmark_real/selection_bound_halves.md]

For the rigid bound and the deformed positions' bound each: the validation poses `liver-p2p calibrate-bound` (and
`--deformed`) calibrates on, collected into its --cache (run those first), the scale over the seven features and
over the eight, each calibrated by 2-fold cross-fitting over the calibration's liver split (seed 0) and judged on the
half that did not make its quantiles; the table, the rule's verdicts and the bound's cost are written to --out.
"""

from __future__ import annotations

import argparse
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.bound_report import TRUE_BINS
from liver_p2p_reg.bench.bound_select import cross_fitted, rule_failures
from liver_p2p_reg.cli.calibrate_cmd import DEFAULT_VAL, validation_collections
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.error_bound import FEATURES

MIN_GAIN = 0.02  # (b) at least 2 points below the seven's
COVERAGE_FLOOR = 0.85
MAX_BOUND_MS = 10.0  # (d) the bound's cost target, median per registration


def choose(seven: dict, eight: dict) -> tuple[int, list[str]]:
    """The rule's choice (7 or 8 features) and why the eight qualify or not."""
    fails = rule_failures(eight, seven, MIN_GAIN, COVERAGE_FLOOR)
    if not eight["bound_ms"] <= MAX_BOUND_MS:
        fails.append(f"(d) bound {eight['bound_ms']:.1f} ms > {MAX_BOUND_MS:g} ms")
    return (7, fails) if fails else (len(FEATURES), ["qualifies"])


def section(name: str, data: dict, config: Config) -> tuple[list[str], int]:
    """One bound's table and verdict."""
    rows = {n: cross_fitted(data, config, n_features=n) for n in (7, len(FEATURES))}
    # The bound's cost as collected. The run that decided (cd369de's collections, before 71cf60c) made the refits in
    # every bound, so it was the eight's cost (and overstated the seven's). Collections made since time the bound
    # without them (they are made on request, after the timer): there (d) understates the eight's cost by ~3-4 ms.
    cost = float(np.nanmedian(data["bound_ms"]))
    for row in rows.values():
        row["bound_ms"] = cost
    chosen, why = choose(rows[7], rows[len(FEATURES)])
    bins = list(TRUE_BINS)
    lines = [
        f"## {name} ({len(data['count'])} validation poses)",
        "",
        "| scale features | bad poses with OK | good poses warned | "
        + " | ".join(f"coverage [{lo:.2f}, {hi:.2f})" for lo, hi in bins)
        + " | bound (median ms) |",
        "|---|---|---|" + "---|" * len(bins) + "---|",
    ]
    for n, row in rows.items():
        cov = " | ".join(f"{row['coverage'][b]:.1%}" for b in bins)
        label = "seven (today)" if n == 7 else "eight (+ log_halves)"
        lines.append(f"| {label} | {row['bad_ok']} | {row['good_warned']:.1%} | {cov} | {row['bound_ms']:.1f} |")
    verdict = "the eight" if chosen == len(FEATURES) else "the seven (today stays)"
    lines += ["", "- eight: " + "; ".join(why), "", f"**Chosen: {verdict}.**", ""]
    return lines, chosen


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="out/bound", help="calibrate-bound's --cache (default: out/bound)")
    ap.add_argument("--out", default="docs/benchmark_real/selection_bound_halves.md")
    args = ap.parse_args()
    lines = [
        "# Selection of the error bound's half-view feature (validation collections)",
        "",
        f"Generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC by `.venv/bin/python "
        "scripts/select_bound_halves.py`; rule: [RULE_bound_halves.md](RULE_bound_halves.md). The validation poses "
        f"of {', '.join(Path(d).name for d in DEFAULT_VAL)} (2 mm noise), 2-fold cross-fitting over the "
        "calibration's liver split (seed 0), judged at true visibility [0.05, 0.3) on the half that did not make the "
        "quantiles; WARN above 10 mm or for any other reason. The bound's cost is the median over the collection "
        "(2 workers on 2 cores; collections made before 71cf60c made the half-view refits in every bound, later "
        "ones only on request, outside the timed bound).",
        "",
    ]
    for name, deformed in (("Rigid bound", False), ("Deformed positions' bound (poses where the stage applied)", True)):
        part, _ = section(name, *validation_collections(args.cache, deformed))
        lines += part
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
