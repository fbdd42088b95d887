"""`liver-p2p demo`: the main job — every bundled bag through the live ROS 2 graph (replay without rclpy), per-case table."""

from __future__ import annotations

import argparse
from pathlib import Path

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError


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
    p = subparsers.add_parser(
        "demo", help="run every bundled bag through the live ROS 2 graph (or the replay without rclpy)"
    )
    p.add_argument("--method", help="registration method (default: the configured default)")
    p.add_argument("--config", help="YAML configuration file")
    p.add_argument(
        "--deform",
        action="store_true",
        help="run the non-rigid stage after each pose (deform: true), in the live graph and the replay",
    )
    p.add_argument(
        "--out",
        default="out/demo",
        help="folder for recorded/output bags, node logs and an overlay PNG per bag, replaced on each run "
        "(default: out/demo)",
    )
    p.add_argument("--replay", action="store_true", help="skip the live graph: the ROS-free replay only")
    p.add_argument("--bags", default="*", help="only the bundled bags whose name matches this glob (default: all)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from liver_p2p_reg.bags.replay import format_flags, format_table, replay_bags
    from liver_p2p_reg.o3d import quiet_open3d

    quiet_open3d()  # RANSAC's C++ warnings would interleave with the table on stdout

    config = Config.from_yaml(args.config) if args.config else Config()
    if args.method:
        config = config.replace(method=args.method)
    if args.deform:
        config = config.replace(deform=True)
    bags = bundled_bags_dir()
    if bags is None:
        raise InputError("no bundled bags found (expected a bags/ folder next to the package)")
    try:  # pathlib refuses an empty or absolute pattern with ValueError / NotImplementedError
        matched = list(bags.glob(args.bags))
    except (ValueError, NotImplementedError):
        raise InputError(f"--bags {args.bags!r}: give a name pattern such as 'phantom_*' (no path)") from None
    paths = sorted(p for p in matched if (p / "metadata.yaml").is_file() or p.suffix == ".mcap")
    if not paths:
        raise InputError(f"no bundled bag matches {args.bags!r} in {bags}")
    out = _demo_out(args.out, bags)
    graph = None
    if not args.replay:
        try:
            from liver_p2p_reg.livegraph import demo as graph_demo  # the rclpy adapter: importable only where rclpy is
        except ImportError as exc:
            print(f"rclpy not importable ({exc}): running the ROS-free replay instead of the live graph", flush=True)
        else:
            graph = _run_graph(graph_demo, paths, config, out)
    print(f"Replaying {len(paths)} bundled bags from {bags} with method {config.method} (no ROS) ...", flush=True)
    rows = replay_bags(paths, config, out_dir=out / "replay", progress=graph is None, overwrite=True, plot_dir=out)
    if graph is None:
        print(format_table(rows))
        print(f"Output bags: {out}/replay/; an overlay PNG of each bag's last registered frame: {out}/")
        for line in format_flags(rows):  # why a bag is not OK, in the node's own words, and which frame that is
            print(line)
        return 1 if any(r.status not in ("OK", "WARN") for r in rows) else 0
    return _report_graph(graph, rows, out)


def _demo_out(value: str, bags: Path) -> Path:
    """The demo's output folder, checked before any work: a folder (made if missing), outside the bundled bags
    (it writes OUT/<bag>/ and OUT/replay/, which inside bags/ would land in or beside the bags it reads)."""
    from liver_p2p_reg.cli.output_paths import output_folder
    from liver_p2p_reg.files import path_inside

    out = output_folder(value, "--out", inputs=[bags])
    if out is None:
        raise InputError("--out: give a folder")
    if path_inside(out, bags):
        raise InputError(f"--out {out} is inside {bags}, the bundled bags the demo reads; choose another folder")
    return out


def _run_graph(graph_demo, paths: list[Path], config: Config, out: Path) -> tuple[list, float]:
    print(
        f"Live ROS 2 graph: register_node and a preop_loader_node per bag as processes (method {config.method}); "
        f"each bag's /intraop/* played in real time, then ~/reregister ...",
        flush=True,
    )
    return graph_demo.run_graph(paths, out, params=graph_demo.node_params(config))


def _report_graph(graph: tuple[list, float], replay_rows: list, out: Path) -> int:
    import numpy as np

    from liver_p2p_reg.livegraph.demo import format_graph_table

    rows, startup_s = graph
    replay_tre = {r.bag: r.rms_tre_mm for r in replay_rows}
    print(format_graph_table(rows, replay_tre, deform=any(r.deform for r in replay_rows)))
    deltas = [abs(r.rms_tre_mm - replay_tre[r.bag]) for r in rows if np.isfinite(r.rms_tre_mm) and r.bag in replay_tre]
    latency = [v for r in rows for v in r.latency_ms]
    poses = sum(r.registered for r in rows)
    print(
        f"{poses}/{sum(r.frames for r in rows)} clouds got a pose; latency publish->pose p50 "
        f"{np.percentile(latency, 50):.0f} ms, p95 {np.percentile(latency, 95):.0f} ms; process start to first "
        f"pose {startup_s:.1f} s; largest |RMS-TRE - replay's| {max(deltas, default=float('nan')):.3f} mm"
        if latency
        else "no pose arrived"
    )
    print(f"Recorded /registration/* and /diagnostics per bag, node logs: {out}/; overlay PNGs: {out}/")
    for row in rows:
        print(f"{row.bag}: ~/reregister -> {row.reregister}")
        if row.status != "OK":
            print(f"{row.bag}: {row.status}: {row.message}")
    return 1 if any(r.status not in ("OK", "WARN") for r in rows) or not latency else 0
