"""Latency of the learned matcher (features + network) and of learned-p2p end to end on 2 CPU threads.

Usage: .venv/bin/python scripts/bench_learned.py [--weights PATH] [--repeats 30] [--threads 2] [--device cpu]
Draws one phantom pair at visibility ~0.3 (N ~ 2000, M ~ 600 after voxelization) and prints medians.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time

import numpy as np
import torch

from liver_p2p_reg.config import Config
from liver_p2p_reg.phantom.loader import PairSampler, build_store
from liver_p2p_reg.registration.features.learned.provider import LearnedProvider
from liver_p2p_reg.registration.preprocess import preprocess_pair
from liver_p2p_reg.registration.registrar import Registrar


def write_reference(path: str, weights: str) -> None:
    """A small fixed input and the descriptors the weights give for it (test_learned_weights.py)."""
    rng = np.random.default_rng(2024)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    source = (d * np.array([0.9, 0.6, 0.45]) * (1 + 0.1 * np.sin(4 * d[:, :1]))).astype(np.float32)
    target = (source[source[:, 0] > 0.25] @ np.diag([1.0, -1.0, -1.0]).astype(np.float32)).astype(np.float32)
    xs, xt = LearnedProvider(weights_path=weights).describe(torch.as_tensor(source), torch.as_tensor(target), {})
    np.savez_compressed(path, source=source, target=target, x_source=xs.numpy(), x_target=xt.numpy())
    print(f"wrote {path}: source {source.shape}, target {target.shape}, d={xs.shape[1]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--visibility", type=float, default=0.3)
    ap.add_argument("--write-reference", metavar="NPZ", help="only write the weights test's reference output here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.write_reference:
        write_reference(args.write_reference, args.weights)
        return
    with tempfile.TemporaryDirectory() as tmp:
        store = build_store(tmp, livers=1, deformations=1, seed=3, target_tets=1500, progress=False)
        case = PairSampler(store, seed=0, visibility_range=(args.visibility, args.visibility)).sample()
    config = Config(device=args.device, weights_path=args.weights, num_threads=args.threads)
    prep = preprocess_pair(case["src_pcd"], case["tgt_pcd"], config)
    provider = LearnedProvider(weights_path=args.weights, device=args.device)
    src = torch.as_tensor(prep.source, dtype=torch.float32, device=args.device)
    tgt = torch.as_tensor(prep.target, dtype=torch.float32, device=args.device)

    def timed(fn, repeats: int) -> float:
        fn()  # warm-up
        out = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            if args.device == "cuda":
                torch.cuda.synchronize()
            out.append(1e3 * (time.perf_counter() - t))
        return statistics.median(out)

    cold = timed(lambda: provider.describe(src, tgt, {}), args.repeats)
    cache: dict = {}
    warm = timed(lambda: provider.describe(src, tgt, cache), args.repeats)
    reg = Registrar(config)
    e2e = timed(lambda: reg.register(case["src_pcd"], case["tgt_pcd"], method="learned-p2p"), args.repeats)
    print(
        json.dumps(
            {
                "n_source": len(prep.source),
                "n_target": len(prep.target),
                "threads": args.threads,
                "device": args.device,
                "describe_ms_median_cold_source": round(cold, 1),
                "describe_ms_median_cached_source": round(warm, 1),
                "register_learned_p2p_ms_median": round(e2e, 1),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
