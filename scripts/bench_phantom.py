"""Benchmark the phantom generator: seconds per liver + deformation, tetrahedra, deformation statistics."""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")  # the budget is per core

import numpy as np  # noqa: E402

from liver_p2p_reg.phantom.anatomy import make_liver  # noqa: E402
from liver_p2p_reg.phantom.dataset import make_case  # noqa: E402
from liver_p2p_reg.phantom.simulate import simulate_liver  # noqa: E402
from liver_p2p_reg.registration.visibility import VisibilityMeter  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--livers", type=int, default=5)
    parser.add_argument("--deformations", type=int, default=5, help="for the deformation statistics")
    parser.add_argument("--first-seed", type=int, default=500_000)
    parser.add_argument("--tets", type=int, default=10_000)
    args = parser.parse_args()
    one, one_cpu, anatomy_s, tets, nodes, rms, mx, rot, per_def, crop_s = [], [], [], [], [], [], [], [], [], []
    for i in range(args.livers):
        seed = args.first_seed + i
        t0 = time.perf_counter()
        c0 = time.process_time()  # CPU time: robust when other jobs share the cores
        liver = make_liver(seed)
        t1 = time.perf_counter()
        simulate_liver(seed, 1, target_tets=args.tets, liver=liver)
        t2 = time.perf_counter()
        one_cpu.append(time.process_time() - c0)
        anatomy_s.append(t1 - t0)
        one.append(t2 - t0)
        t3 = time.perf_counter()
        sim = simulate_liver(seed, args.deformations, target_tets=args.tets, liver=liver)
        per_def.append((time.perf_counter() - t3 - (t2 - t1)) / max(args.deformations - 1, 1))
        tets.append(sim.n_tets)
        nodes.append(sim.n_nodes)
        rms += [d.rms_mm for d in sim.deformations]
        mx += [d.max_mm for d in sim.deformations]
        rot += [d.rigid_rotation_deg for d in sim.deformations]
        meter = VisibilityMeter(sim.vertices_mm)
        for vis, mode in ((0.25, "random"), (0.95, "random"), (0.3, "camera")):
            t4 = time.perf_counter()
            make_case(sim, 0, vis, crop_mode=mode, seed=1, meter=meter)
            crop_s.append((mode, time.perf_counter() - t4))
    print(f"livers: {args.livers}, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}")
    print(f"anatomy (implicit + marching cubes + smoothing): {np.mean(anatomy_s):.2f} s/liver")
    print(f"one liver + one deformation (anatomy, tet mesh, FEM): mean {np.mean(one):.2f} s, max {np.max(one):.2f} s")
    print(f"  CPU time of the same: mean {np.mean(one_cpu):.2f} s, max {np.max(one_cpu):.2f} s")
    print(f"each further deformation: {np.mean(per_def):.2f} s")
    print(
        f"tetrahedra: mean {np.mean(tets):.0f} (min {np.min(tets)}, max {np.max(tets)}); nodes: mean {np.mean(nodes):.0f}"
    )
    for mode in ("random", "camera"):
        times = [t for m, t in crop_s if m == mode]
        print(f"one {mode} target (resample + crop to visibility + pose): {np.mean(times):.2f} s")
    rms, mx = np.array(rms), np.array(mx)
    print(
        f"fiducial RMS after rigid removal over {len(rms)} deformations: mean {rms.mean():.2f} mm,"
        f" median {np.median(rms):.2f}, p95 {np.percentile(rms, 95):.2f}, max {rms.max():.2f}"
    )
    print(f"max fiducial displacement: mean {mx.mean():.2f} mm, max {mx.max():.2f}")
    print(f"rigid rotation removed by Procrustes: mean {np.mean(rot):.2f} deg, max {np.max(rot):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
