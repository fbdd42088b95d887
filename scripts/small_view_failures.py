"""Where a method's poses beyond the rigid bound come from, per visibility bin (liver_p2p_reg/bench/failure_sources.py).

    .venv/bin/python scripts/small_view_failures.py [--sets real-val-v2,real-val-v2-arap,real-val-camera-v2] \
        [--config config/ransac_candidate_020.yaml] [--method learned-p2p-ransac-icp] [--sensor-aware] \
        [--out out/failures/NAME] [--readme FILE --block NAME]

Every case of each set below visibility 0.3, beside its copy with 2 mm of the benchmark's noise (as the selection
runs), registered with the configured method; ICP from the true pose beside it; on a failure (> 5 mm beyond that
bound) ICP from each candidate. The rows go to
OUT/SET.json (kept: a second call with the same settings reads them instead of registering again).
Meant for the validation sets: it says what to work on, not how good the method is.
"""

from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path

from liver_p2p_reg.bench.case_runs import NOISE_MM, set_rows
from liver_p2p_reg.bench.failure_sources import MARGIN_MM, run_case, summary_table
from liver_p2p_reg.bench.readme import check_readme, write_headline
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.registrar import available_methods

TOP_VISIBILITY = 0.3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="real-val-v2,real-val-v2-arap,real-val-camera-v2")
    parser.add_argument("--config", help="YAML of settings (default: the defaults)")
    parser.add_argument("--method", help="the method (default: the config's)")
    parser.add_argument("--sensor-aware", action="store_true", help="give each registration its case's sensor origin")
    parser.add_argument("--out", default="out/failures/default")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--readme", help="markdown file to write the table into (its --block)")
    parser.add_argument("--block", default="FAILURE-SOURCES")
    args = parser.parse_args(argv)
    try:
        if args.readme:  # before the work, not after it
            check_readme(args.readme, args.block)
        config = Config.from_yaml(args.config) if args.config else Config()
        config = config.replace(method=args.method) if args.method else config
        if config.method not in available_methods():
            raise InputError(f"unknown method {config.method!r}; choose one of {', '.join(available_methods())}")
        run = partial(run_case, sensor_aware=True) if args.sensor_aware else run_case
        # the margin decides which poses get ICP from every candidate, so kept rows hold to it
        tag = {"margin_mm": MARGIN_MM, **({"sensor_aware": True} if args.sensor_aware else {})}
        rows = {
            name: set_rows(
                name,
                run,
                config.to_dict(),
                Path(args.out),
                below_visibility=TOP_VISIBILITY,
                workers=args.workers,
                tag=tag,
            )
            for name in args.sets.split(",")
        }
    except InputError as exc:
        parser.exit(2, f"error: {exc}\n")
    errors = [r["error"] for rows_ in rows.values() for r in rows_ if r["error"]]
    if len(errors) == sum(map(len, rows.values())):  # nothing to show: say why instead of an empty table
        parser.exit(2, f"error: every registration raised, e.g. {errors[0] if errors else 'no cases'}\n")
    settings = (f"`--config {args.config}`" if args.config else "the defaults") + (
        ", each registration given its sensor origin (free space)" if args.sensor_aware else ""
    )
    caption = (
        f"Method `{config.method}` with {settings}; {NOISE_MM:g} mm noise copies beside the noiseless cases; "
        f"{len(errors)} registrations raised. Command: `python scripts/small_view_failures.py --sets {args.sets}"
        + (f" --config {args.config}" if args.config else "")
        + (f" --method {args.method}" if args.method else "")
        + (" --sensor-aware" if args.sensor_aware else "")
        + f" --out {args.out}"
        + (f" --readme {args.readme} --block {args.block}`" if args.readme else "`")
    )
    write_headline(caption, summary_table(rows, TOP_VISIBILITY), args.readme, args.block)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
