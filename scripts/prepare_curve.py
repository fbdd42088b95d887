"""Accuracy versus patient-preparation minutes on the real-anatomy validation livers (issue 18).

    python scripts/prepare_curve.py --minutes 1,2,5,10 --livers 4 --out out/prepare_curve \
        --png docs/prepare/curve.png --readme README.md

For each budget M it runs `liver-p2p benchmark --dataset real-val-v1 --prepare-minutes M` (2 mm
noise added to every case, each liver prepared once and cached) on the first `--livers` livers
of the set, and tabulates, at visibility [0.2,0.3) with 2 mm noise and over all cases, the mean
RMS-TRE, its ratio to the oracle and success at 10 mm of the general and the prepared methods.
The table goes into the README's PREPARE block and the curve into a PNG.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

import numpy as np

CASES_PER_LIVER = 32  # real-val-v1: 4 deformations x 8 visibility bins
METHODS = ("procrustes", "learned-p2p", "learned-p2p-icp")


def run(minutes: float, args: argparse.Namespace) -> Path:
    out = Path(args.out) / f"{minutes:g}min"
    cmd = [sys.executable, "-m", "liver_p2p_reg", "-q", "benchmark", "--dataset", args.dataset]
    cmd += ["--methods", ",".join(METHODS), "--out", str(out), "--prepare-minutes", f"{minutes:g}"]
    cmd += ["--noise-levels", "2", "--noise-bins", "all", "--limit", str(args.livers * CASES_PER_LIVER)]
    cmd += ["--workers", str(args.workers)]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return out / "cases.csv"


def stats(path: Path) -> dict[str, dict[str, tuple[float, float, int]]]:
    """method -> {"low": (mean, success10, n), "all": (...)} on the 2 mm noise rows."""
    with open(path, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if float(r["added_noise_mm"] or 0) == 2.0 and not r["variant"]]
    out: dict[str, dict[str, tuple[float, float, int]]] = {}
    for method in sorted({r["method"] for r in rows}):
        mine = [r for r in rows if r["method"] == method]
        for part, sel in (("low", [r for r in mine if 0.2 <= float(r["visibility"]) < 0.3]), ("all", mine)):
            tre = np.array([float(r["rms_tre_mm"]) for r in sel])
            ok = np.array([float(r["rms_tre_mm"]) < 10 and r["failed"] != "true" for r in sel])
            out.setdefault(method, {})[part] = (float(tre.mean()), float(ok.mean()), len(sel))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", default="1,2,5,10")
    parser.add_argument("--livers", type=int, default=4, help="first N livers of the set")
    parser.add_argument("--dataset", default="real-val-v1")
    parser.add_argument("--out", default="out/prepare_curve")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--png", help="write the curve here")
    parser.add_argument("--readme", help="replace the README's PREPARE block with the table")
    args = parser.parse_args()
    # Run in the order given (the budget that matters most first: an interrupted run keeps its cache),
    # tabulate and plot in increasing order.
    results = {m: stats(run(m, args)) for m in [float(m) for m in args.minutes.split(",")]}
    budgets = sorted(results)
    header = "| preparation | method | mean RMS-TRE [0.2,0.3) 2 mm | / oracle | success < 10 mm [0.2,0.3) | mean all 2 mm | success < 10 mm all |"
    lines = [header, "|---|---|---|---|---|---|---|"]
    first = results[budgets[0]]
    oracle = first["procrustes"]["low"][0]
    for name in ("learned-p2p", "learned-p2p-icp"):
        low, everything = first[name]["low"], first[name]["all"]
        lines.append(
            f"| none (general weights) | {name} | {low[0]:.2f} | {low[0] / oracle:.2f} | {100 * low[1]:.1f} % "
            f"| {everything[0]:.2f} | {100 * everything[1]:.1f} % |"
        )
    for m in budgets:
        for name in ("learned-p2p[prepared]", "learned-p2p-icp[prepared]"):
            low, everything = results[m][name]["low"], results[m][name]["all"]
            lines.append(
                f"| {m:g} min | {name} | {low[0]:.2f} | {low[0] / oracle:.2f} | {100 * low[1]:.1f} % "
                f"| {everything[0]:.2f} | {100 * everything[1]:.1f} % |"
            )
    n_low = first["procrustes"]["low"][2]
    block = [
        f"`{args.dataset}`, first {args.livers} livers, 2 mm noise on every case ({n_low} cases at [0.2,0.3)); "
        f"oracle {oracle:.2f} mm there. Command: `python scripts/prepare_curve.py --minutes {args.minutes} "
        f"--livers {args.livers}`.",
        "",
        *lines,
    ]
    print("\n".join(block))
    if args.png:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
        from liver_p2p_reg.plotting import pyplot

        plt = pyplot()
        fig, ax = plt.subplots(figsize=(6, 4))
        for name, colour in (("learned-p2p", "tab:orange"), ("learned-p2p-icp", "tab:green")):
            ax.plot(budgets, [results[m][f"{name}[prepared]"]["low"][0] for m in budgets], "o-", color=colour,
                    label=f"{name} [prepared]")  # fmt: skip
            ax.axhline(first[name]["low"][0], color=colour, ls="--", label=f"{name} (general)")
        ax.axhline(oracle, color="black", ls=":", label="oracle")
        ax.set_xlabel("preparation per liver (min, 2 CPU cores)")
        ax.set_ylabel("mean RMS-TRE [0.2,0.3), 2 mm noise (mm)")
        ax.set_xscale("log")
        ax.set_xticks(budgets, [f"{m:g}" for m in budgets])
        ax.legend(fontsize=7)
        Path(args.png).parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(args.png, dpi=120)
    if args.readme:
        from liver_p2p_reg.bench.readme import replace_readme_block

        replace_readme_block(Path(args.readme), "\n".join(block), "PREPARE")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
