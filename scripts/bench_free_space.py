"""Time the free-space scoring per registration (its `runtime_ms.free_space` stage) on camera crops.

    LIVER_P2P_DATA=/work/data .venv/bin/python scripts/bench_free_space.py --threads 2

Registers the first N cases of a camera-crop set with their stored sensor origin and reports the
median / p95 / max of the free-space stage (the scorer: the view's depth image, then every
scored pose: P2P's candidates and twins, the ICP-screened ones and the final pose) and of the
whole registration. Run it on an idle machine: the numbers are wall clock.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from liver_p2p_reg.bench.cases import list_case_paths, read_case, resolve_dataset, sensor_origin_mm
from liver_p2p_reg.config import Config
from liver_p2p_reg.registration.registrar import Registrar


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="insilico-val-camera-v1")
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--method", default=Config().method)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    folder, _ = resolve_dataset(args.dataset, None)
    registrar = Registrar(Config(num_threads=args.threads))
    stage, total = [], []
    for k, path in enumerate(list_case_paths(folder)[: args.cases + 1]):
        case = read_case(path)
        result = registrar.register(
            case["src_pcd"], case["tgt_pcd"], method=args.method, sensor_origin_mm=sensor_origin_mm(case)
        )
        if k == 0:
            continue  # the first one loads the model
        stage.append(result.runtime_ms.get("free_space", float("nan")))
        total.append(result.runtime_ms["total"])
    for name, values in (("free_space", stage), ("total", total)):
        v = np.asarray(values)
        print(
            f"{name:>10}: median {np.median(v):.2f} ms, p95 {np.percentile(v, 95):.2f} ms, max {v.max():.2f} ms "
            f"({len(v)} registrations, {args.method}, {args.threads} threads)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
