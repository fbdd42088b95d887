"""Time the non-rigid stage's one-off model build per preop liver (tet mesh + stiffness + modes), 2 threads.

Usage: OMP_NUM_THREADS=2 .venv/bin/python scripts/bench_deform_build.py data/real-test-v2 [--readme docs/results/deformation.md]

Builds each liver's elastic model (the first case of each liver; the mesh's triangles where the case stores
them) three times with the default settings and reports the median, with the mesh sizes, as the block
DEFORM-BUILD of the readme file.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from liver_p2p_reg.bench.readme import replace_readme_block
from liver_p2p_reg.config import Config
from liver_p2p_reg.phantom.casefile import read_case, source_triangles
from liver_p2p_reg.registration.deform import elastic_model
from liver_p2p_reg.registration.threads import pin_threads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder")
    parser.add_argument("--readme")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    pin_threads(2)
    config = Config(deform=True)
    seen: set[int] = set()
    rows = []
    for path in sorted(Path(args.folder).glob("*.npz")):
        case = read_case(path)
        if case["liver_id"] in seen:
            continue
        seen.add(case["liver_id"])
        times, model = [], None
        for _ in range(args.repeats):
            start = time.perf_counter()
            model = elastic_model({}, case["src_pcd"], source_triangles(case), config)
            times.append((time.perf_counter() - start) * 1e3)
        assert model is not None
        n_tris = 0 if source_triangles(case) is None else len(source_triangles(case))
        rows.append(
            (case["liver_id"], len(case["src_pcd"]), n_tris, len(model.mesh.nodes_mm), statistics.median(times))
        )
        print(rows[-1], flush=True)
    lines = [
        f"Model build per liver (`scripts/bench_deform_build.py {args.folder}`; median of {args.repeats}, 2 threads, "
        f"{config.deform_modes} modes, {config.deform_target_tets} target tetrahedra):",
        "",
        "| liver | preop vertices | triangles | mesh nodes | build (ms) |",
        "|---|---|---|---|---|",
        *(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]:.0f} |" for r in rows),
        "",
        f"Largest: {max(r[4] for r in rows):.0f} ms (target: <= 10 s for a 20k-vertex mesh).",
    ]
    print("\n".join(lines))
    if args.readme:
        replace_readme_block(Path(args.readme), "\n".join(lines), "DEFORM-BUILD")


if __name__ == "__main__":
    main()
