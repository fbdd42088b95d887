"""Survey mode with the non-rigid stage on simulated sweeps over real test livers: the node core's own tracking.

    .venv/bin/python scripts/survey_real_sweeps.py [--families fem,arap] [--frames 70] \
        [--readme docs/results/survey_deform.md]

For each test liver of the real split and each deformation family: one deformation (the test sets' generator,
`simulate_liver`), and a laparoscope sweeping over its anterior surface as the bundled sweep bags do
(`bundled_cases.sweep_views`: depth-camera noise and 2 % flying pixels, at most 3800 points per frame; --frames
of them).
The frames are fed to the node core (`NodeCore`, survey mode, the default method, `deform` on, the preop mesh
given) once with the stage fitting the frame and once fitting the fused survey (`survey_deform_fused`).
Unlike scripts/survey_deform.py, tracking here is survey mode's own, not perfect. Reported per family: mean
interior RMS-TRE over all frames and over the last 10 of each sweep, of the rigid pose, of the stage on the frame
and on the fused survey (the rigid error where the stage was not applied), the oracle, and the frames a good
rigid pose (< 10 mm) was made worse by more than 1 mm. A sweep whose tracking fails stops fusing (survey mode's
rule); its later frames are registered one by one and the stage fits each frame, in both runs.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator

import numpy as np
from tqdm import tqdm

from liver_p2p_reg.bench.readme import write_headline
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.phantom.bundled_cases import sweep_views
from liver_p2p_reg.phantom.real import load_real_liver, real_split
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration.baselines import kabsch_np
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.outputs import CoreOutput

MARK = "SURVEY-REAL-SWEEPS"


def liver_sweeps(liver_id: int, family: str, n_deformations: int, n_frames: int) -> list[dict]:
    """One deformed liver (a real one of the val or test split by its seed, else procedural), one sweep over each of
    its deformations: the preop mesh and fiducials, each frame and its fiducials (camera frame), its `liver_id`."""
    stems = {load_real_liver(s).seed: s for s in real_split()["val"] + real_split()["test"]}
    liver = load_real_liver(stems[liver_id]) if liver_id in stems else None
    sim = simulate_liver(liver_id, n_deformations, target_tets=10_000, liver=liver, family=family)
    sweeps = []
    for d, deformation in enumerate(sim.deformations):
        # one deformation: the sweep this script has always made of that liver; more: a sweep path of each
        rng = np.random.default_rng([liver_id, 88] if n_deformations == 1 else [liver_id, 88, d])
        _, frames, frame_fids, _ = sweep_views(
            deformation.surface_mm,
            sim.triangles,
            2 * len(sim.vertices_mm),
            deformation.fiducials_mm,
            n_frames,
            rng,
            noisy=True,
        )
        sweeps.append(
            {
                "liver_id": liver_id,
                "vertices": sim.vertices_mm,
                "triangles": sim.triangles,
                "fiducials": sim.fiducials_mm,
                "frames": frames,
                "frame_fiducials": frame_fids,
            }
        )
    return sweeps


def real_sweep(stem: str, family: str, n_frames: int) -> dict:
    """One deformed real liver and a sweep over it: preop mesh and fiducials, frames and their fiducials (camera)."""
    return liver_sweeps(load_real_liver(stem).seed, family, 1, n_frames)[0]


def survey_outputs(sweep: dict, fused: bool, deform: bool = True) -> Iterator[tuple[int, CoreOutput, np.ndarray]]:
    """Each frame that got a pose from the node core (survey mode, `deform` on, the stage fitting the fused survey or
    the frame; with `deform` off the same rigid poses): its index, the output and the frame's true fiducials."""
    core = NodeCore(Config(mode="survey", deform=deform, survey_deform_fused=fused))
    core.set_preop_mesh(sweep["vertices"], sweep["triangles"], "ct", 5)
    core.set_preop(sweep["vertices"], "ct", 5)
    core.set_preop_fiducials(sweep["fiducials"], 5)
    for k, (points, fid_t) in enumerate(zip(sweep["frames"], sweep["frame_fiducials"], strict=True)):
        stamp = 1_000 + k
        core.set_intraop_fiducials(fid_t, stamp)
        core.on_intraop_points(points, "camera", stamp)
        output = core.process_pending(float(k))
        if output is not None and output.pose is not None:
            yield k, output, fid_t


def replay_sweep(sweep: dict, fused: bool) -> np.ndarray:
    """Per frame that got a pose: oracle, rigid and after-the-stage interior RMS-TRE (mm), and 1 while the survey fused."""
    rows = []
    for _, output, fid_t in survey_outputs(sweep, fused):
        result = output.result
        rigid = result.rms_tre_mm
        applied = output.deformed_preop_mm is not None
        oracle = rms_tre_mm(kabsch_np(sweep["fiducials"], fid_t), sweep["fiducials"], fid_t)
        fusing = output.diagnostics[0].values.get("survey_state") == "fusing"
        rows.append((oracle, rigid, result.deformed_rms_tre_mm if applied else rigid, fusing))
    return np.asarray(rows, float)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", default="fem,arap")
    parser.add_argument("--frames", type=int, default=70, help="frames per sweep (as the bundled sweeps: 14 s at 5 Hz)")
    parser.add_argument("--readme", help="write the block into this markdown file")
    args = parser.parse_args(argv)
    stems = real_split()["test"]
    lines = [
        f"Command: `.venv/bin/python scripts/survey_real_sweeps.py --families {args.families} --frames {args.frames}`",
        "",
        f"{len(stems)} real test livers per family, one sweep of {args.frames} frames each; interior RMS-TRE (mm), "
        "mean over the frames that got a pose, and over the last 10 of each sweep:",
        "",
        "| family | frames | fused (survey state `fusing`) | oracle | rigid (survey mode) | stage on the frame | stage on "
        "the fused survey | last 10: rigid | last 10: frame | last 10: fused survey | harmed: frame / fused |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for family in args.families.split(","):
        per = {False: [], True: []}
        for stem in tqdm(stems, desc=family, unit="liver"):
            sweep = real_sweep(stem, family, args.frames)
            for fused in (False, True):
                per[fused].append(replay_sweep(sweep, fused))
        frame_rows, fused_rows = np.concatenate(per[False]), np.concatenate(per[True])
        last = {f: np.concatenate([r[-10:] for r in per[f]]) for f in per}

        def harmed(rows: np.ndarray) -> int:
            return int(((rows[:, 1] < 10.0) & (rows[:, 2] > rows[:, 1] + 1.0)).sum())

        lines.append(
            f"| {family} | {len(fused_rows)} | {100 * fused_rows[:, 3].mean():.0f} % | {fused_rows[:, 0].mean():.2f} | {fused_rows[:, 1].mean():.2f} | "
            f"{frame_rows[:, 2].mean():.2f} | {fused_rows[:, 2].mean():.2f} | {last[True][:, 1].mean():.2f} | "
            f"{last[False][:, 2].mean():.2f} | {last[True][:, 2].mean():.2f} | "
            f"{harmed(frame_rows)} / {harmed(fused_rows)} |"
        )
    write_headline(lines[0], lines[2:], args.readme, MARK)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
