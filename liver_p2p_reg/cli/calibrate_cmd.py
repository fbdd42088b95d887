"""`liver-p2p calibrate-bound`: the error bound's split-conformal calibration on validation sets, judged on test sets."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from pathlib import Path

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import path_inside, write_text_atomic

# generator and real-anatomy, random and camera crops (`liver-p2p dataset generate --testset NAME --out data`)
DEFAULT_VAL = ("data/insilico-val-v2", "data/insilico-val-camera-v2", "data/real-val-v2", "data/real-val-camera-v2")
RESULTS_PAGE = Path("docs/results/error_bound.md")
DEFORMED_RESULTS_PAGE = Path("docs/results/error_bound_deformed.md")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate-bound",
        help="calibrate the per-point error bound by split-conformal prediction on validation sets "
        "(and judge it on test sets)",
    )
    p.add_argument(
        "--val",
        nargs="+",
        default=list(DEFAULT_VAL),
        metavar="DIR",
        help="validation case folders (default: %(default)s)",
    )
    p.add_argument(
        "--judge",
        nargs="+",
        default=[],
        metavar="DIR",
        help="test case folders to judge the calibration on (writes the results page)",
    )
    p.add_argument("--noise-mm", type=float, default=2.0, help="sensor noise added to every target (default: 2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the liver split (default: 0)")
    p.add_argument("--workers", type=int, default=2, help="registration processes (default: 2)")
    p.add_argument("--cache", default="out/bound", help="collected poses per set, reused when unchanged")
    p.add_argument("--out", help="calibration file to write (default: the bundled one)")
    p.add_argument("--force", action="store_true", help="replace an existing, different calibration file")
    p.add_argument(
        "--deformed",
        action="store_true",
        help="calibrate the bound of the non-rigid stage's deformed positions instead (deform on; fitted on the "
        f"poses where it was applied; default --out the bundled deformed one, --report {DEFORMED_RESULTS_PAGE})",
    )
    p.add_argument("--report", help=f"results page of --judge (default: {RESULTS_PAGE})")
    p.add_argument(
        "--readme",
        nargs="?",
        const="README.md",
        metavar="README",
        help="also write README's ERROR_BOUND block (default README: ./README.md)",
    )
    p.add_argument("--config", help="YAML configuration (method, weights) the calibration is for")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from liver_p2p_reg.bench import bound_data
    from liver_p2p_reg.bench.bound_fit import SCALE_FEATURES, calibrate
    from liver_p2p_reg.registration.error_calibration import (
        BUNDLED_CALIBRATION,
        BUNDLED_DEFORMED_CALIBRATION,
        DEFORMED,
        RIGID,
        deform_settings,
        pose_settings,
        read_calibration,
    )
    from liver_p2p_reg.registration.weights_id import weights_sha256

    _check_args(args)
    config = (Config.from_yaml(args.config) if args.config else Config()).validate()
    # the rigid bound is fitted on the pose's errors whatever the --config says about the stage
    config = config.replace(deform=bool(args.deformed)).validate()
    out = Path(args.out) if args.out else (BUNDLED_DEFORMED_CALIBRATION if args.deformed else BUNDLED_CALIBRATION)
    weights = weights_sha256(config)  # "" for a method without weights
    collected = bound_data.concat([collected_set(Path(d), args, config, weights) for d in args.val])
    val = _applied(collected, args)
    cal = calibrate(val, args.seed, n_features=SCALE_FEATURES[DEFORMED if args.deformed else RIGID])
    if args.deformed:
        cal.update(positions=DEFORMED, deform=deform_settings(config))
    sets = [{"set": Path(d).name, "cases": int((collected["set"] == Path(d).name).sum())} for d in args.val]
    if args.deformed:  # the poses it was fitted on: those where the stage was applied
        for entry in sets:
            entry["applied_poses"] = int((val["set"] == entry["set"]).sum())
    cal.update(
        method=config.method,
        weights_sha256=weights,
        pose=pose_settings(config),
        provenance={
            "summary": f"{', '.join(s['set'] for s in sets)} ({len(val['count'])} poses, "
            f"{args.noise_mm:g} mm noise, seed {args.seed}; scale fitted on livers {cal['fit_livers']}, quantiles "
            f"on livers {cal['calibration_livers']})",
            "sets": sets,
            "case_ids_sha256": hashlib.sha256("\n".join(sorted(val["case_id"])).encode()).hexdigest(),
            "noise_mm": args.noise_mm,
            "seed": args.seed,
            "command": "liver-p2p calibrate-bound "
            + ("--deformed " if args.deformed else "")
            + " ".join(f"--val {d}" for d in args.val),
        },
    )
    text = json.dumps(cal, indent=1) + "\n"
    if out.exists() and out.read_bytes() == text.encode():
        print(f"{out}: unchanged (the calibration was reproduced bitwise)")
    elif out.exists() and not args.force:
        raise InputError(f"{out} exists and differs from this calibration; give --force to replace it")
    else:
        _write_atomic(out, text)
        print(f"wrote {out}")
    if args.judge:
        _judge(args, config, weights, read_calibration(out))
    return 0


def _check_args(args: argparse.Namespace) -> None:
    """The numbers and paths checked before any registration: one line each, not an error after minutes of work."""
    import math

    if not (math.isfinite(args.noise_mm) and args.noise_mm >= 0):
        raise InputError(f"--noise-mm must be a finite number >= 0, got {args.noise_mm}")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    _check_sets(args.val, "--val")
    _check_sets(args.judge, "--judge")
    for option, value in (("--readme", args.readme), ("--report", args.report)):
        if value and not args.judge:  # both are written from the judged test sets only
            raise InputError(f"{option} writes the judged results: give --judge DIR... too")
    _check_outputs(args)


def _check_sets(folders: list[str], option: str) -> None:
    """Each set a folder of cases, given once: a set's poses are keyed by its folder's name, so a repeat (or
    another folder of the same name) would count its poses twice."""
    from liver_p2p_reg.bench.cases import list_case_paths

    seen: dict[str, str] = {}
    for given in folders:
        folder = Path(given)
        if not folder.is_dir():
            raise InputError(f"{folder} is not a folder of cases (make it with liver-p2p dataset)")
        for key in (str(folder.resolve()), folder.name):
            if key in seen:
                raise InputError(f"{option} names {seen[key]} and {given}: give each set once, under its own name")
            seen[key] = given
        list_case_paths(folder)  # one line now when it holds no case, not after the other sets' registrations


def _check_outputs(args: argparse.Namespace) -> None:
    """--cache, --out, --report and --readme: none an input nor inside a set's folder, an existing --report
    only with --force, the README with its block's markers; all before the registrations."""
    from liver_p2p_reg.bench.readme import check_readme
    from liver_p2p_reg.cli.output_paths import distinct_outputs, given_paths, output_file, output_folder, refuse_inputs

    inputs = given_paths(args.val, args.judge, args.config)
    sets = [Path(d) for d in [*args.val, *args.judge]]
    output_folder(args.cache, "--cache", inputs=inputs)
    _outside_sets(Path(args.cache), "--cache", sets)
    out = Path(args.out) if args.out else None
    if out is not None:
        if out.is_dir():
            raise InputError(f"--out {out} is a folder; give the calibration file's path (.json)")
        refuse_inputs(out, "--out", inputs)
        _outside_sets(out, "--out", sets)
    if args.report:  # before output_file: --force replaces an earlier page, never a set's file
        _outside_sets(Path(args.report), "--report", sets)
    report = output_file(args.report, args.force, "--report", inputs=inputs)
    if args.readme:
        check_readme(args.readme, "ERROR_BOUND_DEFORMED" if args.deformed else "ERROR_BOUND")
        refuse_inputs(Path(args.readme), "--readme", inputs)
    readme = Path(args.readme) if args.readme else None
    if args.judge and report is None:  # the default page is written too
        report = DEFORMED_RESULTS_PAGE if args.deformed else RESULTS_PAGE
    distinct_outputs({"--out": [out], "--report": [report], "--readme": [readme]})


def _outside_sets(path: Path, option: str, sets: list[Path]) -> None:
    """An output never lands in a set's folder: it would replace its files or be read as one of its cases."""
    for folder in sets:
        if path_inside(path, folder):
            raise InputError(f"{option} {path} is inside {folder}, a set this command reads; choose another path")


def _write_atomic(path: Path, text: str) -> None:
    """Write a file in one step, its folder made: a run cut short never leaves half a calibration or page."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, text)


def _applied(data: dict, args: argparse.Namespace) -> dict:
    """With --deformed, the poses where the non-rigid stage was applied (the only ones its bound is used for)."""
    from liver_p2p_reg.bench import bound_data

    if not args.deformed:
        return data
    applied = data["deform_applied"].astype(bool)
    if not applied.any():
        raise InputError("the non-rigid stage was applied on none of these poses: nothing to calibrate")
    return bound_data.subset(data, applied)


def validation_collections(cache: str, deformed: bool) -> tuple[dict, Config]:
    """The validation poses `calibrate-bound` (`--deformed`) calibrates on with its defaults (DEFAULT_VAL, 2 mm noise,
    the default settings), from `cache` (collected there when missing), and those settings; with `deformed`, the
    poses where the stage was applied. What the bound's selection rules compare candidates on."""
    from liver_p2p_reg.bench import bound_data
    from liver_p2p_reg.registration.weights_id import weights_sha256

    config = Config().validate().replace(deform=deformed).validate()
    args = argparse.Namespace(cache=cache, noise_mm=2.0, workers=2, deformed=deformed)
    collected = [collected_set(Path(d), args, config, weights_sha256(config)) for d in DEFAULT_VAL]
    return _applied(bound_data.concat(collected), args), config


def collected_set(folder: Path, args: argparse.Namespace, config: Config, weights: str) -> dict:
    """The collected poses of a set: from the cache when made with the same cases, settings and weights."""
    from liver_p2p_reg.bench import bound_data

    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder of cases (make it with liver-p2p dataset)")
    cache = collection_cache(folder, args, config, weights)
    cached = bound_data.load_cached(cache) if cache.exists() else None
    if cached is not None:
        return cached
    data = bound_data.collect_set(folder, args.noise_mm, config, args.workers, progress=sys.stderr.isatty())
    bound_data.save(cache, data)
    return data


def collection_cache(
    folder: Path, args: argparse.Namespace, config: Config, weights: str, evidence: dict | None = None
) -> Path:
    """Where a set's collection is cached: keyed by the cases' content (not their names: a set regenerated under
    the same names is registered again), the settings, the weights, the features and what they are computed with
    (`evidence`, default error_bound.EVIDENCE_SETTINGS: a change of the interior's stand-in or of a feature's
    sampling is a new collection, never a stale one reused silently) and the noise."""
    from liver_p2p_reg.bench.cases import list_case_paths
    from liver_p2p_reg.registration.error_bound import EVIDENCE_SETTINGS, FEATURES

    cases = [[p.name, _file_sha256(p)] for p in list_case_paths(folder)]
    settings = EVIDENCE_SETTINGS if evidence is None else evidence
    key = json.dumps([config.to_dict(), weights, FEATURES, settings, args.noise_mm, cases])
    stamp = hashlib.sha256(key.encode()).hexdigest()[:16]
    return Path(args.cache) / f"{folder.name}-noise{args.noise_mm:g}mm-{stamp}.npz"


def _file_sha256(path: Path) -> str:
    """The SHA-256 of a case file's bytes (read in blocks: a set is hundreds of MB)."""
    digest = hashlib.sha256()
    try:  # in blocks, by hand: hashlib.file_digest is Python 3.11+, and 3.10 is supported
        with open(path, "rb") as fh:
            while block := fh.read(1 << 20):
                digest.update(block)
        return digest.hexdigest()
    except OSError as exc:
        raise InputError(f"cannot read case {path}: {exc.strerror or exc}") from None


def _judge(args: argparse.Namespace, config: Config, weights: str, calibration) -> None:
    from liver_p2p_reg.bench import bound_data
    from liver_p2p_reg.bench.bound_markdown import results_page
    from liver_p2p_reg.bench.readme import replace_readme_block

    data = _applied(bound_data.concat([collected_set(Path(d), args, config, weights) for d in args.judge]), args)
    flag = ["--deformed"] if args.deformed else []
    command = "liver-p2p calibrate-bound " + " ".join([*flag, "--judge", *args.judge])
    report = Path(args.report or (DEFORMED_RESULTS_PAGE if args.deformed else RESULTS_PAGE))
    # the block links the page from wherever it is written (the README, or a results page beside it)
    link = os.path.relpath(report, Path(args.readme).parent) if args.readme else ""
    page, block = results_page(
        data,
        calibration,
        config.error_coverage,
        config.structure_error_warn_mm,
        args.seed,
        command,
        args.deformed,
        link,
    )
    _write_atomic(report, page)
    print(f"wrote {report}")
    if args.readme:
        name = "ERROR_BOUND_DEFORMED" if args.deformed else "ERROR_BOUND"
        replace_readme_block(Path(args.readme), block, name)
        print(f"wrote the {name} block of {args.readme}")
