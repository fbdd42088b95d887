"""The README's non-rigid headline: the default's `+deform` rows of benchmark runs, rigid -> deformed, per range.

Usage: .venv/bin/python scripts/deform_headline.py docs/benchmark_real_test_v2_deform docs/benchmark_real_test_v2_arap_deform --readme README.md

Reads each OUT's cases.csv and writes the block DEFORM: one row per (set, visibility range) for
`learned-p2p-icp+deform` (the rows with the benchmark's 2 mm noise), the same numbers as each run's summary.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from liver_p2p_reg.bench.cases_csv import read_rows
from liver_p2p_reg.bench.deform_table import table_deform
from liver_p2p_reg.bench.readme import write_headline

METHOD = "learned-p2p-icp+deform"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outs", nargs="+")
    parser.add_argument("--readme")
    args = parser.parse_args()
    lines: list[str] = []
    for out in map(Path, args.outs):
        dataset = json.loads((out / "settings.json").read_text())["dataset"]
        rows = [r for r in read_rows(out / "cases.csv") if r["method"] == METHOD and 0.1 <= r["visibility"] < 0.3]
        table = table_deform(rows) or []
        body = [line.replace(f"| {METHOD} |", f"| `{dataset}` |", 1) for line in table]
        if not body:
            raise SystemExit(f"{out}: no {METHOD} rows")
        if not lines:
            lines += [body[0].replace("| method |", "| set |", 1), body[1]]
        lines += body[2:]
    caption = (
        f"`{METHOD}` against its own rigid pose, real CT test livers, 2 mm noise "
        f"(`.venv/bin/python scripts/deform_headline.py {' '.join(args.outs)} --readme README.md`):"
    )
    write_headline(caption, lines, args.readme, "DEFORM")


if __name__ == "__main__":
    main()
