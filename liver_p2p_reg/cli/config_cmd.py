"""`liver-p2p config`: print the default configuration (plain YAML or ROS parameter file)."""

from __future__ import annotations

import argparse

import yaml

from liver_p2p_reg.cli.output_paths import given_paths, output_file
from liver_p2p_reg.config import Config


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("config", help="print the default configuration")
    p.add_argument("--ros", action="store_true", help="ROS 2 parameter-file format")
    p.add_argument("--config", help="start from this YAML file instead of the defaults")
    p.add_argument("--write", metavar="PATH", help="write to PATH instead of printing")
    p.add_argument("--force", action="store_true", help="overwrite PATH if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    config = Config.from_yaml(args.config) if args.config else Config()
    text = config.to_ros_yaml() if args.ros else yaml.safe_dump(config.to_dict(), sort_keys=False)
    if args.write:
        inputs = given_paths(args.config)
        output_file(args.write, args.force, "--write", inputs=inputs).write_text(text)
    else:
        print(text, end="")
    return 0
