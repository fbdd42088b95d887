"""Benchmark the P2P module alone (given features): median runtime vs K on N source / M target points.

Usage: python scripts/bench_p2p.py [--n 2000] [--m 500] [--d 32] [--threads 2] [--repeats 30]
Prints a table of median / p90 milliseconds for K = 1..8 (every patch row matched, no consensus twins),
for the complete-to-partial path alone, for K = 5 with the paper's matching and fit (mutual NN, no
robust re-fit) and for K = 5 with Config's defaults.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import numpy as np
import torch

from liver_p2p_reg.config import Config, P2PSection
from liver_p2p_reg.registration.p2p import p2p_register


def make_problem(n: int, m: int, d: int, seed: int) -> tuple[torch.Tensor, ...]:
    """A sphere-like source, a rigidly moved partial crop as target, noisy shared features."""
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(n, 3))
    source /= np.linalg.norm(source, axis=1, keepdims=True)
    crop = np.argsort(np.linalg.norm(source - source[0], axis=1))[:m]
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    target = source[crop] @ q.T + rng.normal(size=3) * 0.1
    feats = rng.normal(size=(n, d))
    x_source = feats / np.linalg.norm(feats, axis=1, keepdims=True)
    noisy = feats[crop] + 0.3 * rng.normal(size=(m, d))
    x_target = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
    return tuple(torch.as_tensor(a, dtype=torch.float32) for a in (source, target, x_source, x_target))


def table_settings(**changes: Any) -> P2PSection:
    """The rows' P2P settings: every patch row matched and no consensus twins (what this table has
    always measured), with `changes` on top."""
    return P2PSection(**{"max_patch_rows": 0, "consensus_seeds": 0, **changes})


def time_ms(settings: P2PSection, problem: tuple[torch.Tensor, ...], repeats: int) -> tuple[list[float], list[float]]:
    """Wall-clock and process-CPU milliseconds of `repeats` calls (after two warm-up calls).

    CPU time is reported too because a shared machine inflates wall time; with one thread
    CPU time is what the module would take on an idle core.
    """
    with torch.no_grad():
        for _ in range(2):
            p2p_register(*problem, settings)
        wall, cpu = [], []
        for _ in range(repeats):
            start, start_cpu = time.perf_counter(), time.process_time()
            p2p_register(*problem, settings)
            wall.append((time.perf_counter() - start) * 1e3)
            cpu.append((time.process_time() - start_cpu) * 1e3)
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="source points")
    parser.add_argument("--m", type=int, default=500, help="target points")
    parser.add_argument("--d", type=int, default=32, help="feature dimension")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    problem = make_problem(args.n, args.m, args.d, args.seed)
    print(f"N={args.n} M={args.m} d={args.d} threads={args.threads} repeats={args.repeats} torch {torch.__version__}")
    print(f"{'variant':<22}{'median ms':>10}{'p90 ms':>10}{'median cpu ms':>15}")
    rows = [("complete-to-partial", table_settings(k=0))]
    rows += [(f"p2p K={k}", table_settings(k=k)) for k in range(1, 9)]
    # the paper's module (mutual NN, one Procrustes per candidate) vs this project's default
    rows.append(("p2p K=5, paper's fit", table_settings(k=5, mutual_only=True, refit_iterations=0)))
    rows.append(("p2p K=5, Config's", Config().p2p))
    for name, settings in rows:
        wall, cpu = time_ms(settings, problem, args.repeats)
        p90 = sorted(wall)[int(0.9 * (len(wall) - 1))]
        print(f"{name:<22}{statistics.median(wall):>10.2f}{p90:>10.2f}{statistics.median(cpu):>15.2f}")


if __name__ == "__main__":
    main()
