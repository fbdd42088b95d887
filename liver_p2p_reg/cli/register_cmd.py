"""`liver-p2p register SOURCE TARGET`: register two point-cloud files and print the JSON result."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from ..cloud_io import load_points, save_points
from ..confidence import pose_warnings
from ..config import SELECTION_RULES, Config
from ..errors import InputError
from ..metrics import transform_points
from ..o3d import quiet_open3d
from ..overlay import plot_registration
from ..registrar import Registrar

PLOT_SUFFIXES = (".png", ".pdf", ".svg")
MOVED_SUFFIXES = (".ply", ".pcd", ".xyz", ".npy")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "register",
        help="register a complete preoperative surface (SOURCE) to a partial view (TARGET)",
        description="Estimate the rigid transform mapping SOURCE (complete, mm) into TARGET (partial, mm). "
        "Prints the result as JSON; the node's warnings (residual, ambiguity, uncertainty above their "
        "thresholds) go to stderr.",
    )
    p.add_argument("source", metavar="SOURCE", help="complete preoperative surface (PLY/PCD/XYZ/STL/OBJ/NPY/NPZ, mm)")
    p.add_argument("target", metavar="TARGET", help="partial intraoperative surface (same formats, mm)")
    p.add_argument("--method", help=f"registration method (default: {Config().method}; a wrong name lists them)")
    p.add_argument("--k", type=int, help="number of P2P patch candidates (default: 5)")
    p.add_argument("--selection", choices=SELECTION_RULES, help="P2P candidate selection rule")
    p.add_argument("--seed", type=int, help="random seed (RANSAC, mesh sampling)")
    p.add_argument("--config", help="YAML configuration (plain mapping or ROS parameter file)")
    p.add_argument("--device", choices=("cpu", "cuda"), help="torch device")
    p.add_argument("--source-fiducials", metavar="F", help="(F, 3) fiducials in the source frame (mm)")
    p.add_argument("--target-fiducials", metavar="F", help="the same fiducials in the target frame (mm)")
    p.add_argument(
        "--sensor-origin",
        metavar="X,Y,Z",
        help="where the depth sensor stood when it saw TARGET (mm, TARGET's frame; (0,0,0) for a cloud in the "
        "sensor's own frame; write --sensor-origin=-10,0,5 when it starts with a minus): poses that put "
        "SOURCE's surface where the sensor saw none are then ruled out (free space); default: unknown",
    )
    p.add_argument("--output", "-o", metavar="PATH", help="also write the JSON result to PATH")
    p.add_argument(
        "--plot",
        metavar="PNG",
        help="also draw the moved SOURCE over TARGET (three views, distances, fiducial errors) to PNG/PDF/SVG",
    )
    p.add_argument("--moved", metavar="PATH", help="also write SOURCE moved into TARGET's frame (PLY/PCD/XYZ/NPY, mm)")
    p.add_argument("--force", action="store_true", help="overwrite --output / --plot / --moved files that exist")
    p.set_defaults(func=run)


def _config(args: argparse.Namespace) -> Config:
    config = Config.from_yaml(args.config) if args.config else Config()
    overrides = {
        name: getattr(args, name)
        for name in ("method", "k", "selection", "seed", "device")
        if getattr(args, name, None) is not None
    }
    return config.replace(**overrides) if overrides else config


def _output_path(value: str | None, force: bool, option: str, suffixes: tuple[str, ...] = ()) -> Path | None:
    """Checked before registering, so a bad path costs nothing and nothing is half-written."""
    if not value:
        return None
    path = Path(value)
    if suffixes and path.suffix.lower() not in suffixes:
        raise InputError(f"{option} {path}: use one of {', '.join(suffixes)}")
    if path.exists() and not force:
        raise InputError(f"{path} exists; pass --force to overwrite it")
    if not path.parent.exists():
        raise InputError(f"output folder does not exist: {path.parent}")
    return path


def sensor_origin(text: str | None) -> list[float] | None:
    """`X,Y,Z` in mm -> three numbers; a bad value is one InputError line."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(abs(v) < float("inf") for v in values):
        raise InputError(f"--sensor-origin must be three finite numbers X,Y,Z in mm, got {text!r}")
    return values


def run(args: argparse.Namespace) -> int:
    origin = sensor_origin(args.sensor_origin)
    output = _output_path(args.output, args.force, "--output")
    plot = _output_path(args.plot, args.force, "--plot", PLOT_SUFFIXES)
    moved = _output_path(args.moved, args.force, "--moved", MOVED_SUFFIXES)
    if (args.source_fiducials is None) != (args.target_fiducials is None):
        raise InputError("give both --source-fiducials and --target-fiducials, or neither")
    config = _config(args)
    quiet_open3d()  # stdout carries the JSON result only
    source = load_points(args.source, seed=config.seed)
    target = load_points(args.target, seed=config.seed)
    fid_s = fid_t = None
    if args.source_fiducials is not None:
        fid_s = load_points(args.source_fiducials)
        fid_t = load_points(args.target_fiducials)  # Registrar refuses NaN/inf pairs
    result = Registrar(config).register(
        source,
        target,
        method=config.method,
        source_fiducials_mm=fid_s,
        target_fiducials_mm=fid_t,
        sensor_origin_mm=origin,
    )
    text = json.dumps(result.to_json_dict(), indent=2)
    if output is not None:
        output.write_text(text + "\n")
    print(text)
    # The node's WARN rules, on stderr: the pose is still returned (exit 0), but flagged.
    reasons = pose_warnings(
        result.residual_mm, result.ambiguous, result.uncertainty_mm, config, result.free_space_violation
    )
    warnings = list(reasons.values())
    if result.free_space.startswith("off"):  # an origin was given but cannot be the target's sensor
        warnings.append(f"--sensor-origin ignored: {result.free_space.removeprefix('off: ')}")
    for message in warnings:
        logging.getLogger("liver_p2p_reg").warning(message)
    if moved is not None:
        save_points(moved, transform_points(result.T_target_source, source))
    if plot is not None:
        plot_registration(
            source,
            target,
            result,
            plot,
            warnings=warnings,
            residual_warn_mm=config.residual_warn_mm,
            source_fiducials_mm=fid_s,
            target_fiducials_mm=fid_t,
        )
    return 0
