"""Where the non-rigid stage's error comes from: the mode basis itself, or what a partial view can tell it.

    .venv/bin/python scripts/deform_ceiling.py [--sets real-val-v2,real-val-v2-arap] [--modes 24,48,96] \
        [--true-pose docs/deform/true_pose] [--readme docs/deform/ceiling.md]

1. The basis: for one case per (liver, deformation) of each set, the true displacement of the interior
   markers (the truth's inverse pose applied to their deformed positions) is fitted, by linear least
   squares, with a small rigid motion alone and with a small rigid motion plus the stage's first m
   non-rigid modes of that liver's elastic model (built as the stage builds it). Fitted on every
   other marker, measured on the others: what the basis could give if the data determined it.
2. The data: the rows `procrustes+deform` and `bound+deform` that `liver-p2p benchmark` wrote under
   --true-pose/<set> (the stage started from the oracle pose and from ICP started at the true pose),
   against their rigid starts, per visibility bin.
Validation sets only: this is a diagnosis, not a judgement.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.cases import BIN_LABELS, list_case_paths, read_case, resolve_dataset, visibility_bin
from liver_p2p_reg.bench.readme import write_headline
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.deform import elastic_model

MARK = "DEFORM-CEILING"


def small_rigid_basis(points_mm: np.ndarray) -> np.ndarray:
    """(P, 3, 6): a point's displacement per unit translation and per unit (linearized) rotation about the centroid."""
    r = points_mm - points_mm.mean(axis=0)
    out = np.zeros((len(points_mm), 3, 6))
    for axis in range(3):
        out[:, axis, axis] = 1.0
        e = np.zeros(3)
        e[axis] = 1.0
        out[:, :, 3 + axis] = np.cross(e, r)
    return out


def held_out_rms_mm(basis: np.ndarray, displacement_mm: np.ndarray) -> float:
    """RMS misfit (mm) on the odd markers of the least-squares fit of `basis` (P, 3, k) on the even ones."""
    fit = np.arange(len(basis)) % 2 == 0
    x, *_ = np.linalg.lstsq(basis[fit].reshape(-1, basis.shape[-1]), displacement_mm[fit].ravel(), rcond=None)
    miss = basis[~fit] @ x - displacement_mm[~fit]
    return float(np.sqrt((miss**2).sum(axis=1).mean()))


def basis_rows(dataset: str, modes: list[int]) -> list[float]:
    """Mean held-out misfit over the set's (liver, deformation) pairs: rigid alone, then rigid + each mode count."""
    folder, _ = resolve_dataset(dataset, None)
    paths = [p for p in list_case_paths(folder) if p.stem.endswith("_T000")]  # one view per deformation
    caches: dict[int, dict] = {m: {} for m in modes}
    rows = []
    for path in paths:
        case = read_case(path)
        src = np.asarray(case["src_marker"], float)
        # the truth's rigid part removed: what is left is the deformation (and any rigid share of it)
        moved = (np.asarray(case["tgt_marker"], float) - case["t_gt"]) @ np.asarray(case["R_gt"], float)
        shift = moved - src
        rigid = small_rigid_basis(src)
        row = [held_out_rms_mm(rigid, shift)]
        for m in modes:
            model = elastic_model(
                caches[m], np.asarray(case["src_pcd"], float), case.get("src_triangles"), Config(deform_modes=m)
            )
            ids, weights = model.embed(src)
            row.append(held_out_rms_mm(np.concatenate([rigid, model.basis_at(ids, weights)], axis=2), shift))
        rows.append(row)
    return [len(paths), *np.mean(rows, axis=0)]


def true_pose_rows(folder: Path) -> list[list[str]]:
    """Per bin: mean RMS-TRE of procrustes, procrustes+deform, bound, bound+deform and the stage's applied share."""
    by: dict[tuple[int, str], list[dict]] = {}
    with open(folder / "cases.csv", newline="") as f:
        for row in csv.DictReader(f):
            b = visibility_bin(float(row["visibility"]))
            by.setdefault((b, row["method"]), []).append(row)
    out = []
    for b in sorted({k[0] for k in by}):
        cells = [BIN_LABELS[b], str(len(by[(b, "procrustes")]))]
        for method in ("procrustes", "procrustes+deform", "bound", "bound+deform"):
            cells.append(f"{np.mean([float(r['rms_tre_mm']) for r in by[(b, method)]]):.2f}")
        applied = [r["deform_applied"] == "true" for r in by[(b, "bound+deform")]]
        cells.append(f"{100 * np.mean(applied):.0f} %")
        out.append(cells)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="real-val-v2,real-val-v2-arap")
    parser.add_argument("--modes", default="24,48,96")
    parser.add_argument("--true-pose", default="docs/deform/true_pose", help="benchmark folders, one per set")
    parser.add_argument("--readme", help="write the block into this markdown file")
    args = parser.parse_args(argv)
    sets, modes = args.sets.split(","), [int(m) for m in args.modes.split(",")]
    lines = [
        f"Command: `.venv/bin/python scripts/deform_ceiling.py --sets {args.sets} --modes {args.modes} "
        f"--true-pose {args.true_pose}`",
        "",
        "**The basis.** Held-out RMS misfit (mm) of the true marker displacements, fitted with a small rigid motion "
        "alone and with the rigid motion plus the stage's first m modes:",
        "",
        "| set | deformations | rigid alone | " + " | ".join(f"rigid + {m} modes" for m in modes) + " |",
        "|---|---|---|" + "---|" * len(modes),
    ]
    for name in sets:
        n, *values = basis_rows(name, modes)
        lines.append(f"| {name} | {int(n)} | " + " | ".join(f"{v:.2f}" for v in values) + " |")
    lines += [
        "",
        "**The stage from the true pose.** Mean RMS-TRE (mm), 2 mm noise, the stage at its defaults; "
        "`applied`: its share of the `bound+deform` poses:",
        "",
        "| set | bin | poses | oracle | oracle + stage | ICP from the true pose | that + stage | applied |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in sets:
        lines += [f"| {name} | " + " | ".join(cells) + " |" for cells in true_pose_rows(Path(args.true_pose) / name)]
    write_headline(lines[0], lines[2:], args.readme, MARK)  # printed, and written into --readme's block
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
