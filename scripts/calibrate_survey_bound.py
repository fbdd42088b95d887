"""Survey mode's error bounds: split-conformal quantiles on survey-mode frames of validation sweeps, judged on test
sweeps; of the deformed positions where the stage fitted the fused survey (`--positions deformed`), or of the rigid
pose of the frames tracked on the fused survey (`--positions rigid`).

    .venv/bin/python scripts/calibrate_survey_bound.py [--positions deformed] [--frames 70] [--out out/survey_bound] \
        [--write liver_p2p_reg/weights/error_bound_deformed_survey_v1.json] [--readme docs/results/survey_deform.md]
    .venv/bin/python scripts/calibrate_survey_bound.py --positions rigid \
        [--write liver_p2p_reg/weights/error_bound_survey_v1.json] [--readme docs/results/survey_deform.md]

Why: the stage on a fused survey is far more accurate than on one view, and the frame's pose evidence does not
show it: the single-view calibration's bound (`error_bound_deformed_v1.json`) over-covers those fits (the judged
table's `single views` rows). The same holds for the rigid pose of a frame tracked on the fused survey (method
`evaluate`, scored on the frame alone): the single-view `error_bound_v1.json` over-covered it.

Calibration: the deformed calibration's livers of the validation split (those that calibrated its quantiles, not
those that fitted its scale model: 4 real, 3 procedural), two FEM deformations each, one simulated 70-frame sweep per
deformation (`survey_real_sweeps.real_sweep`'s camera, depth noise, flying pixels), fed to the node core in survey
mode with the stage fitting the fused survey. Every frame where the stage was applied to the survey is one pose
(rigid: every frame whose pose was tracked on the fused survey, the stage off: the same poses);
the scale model (its coefficients) is the single-view calibration's, unchanged; the quantiles are new, one group (the
frame's own visibility does not tell how much of the organ the survey holds), each sweep weighing the same.
Judged: the 8 real test livers, one deformation per family (FEM and ARAP, which the stage does not model), the
same sweeps as `survey_real_sweeps.py`; the single-view bound beside the survey bound.
Collections are cached under --out, in a subfolder named by a hash of the survey settings, the weights and the
features with what they are computed with: a change of any is collected anew (or delete a folder to collect it anew).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
from survey_real_sweeps import liver_sweeps, survey_outputs  # the same sweeps and node runs
from tqdm import tqdm

from liver_p2p_reg.bench import bound_data
from liver_p2p_reg.bench.bound_fit import COVERAGES, conformal_quantile, coverage_at, scores
from liver_p2p_reg.bench.readme import write_headline
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import transform_points
from liver_p2p_reg.phantom.real import load_real_liver, real_split
from liver_p2p_reg.registration.error_bound import EVIDENCE_SETTINGS, FEATURES, INTERIOR_STAND_IN
from liver_p2p_reg.registration.error_calibration import (
    BUNDLED_CALIBRATION,
    BUNDLED_DEFORMED_CALIBRATION,
    BUNDLED_SURVEY_CALIBRATION,
    BUNDLED_SURVEY_RIGID_CALIBRATION,
    DEFORMED,
    RIGID,
    SURVEY,
    SURVEY_TRACKED_METHOD,
    deform_settings,
    pose_settings,
    read_calibration,
)
from liver_p2p_reg.registration.weights_id import weights_sha256

# per kind of positions: the single-view calibration it starts from, the survey one it writes, its results block,
# and the prefix of its cached collections
POSITIONS = {
    DEFORMED: (BUNDLED_DEFORMED_CALIBRATION, BUNDLED_SURVEY_CALIBRATION, "SURVEY-BOUND", ""),
    RIGID: (BUNDLED_CALIBRATION, BUNDLED_SURVEY_RIGID_CALIBRATION, "SURVEY-RIGID-BOUND", "rigid_"),
}
DEFORMATIONS_PER_LIVER = 2  # calibration sweeps per validation liver


def survey_poses(sweep: dict, sweep_id: int, positions: str = DEFORMED) -> list[dict]:
    """Per frame where the stage fitted the fused survey (rigid: per frame tracked on the fused survey): the
    positions' errors at the interior markers and the bound's features there (the frame's pose evidence), as
    `bound_data` rows."""
    rows = []
    for k, output, fid_t in survey_outputs(sweep, fused=True, deform=positions == DEFORMED):
        result = output.result
        if positions == RIGID:
            if result.method != SURVEY_TRACKED_METHOD or result.error_model is None:
                continue
            moved = transform_points(result.T_target_source, sweep["fiducials"])
        elif output.deformed_preop_mm is None or output.diagnostics[0].values.get("deform_view") != SURVEY:
            continue
        else:
            moved = result.deformation.deformed_position_mm(sweep["fiducials"])
        err = np.linalg.norm(moved - fid_t, axis=1)
        rows.append(
            {
                "case_id": f"{sweep_id}:{k}",
                "liver_id": sweep["liver_id"],
                "visibility": float(result.visibility),
                "method_visibility": float(result.visibility),
                "ok": True,
                "reasons": "",
                "bound_ms": np.nan,
                "deform_applied": positions == DEFORMED,
                "errors": err,
                "features": result.error_model.evidence.features(sweep["fiducials"]),
                "interior_features": bound_data.interior_features(result.error_model.evidence),
                "rms_mm": float(np.sqrt(np.mean(err**2))),
            }
        )
    return rows


def evidence_stamp(deformed: bool) -> str:
    """The cache's subfolder: a hash of what the collected poses depend on besides the sweeps (the survey settings,
    the weights, the features and what they are computed with), so a change of any is collected again."""
    config = Config(mode="survey", deform=deformed)
    key = json.dumps([config.to_dict(), weights_sha256(config), FEATURES, EVIDENCE_SETTINGS])
    return hashlib.sha256(key.encode()).hexdigest()[:16]


def collect(path: Path, livers: list[int], family: str, n_deformations: int, n_frames: int, positions: str) -> dict:
    """The survey poses of every sweep over `livers` (cached at `path`), with `sweep` (its index) per pose."""
    if path.exists():
        cached = bound_data.load_cached(path)  # one made before a key was added is collected again
        if cached is not None and "sweep" in cached:
            return cached
    rows, sweep_of, n_sweeps = [], [], 0
    for liver_id in tqdm(livers, desc=f"{path.stem}", unit="liver"):
        for sweep in liver_sweeps(liver_id, family, n_deformations, n_frames):
            poses = survey_poses(sweep, n_sweeps, positions)
            rows += poses
            sweep_of += [n_sweeps] * len(poses)
            n_sweeps += 1
    data = bound_data.stack_rows(rows, f"{path.stem}", 2.0)
    data["sweep"] = np.asarray(sweep_of, np.int64)
    return bound_data.load(bound_data.save(path, data))


def sweep_weights(data: dict) -> np.ndarray:
    """Per pose 1 / (its sweep's poses): each sweep weighs the same, however many of its frames were fused."""
    counts = np.bincount(data["sweep"])
    return 1.0 / counts[data["sweep"]]


def fit(data: dict, single: dict) -> dict:
    """The survey calibration (JSON-ready): the single-view calibration with one group's new quantiles."""
    coef = np.asarray(single["coefficients"], float)
    point, pose = scores(data, coef)
    w_pose = sweep_weights(data)
    w_point = np.repeat(w_pose / data["count"], data["count"])
    n = len(pose)
    deformed = single.get("positions") == DEFORMED
    config = Config(mode="survey", deform=deformed)  # what the sweeps ran with (survey_outputs)
    out = dict(single)
    out.update(
        {
            "method": config.method,
            "weights_sha256": weights_sha256(config),
            "pose": pose_settings(config),
            **({"deform": deform_settings(config)} if deformed else {}),
            "left_out_failed_poses": 0,  # a frame without a pose has no survey fit to bound
            "visibility_edges": [],
            "point_quantiles": [[conformal_quantile(point, w_point, c, n) for c in COVERAGES]],
            "pose_quantiles": [[conformal_quantile(pose, w_pose, c, n) for c in COVERAGES]],
            "calibration_poses_per_group": [n],
            "calibration_livers": sorted({int(v) for v in data["liver_id"]}),
            "view": SURVEY,
            "pose_interior": INTERIOR_STAND_IN,  # its pose scores are over the stand-in (bound_fit.scores)
        }
    )
    out.pop("fit_livers", None)
    return out


def judged(data: dict, calibration, coverage: float = 0.9) -> tuple[float, tuple[float, float], float, float, float]:
    """Marker coverage and its 95 % bootstrap interval over sweeps (frames of one sweep are not independent), pose
    (interior RMS) coverage, median pose bound and median interior RMS error (mm); each sweep weighs the same."""
    point_bound, pose_bound = coverage_at(data, calibration, coverage)
    inside = np.bincount(bound_data.pose_index(data), data["errors"] <= point_bound) / data["count"]
    per_sweep = np.array([inside[data["sweep"] == k].mean() for k in np.unique(data["sweep"])])
    rng = np.random.default_rng(0)
    boot = per_sweep[rng.integers(0, len(per_sweep), size=(2000, len(per_sweep)))].mean(axis=1)
    w = sweep_weights(data)
    return (
        float(per_sweep.mean()),
        (float(np.quantile(boot, 0.025)), float(np.quantile(boot, 0.975))),
        float(np.sum(w * (data["rms_mm"] <= pose_bound)) / w.sum()),
        float(np.median(pose_bound)),
        float(np.median(data["rms_mm"])),
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--positions", choices=sorted(POSITIONS), default=DEFORMED)
    parser.add_argument("--frames", type=int, default=70)
    parser.add_argument("--out", default="out/survey_bound", help="cache of the collected poses")
    parser.add_argument("--write", help="write the calibration JSON here (the bundled file is the default's)")
    parser.add_argument("--readme", help="write the judgement block into this markdown file")
    args = parser.parse_args(argv)
    single_path, bundled, mark, prefix = POSITIONS[args.positions]
    deformed = args.positions == DEFORMED
    single = json.loads(Path(single_path).read_text())
    out = Path(args.out) / evidence_stamp(deformed)
    cal = collect(
        out / f"{prefix}val_fem_{args.frames}.npz",
        [int(v) for v in single["calibration_livers"]],
        "fem",
        DEFORMATIONS_PER_LIVER,
        args.frames,
        args.positions,
    )
    survey = fit(cal, single)
    survey["provenance"] = {
        "summary": (
            f"survey-mode fits of {len(set(cal['sweep'].tolist()))} simulated {args.frames}-frame sweeps (FEM, "
            f"{DEFORMATIONS_PER_LIVER} per validation liver of the {'deformed ' if deformed else ''}calibration's "
            f"quantile half: {survey['calibration_livers']}), {len(cal['count'])} frames "
            + ("where the stage fitted the fused survey" if deformed else "tracked on the fused survey")
            + f"; scale model of {Path(single_path).name}"
        ),
        "command": "scripts/calibrate_survey_bound.py" + ("" if deformed else " --positions rigid"),
        "date": time.strftime("%Y-%m-%d", time.gmtime()),
    }
    if args.write:
        Path(args.write).write_text(json.dumps(survey, indent=1) + "\n")
    test_ids = [load_real_liver(s).seed for s in real_split()["test"]]
    new = read_calibration(args.write) if args.write else read_calibration("", bundled)
    old = read_calibration("", single_path)
    lines = [
        "Command: `.venv/bin/python scripts/calibrate_survey_bound.py"
        + ("" if deformed else " --positions rigid")
        + f" --frames {args.frames}"
        + (f" --write {args.write}" if args.write else "")
        + "`",
        "",
        f"Calibrated on {survey['provenance']['summary']}; 90 % quantiles: point {survey['point_quantiles'][0][1]:.2f}, "
        f"interior {survey['pose_quantiles'][0][1]:.2f} (the single-view calibration's: "
        f"{', '.join(f'{q[1]:.2f}' for q in single['pose_quantiles'])} per visibility group).",
        "",
        f"Judged on the {len(test_ids)} real test livers, one sweep per family ("
        + (
            "the frames where the stage fitted the fused survey"
            if deformed
            else "the frames tracked on the fused survey"
        )
        + "); 90 % bound, each sweep weighing the same:",
        "",
        "| family | frames | bound | marker coverage [95 % interval over sweeps] | interior coverage | median bound "
        "| median interior error | ratio |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for family in ("fem", "arap"):
        data = collect(
            out / f"{prefix}test_{family}_{args.frames}.npz", test_ids, family, 1, args.frames, args.positions
        )
        for name, calibration in (("single views", old), ("survey", new)):
            point_cov, (lo, hi), pose_cov, bound, err = judged(data, calibration)
            lines.append(
                f"| {family.upper()} | {len(data['count'])} | {name} | {100 * point_cov:.1f} % [{100 * lo:.1f}, "
                f"{100 * hi:.1f}] | {100 * pose_cov:.1f} % | {bound:.2f} mm | {err:.2f} mm | {bound / err:.2f} |"
            )
    write_headline(lines[0], lines[2:], args.readme, mark)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
