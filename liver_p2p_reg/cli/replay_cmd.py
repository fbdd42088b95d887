"""`liver-p2p replay BAG... [--out OUT] [--method ...]`: drive the node core with recorded bags."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from liver_p2p_reg.config import NODE_MODES, Config
from liver_p2p_reg.errors import InputError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("replay", help="replay rosbag2/MCAP bags through the registration node core")
    p.add_argument("bags", nargs="+", help="rosbag2 directories (with metadata.yaml) or .mcap files")
    p.add_argument("--out", help="folder for output bags with /registration/* and /diagnostics added")
    p.add_argument("--plots", metavar="DIR", help="draw each bag's last registered frame to DIR/<bag>.png")
    p.add_argument("--force", action="store_true", help="overwrite existing output bags and plots")
    p.add_argument("--method", help="registration method (default: the configured one)")
    p.add_argument("--mode", choices=NODE_MODES, help="node mode (default: the configured one)")
    p.add_argument("--config", help="YAML configuration file (plain or ROS parameter file)")
    p.add_argument("--max-frames", type=int, default=0, help="register at most this many frames per bag (0: all)")
    p.add_argument("--json", help="also write the per-bag rows as JSON here")
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
    from liver_p2p_reg.registration.methods import check_method_name

    config = Config.from_yaml(args.config) if args.config else Config()
    changes = {k: v for k, v in (("method", args.method), ("mode", args.mode)) if v}
    if changes:
        config = config.replace(**changes)
    check_method_name(config.method)  # before reading any bag or importing torch
    from liver_p2p_reg.bags.io import is_bag_path
    from liver_p2p_reg.bags.replay import format_flags, format_table, replay_bags

    paths = [Path(b) for b in args.bags]
    for path in paths:
        if not path.exists():
            raise InputError(f"bag not found: {path}")
        if not is_bag_path(path):
            raise InputError(f"not a rosbag2 directory or .mcap file: {path}")
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
    )
    if slicer is not None:
        finish_replay(slicer, args.slicer_wait)
    print(format_table(rows))
    for line in format_flags(rows):
        print(line)
    if args.json:
        Path(args.json).write_text(json.dumps([row.__dict__ for row in rows], indent=2, default=str))
    return 1 if any(row.status == "ERROR" for row in rows) else 0
