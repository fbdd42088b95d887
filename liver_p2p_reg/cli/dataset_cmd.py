"""`liver-p2p dataset`: generate in silico registration cases, a training store, or named test sets; print statistics."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from liver_p2p_reg.cli.output_paths import output_file
from liver_p2p_reg.errors import InputError

# what matplotlib writes (its suffix picks the format)
PICTURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".eps", ".ps", ".tif", ".tiff", ".webp")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("dataset", help="generate in silico liver datasets and print their statistics")
    sub = p.add_subparsers(dest="dataset_command", metavar="ACTION")
    g = sub.add_parser(
        "generate",
        help="generate cases (one NPZ each + manifest.csv), a training store (--store) or a named test set (--testset)",
    )
    g.add_argument("--out", help="output directory for cases (or the data root with --testset)")
    g.add_argument("--store", help="build a training store of livers + deformations here (for PairSampler) instead")
    g.add_argument(
        "--testset",
        help="generate a named set: insilico-test-v1, insilico-camera-v1, insilico-smoke (test); "
        "insilico-val-v1, insilico-val-camera-v1 (validation, for tuning); real-val-v1, real-val-camera-v1, "
        "real-val-density-v1 and real-test-* (real CT livers, built from ../shared/data/livers); the v2 sets "
        "reach down to visibility 0.05: insilico-{val,test}[-camera]-v2, real-{val,test}[-camera]-v2, each "
        "also with -arap (the second deformation family)",
    )
    g.add_argument("--livers", type=int, default=10)
    g.add_argument("--deformations", type=int, default=5, help="deformations per liver")
    g.add_argument(
        "--family",
        default="fem",
        help="deformation family: fem (linear elasticity) or arap (as-rigid-as-possible with handles)",
    )
    g.add_argument(
        "--targets",
        type=int,
        default=8,
        help="targets per deformation; target t gets visibility bin t mod #bins (8 random, 2 camera)",
    )
    g.add_argument("--crop", default="random", help="random (geodesic patch) or camera (anterior laparoscope view)")
    g.add_argument("--noise", type=float, default=0.0, help="noise level L: uniform [-L/2, L/2] mm per coordinate")
    g.add_argument("--seed", type=int, default=0, help="liver ids are seed*10000+i; 900-999 are reserved for test sets")
    g.add_argument("--split", default="train", help="split name written to the manifest")
    g.add_argument("--tets", type=int, default=10_000, help="approximate tetrahedra per liver")
    g.add_argument("--workers", type=int, default=1)
    g.add_argument("--no-progress", action="store_true")
    g.set_defaults(func=run_generate)
    s = sub.add_parser("stats", help="print distributions and write Fig. 4-style histograms")
    s.add_argument("dir", help="a generated dataset directory")
    s.add_argument(
        "--png", help="histogram picture path, .png/.pdf/.svg/... (default DIR/stats.png, replaced each run)"
    )
    s.add_argument("--force", action="store_true", help="overwrite an existing --png file")
    s.add_argument("--json", action="store_true", help="print JSON instead of text")
    s.set_defaults(func=run_stats)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_generate(args: argparse.Namespace) -> int:
    from liver_p2p_reg.phantom.dataset import DatasetSpec, generate_dataset
    from liver_p2p_reg.phantom.loader import build_store
    from liver_p2p_reg.phantom.testset import ensure_testset

    logging.getLogger("skfem").setLevel(logging.WARNING)  # one INFO line per assembly otherwise
    chosen = [x for x in (args.out and not args.testset, args.store, args.testset) if x]
    if len(chosen) != 1:
        raise InputError("give exactly one of --out DIR, --store DIR or --testset NAME [--out ROOT]")
    if args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    progress = not args.no_progress
    if args.testset:
        path = ensure_testset(args.testset, root=args.out, workers=args.workers, progress=progress)
        print(f"test set {args.testset}: {path}")
        return 0
    if args.store:
        store = build_store(
            args.store, args.livers, args.deformations, args.seed, args.workers, args.tets, progress=progress
        )
        print(f"training store: {store}")
        return 0
    spec = DatasetSpec(
        livers=args.livers,
        deformations=args.deformations,
        targets=args.targets,
        crop=args.crop,
        noise_mm=args.noise,
        seed=args.seed,
        split=args.split,
        target_tets=args.tets,
        family=args.family,
    )
    manifest = generate_dataset(args.out, spec, workers=args.workers, progress=progress)
    print(f"manifest: {manifest}")
    return 0


def run_stats(args: argparse.Namespace) -> int:
    from liver_p2p_reg.phantom.manifest import read_manifest
    from liver_p2p_reg.phantom.stats import STAT_COLUMNS, plot_histograms, summarize

    directory = Path(args.dir)
    # a path the user names is theirs: replaced only with --force (the default DIR/stats.png is this command's own)
    target = output_file(args.png, args.force, "--png", suffixes=PICTURE_SUFFIXES) or directory / "stats.png"
    rows = read_manifest(directory)
    summary = summarize(rows)
    png = plot_histograms(rows, target, title=directory.name)
    summary["histograms_png"] = str(png)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"{directory}: {summary['cases']} cases, {summary['livers']} livers")
    for key, label in STAT_COLUMNS:
        s = summary[key]
        print(
            f"  {label:24s} mean {s['mean']:7.2f}  std {s['std']:6.2f}  min {s['min']:7.2f}"
            f"  p50 {s['p50']:7.2f}  p95 {s['p95']:7.2f}  max {s['max']:7.2f}"
        )
    print("  cases per visibility bin: " + ", ".join(f"{k} {v}" for k, v in summary["visibility_bins"].items()))
    print(f"  max |visibility - requested|: {summary['visibility_abs_error_max']:.3f}")
    print(f"  histograms: {png}")
    return 0
