"""cases.csv of a benchmark run: its columns, typed reading, sorted atomic writing, the append-only log."""

from __future__ import annotations

import csv
import io
import logging
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

CASES_CSV = "cases.csv"
# Columns before the per-stage runtimes / after them; per-stage columns are `runtime_<stage>_ms`.
HEAD_COLUMNS = (
    "case_id",
    "method",
    "base_method",
    "variant",
    "visibility",
    "noise_mm",
    "added_noise_mm",
    "crop_mode",
    "density",
    "deformation_rms_mm",
    "rms_tre_mm",
    "max_tre_mm",
    "initial_rms_tre_mm",
    "residual_mm",
    "runtime_ms",
)
TAIL_COLUMNS = (
    "chosen_candidate",
    "n_candidates",
    "n_matches",
    "method_visibility",
    "failed",
    "reason",
    "ambiguous",
    "uncertainty_mm",
    "free_space_violation",
    "error_bound_mm",
    "bound_coverage",
    "seed",
    "rigid_rms_tre_mm",
    "deform_applied",
    "deform_reason",
)
FLOAT_COLUMNS = {
    "visibility",
    "noise_mm",
    "added_noise_mm",
    "deformation_rms_mm",
    "rms_tre_mm",
    "max_tre_mm",
    "initial_rms_tre_mm",
    "residual_mm",
    "runtime_ms",
    "method_visibility",
    "uncertainty_mm",
    "free_space_violation",
    "error_bound_mm",
    "bound_coverage",
    "rigid_rms_tre_mm",
}
INT_COLUMNS = {"n_candidates", "n_matches", "seed"}
BOOL_COLUMNS = {"failed", "ambiguous", "deform_applied"}


def _format(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else repr(value))
    return "" if value is None else str(value)


def _parse(column: str, text: str) -> Any:
    """A cell as its column's type; ValueError when it is none (a row cut short or damaged)."""
    if column in BOOL_COLUMNS:
        if text not in ("true", "false", ""):  # "" where a column does not apply (deform_applied of a rigid row)
            raise ValueError(f"{column} {text!r} is not true or false")
        return text == "true"
    if column in INT_COLUMNS:
        return int(text) if text else 0
    if column in FLOAT_COLUMNS or (column.startswith("runtime_") and column.endswith("_ms")):
        return float(text) if text else math.nan
    return text


def columns_for(rows: Iterable[dict[str, Any]]) -> list[str]:
    """Fixed columns plus one `runtime_<stage>_ms` column per stage seen in any row (sorted)."""
    stages = sorted({k for r in rows for k in r if k.startswith("runtime_") and k != "runtime_ms"})
    return [*HEAD_COLUMNS, *stages, *TAIL_COLUMNS]


def read_rows(path: Path) -> list[dict[str, Any]]:
    """Rows of a cases.csv with typed values (floats, ints, bools); damaged rows are left out with one warning,
    so a resumed run registers them again instead of trusting them."""
    with open(path, newline="") as fh:
        text = fh.read()
    cut = bool(text) and not text.endswith("\n")  # an append cut off mid-line (killed, disk full)
    text = text[: text.rfind("\n") + 1]
    rows, damaged = [], int(cut)
    for row in csv.DictReader(io.StringIO(text, newline="")):
        typed = _typed(row)
        if typed is None:
            damaged += 1
        else:
            rows.append(typed)
    if damaged:
        log.warning(
            "%s: left out %d damaged row(s) (cut short or unparsable); a run registers them again", path, damaged
        )
    return rows


def _typed(row: dict[str | None, Any]) -> dict[str, Any] | None:
    """A row with typed values, or None when a column is missing, extra or unparsable or it names no case/method."""
    if None in row or any(v is None for v in row.values()) or not row.get("case_id") or not row.get("method"):
        return None
    try:
        return {k: _parse(k, v) for k, v in row.items() if k is not None}
    except ValueError:
        return None


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write all rows sorted by (case_id, method), atomically."""
    rows = sorted(rows, key=lambda r: (r["case_id"], r["method"]))
    header = columns_for(rows)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for row in rows:
            writer.writerow([_format(row.get(col, math.nan if col.startswith("runtime_") else "")) for col in header])
    os.replace(tmp, path)


class CsvLog:
    """Append-only cases.csv that survives interruption; rewritten only when a new stage column appears."""

    def __init__(self, path: Path, rows: list[dict[str, Any]]) -> None:
        self.path = path
        self.rows = list(rows)
        self.header = columns_for(self.rows)
        write_rows(path, self.rows)

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        if any(k not in self.header for k in row):
            self.header = columns_for(self.rows)
            write_rows(self.path, self.rows)
            return
        line = io.StringIO()
        csv.writer(line).writerow(
            [_format(row.get(c, math.nan if c.startswith("runtime_") else "")) for c in self.header]
        )
        # one write of the whole line, on disk before the next run starts: a kill leaves at most one cut line
        with open(self.path, "a", newline="") as fh:
            fh.write(line.getvalue())
            fh.flush()
            os.fsync(fh.fileno())
