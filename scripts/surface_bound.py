"""What a rigid surface fit can reach under the organ's deformation: ICP started from the true pose, per visibility bin.

    LIVER_P2P_DATA=/work/data .venv/bin/python scripts/surface_bound.py --dataset insilico-val-camera-v1

For every case: the Procrustes oracle (fiducials) and the trimmed ICP of the configured
refinement started from the oracle pose (method `track`): the local surface optimum next to the
truth. No selection rule, free-space term or better matcher gets a rigid surface registration
below it on average; its ratio to the oracle is the floor of "mean / oracle" for the `-icp` methods.
"""

from __future__ import annotations

import argparse

import numpy as np

from liver_p2p_reg.bench.cases import BIN_LABELS, list_case_paths, read_case, resolve_dataset, visibility_bin
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.registration.baselines import kabsch_np
from liver_p2p_reg.registration.registrar import Registrar


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="insilico-val-camera-v1")
    args = parser.parse_args(argv)
    folder, _ = resolve_dataset(args.dataset, None)
    registrar = Registrar(Config())
    per_bin: dict[int, list[tuple[float, float]]] = {}
    for path in list_case_paths(folder):
        case = read_case(path)
        fid_s, fid_t = np.asarray(case["src_marker"], float), np.asarray(case["tgt_marker"], float)
        truth = kabsch_np(fid_s, fid_t)
        fit = registrar.register(case["src_pcd"], case["tgt_pcd"], method="track", initial_T_mm=truth)
        b = visibility_bin(float(case["visibility"]))
        if b is not None:
            per_bin.setdefault(b, []).append(
                (rms_tre_mm(truth, fid_s, fid_t), rms_tre_mm(fit.T_target_source, fid_s, fid_t))
            )
    print(f"{args.dataset}: mean RMS-TRE (mm) of the oracle and of ICP from the true pose")
    print("| bin | cases | oracle | ICP from the true pose | ratio |")
    print("|---|---|---|---|---|")
    for b in sorted(per_bin):
        oracle, icp = np.mean(per_bin[b], axis=0)
        print(f"| {BIN_LABELS[b]} | {len(per_bin[b])} | {oracle:.2f} | {icp:.2f} | {icp / oracle:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
