"""rclpy adapter: `make demo` on the real graph: loader + register_node processes, every bundled bag played into them."""

from __future__ import annotations

import signal
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rclpy.serialization import serialize_message

from liver_p2p_reg.bags.io import BagWriter, read_messages
from liver_p2p_reg.bags.player import BagPlayer, Played
from liver_p2p_reg.bags.replay import fmt, markdown_table
from liver_p2p_reg.bags.replay_outputs import DEFORM_OUTPUT_TOPICS, OUTPUT_TOPICS
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.livegraph.graph import (
    GraphProbe,
    NodeProcess,
    level_of,
    set_isolated_environment,
    stamp_ns,
    values_of,
)
from liver_p2p_reg.ros.messages import mesh_marker_mm
from liver_p2p_reg.ros.pointcloud2 import M_PER_MM, cloud_to_points_m
from liver_p2p_reg.ros.topics import (
    TOPIC_DIAGNOSTICS,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
)
from liver_p2p_reg.stream.outputs import DIAG_NAME, LEVEL_NAMES, PREOP_DIAG_NAME

RECORDED_TYPES = {**OUTPUT_TOPICS, **DEFORM_OUTPUT_TOPICS}  # what the graph publishes, recorded like replay's
SETTLE_S = 15.0  # after the last cloud, how long the last registration may take to arrive


@dataclass
class GraphRow:
    """One bag through the live graph: what /diagnostics and /registration/pose said."""

    bag: str
    frames: int
    registered: int
    visibility: float
    rms_tre_mm: float
    residual_mm: float
    status: str
    latency_ms: list[float] = field(default_factory=list)  # cloud published -> its pose received
    tre_by_stamp: dict[int, float] = field(default_factory=dict)
    poses: dict[int, np.ndarray] = field(default_factory=dict)  # stamp -> (7,) xyz + quaternion xyzw
    reregister: str = ""  # the service's answer (success and message)
    warm_up_ms: float = float("nan")
    message: str = ""
    deform_applied: int = 0  # poses the non-rigid stage was applied on (deform on)
    deformed_rms_tre_mm: float = float("nan")  # mean over those

    def latency_p(self, q: float) -> float:
        return float(np.percentile(self.latency_ms, q)) if self.latency_ms else float("nan")


def model_files(bag: Path, folder: Path) -> tuple[Path, Path | None, Path | None]:
    """The bag's preop model (and fiducials) as .npy files in metres, and its /preop/mesh as a PLY in metres
    (None without one), for preop_loader_node."""
    messages = {m.topic: m.msg for m in read_messages(bag, [TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS, TOPIC_PREOP_MESH])}
    if TOPIC_PREOP not in messages:
        raise InputError(f"{bag} has no {TOPIC_PREOP}")
    folder.mkdir(parents=True, exist_ok=True)
    model = folder / "preop_points_m.npy"
    np.save(model, cloud_to_points_m(messages[TOPIC_PREOP]))
    fiducials = None
    if TOPIC_PREOP_FIDUCIALS in messages:
        fiducials = folder / "preop_fiducials_m.npy"
        np.save(fiducials, cloud_to_points_m(messages[TOPIC_PREOP_FIDUCIALS]))
    mesh = None
    if TOPIC_PREOP_MESH in messages:
        from liver_p2p_reg.o3d import o3d_module

        o3d = o3d_module()
        vertices_mm, triangles = mesh_marker_mm(messages[TOPIC_PREOP_MESH])  # welded as register_node welds it
        mesh = folder / "preop_mesh_m.ply"
        surface = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(vertices_mm * M_PER_MM), o3d.utility.Vector3iVector(triangles)
        )
        if not o3d.io.write_triangle_mesh(str(mesh), surface):
            raise InputError(f"could not write {mesh}")
    return model, fiducials, mesh


def run_bag(
    probe: GraphProbe, bag: Path, out_dir: Path, log_dir: Path, env: dict[str, str], deform: bool = False
) -> GraphRow:
    """Loader for the bag's model, then its /intraop/* played live, then one ~/reregister call."""
    model, fiducials, mesh = model_files(bag, out_dir)
    diag_index = probe.count(TOPIC_DIAGNOSTICS)
    starts = {topic: probe.count(topic) for topic in RECORDED_TYPES}
    params = {"model_path": str(model), "units": "m"}
    if fiducials is not None:
        params["fiducials_path"] = str(fiducials)
    if mesh is not None and deform:  # the stage's surface; without the stage the graph runs as it always did
        params["mesh_path"] = str(mesh)
    loader = NodeProcess("preop_loader_node", params, env=env, log_dir=log_dir, name=f"loader_{bag.name}")
    try:
        ready = probe.wait_for(lambda: _warmed_up(probe, diag_index), 120.0)  # not the mesh's, logged before
        if not ready:
            raise InputError(f"register_node reported no preop model for {bag.name} (see {log_dir})")
        warm_up_ms = float(values_of(ready[-1][0]).get("warm_up_ms", "nan"))
        player = BagPlayer(probe.node, bag, [TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS])
        player.wait_for_subscribers(20.0)
        played = player.play(1.0)
        clouds = {p.stamp_ns: p for p in played if p.topic == TOPIC_INTRAOP}
        last = max(clouds)
        probe.wait_for(lambda: last in _attempt_stamps(probe, diag_index), SETTLE_S)
        answer = probe.reregister()
        rereg = "no answer" if answer is None else f"{'pose' if answer.success else 'no pose'}: {answer.message}"
    finally:
        loader.stop(signal.SIGINT)
    row = _row(bag.name, probe, diag_index, starts, clouds)
    row.reregister, row.warm_up_ms = rereg, warm_up_ms
    _record(probe, starts, out_dir / "recorded")
    return row


def _warmed_up(probe: GraphProbe, diag_index: int) -> list[tuple[object, float]]:
    """The preop model's own statuses since `diag_index` (warmed up, unchanged or refused), not its mesh's."""
    preop = probe.diagnostics(diag_index, PREOP_DIAG_NAME)
    return [(s, t) for s, t in preop if "mesh_triangles" not in values_of(s)]


def _attempts(probe: GraphProbe, diag_index: int) -> list[tuple[object, float]]:
    """Registration diagnostics (not the periodic status, which carries counters) since `diag_index`."""
    return [(s, t) for s, t in probe.diagnostics(diag_index, DIAG_NAME) if "received_clouds" not in values_of(s)]


def _attempt_stamps(probe: GraphProbe, diag_index: int) -> set[int]:
    return {int(values_of(s).get("stamp_ns", -1)) for s, _ in _attempts(probe, diag_index)}


def _row(name: str, probe: GraphProbe, diag_index: int, starts: dict, clouds: dict[int, Played]) -> GraphRow:
    per_stamp: dict[int, dict[str, str]] = {}
    levels = []
    for status, _ in _attempts(probe, diag_index):
        values = values_of(status)
        stamp = int(values.get("stamp_ns", -1))
        if stamp in clouds and stamp not in per_stamp:  # the first attempt per cloud; the service's comes later
            per_stamp[stamp] = values
            levels.append((level_of(status), status.message))
    poses = {}
    latency = []
    for item in probe.since(TOPIC_POSE, starts[TOPIC_POSE]):
        stamp = stamp_ns(item.msg)
        if stamp in clouds and stamp not in poses:
            p, q = item.msg.pose.position, item.msg.pose.orientation
            poses[stamp] = np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
            latency.append((item.received_s - clouds[stamp].published_s) * 1e3)
    posed = [v for s, v in per_stamp.items() if s in poses]

    def mean(key: str) -> float:
        values = [float(v[key]) for v in posed if key in v]
        return float(np.mean(values)) if values else float("nan")

    worst = max(levels, default=(2, "no registration diagnostics"))
    return GraphRow(
        bag=name,
        frames=len(clouds),
        registered=len(poses),
        visibility=mean("visibility"),
        rms_tre_mm=mean("rms_tre_mm"),
        residual_mm=mean("residual_mm"),
        status=LEVEL_NAMES.get(worst[0], str(worst[0])) if poses or worst[0] else "ERROR",
        latency_ms=latency,
        tre_by_stamp={s: float(v["rms_tre_mm"]) for s, v in per_stamp.items() if "rms_tre_mm" in v},
        poses=poses,
        message=worst[1],
        deform_applied=sum(v.get("deform_applied") == "true" for v in posed),
        deformed_rms_tre_mm=mean("deformed_rms_tre_mm"),
    )


def _record(probe: GraphProbe, starts: dict, path: Path) -> None:
    """What the graph published during this bag, as a rosbag2 (MCAP) directory."""
    with BagWriter(path, overwrite=True) as writer:
        items = [(t, r) for t in RECORDED_TYPES for r in probe.since(t, starts[t])]
        for topic, item in sorted(items, key=lambda x: x[1].received_s):
            ns = time.time_ns() - int((time.monotonic() - item.received_s) * 1e9)  # wall clock of arrival
            writer.write_raw(topic, RECORDED_TYPES[topic], ns, serialize_message(item.msg))


def run_graph(
    bags: Sequence[Path], out_dir: Path, *, params: dict | None = None, log=print
) -> tuple[list[GraphRow], float]:
    """Start register_node on an isolated domain, run every bag through it; (rows, process start to
    first pose in s). Node logs go to out_dir/logs."""
    env = set_isolated_environment()
    log_dir = out_dir / "logs"
    node = NodeProcess("register_node", params or {}, env=env, log_dir=log_dir)
    probe = GraphProbe()
    rows: list[GraphRow] = []
    try:
        if not probe.wait_for_subscriber(TOPIC_INTRAOP, 60.0):
            raise InputError(f"register_node did not come up (see {log_dir}/register_node.stderr)")
        for bag in bags:
            deform = bool((params or {}).get("deform"))  # the loader then gives the node the bag's mesh too
            rows.append(run_bag(probe, bag, out_dir / bag.name.removesuffix(".mcap"), log_dir, env, deform))
            log(f"  {bag.name}: {rows[-1].registered}/{rows[-1].frames} poses, {rows[-1].status}")
            if not node.alive():
                raise InputError(f"register_node exited with status {node.proc.returncode} (see {log_dir})")
        first_pose = probe.since(TOPIC_POSE)
        startup_s = first_pose[0].received_s - node.started_s if first_pose else float("nan")
    finally:
        code, took = node.stop(signal.SIGINT)
        probe.close()
    if code != 0:
        raise InputError(f"register_node ended with status {code} after SIGINT ({took:.1f} s; see {log_dir})")
    return rows, startup_s


def format_graph_table(
    rows: Sequence[GraphRow], replay_tre: dict[str, float] | None = None, deform: bool = False
) -> str:
    """Per-bag table: visibility, RMS-TRE, residual, status, latency p50/p95 (and replay's TRE; with `deform`
    the deformed RMS-TRE and on how many poses the stage was applied)."""
    header = ["bag", "poses", "visibility", "RMS-TRE mm", "residual mm", "status", "latency ms p50", "p95"]
    if replay_tre is not None:
        header.append("replay RMS-TRE mm")
    if deform:
        header += ["deformed RMS-TRE mm", "deform applied"]
    body = []
    for r in rows:
        line = [
            r.bag,
            f"{r.registered}/{r.frames}",
            fmt(r.visibility),
            fmt(r.rms_tre_mm),
            fmt(r.residual_mm),
            r.status,
            fmt(r.latency_p(50), 0),
            fmt(r.latency_p(95), 0),
        ]
        if replay_tre is not None:
            line.append(fmt(replay_tre.get(r.bag, float("nan"))))
        if deform:
            line += [fmt(r.deformed_rms_tre_mm), f"{r.deform_applied}/{r.registered}"]
        body.append(line)
    return markdown_table(header, body)


def node_params(config: Config) -> dict:
    """The register_node parameters that differ from the defaults (what `--method`/`--config` changed)."""
    defaults = Config().to_dict()
    return {k: v for k, v in config.to_dict().items() if v != defaults[k]}
