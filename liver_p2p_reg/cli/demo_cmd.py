"""`liver-p2p demo`: the main job — replay every bundled bag and print the per-case table."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..config import Config
from ..errors import InputError


def bundled_bags_dir() -> Path | None:
    """Where the bundled bags are: the source checkout, or an ament share/ install."""
    here = Path(__file__).resolve()
    candidates = [here.parents[2] / "bags"]
    try:  # installed with colcon: share/liver_p2p_reg/bags
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory("liver_p2p_reg")) / "bags")
    except Exception:  # ament_index_python absent or package not in the index
        pass
    for path in candidates:
        if path.is_dir() and any(p.is_dir() for p in path.iterdir()):
            return path
    return None


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="replay every bundled bag and print the per-case table")
    p.add_argument("--method", help="registration method (default: the configured default)")
    p.add_argument("--config", help="YAML configuration file")
    p.add_argument(
        "--out",
        default="out/demo",
        help="folder for the output bags and an overlay PNG per bag, replaced on each demo run (default: out/demo)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..o3d import quiet_open3d
    from ..ros.replay import format_flags, format_table, replay_bags

    quiet_open3d()  # RANSAC's C++ warnings would interleave with the table on stdout

    config = Config.from_yaml(args.config) if args.config else Config()
    if args.method:
        config = config.replace(method=args.method)
    bags = bundled_bags_dir()
    if bags is None:
        raise InputError("no bundled bags found (expected a bags/ folder next to the package)")
    paths = sorted(p for p in bags.iterdir() if (p / "metadata.yaml").is_file() or p.suffix == ".mcap")
    print(f"Replaying {len(paths)} bundled bags from {bags} with method {config.method} ...", flush=True)
    rows = replay_bags(paths, config, out_dir=Path(args.out), progress=True, overwrite=True, plot_dir=Path(args.out))
    print(format_table(rows))
    print(f"Output bags and an overlay PNG of each bag's last registered frame: {args.out}/")
    for line in format_flags(rows):  # why a bag is not OK, in the node's own words, and which frame that is
        print(line)
    failed = [r for r in rows if str(getattr(r, "status", "OK")) not in ("OK", "WARN")]
    return 1 if failed else 0
