"""Choose `uncertainty_warn_mm` on validation livers of the training store (never the test set).

Usage: .venv/bin/python scripts/calibrate_confidence.py [--store DIR] [--method learned-p2p-icp]

Draws pairs from the store's held-out validation livers (the last `val_livers` of config/train.yaml,
which training never sees), mostly at low visibility where poses go wrong: random crops at
[0.2,0.3) and [0.3,0.6), laparoscope crops at [0.2,0.4), random crops with 4 mm noise, and a few
near-complete views. Registers each with the method and prints, per candidate threshold, how
many poses off by > 20 mm the node would have warned about (residual, ambiguity or
uncertainty) and how many within 10 mm it would have warned about needlessly.
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np
import torch
import yaml

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.phantom.loader import PairSampler
from liver_p2p_reg.registration.confidence import pose_warnings
from liver_p2p_reg.registration.registrar import Registrar

# (visibility range, crop mode, noise mm, pairs, seed)
SETS = (
    ((0.2, 0.3), "random", 0.0, 80, 123),
    ((0.3, 0.6), "random", 0.0, 60, 125),
    ((0.2, 0.4), "camera", 0.0, 60, 126),
    ((0.2, 0.35), "random", 4.0, 60, 127),
    ((0.9, 1.0), "random", 0.0, 30, 124),
)
BAD_MM, GOOD_MM = 20.0, 10.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    train = yaml.safe_load(open("config/train.yaml"))
    ap.add_argument("--store", default=train["store_dir"])
    ap.add_argument("--val-livers", type=int, default=train["val_livers"])
    ap.add_argument("--method", default=Config().method)
    ap.add_argument("--thresholds", default="10,12,15,20,25")
    args = ap.parse_args()
    torch.set_num_threads(1)
    config = Config()
    rows = []  # (rms_tre_mm, uncertainty_mm, warned without the uncertainty rule)
    for (lo, hi), mode, noise, pairs, seed in SETS:
        sampler = PairSampler(
            args.store, seed=seed, visibility_range=(lo, hi), crop_modes=(mode,), noise_levels_mm=(noise,)
        )
        sampler.files = sampler.files[-args.val_livers :]  # validation livers only
        registrar = Registrar(config)
        for _ in range(pairs):
            case = sampler.sample()
            result = registrar.register(case["src_pcd"], case["tgt_pcd"], method=args.method)
            tre = rms_tre_mm(result.T_target_source, case["src_marker"], case["tgt_marker"])
            # the node's other WARN rules (residual, ambiguity): the uncertainty rule is what is being chosen
            reasons = pose_warnings(result.residual_mm, result.ambiguous, result.uncertainty_mm, config)
            other = bool(set(reasons) - {"uncertainty"})
            rows.append((tre, result.uncertainty_mm, other))
        print(f"{mode} [{lo}, {hi}) noise {noise:g} mm: {pairs} pairs", flush=True)
    tre = np.array([r[0] for r in rows])
    unc = np.array([r[1] for r in rows])
    other = np.array([r[2] for r in rows])
    bad, good = tre > BAD_MM, tre <= GOOD_MM
    print(
        f"\n{args.method}, {len(rows)} validation pairs: {bad.sum()} off by > {BAD_MM:g} mm, {good.sum()} within {GOOD_MM:g} mm"
    )
    print(
        f"uncertainty_mm median: poses within {GOOD_MM:g} mm {statistics.median(unc[good]):.1f}, "
        f"off by > {BAD_MM:g} mm {statistics.median(unc[bad]) if bad.any() else float('nan'):.1f}"
    )
    print(
        f"residual + ambiguity alone: warned {int((other & bad).sum())} of {bad.sum()} bad, {int((other & good).sum())} good\n"
    )
    print(f"| uncertainty_warn_mm | bad warned (of {bad.sum()}) | good warned (of {good.sum()}) | warned in all |")
    print("|---|---|---|---|")
    for threshold in (float(t) for t in args.thresholds.split(",")):
        warned = other | ~(unc <= threshold)
        print(
            f"| {threshold:g} | {int((warned & bad).sum())} | {int((warned & good).sum())} | {int(warned.sum())} / {len(rows)} |"
        )


if __name__ == "__main__":
    try:
        main()
    except LiverP2PError as exc:  # e.g. no store yet: one line, not a traceback
        raise SystemExit(f"calibrate_confidence: {exc}") from None
