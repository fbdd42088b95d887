"""Replay rosbag2/MCAP bags through the node core in timestamp order; write output bags; per-case table."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.io import MARKER, POINTCLOUD2, BagWriter, bag_custom_data, read_messages
from liver_p2p_reg.bags.make import CASE_KEY
from liver_p2p_reg.bags.replay_outputs import ReplayOutputs
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.registration.confidence import result_warnings
from liver_p2p_reg.registration.methods import check_method_name
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.ros.messages import (
    feed_intraop_fiducials_msg,
    feed_intraop_msg,
    feed_preop_fiducials_msg,
    feed_preop_mesh_msg,
    feed_preop_msg,
    feed_structure_labels_msg,
    feed_structures_msg,
)
from liver_p2p_reg.ros.pointcloud2 import cloud_to_points_mm, stamp_to_ns
from liver_p2p_reg.ros.topics import (
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
    TOPIC_PREOP_STRUCTURES,
    TOPIC_STRUCTURE_LABELS,
)
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.outputs import ERROR, LEVEL_NAMES, OK, CoreOutput
from liver_p2p_reg.structures_io import Structure, structure_bounds

LOG = logging.getLogger("liver_p2p_reg.replay")
__all__ = ["ReplayRow", "format_table", "replay_bag", "replay_bags"]


@dataclass
class ReplayRow:
    """One bag's replay summary (one row of the table)."""

    bag: str
    frames: int  # intraop clouds in the bag
    registered: int  # registrations that produced a pose
    visibility: float  # mean over registered frames (NaN if none)
    rms_tre_mm: float  # mean over registered frames (NaN without ground truth)
    max_rms_tre_mm: float  # worst frame
    residual_mm: float  # mean over registered frames
    runtime_ms_p50: float
    uncertainty_mm: float = float("nan")  # mean over registered frames
    runtime_ms: list[float] = field(default_factory=list)  # per registration, total
    tracked: int = 0  # registrations tracked from the previous pose (continuous mode)
    status: str = "OK"  # worst diagnostic level over the registrations
    message: str = ""  # the node's message on the first frame at that level ...
    message_frame: int = 0  # ... and that frame's number (1-based intraop frame; 0: none)
    output: str = ""  # output bag path ("" when not written)
    info: dict = field(default_factory=dict)  # the bag's case description (custom_data)
    # one dict per registration that gave a pose: stamp_ns, rms_tre_mm (None without ground truth),
    # level, method, and in survey mode survey_state / survey_visibility; with `deform` deform_applied, deform_ms and
    # deformed_rms_tre_mm (None unless applied with ground truth)
    per_frame: list[dict] = field(default_factory=list)
    deform: bool = False  # replayed with the non-rigid stage on
    deform_applied: int = 0  # registrations the stage was applied on
    deformed_rms_tre_mm: float = float("nan")  # mean over those (with ground truth)


def replay_bag(
    path: str | Path,
    config: Config,
    *,
    out_path: str | Path | None = None,
    overwrite: bool = False,
    registrar: Registrar | None = None,
    max_frames: int | None = None,
    plot_path: str | Path | None = None,
    observer: object | None = None,
    record_path: str | Path | None = None,
    structures: list[Structure] | None = None,
) -> ReplayRow:
    """Drive a NodeCore with a bag's messages in log-time order; optionally write inputs + outputs.

    Bag time stands in for the clock, so the rate limit and latest-only policy behave as live.
    max_frames: stop registering after this many registrations (quick tests); 0/None = all.
    plot_path: also draw the last registered frame (overlay.plot_registration) to this PNG.
    observer: gets on_input(topic, msg) for every message read and on_output(CoreOutput) for
    every output (the Slicer link of `replay --slicer`).
    record_path: flight-record the replay there (bags/recorder.py; else config.record_path, if set).
    structures: moved with every pose (the command line's --structures; else those the bag carries).
    """
    from liver_p2p_reg.bags.recorder import recorder_factory

    path = Path(path)
    info = _bag_info(path)
    if info.get("sensor_frame") is False and config.sensor_at_frame_origin:
        # clouds in another frame than their sensor's (simulated random crops): (0, 0, 0) is no sensor origin
        config = config.replace(sensor_at_frame_origin=False)
    if record_path:
        config = config.replace(record_path=str(record_path))
    core = NodeCore(config, registrar, recorder_factory("overwrite" if overwrite else "refuse"))
    if structures:
        core.structures.set_structures(structures)
    writer = BagWriter(out_path, overwrite=overwrite) if out_path else None
    sink = ReplayOutputs(writer, observer)
    outputs = sink.outputs
    last_ns = 0
    try:
        for item in read_messages(path):
            last_ns = item.timestamp_ns
            if observer is not None:
                observer.on_input(item.topic, item.msg)
            sink.copy_input(item)
            if item.topic == TOPIC_STRUCTURE_LABELS and not structures:  # std_msgs/String
                feed_structure_labels_msg(core, item.msg.data)
            if item.topic == TOPIC_PREOP_MESH and item.msgtype == MARKER:  # as register_node: kept, then prepared
                diag = feed_preop_mesh_msg(core, item.msg)
                sink.report([diag, core.prepare_deformation() if diag.level == OK else None], item.timestamp_ns)
            if item.msgtype != POINTCLOUD2:
                continue
            if item.topic == TOPIC_PREOP:
                sink.report([feed_preop_msg(core, item.msg)], item.timestamp_ns)
            elif item.topic == TOPIC_PREOP_STRUCTURES and not structures:
                feed_structures_msg(core, item.msg)
            elif item.topic == TOPIC_PREOP_FIDUCIALS:
                feed_preop_fiducials_msg(core, item.msg)
            elif item.topic == TOPIC_INTRAOP_FIDUCIALS:
                feed_intraop_fiducials_msg(core, item.msg)
                sink.latest["fiducials"] = item.msg
            elif item.topic == TOPIC_INTRAOP:
                sink.frames += 1
                sink.latest["cloud"] = item.msg
                if max_frames and len(outputs) >= max_frames:
                    continue
                for diag in feed_intraop_msg(core, item.msg):
                    sink.emit(CoreOutput([diag]), item.timestamp_ns, item.timestamp_ns)
                sink.emit(
                    core.process_pending(item.timestamp_ns * 1e-9),
                    stamp_to_ns(item.msg.header.stamp),
                    item.timestamp_ns,
                )
        if not (max_frames and len(outputs) >= max_frames):
            sink.emit(core.flush(), last_ns, last_ns + 1)
    finally:
        core.close_recording()
        if writer is not None:
            writer.close()
    frames, last_posed = sink.frames, sink.last_posed
    if plot_path is not None and last_posed is not None:
        output, cloud, fiducials, frame = last_posed
        title = f"{path.name}, frame {frame} of {frames} (the last registered)"
        _plot_frame(plot_path, core, output, cloud, fiducials, title=title)
    row = _summarize(path, frames, outputs, str(out_path or ""), info, sink.output_frames, core.config.mode)
    row.deform = core.config.deform
    return row


def _bag_info(path: Path) -> dict:
    """The case description a bag carries in its metadata (bag_make.CASE_KEY), {} if none."""
    custom = bag_custom_data(path)
    if CASE_KEY not in custom:
        return {}
    try:
        info = json.loads(custom[CASE_KEY])
    except ValueError:
        return {}
    return info if isinstance(info, dict) else {}


def _plot_frame(
    plot_path: str | Path, core: NodeCore, output: CoreOutput, cloud: object, fiducials: object, title: str
) -> None:
    """The overlay PNG of one registered frame, with the bag's ground-truth fiducials when it has them."""
    from liver_p2p_reg.overlay import plot_registration

    fid_s, fid_t = core.preop_fiducials_mm, None
    if fid_s is not None and fiducials is not None:
        fid_t = cloud_to_points_mm(fiducials)
    if fid_t is None or fid_t.shape != fid_s.shape:
        fid_s = fid_t = None
    result = output.result
    warnings = None
    if output.level != OK:  # the node's reasons, else (e.g. a units warning) its whole message
        reasons = result_warnings(result, core.config, structure_bounds(output.structures) or None)
        warnings = list(reasons.values()) or [output.summary]
    plot_registration(
        core.preop_mm,
        cloud_to_points_mm(cloud),
        result,
        plot_path,
        warnings=warnings,
        residual_warn_mm=core.config.residual_warn_mm,
        source_fiducials_mm=fid_s,
        target_fiducials_mm=fid_t,
        title=title,
    )


def _summarize(
    path: Path, frames: int, outputs: list[CoreOutput], out: str, info: dict, output_frames: list[int], mode: str
) -> ReplayRow:
    results = [o.result for o in outputs if o.pose is not None and o.result is not None]
    worst = max((o.level for o in outputs), default=ERROR)
    if frames == 0:
        worst = ERROR
    runtimes = [float(r.runtime_ms.get("total", np.nan)) for r in results]
    tres = [r.rms_tre_mm for r in results if r.rms_tre_mm is not None]

    def mean(values: list[float]) -> float:
        return float(np.mean(values)) if values else float("nan")

    messages = [(o.summary, f) for o, f in zip(outputs, output_frames, strict=True) if o.level == worst]
    posed = [o for o in outputs if o.pose is not None and o.result is not None]
    per_frame = [
        {
            "stamp_ns": o.pose.stamp_ns,
            "rms_tre_mm": o.result.rms_tre_mm,
            "level": o.level,
            "method": o.result.method,
            **{k: v for k, v in o.diagnostics[0].values.items() if k.startswith("survey_")},
            **_deform_frame(o),
        }
        for o in posed
    ]
    applied = [o for o in posed if o.deformed_preop_mm is not None]
    deformed_tres = [o.result.deformed_rms_tre_mm for o in applied if o.result.deformed_rms_tre_mm is not None]
    return ReplayRow(
        bag=path.name,
        frames=frames,
        registered=len(results),
        visibility=mean([r.visibility for r in results]),
        rms_tre_mm=mean(tres),
        max_rms_tre_mm=float(np.max(tres)) if tres else float("nan"),
        residual_mm=mean([r.residual_mm for r in results]),
        runtime_ms_p50=float(np.median(runtimes)) if runtimes else float("nan"),
        uncertainty_mm=mean([r.uncertainty_mm for r in results]),
        runtime_ms=runtimes,
        tracked=sum(r.method == "track" for r in results),
        status=LEVEL_NAMES[worst] if results or worst != OK else "ERROR",
        message=messages[0][0] if messages else _nothing_registered(frames, mode),
        message_frame=messages[0][1] if messages else 0,
        output=out,
        info=info,
        per_frame=per_frame,
        deform_applied=len(applied),
        deformed_rms_tre_mm=mean(deformed_tres),
    )


def _nothing_registered(frames: int, mode: str) -> str:
    """Why a bag's replay gave no output at all (its status is ERROR and it says so in one line)."""
    if frames == 0:
        return "no intraop frames"
    if mode == "on_demand":  # the node's on_demand waits for ~/reregister, which no replay calls
        return (
            f"none of its {frames} frames was registered: mode on_demand registers only when ~/reregister is "
            "called, which a replay never does; use --mode once or continuous"
        )
    return f"none of its {frames} frames was registered"


def _deform_frame(output: CoreOutput) -> dict:
    """A registration's non-rigid stage for per_frame: applied or not, the deformed RMS-TRE ({} when it did not run)."""
    if "deform_applied" not in output.diagnostics[0].values:
        return {}
    applied = output.deformed_preop_mm is not None
    return {
        "deform_applied": applied,
        "deformed_rms_tre_mm": output.result.deformed_rms_tre_mm if applied else None,
        "deform_ms": float(output.diagnostics[0].values["deform_ms"]),
    }


def replay_bags(
    paths: Sequence[str | Path],
    config: Config,
    out_dir: str | Path | None = None,
    progress: bool = True,
    overwrite: bool = False,
    max_frames: int | None = None,
    plot_dir: str | Path | None = None,
    observer: object | None = None,
    record: str | Path | None = None,
    structures: list[Structure] | None = None,
) -> list[ReplayRow]:
    """Replay several bags with one Registrar (method caches shared); output bags go to out_dir/<name>,
    overlay PNGs of each bag's last registered frame to plot_dir/<name>.png, flight recordings to
    `record` (one bag) or record/<name>.mcap (several); `structures` move with every bag's poses."""
    if not paths:
        raise InputError("no bags given")
    check_method_name(config.method)  # an unknown method is one InputError up front, not an ERROR per frame
    plots = {Path(p): None if plot_dir is None else Path(plot_dir) / f"{_bag_name(Path(p))}.png" for p in paths}
    if plot_dir is not None:
        existing = [str(p) for p in plots.values() if p.exists()]
        if existing and not overwrite:
            raise InputError(f"{existing[0]} exists; pass --force to overwrite the plots")
        Path(plot_dir).mkdir(parents=True, exist_ok=True)
    registrar = Registrar(config)
    rows = []
    iterator = paths
    if progress:
        from tqdm import tqdm

        iterator = tqdm(paths, desc="replay", unit="bag")
    for path in iterator:
        path = Path(path)
        out = None if out_dir is None else Path(out_dir) / _bag_name(path)
        recording = record if not record or len(paths) == 1 else Path(record) / f"{_bag_name(path)}.mcap"
        rows.append(
            replay_bag(
                path,
                config,
                out_path=out,
                overwrite=overwrite,
                registrar=registrar,
                max_frames=max_frames,
                plot_path=plots[path],
                observer=observer,
                record_path=recording,
                structures=structures,
            )
        )
    return rows


def _bag_name(path: Path) -> str:
    return path.name.removesuffix(".mcap")


def fmt(value: float, digits: int = 2) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def format_flags(rows: Sequence[ReplayRow]) -> list[str]:
    """Why each bag is not OK, in the node's words, saying which frame the message (and its RMS-TRE) is."""
    return [
        f"{r.bag}: {r.status} (frame {r.message_frame} of {r.frames}, the first at {r.status}): {r.message}"
        if r.message_frame
        else f"{r.bag}: {r.status}: {r.message}"
        for r in rows
        if r.status != "OK"
    ]


def format_table(rows: Sequence[ReplayRow]) -> str:
    """Markdown-style table: bag, frames, visibility, RMS-TRE (mean and worst frame), residual,
    uncertainty, runtime (p50), status; when any bag was replayed with `deform`, the deformed RMS-TRE
    (mean over the frames the stage was applied on) and on how many it was."""
    header = "bag|frames|visibility|RMS-TRE mm (mean)|(worst frame)|residual mm|uncertainty mm|runtime ms (p50)|status"
    header = header.split("|")
    deform = any(r.deform for r in rows)
    if deform:
        header += ["deformed RMS-TRE mm (mean)", "deform applied"]
    body = []
    for r in rows:
        line = [
            r.bag,
            f"{r.registered}/{r.frames}",
            fmt(r.visibility),
            fmt(r.rms_tre_mm),
            fmt(r.max_rms_tre_mm),
            fmt(r.residual_mm),
            fmt(r.uncertainty_mm, 1),
            fmt(r.runtime_ms_p50, 0),
            r.status,
        ]
        if deform:
            line += [fmt(r.deformed_rms_tre_mm), f"{r.deform_applied}/{r.registered}" if r.deform else "-"]
        body.append(line)
    return markdown_table(header, body)


def markdown_table(header: Sequence[str], body: Sequence[Sequence[str]]) -> str:
    """A Markdown table with padded columns (readable as plain text too)."""
    widths = [max(len(h), *(len(row[i]) for row in body)) if body else len(h) for i, h in enumerate(header)]
    lines = ["| " + " | ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)) + " |"]
    lines.append("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for row in body:
        lines.append("| " + " | ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) + " |")
    return "\n".join(lines)
