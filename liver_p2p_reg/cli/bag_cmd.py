"""`liver-p2p bag make|import|play|info`: build rosbag2 (MCAP) bags from cases or files; play them on ROS 2."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from liver_p2p_reg.errors import InputError

if TYPE_CHECKING:  # imported when a subcommand runs, so `liver-p2p --help` stays instant
    import numpy as np


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("bag", help="make rosbag2 bags from cases or files; import P2P dataset cases")
    sub = p.add_subparsers(dest="bag_command", metavar="ACTION", required=True)

    make = sub.add_parser("make", help="bag from a dataset case NPZ or from a source mesh + target cloud")
    make.add_argument("out", help="output rosbag2 directory")
    make.add_argument("--case", help="dataset case NPZ (src_pcd, tgt_pcd, src_marker, tgt_marker)")
    make.add_argument("--source", help="preop model: mesh or cloud file in mm (PLY/STL/OBJ/PCD/XYZ/NPY)")
    make.add_argument("--target", help="intraop cloud file in mm, in the sensor frame")
    make.add_argument("--fiducials", help="fiducial pairs: text/NPY file with F rows 'xs ys zs xt yt zt' (mm)")
    _common(make)
    make.set_defaults(func=run_make)

    imp = sub.add_parser("import", help="convert a case in the public P2P dataset NPZ format into a bag")
    imp.add_argument("npz", help="case NPZ (keys src_pcd, tgt_pcd, src_marker, tgt_marker)")
    imp.add_argument("out", help="output rosbag2 directory")
    _common(imp)
    imp.set_defaults(func=run_import)

    play = sub.add_parser("play", help="publish a bag on live ROS 2 topics (rclpy; no rosbag2 needed)")
    play.add_argument("bag", help="rosbag2 directory or .mcap file")
    play.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1: recorded timing)")
    play.add_argument("--loop", action="store_true", help="play again and again until Ctrl-C")
    play.add_argument(
        "--clock",
        action="store_true",
        help="also publish /clock from the bag's times (for nodes run with use_sim_time:=true)",
    )
    play.add_argument(
        "--wait-s", type=float, default=2.0, help="wait this long for subscribers before publishing (default 2)"
    )
    play.add_argument(
        "--all-topics",
        action="store_true",
        help="play every topic; by default only register_node's inputs (/preop/*, /intraop/*), not a recording's "
        "/registration/*, /diagnostics or /flight_recorder/*",
    )
    play.set_defaults(func=run_play)

    info = sub.add_parser("info", help="list the topics, message counts and size of a bag")
    info.add_argument("bag", help="rosbag2 directory or .mcap file")
    info.set_defaults(func=run_info)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=5, help="intraop frames (default 5)")
    p.add_argument("--frame-id", default="camera", help="sensor frame of the intraop clouds (default camera)")
    p.add_argument("--motion-mm", type=float, default=1.5, help="sensor motion over the frames, mm (default 1.5)")
    p.add_argument("--motion-deg", type=float, default=1.0, help="sensor rotation over the frames, deg (default 1)")
    p.add_argument("--period-s", type=float, default=0.5, help="time between frames, s (default 0.5)")
    p.add_argument("--max-preop-points", type=int, default=6000)
    p.add_argument("--max-intraop-points", type=int, default=8000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="overwrite an existing output bag")


def _make(args: argparse.Namespace, case: dict) -> int:
    from liver_p2p_reg.bags.io import bag_size_bytes
    from liver_p2p_reg.bags.make import make_case_bag

    out = make_case_bag(
        args.out,
        case["source_mm"],
        case["target_mm"],
        source_fiducials_mm=case.get("source_fiducials_mm"),
        target_fiducials_mm=case.get("target_fiducials_mm"),
        source_triangles=case.get("source_triangles"),  # a generated case's mesh: /preop/mesh
        n_frames=args.frames,
        frame_id=args.frame_id,
        motion_mm=args.motion_mm,
        motion_deg=args.motion_deg,
        frame_period_s=args.period_s,
        max_preop_points=args.max_preop_points,
        max_intraop_points=args.max_intraop_points,
        seed=args.seed,
        info=case.get("info"),
        overwrite=args.force,
    )
    print(f"wrote {out} ({bag_size_bytes(out) / 1e6:.2f} MB, {args.frames} intraop frames)")
    return 0


def _check_out(args: argparse.Namespace, *inputs: str | None) -> None:
    """OUT checked before any work (output_paths.output_bag)."""
    from liver_p2p_reg.cli.output_paths import given_paths, output_bag

    if Path(args.out).suffix.lower() == ".mcap":  # a rosbag2 bag is a folder; a folder named x.mcap misleads
        raise InputError(f"OUT {args.out}: a bag is a folder (metadata.yaml + .mcap); name it without .mcap")
    output_bag(Path(args.out), args.force, "OUT", given_paths(*inputs))


def run_make(args: argparse.Namespace) -> int:
    from liver_p2p_reg.bags.make import load_case_npz

    _check_out(args, args.case, args.source, args.target, args.fiducials)
    if args.case:
        if args.source or args.target:
            raise InputError("give either --case or --source/--target, not both")
        return _make(args, load_case_npz(args.case))
    if not (args.source and args.target):
        raise InputError("bag make needs --case NPZ, or --source and --target files")
    from liver_p2p_reg.cloud_io import load_points

    case: dict = {
        "source_mm": load_points(args.source, seed=args.seed),
        "target_mm": load_points(args.target, seed=args.seed),
        "info": {"source": Path(args.source).name, "target": Path(args.target).name},
    }
    if args.fiducials:
        pairs = _load_pairs(Path(args.fiducials))
        case["source_fiducials_mm"], case["target_fiducials_mm"] = pairs[:, :3], pairs[:, 3:6]
    return _make(args, case)


def run_import(args: argparse.Namespace) -> int:
    from liver_p2p_reg.bags.make import load_case_npz

    _check_out(args, args.npz)
    return _make(args, load_case_npz(args.npz))


def run_play(args: argparse.Namespace) -> int:
    try:
        from liver_p2p_reg.bags.player import main_play
    except ImportError as exc:
        raise InputError(f"bag play needs rclpy ({exc}): pip install -e '.[ros]' or source ROS 2 Jazzy") from None
    if not args.rate > 0:
        raise InputError(f"--rate must be > 0, got {args.rate}")
    # not found, a pipe, no bag, a malformed metadata.yaml: one line from main_play's bag_topics, before rclpy starts
    return main_play(args.bag, args.rate, args.loop, args.wait_s, clock=args.clock, all_topics=args.all_topics)


def run_info(args: argparse.Namespace) -> int:
    from liver_p2p_reg.bags.io import bag_custom_data, bag_size_bytes, bag_topics

    path = Path(args.bag)
    if not path.exists():
        raise InputError(f"bag not found: {path}")
    for topic, (msgtype, count) in sorted(bag_topics(path).items()):
        print(f"{topic:36s} {msgtype:40s} {count}")
    for key, value in bag_custom_data(path).items():
        print(f"{key}: {value}")
    print(f"size: {bag_size_bytes(path) / 1e6:.2f} MB")
    return 0


def _load_pairs(path: Path) -> np.ndarray:
    import numpy as np

    if not path.is_file():
        raise InputError(f"fiducials file not found: {path}")
    try:
        pairs = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, ndmin=2, delimiter=None, comments="#")
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read fiducials {path}: {exc}") from None
    pairs = np.asarray(pairs, dtype=np.float64)
    if pairs.ndim != 2 or pairs.shape[1] != 6 or len(pairs) < 3:
        raise InputError(f"{path}: expected >= 3 rows of 6 numbers (source xyz, target xyz), got shape {pairs.shape}")
    return pairs
