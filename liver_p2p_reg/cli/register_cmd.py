"""`liver-p2p register SOURCE TARGET...`: register one preoperative surface to one or more views.

Everything that can be checked (arguments, output paths, input files, method name) is checked
before torch, Open3D or a model is loaded; those load with the first registration.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from liver_p2p_reg.cli.output_paths import distinct_outputs, given_paths, output_file
from liver_p2p_reg.cli.register_inputs import load_fiducials, load_initial_transform, sensor_origin, warn_unused_weights
from liver_p2p_reg.config import SELECTION_RULES
from liver_p2p_reg.errors import InputError, LiverP2PError

PLOT_SUFFIXES = (".png", ".pdf", ".svg")
MOVED_SUFFIXES = (".ply", ".pcd", ".xyz", ".npy")
LOG = logging.getLogger("liver_p2p_reg")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.methods import method_names

    p = subparsers.add_parser(
        "register",
        help="register a complete preoperative surface (SOURCE) to one or more partial views (TARGET...)",
        description="Estimate the rigid transform mapping SOURCE (complete, mm) into each TARGET (partial, mm), "
        "in one process (start-up and SOURCE's preparation are paid once). The JSON result goes to --output, "
        "else to stdout (one object per line with several targets); a short summary per target goes to "
        "stdout when the JSON went to a file, else to stderr. The node's warnings (residual, ambiguity, "
        "uncertainty above their thresholds) go to stderr; the pose is still returned (exit 0).",
    )
    p.add_argument("source", metavar="SOURCE", help="complete preoperative surface (PLY/PCD/XYZ/STL/OBJ/NPY/NPZ, mm)")
    p.add_argument("targets", metavar="TARGET", nargs="+", help="partial intraoperative surface(s) (same formats, mm)")
    p.add_argument(
        "--method", help=f"registration method (default: {Config().method}); one of: {', '.join(method_names())}"
    )
    p.add_argument("--k", type=int, help="number of P2P patch candidates (default: 5)")
    p.add_argument("--selection", choices=SELECTION_RULES, help="P2P candidate selection rule")
    p.add_argument("--seed", type=int, help="random seed (RANSAC, mesh sampling)")
    p.add_argument("--config", help="YAML configuration (plain mapping or ROS parameter file)")
    p.add_argument("--device", choices=("cpu", "cuda"), help="torch device")
    p.add_argument(
        "--weights",
        dest="weights_path",
        metavar="PATH",
        help="matcher weights: general ones, or a file from `liver-p2p prepare` for this SOURCE's liver",
    )
    p.add_argument("--source-fiducials", metavar="F", help="(F, 3) fiducials in the source frame (mm)")
    p.add_argument("--target-fiducials", metavar="F", help="the same fiducials in the target frame (mm)")
    p.add_argument(
        "--initial-transform",
        metavar="FILE",
        help="prior pose for --method track (ICP from it, no global search) or --method evaluate (scored as is): "
        "a 4x4 matrix as text or NPY, "
        "or a JSON result of an earlier registration",
    )
    p.add_argument(
        "--sensor-origin",
        metavar="X,Y,Z",
        help="where the depth sensor stood when it saw TARGET (mm, TARGET's frame; (0,0,0) for a cloud in the "
        "sensor's own frame; e.g. --sensor-origin -10,0,5): poses that put "
        "SOURCE's surface where the sensor saw none are then ruled out (free space); default: unknown",
    )
    p.add_argument(
        "--structures",
        metavar="FILE[:LABEL]",
        nargs="+",
        action="extend",
        help="subsurface structures (tumours, vessels; points or a mesh's vertices, mm, SOURCE's frame; LABEL "
        "defaults to the file's name): each view's JSON gets `structures`, their points moved by the pose with an "
        "error bound per point, and the verdict follows those bounds",
    )
    p.add_argument(
        "--output",
        "-o",
        metavar="PATH",
        help="write the JSON result to PATH; with several targets PATH is a folder (PATH/<target name>.json)",
    )
    p.add_argument(
        "--deform",
        action="store_true",
        help="also run the non-rigid stage after the rigid pose (config `deform`): the JSON gets a `deformation` "
        "block, structures their `deformed_position_mm`, --moved the deformed surface; SOURCE's triangles "
        "(a mesh file) give its closed surface, else it is rebuilt from the points",
    )
    p.add_argument("--json", action="store_true", help="also print the JSON result on stdout when --output is given")
    p.add_argument(
        "--plot",
        metavar="PNG",
        help="also draw the moved SOURCE over TARGET (three views, distances, fiducial errors) to PNG/PDF/SVG "
        "(with several targets: a folder, one <target name>.png each)",
    )
    p.add_argument(
        "--moved",
        metavar="PATH",
        help="also write SOURCE moved into TARGET's frame (PLY/PCD/XYZ/NPY, mm; with several targets: a folder, "
        "one <target name>.ply each)",
    )
    p.add_argument(
        "--record",
        metavar="PATH",
        help="also flight-record SOURCE, every TARGET, the parameters and each pose to PATH (.mcap; "
        "`liver-p2p replay PATH` re-runs them and checks every pose bit for bit)",
    )
    p.add_argument(
        "--force", "--overwrite", action="store_true", help="overwrite --output / --plot / --moved / --record files"
    )
    # Also accepted after the subcommand; SUPPRESS keeps a `liver-p2p -q register ...` in effect.
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="only print errors")
    p.add_argument(
        "--slicer",
        metavar="HOST:PORT",
        help="also send the model, TARGET, the CTToSensor transform and the verdict to 3D Slicer "
        "(its OpenIGTLinkIF connector of type Server, e.g. localhost:18944); README 'See it in 3D Slicer'",
    )
    p.set_defaults(func=run)


def _config(args: argparse.Namespace):
    from liver_p2p_reg.config import Config

    config = Config.from_yaml(args.config) if args.config else Config()
    overrides = {
        name: getattr(args, name)
        for name in ("method", "k", "selection", "seed", "device", "weights_path")
        if getattr(args, name, None) is not None
    }
    if getattr(args, "deform", False):
        overrides["deform"] = True
    return config.replace(**overrides) if overrides else config


def _output_paths(
    value: str | None,
    targets: list[Path],
    force: bool,
    option: str,
    suffixes: tuple[str, ...],
    default_suffix: str,
    inputs: list[Path],
) -> list[Path | None]:
    """One output path per target, checked before registering (a bad path costs nothing, nothing is half-written):
    the path itself for one target, FOLDER/<target name><suffix> for several."""
    if not value:
        return [None] * len(targets)
    if len(targets) == 1:
        return [output_file(value, force, option, inputs=inputs, suffixes=suffixes)]
    folder = Path(value)
    if folder.suffix or (folder.exists() and not folder.is_dir()):
        raise InputError(f"{option} {folder}: with several targets, give a folder (one <target name> file each)")
    if not folder.is_dir() and not folder.parent.is_dir():
        raise InputError(f"output folder does not exist: {folder.parent}")
    paths = [folder / f"{t.stem}{default_suffix}" for t in targets]
    seen: dict[Path, Path] = {}
    for target, path in zip(targets, paths, strict=True):
        if path in seen:
            raise InputError(f"{seen[path]} and {target} would both write {path}; register them in separate calls")
        seen[path] = target
        if folder.is_dir():  # else the folder is made when the first result is written, and holds nothing yet
            output_file(path, force, option, inputs=inputs)
    return paths


def run(args: argparse.Namespace) -> int:
    from liver_p2p_reg.registration.methods import METHODS, Method, check_method_name

    args.sensor_origin_mm = sensor_origin(args.sensor_origin)
    targets = [Path(t) for t in args.targets]
    several = len(targets) > 1
    # --force replaces earlier outputs, never a file this command reads
    inputs = given_paths(
        args.source, targets, args.source_fiducials, args.target_fiducials, args.config, args.initial_transform,
        args.weights_path, args.structures,
    )  # fmt: skip
    outputs = _output_paths(args.output, targets, args.force, "--output", (), ".json", inputs)
    plots = _output_paths(args.plot, targets, args.force, "--plot", PLOT_SUFFIXES, ".png", inputs)
    moved = _output_paths(args.moved, targets, args.force, "--moved", MOVED_SUFFIXES, ".ply", inputs)
    config = _config(args)
    # --record wins; a config's record_path records too, as the node reads it: a folder gets flight_<time>.mcap,
    # and an existing recording is evidence, so a new name is taken rather than --force asked for
    record, record_option = getattr(args, "record", None), "--record"
    if not record and config.record_path:
        from liver_p2p_reg.bags.recorder import recording_path

        record, record_option = recording_path(config.record_path, "new"), "record_path (--config)"
        LOG.info("recording to %s (record_path of --config)", record)
    args.record_path = output_file(record, args.force, record_option, inputs=inputs, suffixes=(".mcap",))
    distinct_outputs({"--output": outputs, "--plot": plots, "--moved": moved, record_option: [args.record_path]})
    if (args.source_fiducials is None) != (args.target_fiducials is None):
        raise InputError("give both --source-fiducials and --target-fiducials, or neither")
    if several and args.target_fiducials is not None:
        raise InputError("--source-fiducials/--target-fiducials go with a single TARGET")
    check_method_name(config.method)
    warn_unused_weights(config.method, config.weights_path)
    prior = METHODS.get(config.method, Method("")).prior  # track (ICP from it) and evaluate (as is)
    if prior and args.initial_transform is None:
        raise InputError(f"--method {config.method} starts from a prior pose: give it with --initial-transform FILE")
    if args.initial_transform is not None and not prior:
        raise InputError("--initial-transform is used by --method track and --method evaluate only")
    from liver_p2p_reg.cli.register_outputs import source_mesh
    from liver_p2p_reg.cloud_io import check_point_file, load_points

    source_path = check_point_file(args.source)
    for path in [*targets, args.source_fiducials, args.target_fiducials]:
        if path is not None:
            check_point_file(path)
    initial_T = load_initial_transform(Path(args.initial_transform)) if args.initial_transform else None
    from liver_p2p_reg.structures_io import far_from_model, load_structures

    args.structure_list = load_structures(args.structures or [])  # InputError: one line, exit 2
    source = load_points(source_path, seed=config.seed)
    for structure in args.structure_list:  # a structure must lie at the organ, in its frame and units
        if problem := far_from_model(structure, source):
            raise InputError(problem)
    args.source_mesh = source_mesh(source_path) if config.deform else None  # the stage's closed surface
    from liver_p2p_reg.registration.error_calibration import check_calibrations

    check_calibrations(config)  # before the registrations (each pose checks again, after its rigid method)
    views = [load_points(t, seed=config.seed) for t in targets]  # every file is read before any work
    fiducials = (None, None)
    if args.source_fiducials is not None:  # the Registrar refuses NaN/inf pairs
        extent_max_mm = config.expected_extent_max_mm
        fiducials = (
            load_fiducials(args.source_fiducials, "--source-fiducials", extent_max_mm),
            load_fiducials(args.target_fiducials, "--target-fiducials", extent_max_mm),
        )
    slicer = None
    if args.slicer:  # connected before registering: no Slicer is one line, not a lost registration
        from liver_p2p_reg.cli.slicer import connect_to_slicer

        slicer = connect_to_slicer(args.slicer)
    prefetch = _prefetch_open3d(source, views, config)
    try:
        return _register_all(
            args,
            config,
            source_path,
            source,
            list(zip(targets, views, strict=True)),
            fiducials,
            initial_T,
            (outputs, plots, moved),
            slicer,
        )
    finally:
        if prefetch is not None:
            prefetch.close()
        if slicer is not None:
            slicer.endpoint.close()


def _prefetch_open3d(source, views, config):
    """Start Open3D's share of the registrations in a child process (registration/prefetch.py), which imports Open3D there
    while this process imports torch: the ICP's source normals, and RANSAC's pose of each view small enough
    for the default's candidate; learned `-icp` methods only, the ones that need both libraries. The child
    works on exactly the points the pipeline will (the Registrar's finite points, normalized as
    `preprocess.preprocess_pair` does); should they differ, the pipeline computes its own."""
    from liver_p2p_reg.registration.methods import METHODS

    if not (config.method.startswith("learned") and config.method.endswith("-icp")) or "open3d" in sys.modules:
        return None  # another method, or Open3D is here already (an STL/OBJ source): nothing to gain
    import numpy as np

    from liver_p2p_reg.registration.prefetch import BackgroundOpen3D
    from liver_p2p_reg.registration.preprocess import source_normalization

    finite = source[np.isfinite(source).all(axis=1)]
    try:
        full = source_normalization(finite).apply(finite)
    except InputError:
        return None  # the registration reports it
    row = METHODS.get(config.method)
    candidate = row is not None and row.ransac_candidate and config.ransac_candidate_visibility > 0
    try:
        return BackgroundOpen3D(
            full, config.normal_radius_norm, source_mm=source, views_mm=views if candidate else [], config=config
        )
    except OSError as exc:  # a speed-up only: without it this process computes everything itself
        LOG.debug("no Open3D child process (%s)", exc)
        return None


def _register_all(args, config, source_path, source, views: list, fiducials, initial_T, paths, slicer=None) -> int:
    """Register SOURCE to every view in one Registrar; write and print each result as it comes."""
    from liver_p2p_reg.registration.registrar import Registrar

    several = len(views) > 1
    outputs, plots, moved = paths
    for per_target in (outputs, plots, moved):  # several targets: the folders, now that every check passed
        if several and per_target[0] is not None:
            per_target[0].parent.mkdir(exist_ok=True)
    registrar = Registrar(config)
    recorder = None
    if args.record_path is not None:
        from liver_p2p_reg.bags.command_recording import open_command_recording

        recorder = open_command_recording(args.record_path, config, source, overwrite=args.force, mesh=args.source_mesh)
    try:
        return _register_each(args, config, registrar, source_path, source, views, fiducials, initial_T, paths, slicer, recorder)  # fmt: skip
    finally:
        if recorder is not None:
            recorder.close()


def _register_each(args, config, registrar, source_path, source, views, fiducials, initial_T, paths, slicer, recorder):
    """The registrations of _register_all, each recorded when --record is given."""
    from liver_p2p_reg.cli.register_outputs import summary_line, write_extras
    from liver_p2p_reg.structures_io import place_structures

    quiet = bool(getattr(args, "quiet", False))
    several = len(views) > 1
    fid_s, fid_t = fiducials
    outputs, plots, moved = paths
    json_to_stdout = args.output is None or args.json
    summary_stream = sys.stderr if json_to_stdout else sys.stdout
    failed = 0
    for i, (target_path, target) in enumerate(views):
        try:
            result = registrar.register(
                source,
                target,
                method=config.method,
                source_fiducials_mm=fid_s,
                target_fiducials_mm=fid_t,
                initial_T_mm=initial_T,
                sensor_origin_mm=args.sensor_origin_mm,
                source_triangles=args.source_mesh[1] if args.source_mesh else None,
                mesh_vertices_mm=args.source_mesh[0] if args.source_mesh else None,
            )
        except LiverP2PError as exc:
            _record(recorder, i, target_path, target, fiducials, initial_T, args, exc, config, source)
            if not several:
                raise
            print(f"liver-p2p: error: {target_path}: {exc}", file=sys.stderr, flush=True)
            failed += 1
            continue
        _record(recorder, i, target_path, target, fiducials, initial_T, args, result, config, source)
        placed = place_structures(result, args.structure_list)  # [] without --structures
        warnings = _warnings(result, config, placed)
        payload = {"source": str(source_path), "target": str(target_path), **result.to_json_dict()}
        payload.update(status="WARN" if warnings else "OK", warnings=warnings)
        if placed:
            payload["structures"] = [p.to_json_dict() for p in placed]
        if outputs[i] is not None:
            outputs[i].write_text(json.dumps(payload, indent=2) + "\n")
        if json_to_stdout:
            print(json.dumps(payload) if several else json.dumps(payload, indent=2), flush=True)
        for message in warnings:  # the node's WARN rules: the pose is still returned, but flagged
            LOG.warning("%s%s", f"{target_path}: " if several else "", message)
        if slicer is not None:
            from liver_p2p_reg.cli.slicer import send_registration

            send_registration(slicer, source_path, source, target, result, warnings, placed, args.source_mesh)
        written = write_extras(source, target, result, config, warnings, fid_s, fid_t, moved[i], plots[i])
        if not quiet:
            print(summary_line(target_path, payload, outputs[i], written), file=summary_stream, flush=True)
    return 2 if failed else 0


def _record(recorder, i, target_path, target, fiducials, initial_T, args, result, config, source) -> None:
    """One registration into the --record recording (its inputs exactly as registered; bags/recorder.py)."""
    if recorder is None:
        return
    from liver_p2p_reg.bags.command_recording import record_command_registration

    extras = {"sensor_origin_mm": args.sensor_origin_mm, "initial_T_mm": None}
    if initial_T is not None:
        extras["initial_T_mm"] = [[float(v) for v in row] for row in initial_T]
    record_command_registration(
        recorder, i, str(target_path), target, fiducials, extras, result, config, source, args.structure_list
    )


def _warnings(result, config, placed) -> list[str]:
    from liver_p2p_reg.registration.confidence import origin_warnings, result_warnings
    from liver_p2p_reg.structures_io import structure_bounds

    # an origin given that cannot be the target's sensor warns too (the recording's verdict says the same)
    return [*result_warnings(result, config, structure_bounds(placed) or None).values(), *origin_warnings(result)]
