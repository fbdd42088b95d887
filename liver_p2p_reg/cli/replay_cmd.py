"""`liver-p2p replay BAG... [--out OUT] [--method ...]`: drive the node core with recorded bags, or re-run a flight recording."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from liver_p2p_reg.config import NODE_MODES, Config
from liver_p2p_reg.errors import InputError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "replay",
        help="replay rosbag2/MCAP bags through the registration node core, or re-run a flight recording",
        description="Replay bags through the node core; given one flight recording (record_path, --record), "
        "re-run each of its registrations under its recorded parameters and model and check that every pose "
        "is bitwise identical or within floating-point round-off (exit 1 with one line if any differs).",
    )
    p.add_argument("bags", nargs="+", help="rosbag2 directories (with metadata.yaml) or .mcap files, or one recording")
    p.add_argument("--out", help="folder for output bags with /registration/* and /diagnostics added")
    p.add_argument("--plots", metavar="DIR", help="draw each bag's last registered frame to DIR/<bag>.png")
    p.add_argument(
        "--record",
        metavar="PATH",
        help="flight-record the replay to PATH (.mcap; with several bags a folder, one <bag>.mcap each)",
    )
    p.add_argument(
        "--force", "--overwrite", action="store_true", help="overwrite existing output bags, plots and recordings"
    )
    p.add_argument("--method", help="registration method (default: the configured one)")
    p.add_argument("--mode", choices=NODE_MODES, help="node mode (default: the configured one)")
    p.add_argument("--config", help="YAML configuration file (plain or ROS parameter file)")
    p.add_argument(
        "--deform",
        action="store_true",
        help="run the non-rigid stage after each pose (deform: true): --out bags get /registration/deformed_preop, "
        "the table the deformed RMS-TRE and on how many frames the stage was applied",
    )
    p.add_argument("--max-frames", type=int, default=0, help="register at most this many frames per bag (0: all)")
    p.add_argument("--json", help="also write the per-bag rows as JSON here")
    p.add_argument(
        "--structures",
        metavar="FILE[:LABEL]",
        nargs="+",
        action="extend",
        help="subsurface structures (mm, the preop frame) moved with every pose instead of those a bag carries "
        "(/preop/structures): --out bags get /registration/structures, the verdicts follow their error bounds",
    )
    p.add_argument(
        "--slicer",
        metavar="PORT",
        type=int,
        help="serve the replay to 3D Slicer on this OpenIGTLink port (its connector of type Client, e.g. 18944)",
    )
    p.add_argument(
        "--slicer-wait",
        metavar="S",
        type=float,
        default=30.0,
        help="with --slicer: wait up to S s for Slicer to connect before replaying, and for the last messages "
        "to leave after (default 30)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from liver_p2p_reg.bags.flight_replay import is_recording
    from liver_p2p_reg.registration.methods import check_method_name

    if any(is_recording(b) for b in args.bags):
        return _rerun(args)

    config = Config.from_yaml(args.config) if args.config else Config()
    changes = {k: v for k, v in (("method", args.method), ("mode", args.mode)) if v}
    if args.deform:
        changes["deform"] = True
    if changes:
        config = config.replace(**changes)
    check_method_name(config.method)  # before reading any bag or importing torch
    from liver_p2p_reg.bags.io import bag_source, is_bag_path
    from liver_p2p_reg.bags.replay import format_flags, format_table, replay_bags

    paths = [Path(b) for b in args.bags]
    for path in paths:
        if not path.exists():
            raise InputError(f"bag not found: {path}")
        if not is_bag_path(path):
            raise InputError(f"not a rosbag2 directory or .mcap file: {path}")
        bag_source(path)  # a malformed metadata.yaml: one line before the progress bar, not after it
    if args.max_frames < 0:
        raise InputError(f"--max-frames must be >= 0 (0: all frames), got {args.max_frames}")
    if args.slicer is not None and not 0 <= args.slicer_wait < float("inf"):  # NaN and inf waited forever
        raise InputError(f"--slicer-wait must be a finite number of seconds >= 0, got {args.slicer_wait}")
    _check_outputs(args, paths)
    from liver_p2p_reg.structures_io import load_structures

    structures = load_structures(args.structures or [])  # a bad file: one line, exit 2, before any work
    slicer = None
    if args.slicer is not None:
        from liver_p2p_reg.cli.slicer import finish_replay, serve_replay

        slicer = serve_replay(args.slicer, args.slicer_wait)
    rows = replay_bags(
        paths,
        config,
        out_dir=args.out,
        progress=not getattr(args, "quiet", False),
        overwrite=args.force,
        max_frames=args.max_frames,
        plot_dir=args.plots,
        observer=slicer,
        record=args.record,
        structures=structures,
    )
    if slicer is not None:
        finish_replay(slicer, args.slicer_wait)
    print(format_table(rows))
    for line in format_flags(rows):
        print(line)
    if args.json:
        _write_json(Path(args.json), [row.__dict__ for row in rows])
    return 1 if any(row.status == "ERROR" for row in rows) else 0


def _write_json(path: Path, data) -> None:
    """Strict JSON (NaN and infinities as null: jq and browsers refuse the bare tokens), written atomically."""
    from liver_p2p_reg.files import write_text_atomic

    text = json.dumps(_strict(data), indent=2, default=str, allow_nan=False)
    if path.exists() and not path.is_file():  # /dev/null, a pipe with a reader: written to, never replaced
        path.write_text(text)
    else:
        write_text_atomic(path, text)


def _strict(value):
    """`value` with every non-finite float replaced by None (lists, tuples and dicts walked)."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_strict(v) for v in value]
    return value


def _check_outputs(args: argparse.Namespace, bags: list[Path]) -> None:
    """--out, --plots, --record and --json checked before any work: none of them is, or (a bag to replace) holds,
    an input, and no two of them write one path."""
    from liver_p2p_reg.cli.output_paths import (
        distinct_outputs,
        given_paths,
        output_bag,
        output_file,
        output_folder,
        refuse_inputs,
    )
    from liver_p2p_reg.files import path_inside

    inputs = given_paths(bags, args.config, args.structures)
    names = [bag.name.removesuffix(".mcap") for bag in bags]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice and (args.out or args.plots or (args.record and len(bags) > 1)):
        # OUT/<name>, PLOTS/<name>.png and RECORD/<name>.mcap would hold the second bag's output only
        raise InputError(f"two bags are named {twice[0]}: their outputs would share one path; rename one")
    out = output_folder(args.out, "--out", inputs=inputs)
    written: dict[str, list[Path | None]] = {"--out": [], "--plots": [], "--record": []}
    if out is not None:
        for name in names:  # each replayed bag is written to OUT/<bag name>, replacing a bag there with --force
            written["--out"].append(output_bag(out / name, args.force, "--out", inputs, bag_folders=True))
    plots = output_folder(args.plots, "--plots", inputs=inputs, bag_folders=True)
    if plots is not None:
        written["--plots"] = [plots / f"{name}.png" for name in names]
    if args.json:
        json_path = Path(args.json)
        refuse_inputs(json_path, "--json", inputs, bag_folders=True)
        for bag_out in written["--out"]:  # written after the bags: it would replace a file of one
            if path_inside(json_path, bag_out):
                raise InputError(f"--json {json_path} is inside {bag_out}, an output bag; choose another path")
    output_file(args.json, args.force, "--json", inputs=inputs)
    if args.record:
        written["--record"] = _check_record(args.record, args.force, several=len(bags) > 1, inputs=bags)
    distinct_outputs({**written, "--json": [Path(args.json) if args.json else None]})


def _check_record(record: str, force: bool, several: bool, inputs: list[Path]) -> list[Path]:
    """--record checked before any work: a recording that exists is refused unless --force, and --force never
    replaces an input (nor a file of an input recording's series); several bags want a folder. Returns the files
    the recordings will be (their first files; a rotated recording adds continuations next to them)."""
    from liver_p2p_reg.bags.recorder import recording_series
    from liver_p2p_reg.cli.output_paths import output_file, output_folder, refuse_inputs

    path = Path(record)
    # a recording's rotated continuations are read (as inputs) and replaced (as outputs) with it
    read = [f for given in inputs for f in (recording_series(given) if given.suffix == ".mcap" else [given])]
    if several:
        if path.suffix == ".mcap" or (path.exists() and not path.is_dir()):
            raise InputError(f"--record {path}: with several bags, give a folder (one <bag>.mcap each)")
        output_folder(path, "--record", inputs=read)
        targets = [path / f"{bag.name.removesuffix('.mcap')}.mcap" for bag in inputs]  # RECORD/<bag name>.mcap
    else:
        if path.suffix != ".mcap":
            raise InputError(f"--record {path}: a flight recording is an .mcap file")
        output_file(path, True, "--record", inputs=read)  # existence: below, with the continuations
        targets = [path]
    for target in targets:
        for written in recording_series(target):
            refuse_inputs(written, "--record", read, bag_folders=True)
            if (written.exists() or written.is_symlink()) and not force:  # a dangling link is the user's too
                raise InputError(f"{written} exists; pass --force to overwrite it")
    if several:
        path.mkdir(parents=True, exist_ok=True)
    return targets


def _rerun(args: argparse.Namespace) -> int:
    """`liver-p2p replay RECORDING`: re-run every registration; exit 1 with one line if a pose differs."""
    from liver_p2p_reg.bags.flight_replay import rerun_recording

    if len(args.bags) != 1:
        raise InputError("a flight recording is re-run on its own: give one recording and no bags")
    given = [o for o, v in (("--out", args.out), ("--plots", args.plots), ("--method", args.method),
             ("--mode", args.mode), ("--config", args.config), ("--max-frames", args.max_frames),
             ("--slicer", args.slicer), ("--structures", args.structures), ("--deform", args.deform)) if v]  # fmt: skip
    if given:
        raise InputError(f"{', '.join(given)}: a flight recording is re-run under its recorded parameters only")
    written = _check_record(args.record, args.force, several=False, inputs=[Path(args.bags[0])]) if args.record else []
    from liver_p2p_reg.bags.recorder import recording_series
    from liver_p2p_reg.cli.output_paths import distinct_outputs, output_file

    output_file(args.json, args.force, "--json", inputs=recording_series(Path(args.bags[0])))
    distinct_outputs({"--record": written, "--json": [Path(args.json) if args.json else None]})
    report = rerun_recording(args.bags[0], record_path=args.record, overwrite=args.force)
    for note in report.notes:
        print(f"note: {note}")
    print(f"{args.bags[0]}: {report.summary()}")
    if args.json:
        _write_json(Path(args.json), {**report.__dict__, "ok": report.ok})
    if report.registrations == 0:  # nothing compared is nothing verified: not a pass
        print(f"liver-p2p: error: {args.bags[0]} holds no complete registration to re-run", file=sys.stderr)
        return 2
    if not report.ok:
        first = report.differences[0]
        print(
            f"liver-p2p: error: {report.registrations_differing} of {report.registrations} registrations differ from the "
            f"recording (first: {first})",
            file=sys.stderr,
        )
        return 1
    return 0
