"""Do two commits compute the same poses? Every method on fixed cases, this tree vs `--baseline`, bitwise.

    .venv/bin/python scripts/same_numbers.py --baseline ab216e0 [--bags 6]

A refactoring must not change a number. The cases (preop cloud, first intraop cloud, fiducials and
the true pose of each bundled bag) are read once with this tree's code; then each tree registers
them in a fresh process of this venv (the baseline from `git archive`, on PYTHONPATH), through the
public API only (`Registrar`, `available_methods`), with every method it has; `track` and
`evaluate` start from the true pose. The transforms, residuals and uncertainties are compared
bitwise: both runs are on this machine, so nothing may differ in any bit. Exit 1 on any difference.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys
import numpy as np
from liver_p2p_reg import Registrar, available_methods, LiverP2PError
cases = np.load(sys.argv[1], allow_pickle=False)
names = sorted({k.split("/")[0] for k in cases.files})
out = {}
registrar = Registrar()
for method in available_methods():
    for name in names:
        kw = {"source_fiducials_mm": cases[f"{name}/fid_s"], "target_fiducials_mm": cases[f"{name}/fid_t"]}
        if method in ("track", "evaluate"):
            kw["initial_T_mm"] = cases[f"{name}/T_true"]
        try:
            r = registrar.register(cases[f"{name}/source"], cases[f"{name}/target"], method=method, **kw)
        except LiverP2PError as exc:
            out[f"{method}|{name}|error"] = np.frombuffer(str(exc).encode(), dtype=np.uint8)
            continue
        out[f"{method}|{name}|T"] = r.T_target_source
        out[f"{method}|{name}|values"] = np.array([r.residual_mm, r.uncertainty_mm, float(r.ambiguous)])
np.savez(sys.argv[2], **out)
print(__import__("liver_p2p_reg").__file__, len(out))
"""


def extract_cases(n_bags: int, path: Path) -> None:
    """Preop, first intraop cloud, fiducials and the true pose of the first `n_bags` bundled bags -> one npz."""
    sys.path.insert(0, str(ROOT))
    try:
        from liver_p2p_reg.bags.io import read_messages
        from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm
    except ImportError:  # the layout before the move
        from liver_p2p_reg.bags.io import read_messages
        from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm

    wanted = ("/preop/points", "/intraop/points", "/preop/fiducials", "/intraop/fiducials")  # the clouds read here
    arrays = {}
    for bag in sorted(p for p in (ROOT / "bags").iterdir() if p.is_dir())[:n_bags]:
        first: dict[str, np.ndarray] = {}
        for m in read_messages(bag):
            if m.topic in wanted and m.topic not in first:
                first[m.topic] = cloud_to_points_mm(m.msg)
        arrays[f"{bag.name}/source"] = first["/preop/points"]
        arrays[f"{bag.name}/target"] = first["/intraop/points"]
        arrays[f"{bag.name}/fid_s"] = first["/preop/fiducials"]
        arrays[f"{bag.name}/fid_t"] = first["/intraop/fiducials"]
        arrays[f"{bag.name}/T_true"] = kabsch(first["/preop/fiducials"], first["/intraop/fiducials"])
    np.savez(path, **arrays)


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid 4x4 mapping src onto dst (paired rows), written out here so both trees get the same input."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    T = np.eye(4)
    T[:3, :3] = Vt.T @ D @ U.T
    T[:3, 3] = cd - T[:3, :3] @ cs
    return T


def run_tree(tree: Path, cases: Path, out: Path, threads: int) -> dict[str, np.ndarray]:
    """Register the cases with the package found in `tree` (a fresh process); its arrays."""
    env = {"PYTHONPATH": str(tree), "OMP_NUM_THREADS": str(threads), "PATH": "/usr/bin:/bin"}
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(cases), str(out)], env=env, capture_output=True, text=True, cwd=tree
    )
    if done.returncode != 0:
        sys.exit(f"error: the run in {tree} failed:\n{done.stderr[-2000:]}")
    print(f"{tree}: {done.stdout.strip()}")
    with np.load(out, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, help="the commit to compare with (e.g. the one before a move)")
    parser.add_argument("--bags", type=int, default=6, help="how many bundled bags give a case (first frame each)")
    parser.add_argument(
        "--threads", type=int, default=1, help="OMP_NUM_THREADS of both runs (Open3D's methods vary run to run with 2)"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        cases = tmp_path / "cases.npz"
        extract_cases(args.bags, cases)
        archive = subprocess.run(
            ["git", "-C", str(ROOT), "archive", args.baseline, "liver_p2p_reg"], check=True, capture_output=True
        ).stdout
        (tmp_path / "base.tar").write_bytes(archive)
        with tarfile.open(tmp_path / "base.tar") as tar:
            tar.extractall(tmp_path / "base", filter="data")
        new = run_tree(ROOT, cases, tmp_path / "new.npz", args.threads)
        old = run_tree(tmp_path / "base", cases, tmp_path / "old.npz", args.threads)
    methods = sorted({k.split("|")[0] for k in old} | {k.split("|")[0] for k in new})
    report, differing = {}, []
    for method in methods:
        keys = sorted(k for k in set(old) | set(new) if k.startswith(method + "|"))
        same = sum(k in old and k in new and old[k].tobytes() == new[k].tobytes() for k in keys)
        report[method] = f"{same}/{len(keys)} arrays bitwise equal"
        if same != len(keys):
            differing.append(method)
    print(
        json.dumps(
            {"baseline": args.baseline, "cases": args.bags, "threads": args.threads, "methods": report}, indent=1
        )
    )
    if differing:
        sys.exit(f"different: {', '.join(differing)}")


if __name__ == "__main__":
    main()
