"""Generate the bundled bags (bags/insilico_*, bags/phantom_sim_*) and bags/README.md's expected-results table.

    .venv/bin/python scripts/make_bags.py            # cases -> bags -> replay -> README table
    .venv/bin/python scripts/make_bags.py --readme-only   # re-measure the existing bags only

insilico_*: cases of the named test sets insilico-test-v1 / insilico-camera-v1 (the same liver ids,
deformations, targets and seeds as the generator's test sets), one with extra sensor noise.
phantom_sim_*: SIMULATED stand-ins for the paper's in vitro phantom data (no real phantom scans
ship with this package): stronger deformations, a few embedded markers, depth-sensor noise
with outliers and background, hand-drawn-looking selections of the liver in the camera image.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from liver_p2p_reg.bags.io import bag_size_bytes, read_messages
from liver_p2p_reg.bags.make import (
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    make_case_bag,
    make_sweep_bag,
)
from liver_p2p_reg.bags.replay import ReplayRow, replay_bag, replay_bags
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import rms_tre_mm, transform_points
from liver_p2p_reg.phantom.crop import camera_axes, camera_order, sample_surface, vertex_normals
from liver_p2p_reg.phantom.dataset import case_name, generate_dataset, liver_id_for, read_case, sensor_origin_mm
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.phantom.sweep import sweep_frames
from liver_p2p_reg.phantom.testset import testset_spec
from liver_p2p_reg.registration.baselines import kabsch_np
from liver_p2p_reg.registration.preprocess import statistical_inliers
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.registration.visibility import VisibilityMeter
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm
from liver_p2p_reg.stream.survey import FusedSurface

ROOT = Path(__file__).resolve().parents[1]
MAX_BAG_BYTES = 3_000_000
MAX_TOTAL_BYTES = 25_000_000
MAX_PREOP_POINTS = 20_000
MAX_INTRAOP_POINTS = 20_000
PHANTOM_SEED = 950  # liver ids 9_500_000 + i: reserved range, never used for training
PHANTOM_MARKERS = 8
# (test set, liver index, deformation, target, extra noise mm): visibility bins 0.2-1.0, both crops
INSILICO = (
    ("insilico-test-v1", 0, 0, 0, 0.0),
    ("insilico-test-v1", 0, 0, 2, 0.0),
    ("insilico-test-v1", 0, 1, 4, 0.0),
    ("insilico-test-v1", 1, 0, 7, 0.0),
    ("insilico-camera-v1", 0, 0, 0, 0.0),
    ("insilico-camera-v1", 0, 1, 1, 0.0),
    ("insilico-test-v1", 1, 1, 3, 3.0),
)
PHANTOMS = ((0, 0.30), (1, 0.40), (2, 0.35), (3, 0.45))  # (phantom liver index, visibility of the selection)
# Survey sweeps: (kind, liver index) -- an insilico-test-v1 liver (seed 900) and a new simulated phantom.
SWEEPS = (("insilico", 2), ("phantom", 4))
SWEEP_FRAMES = 70  # 14 s at 5 Hz
SWEEP_PERIOD_S = 0.2
SWEEP_MAX_POINTS = 3800  # per frame: the preop model's point density on the visible part
MAX_SWEEP_BYTES = 6_000_000


def insilico_cases() -> list[tuple[str, dict]]:
    """Cases of the named test sets, made by the generator itself (its first two livers only)."""
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for set_name in sorted({entry[0] for entry in INSILICO}):
            spec = testset_spec(set_name)
            spec.livers = 1 + max(e[1] for e in INSILICO if e[0] == set_name)  # same ids: seed*10000 + index
            generate_dataset(Path(tmp) / set_name, spec, workers=1, progress=True, allow_reserved_seed=True)
        for set_name, liver_index, d, t, noise_mm in INSILICO:
            spec = testset_spec(set_name)
            liver_id = liver_id_for(spec.seed, liver_index)
            case = read_case(Path(tmp) / set_name / case_name(liver_id, d, t))
            target, target_fid = case["tgt_pcd"], case["tgt_marker"]
            if noise_mm:  # the benchmark's noise model: uniform in [-noise/2, noise/2] per axis
                rng = np.random.default_rng([liver_id, d, t, 7])
                target = target + rng.uniform(-0.5, 0.5, target.shape) * noise_mm
            eye = sensor_origin_mm(case)
            if eye is not None:  # a camera view: its clouds in the camera's own frame, as a sensor sends them
                axes = camera_axes((target.mean(axis=0) - eye) / np.linalg.norm(target.mean(axis=0) - eye))
                target, target_fid = (target - eye) @ axes, (target_fid - eye) @ axes
            name = f"insilico_L{liver_id}_D{d:02d}_T{t:03d}_{spec.crop}" + (f"_noise{noise_mm:g}mm" if noise_mm else "")
            info = {
                "kind": "insilico",
                "test_set": set_name,
                "case": case_name(liver_id, d, t).removesuffix(".npz"),
                "crop": spec.crop,
                "visibility": round(float(case["visibility"]), 3),
                "noise_mm": float(noise_mm),
                "deformation_rms_mm": round(float(case["deformation_rms_mm"]), 2),
                "deformation_max_mm": round(float(case["deformation_max_mm"]), 2),
                "fiducials": len(case["src_marker"]),
                # random crops are no sensor's view: (0, 0, 0) of their frame is no sensor origin
                "sensor_frame": eye is not None,
            }
            out.append(
                (
                    name,
                    {
                        "source_mm": case["src_pcd"],
                        "target_mm": target,
                        "source_fiducials_mm": case["src_marker"],
                        "target_fiducials_mm": target_fid,
                        "info": info,
                    },
                )
            )
    return out


def farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """Indices of k well-spread points (start: the one nearest the centroid)."""
    chosen = [int(np.argmin(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    while len(chosen) < k:
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(sorted(chosen))


def phantom_shape(sim, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A simulated phantom's deformed surface and fiducials (mm) and the indices of its embedded markers."""
    dfm = sim.deformations[0]
    # Phantom deformations are stronger than the in silico ones (paper: mean 3-5 mm, max 10-24
    # mm); linear elasticity lets the FEM displacement be scaled to that range.
    disp_fid = dfm.fiducials_mm - sim.fiducials_mm
    norms = np.linalg.norm(disp_fid, axis=1)
    alpha = rng.uniform(3.3, 4.7) / norms.mean()
    alpha = min(alpha, 23.0 / norms.max())
    surface = sim.vertices_mm + alpha * (dfm.surface_mm - sim.vertices_mm)
    fids = sim.fiducials_mm + alpha * disp_fid
    return surface, fids, farthest_points(sim.fiducials_mm, PHANTOM_MARKERS)


def depth_sensor_noise(clean: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Points in the camera frame (mm) as a depth camera measures them: axial noise (along the ray)
    growing with depth, small lateral jitter, and 2 % flying pixels along their rays."""
    depth = np.linalg.norm(clean, axis=1, keepdims=True)
    rays = clean / depth
    noisy = clean + rays * rng.normal(0, 1, (len(clean), 1)) * (0.3 + 0.004 * depth) + rng.normal(0, 0.2, clean.shape)
    n_fly = int(0.02 * len(noisy))
    fly = rng.choice(len(noisy), n_fly, replace=False)
    noisy[fly] += rays[fly] * rng.uniform(-30, 30, (n_fly, 1))
    return noisy


def phantom_case(index: int, visibility_wanted: float) -> tuple[str, dict]:
    """A simulated in vitro phantom case seen by a depth camera and cropped by hand."""
    liver_id = PHANTOM_SEED * 10_000 + index
    rng = np.random.default_rng([liver_id, 77])
    sim = simulate_liver(liver_id, 1)
    surface, fids, markers = phantom_shape(sim, rng)
    pts = sample_surface(surface, sim.triangles, len(sim.vertices_mm), rng)
    normals = vertex_normals(surface, sim.triangles)[cKDTree(surface).query(pts)[1]]
    meter = VisibilityMeter(sim.vertices_mm)
    best = None
    for _ in range(20):  # camera poses until one sees enough of the liver (else the best seen)
        order, info = camera_order(pts, normals, rng)
        seen = meter(pts[order]) if len(order) else 0.0
        if best is None or seen > best[2]:
            best = (order, info, seen)
        if seen >= visibility_wanted + 0.03:
            break
    order, info, _ = best
    eye, look_at = info["eye_mm"], info["look_at_mm"]
    z_axis = (look_at - eye) / np.linalg.norm(look_at - eye)
    x_axis = np.cross([0.0, 0.0, 1.0], z_axis)
    x_axis /= np.linalg.norm(x_axis)
    axes = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)  # world -> camera rotation^T
    cam = (pts[order] - eye) @ axes
    # A hand-drawn selection in the image: a wobbly ellipse around the visible liver.
    u, v = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    cu, cv = np.median(u), np.median(v)
    theta = np.arctan2(v - cv, u - cu)
    phase = rng.uniform(0, 2 * np.pi, size=2)
    wobble = 1 + 0.15 * np.sin(3 * theta + phase[0]) + 0.07 * np.sin(5 * theta + phase[1])
    rho = np.hypot(u - cu, (v - cv) * rng.uniform(0.8, 1.25)) / wobble
    by_rho = cam[np.argsort(rho, kind="stable")]
    lo, hi = 100, len(by_rho)  # smallest selection reaching the requested visibility (or all visible)
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (mid + 1, hi) if meter(by_rho[:mid]) < visibility_wanted else (lo, mid)
    clean = by_rho[:lo]
    noisy = depth_sensor_noise(clean, rng)
    # Outliers: background tissue behind the liver inside the selection.
    n_bg = int(0.03 * len(noisy))
    pick = rng.choice(len(clean), n_bg)
    back = clean[pick] / clean[pick, 2:3] * (clean[:, 2].max() + rng.uniform(5, 25, (n_bg, 1)))
    target = np.vstack([noisy, back])[rng.permutation(len(noisy) + n_bg)]
    visibility = meter(clean)
    src_marker = sim.fiducials_mm[markers]
    tgt_marker = (fids[markers] - eye) @ axes
    disp = np.linalg.norm(fids[markers] - src_marker, axis=1)
    all_disp = np.linalg.norm(fids - sim.fiducials_mm, axis=1)
    info = {
        "kind": "phantom (simulated)",
        "phantom_liver": liver_id,
        "visibility": round(float(visibility), 3),
        "deformation_mean_mm": round(float(all_disp.mean()), 2),
        "deformation_max_mm": round(float(all_disp.max()), 2),
        "marker_displacement_mean_mm": round(float(disp.mean()), 2),
        "fiducials": PHANTOM_MARKERS,
        "outliers_share": 0.05,
        "camera_distance_mm": round(float(info["distance_mm"]), 1),
    }
    name = f"phantom_sim_{index + 1:02d}_vis{visibility:.2f}"
    return name, {
        "source_mm": sim.vertices_mm,
        "target_mm": target,
        "source_fiducials_mm": src_marker,
        "target_fiducials_mm": tgt_marker,
        "info": info,
    }


def sweep_case(kind: str, index: int) -> tuple[str, dict]:
    """A scope sweeping over the anterior surface: frames in the moving camera's frame, ground-truth fiducials per frame."""
    if kind == "insilico":
        liver_id = liver_id_for(testset_spec("insilico-test-v1").seed, index)
        sim = simulate_liver(liver_id, 1)
        surface, fids = sim.deformations[0].surface_mm, sim.deformations[0].fiducials_mm
        markers = np.arange(len(fids))
    else:
        liver_id = PHANTOM_SEED * 10_000 + index
        sim = simulate_liver(liver_id, 1)
        surface, fids, markers = phantom_shape(sim, np.random.default_rng([liver_id, 77]))
    rng = np.random.default_rng([liver_id, 88])
    pts = sample_surface(surface, sim.triangles, 2 * len(sim.vertices_mm), rng)
    normals = vertex_normals(surface, sim.triangles)[cKDTree(surface).query(pts)[1]]
    meter = VisibilityMeter(sim.vertices_mm)
    frames, frame_fids, seen, visibility = [], [], [], []
    for frame in sweep_frames(pts, normals, SWEEP_FRAMES, rng):
        idx = frame.visible
        if len(idx) > SWEEP_MAX_POINTS:
            idx = np.sort(rng.choice(idx, SWEEP_MAX_POINTS, replace=False))
        seen.append(idx)
        visibility.append(meter(pts[idx]))
        clean = (pts[idx] - frame.eye_mm) @ frame.axes
        frames.append(depth_sensor_noise(clean, rng) if kind == "phantom" else clean)
        frame_fids.append((fids[markers] - frame.eye_mm) @ frame.axes)
    union = meter(pts[np.unique(np.concatenate(seen))])
    disp = np.linalg.norm(fids - sim.fiducials_mm, axis=1)
    info = {
        "kind": "insilico sweep" if kind == "insilico" else "phantom sweep (simulated)",
        "liver": liver_id,
        "sweep": True,
        "sensor_frame": True,
        "visibility": round(float(np.median(visibility)), 3),
        "visibility_min": round(float(np.min(visibility)), 3),
        "visibility_max": round(float(np.max(visibility)), 3),
        "union_visibility": round(float(union), 3),
        "deformation_mean_mm": round(float(disp.mean()), 2),
        "deformation_max_mm": round(float(disp.max()), 2),
        "fiducials": len(markers),
        "noise": "depth camera + 2 % flying pixels" if kind == "phantom" else "none",
    }
    name = f"sweep_{'insilico' if kind == 'insilico' else 'phantom_sim'}_{liver_id}"
    return name, {
        "source_mm": sim.vertices_mm,
        "frames_mm": frames,
        "source_fiducials_mm": sim.fiducials_mm[markers],
        "frame_fiducials_mm": frame_fids,
        "info": info,
    }


def bound_mm(value: float) -> float:
    """Per-bag test bound: generous enough for platform float noise, tight enough to catch regressions."""
    return float(math.ceil(max(1.5 * value, value + 2.0)))


def write_readme(
    rows: list[ReplayRow], config: Config, out_dir: Path, max_frames: int, survey: list[tuple[ReplayRow, float, float]]
) -> Path:
    lines = [
        "# Bundled bags",
        "",
        "Generated by `.venv/bin/python scripts/make_bags.py` (bags and this file; `--readme-only` re-measures).",
        "Each bag is a rosbag2 directory (metadata.yaml + MCAP, Jazzy metadata version 9): `/preop/points`,",
        "`/preop/fiducials` (latched, frame `ct`), 5 `/intraop/points` frames 0.5 s apart with small sensor motion",
        "and `/intraop/fiducials` (ground truth, same stamps; frame `camera`), all in metres.",
        "Play one with `ros2 bag play bags/<name>`; replay all without ROS with `liver-p2p demo` or",
        "`liver-p2p replay bags/* --out out/replay`.",
        "",
        "- `insilico_*`: cases of the generator's named test sets `insilico-test-v1` (random crops) and",
        "  `insilico-camera-v1` (laparoscope-view crops): same liver ids, deformations, targets and seeds; one",
        "  with extra uniform sensor noise. Visibility 0.2-1.0.",
        "- `phantom_sim_*`: **simulated** stand-ins for the paper's in vitro phantom set (no real phantom data",
        "  ships here): deformations scaled to mean 3-5 mm / max 10-24 mm, 8 embedded markers, depth-camera noise",
        "  (axial 0.3 mm + 0.4 % of depth, lateral 0.2 mm), 2 % flying pixels and 3 % background points, and a",
        "  hand-drawn-looking selection of the liver in the image.",
        "- `sweep_*`: a laparoscope **sweeping** over the anterior surface for 14 s at 5 Hz (70 frames, each in the",
        "  moving camera's own frame, visibility 0.17-0.30 per frame, about 0.56-0.59 together), with ground-truth",
        "  fiducials per frame: an `insilico-test-v1` liver (no noise) and a simulated phantom (depth-camera noise and",
        "  2 % flying pixels). For survey mode (last table); the expected-results table replays them in continuous mode.",
        "",
        "Camera views (`*_camera`, `phantom_sim_*`, `sweep_*`) are in their camera's frame, so the node checks free",
        "space from (0, 0, 0); random crops are no camera's view and say so in their metadata (`sensor_frame: false`),",
        "which replay honours (live, give such clouds `sensor_at_frame_origin: false`).",
        "",
        f"## Expected results (method `{config.method}`, k = {config.k}, replay of all frames)",
        "",
        "Measured on the development machine with the command above. `bound` is what `test/test_ros_bundled_bags.py`",
        f"asserts on the worst frame's RMS-TRE when replaying the first {max_frames} frames of each bag.",
        "",
        "| bag | kind | visibility | deformation mean/max mm | frames | RMS-TRE mm (mean) | RMS-TRE mm (worst frame) | residual mm | uncertainty mm | runtime ms (p50) | status | bound mm | size MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        info = row.info
        dmean = info.get("deformation_mean_mm", info.get("deformation_rms_mm", float("nan")))
        lines.append(
            f"| {row.bag} | {info.get('kind', '?')} | {row.visibility:.2f} | {dmean:.1f}/{info.get('deformation_max_mm', float('nan')):.1f} "
            f"| {row.registered}/{row.frames} | {row.rms_tre_mm:.2f} | {row.max_rms_tre_mm:.2f} | {row.residual_mm:.2f} | {row.uncertainty_mm:.1f} "
            f"| {row.runtime_ms_p50:.0f} | {row.status} | {bound_mm(row.max_rms_tre_mm):.0f} | {bag_size_bytes(out_dir / row.bag) / 1e6:.2f} |"
        )
    runtimes = np.array([ms for row in rows for ms in row.runtime_ms])
    if len(runtimes):
        lines += [
            "",
            f"Per-frame register latency over all bundled frames ({len(runtimes)} registrations, "
            f"{sum(row.tracked for row in rows)} of them tracked from the previous pose): "
            f"p50 {np.percentile(runtimes, 50):.0f} ms, p95 {np.percentile(runtimes, 95):.0f} ms "
            "(`runtime_ms.total` of the core, this machine; `scripts/bench_node.py` also measures it without tracking).",
        ]
    flagged = [row for row in rows if row.status != "OK"]
    if flagged:
        lines += [
            "",
            "Why a bag is not OK: the node's diagnostic message on the first frame at the bag's worst status",
            "(the RMS-TRE in it is that frame's; the table gives the mean and the worst over the frames, and",
            "the overlay PNG of `liver-p2p demo` / `replay --plots` shows the last registered frame, named in its title):",
            "",
        ]
        lines += [
            f"- `{row.bag}`: {row.status} (frame {row.message_frame} of {row.frames}): {row.message}" for row in flagged
        ]
    if survey:
        lines += ["", *survey_table(survey, config)]
    lines.append("")
    path = out_dir / "README.md"
    path.write_text("\n".join(lines))
    return path


def sweep_bounds_mm(bag: Path, config: Config) -> tuple[float, float]:
    """A sweep's oracle (Procrustes on the first frame's ground-truth fiducials) and its surface bound: the
    RMS-TRE of ICP from the true pose on all its frames fused at their true poses (what the best possible
    tracking and fusion would leave to a rigid surface fit under the organ's deformation)."""
    messages = list(
        read_messages(bag, topics=[TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS, TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS])
    )
    by_topic: dict[str, list[np.ndarray]] = {}
    for item in messages:
        by_topic.setdefault(item.topic, []).append(cloud_to_points_mm(item.msg))
    preop, source = by_topic[TOPIC_PREOP][0], by_topic[TOPIC_PREOP_FIDUCIALS][0]
    frames, fiducials = by_topic[TOPIC_INTRAOP], by_topic[TOPIC_INTRAOP_FIDUCIALS]
    oracle = kabsch_np(source, fiducials[0])
    fused = FusedSurface(config.survey_voxel_mm, config.survey_max_points)
    for frame, fid in zip(frames, fiducials, strict=True):  # each frame placed by its own true pose
        frame = frame[statistical_inliers(frame, config.outlier_neighbors, config.outlier_std_ratio)]  # as survey.py
        fused.add(transform_points(np.linalg.inv(kabsch_np(source, fid)), frame))
    fit = Registrar(config).register(preop, fused.points, method="track", initial_T_mm=np.eye(4))
    truth = rms_tre_mm(oracle, source, fiducials[0])
    return truth, rms_tre_mm(oracle @ fit.T_target_source, source, fiducials[0])


def survey_rows(bags: list[Path], config: Config) -> list[tuple[ReplayRow, float, float]]:
    """Replay of each sweep bag in survey mode, with its oracle and surface-bound RMS-TRE."""
    sweeps = [b for b in bags if b.name.startswith("sweep_")]
    survey = config.replace(mode="survey")
    return [(replay_bag(b, survey), *sweep_bounds_mm(b, config)) for b in sweeps]


def survey_table(survey: list[tuple[ReplayRow, float, float]], config: Config) -> list[str]:
    """The survey table: RMS-TRE after the first frame, after 5 s and at the end, against the oracle."""
    lines = [
        f"## Survey mode on the sweep bags (`mode: survey`, method `{config.method}`, survey_step "
        f"{config.survey_step}, max_rate_hz {config.max_rate_hz})",
        "",
        "Each sweep bag replayed with `mode: survey` (same command). RMS-TRE of the pose published for the first",
        "registered frame, for the last frame at most 5 s after it, and for the last frame; the oracle is the",
        "Procrustes fit of the ground-truth fiducials (the deformation stays the same during a sweep); the surface",
        "bound is ICP from the true pose on every frame fused at its true pose (perfect tracking: what a rigid",
        "surface fit leaves under the organ's deformation); `fused visibility` is the fused surface's at the end;",
        "`worst fused frame` the largest RMS-TRE of the frames that tracking accepted into the fused surface.",
        "",
        "| sweep bag | frames registered | RMS-TRE first frame mm | after 5 s mm | end mm | oracle mm | end / oracle | "
        "surface bound mm | end / bound | fused visibility | global registrations | worst fused frame mm | "
        "survey state at the end |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row, oracle, bound in survey:
        frames = row.per_frame
        if not frames:
            lines.append(
                f"| `{row.bag}` | 0/{row.frames} | - | - | - | {oracle:.2f} | - | {bound:.2f} | - | - | - | - | {row.status} |"
            )
            continue
        start = frames[0]["stamp_ns"]
        at_5s = [f for f in frames if f["stamp_ns"] - start <= 5_000_000_000][-1]
        fused = [f["rms_tre_mm"] for f in frames if str(f.get("survey_state", "")).startswith("fusing")]
        end = frames[-1]
        last = row.per_frame[-1]
        lines.append(
            f"| `{row.bag}` | {row.registered}/{row.frames} | {frames[0]['rms_tre_mm']:.2f} | {at_5s['rms_tre_mm']:.2f} "
            f"| {end['rms_tre_mm']:.2f} | {oracle:.2f} | {end['rms_tre_mm'] / oracle:.2f} "
            f"| {bound:.2f} | {end['rms_tre_mm'] / bound:.2f} "
            f"| {float(last.get('survey_visibility', 'nan')):.2f} | {last.get('survey_registrations', '-')} "
            f"| {max(fused) if fused else float('nan'):.2f} | {str(last.get('survey_state', '-')).split(':')[0]} |"
        )
    return lines


def check_size(path: Path, info: dict, limit: int) -> None:
    """Report a written bag; one over its size budget stops the script."""
    size = bag_size_bytes(path)
    print(f"{path.name}: {size / 1e6:.2f} MB {info}", file=sys.stderr)
    if size > limit:
        raise SystemExit(f"{path.name} exceeds {limit} bytes")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "bags")
    parser.add_argument("--readme-only", action="store_true", help="do not regenerate the bags")
    parser.add_argument("--method", help="registration method for the expected results (default: Config's)")
    parser.add_argument("--bags-only", action="store_true", help="write the bags, skip the replay and README")
    parser.add_argument("--test-frames", type=int, default=1, help="frames the bundled-bag test replays")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    config = Config() if not args.method else Config(method=args.method)
    if not args.readme_only:
        for kind, index in SWEEPS:
            name, case = sweep_case(kind, index)
            path = make_sweep_bag(
                args.out / name,
                case.pop("source_mm"),
                case.pop("frames_mm"),
                overwrite=True,
                seed=len(name),
                frame_period_s=SWEEP_PERIOD_S,
                max_preop_points=MAX_PREOP_POINTS,
                **case,
            )
            check_size(path, case["info"], MAX_SWEEP_BYTES)
        cases = insilico_cases() + [phantom_case(i, share) for i, share in PHANTOMS]
        for name, case in cases:
            path = make_case_bag(
                args.out / name,
                case.pop("source_mm"),
                case.pop("target_mm"),
                overwrite=True,
                seed=len(name),
                # full resolution of the generator's clouds: the same point density in source and target
                # keeps the visibility estimate (M/N after voxelization) honest
                max_preop_points=MAX_PREOP_POINTS,
                max_intraop_points=MAX_INTRAOP_POINTS,
                **case,
            )
            check_size(path, case["info"], MAX_BAG_BYTES)
    bags = sorted(p for p in args.out.iterdir() if (p / "metadata.yaml").is_file())
    total = sum(bag_size_bytes(p) for p in bags)
    if total > MAX_TOTAL_BYTES:
        raise SystemExit(f"bags total {total} bytes > {MAX_TOTAL_BYTES}")
    if args.bags_only:
        return 0
    rows = replay_bags(bags, config, progress=True)
    survey = survey_rows(bags, config)
    print(write_readme(rows, config, args.out, args.test_frames, survey).read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
