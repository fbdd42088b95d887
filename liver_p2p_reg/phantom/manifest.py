"""manifest.csv of a generated dataset: one line per case, written and read back with its numbers converted."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from liver_p2p_reg.errors import InputError

MANIFEST_FIELDS = (
    "file",
    "split",
    "liver_id",
    "deformation_id",
    "target_id",
    "crop_mode",
    "noise_mm",
    "visibility",
    "visibility_requested",
    "deformation_rms_mm",
    "deformation_max_mm",
    "initial_rms_tre_mm",
    "n_src",
    "n_tgt",
)


def manifest_row(path: Path, case: dict, split: str) -> dict:
    """One manifest line describing a case."""
    init = np.sqrt(np.mean(np.sum((case["tgt_marker"] - case["src_marker"]) ** 2, axis=1)))
    return {
        "file": path.name,
        "split": split,
        "liver_id": int(case["liver_id"]),
        "deformation_id": int(case["deformation_id"]),
        "target_id": int(case["target_id"]),
        "crop_mode": str(case["crop_mode"]),
        "noise_mm": float(case["noise_mm"]),
        "visibility": round(float(case["visibility"]), 6),
        "visibility_requested": round(float(case["visibility_requested"]), 6),
        "deformation_rms_mm": round(float(case["deformation_rms_mm"]), 6),
        "deformation_max_mm": round(float(case["deformation_max_mm"]), 6),
        "initial_rms_tre_mm": round(float(init), 6),
        "n_src": len(case["src_pcd"]),
        "n_tgt": len(case["tgt_pcd"]),
    }


def write_manifest(out: Path, rows: Sequence[dict]) -> Path:
    """Write OUT/manifest.csv with these rows; returns its path."""
    path = out / "manifest.csv"
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=MANIFEST_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    return path


def read_manifest(directory: str | Path) -> list[dict]:
    """Manifest rows of a generated dataset (numbers converted)."""
    path = Path(directory) / "manifest.csv"
    if not path.is_file():
        raise InputError(f"{directory}: no manifest.csv (not a generated dataset?)")
    rows = []
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            for key in ("liver_id", "deformation_id", "target_id", "n_src", "n_tgt"):
                row[key] = int(row[key])
            for key in (
                "noise_mm",
                "visibility",
                "visibility_requested",
                "deformation_rms_mm",
                "deformation_max_mm",
                "initial_rms_tre_mm",
            ):
                row[key] = float(row[key])
            rows.append(row)
    return rows
