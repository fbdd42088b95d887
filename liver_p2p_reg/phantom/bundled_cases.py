"""The cases of the bundled bags: test-set cases in their sensor's frame, simulated in vitro phantoms, scope sweeps.

insilico_*: cases of the named test sets insilico-test-v1 / insilico-camera-v1 (the same liver ids,
deformations, targets and seeds as the generator's test sets), one with extra sensor noise.
phantom_sim_*: SIMULATED stand-ins for the paper's in vitro phantom data (no real phantom scans
ship with this package): stronger deformations, a few embedded markers, depth-sensor noise
with outliers and background, hand-drawn-looking selections of the liver in the camera image.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from liver_p2p_reg.phantom.casefile import read_case, sensor_origin_mm, source_triangles
from liver_p2p_reg.phantom.crop import camera_axes, camera_order, sample_surface, vertex_normals
from liver_p2p_reg.phantom.dataset import case_name, generate_dataset, liver_id_for
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.phantom.sweep import sweep_frames
from liver_p2p_reg.phantom.testset import testset_spec
from liver_p2p_reg.registration.visibility import VisibilityMeter

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
SWEEP_MAX_POINTS = 3800  # per frame: the preop model's point density on the visible part


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
                        "source_triangles": source_triangles(case),  # the preop mesh (bags: /preop/mesh)
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
        "source_triangles": sim.triangles,
        "target_mm": target,
        "source_fiducials_mm": src_marker,
        "target_fiducials_mm": tgt_marker,
        "info": info,
    }


def sweep_views(
    surface_mm: np.ndarray,
    triangles: np.ndarray,
    n_points: int,
    fiducials_mm: np.ndarray,
    n_frames: int,
    rng: np.random.Generator,
    *,
    noisy: bool,
) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """A scope sweeping over a (deformed) surface: the dense surface sample, each frame's points (at most
    SWEEP_MAX_POINTS, with depth-camera noise when `noisy`) and fiducials in that moment's camera frame, and the
    sample's indices each frame saw."""
    pts = sample_surface(surface_mm, triangles, n_points, rng)
    normals = vertex_normals(surface_mm, triangles)[cKDTree(surface_mm).query(pts)[1]]
    frames, frame_fids, seen = [], [], []
    for frame in sweep_frames(pts, normals, n_frames, rng):
        idx = frame.visible
        if len(idx) > SWEEP_MAX_POINTS:
            idx = np.sort(rng.choice(idx, SWEEP_MAX_POINTS, replace=False))
        seen.append(idx)
        clean = (pts[idx] - frame.eye_mm) @ frame.axes
        frames.append(depth_sensor_noise(clean, rng) if noisy else clean)
        frame_fids.append((fiducials_mm - frame.eye_mm) @ frame.axes)
    return pts, frames, frame_fids, seen


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
    n_points = 2 * len(sim.vertices_mm)
    pts, frames, frame_fids, seen = sweep_views(
        surface, sim.triangles, n_points, fids[markers], SWEEP_FRAMES, rng, noisy=kind == "phantom"
    )
    meter = VisibilityMeter(sim.vertices_mm)
    visibility = [meter(pts[idx]) for idx in seen]
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
        "source_triangles": sim.triangles,
        "frames_mm": frames,
        "source_fiducials_mm": sim.fiducials_mm[markers],
        "frame_fiducials_mm": frame_fids,
        "info": info,
    }
