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
    p.add_argument("--output", "-o", metavar="PATH", help="also write the JSON result to PATH")
    p.add_argument(
        "--plot",
        metavar="PNG",
        help="also draw the moved SOURCE over TARGET (three views, distances, fiducial errors) to PNG/PDF/SVG",
    )
    p.add_argument("--moved", metavar="PATH", help="also write SOURCE moved into TARGET's frame (PLY/PCD/XYZ/NPY, mm)")
    p.add_argument("--force", action="store_true", help="overwrite --output / --plot / --moved files that exist")
    p.add_argument(
        "--slicer",
        metavar="HOST:PORT",
        help="also send the model, TARGET, the CTToSensor transform and the verdict to 3D Slicer "
        "(its OpenIGTLinkIF connector of type Server, e.g. localhost:18944); README 'See it in 3D Slicer'",
    )
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


def run(args: argparse.Namespace) -> int:
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
    slicer = None
    if args.slicer:  # connected before registering: no Slicer is one line, not a lost registration
        from ..igtl.commands import connect_to_slicer

        slicer = connect_to_slicer(args.slicer)
    result = Registrar(config).register(
        source, target, method=config.method, source_fiducials_mm=fid_s, target_fiducials_mm=fid_t
    )
    text = json.dumps(result.to_json_dict(), indent=2)
    if output is not None:
        output.write_text(text + "\n")
    print(text)
    # The node's WARN rules, on stderr: the pose is still returned (exit 0), but flagged.
    warnings = list(pose_warnings(result.residual_mm, result.ambiguous, result.uncertainty_mm, config).values())
    for message in warnings:
        logging.getLogger("liver_p2p_reg").warning(message)
    if slicer is not None:
        from ..igtl.commands import send_registration

        send_registration(slicer, args.source, source, target, result, warnings)
        slicer.endpoint.close()
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
