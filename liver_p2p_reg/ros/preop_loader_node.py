"""rclpy adapter: preop_loader_node publishes a preop model (fiducials, structures) latched on /preop/*, in metres."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.timer import Timer
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import Marker

from liver_p2p_reg.cloud_io import MESH_FORMATS, load_mesh, load_points
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.ros.messages import (
    diagnostic_array,
    preop_structures_cloud,
    structure_labels_json,
    triangle_list_marker,
)
from liver_p2p_reg.ros.node_main import run_node
from liver_p2p_reg.ros.pointcloud2 import M_PER_MM, points_to_cloud, stamp_to_ns
from liver_p2p_reg.ros.rclpy_types import RCLPY_MARKER_TYPES, RCLPY_TYPES
from liver_p2p_reg.ros.topics import (
    TOPIC_DIAGNOSTICS,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
    TOPIC_PREOP_MESH,
    TOPIC_PREOP_STRUCTURES,
    TOPIC_STRUCTURE_LABELS,
    rclpy_qos,
)
from liver_p2p_reg.stream.outputs import ERROR, LOADER_DIAG_NAME, OK, Diagnostic
from liver_p2p_reg.structures_io import Structure, far_from_model, read_structures

TYPES = RCLPY_TYPES.cloud
UNITS_TO_M = {"mm": M_PER_MM, "m": 1.0}
# string parameters and defaults; mesh_path: the /preop/mesh of a model given as points (else model_path's triangles)
FILE_PARAMETERS = (("model_path", ""), ("fiducials_path", ""), ("mesh_path", ""), ("frame_id", "ct"), ("units", "mm"))
STATUS_PERIOD_S = 1.0  # the loader's status on /diagnostics, repeated for late joiners (diagnostics are volatile)


def load_model_m(path: str, units: str, parameter: str = "model_path") -> np.ndarray:
    """Load a mesh/cloud file and return (N, 3) metres; InputError (naming `parameter`) for missing/unreadable files."""
    if units not in UNITS_TO_M:
        raise InputError(f"units must be 'mm' or 'm', got {units!r}")
    if not path:
        raise InputError(f"parameter {parameter} is required (PLY/STL/OBJ/VTK mesh or point cloud)")
    if not Path(path).exists():
        raise InputError(f"{parameter} not found: {path}")
    try:
        points = load_points(path)  # a folder or a pipe: said as such (require_regular_file)
    except InputError as exc:
        raise InputError(f"{parameter}: {exc}") from None
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) == 0:
        raise InputError(f"{path} holds no valid points")
    return points * UNITS_TO_M[units]


def mesh_marker(path: str, units: str, frame_id: str, stamp: Time, *, required: bool = False) -> Marker | None:
    """The file's triangles as a Marker TRIANGLE_LIST in metres (for /preop/mesh), None for a cloud; `required`
    (the mesh_path parameter): InputError instead of None, the file being given as a mesh."""
    if required and not Path(path).is_file():
        raise InputError(f"mesh_path not found: {path}")
    if Path(path).suffix.lower() not in MESH_FORMATS:
        if required:
            raise InputError(f"mesh_path {path} is not a mesh file ({', '.join(sorted(MESH_FORMATS))})")
        return None
    vertices, triangles = load_mesh(path)
    if len(triangles) == 0 or not np.isfinite(vertices).all():
        if required:
            raise InputError(f"mesh_path {path} holds no triangles with finite vertices")
        return None
    vertices_m = vertices * UNITS_TO_M[units]
    return triangle_list_marker(vertices_m, triangles, RCLPY_MARKER_TYPES, frame_id, stamp_to_ns(stamp))


def structure_specs(value: Any) -> list[str]:
    """The structures_paths parameter as a list of 'FILE[:LABEL]' specs: a string array, or one string of
    comma-separated specs (what a launch argument gives); empty entries are skipped."""
    if not isinstance(value, (str, list, tuple)) and value is not None:  # `structures_paths:=true` raised a TypeError
        raise InputError(f"structures_paths must be a string or a list of strings, got {value!r}")
    items = value.split(",") if isinstance(value, str) else list(value or [])
    return [str(item).strip() for item in items if str(item).strip()]


def loader_status(loaded: dict[str, Any]) -> Diagnostic:
    """The loader's diagnostic: OK with what it published, ERROR naming each structure file it could not use."""
    structures: list[Structure] = loaded["structures"]
    values = {
        "model_path": loaded["model_path"],
        "model_points": str(len(loaded["model_m"])),
        "structures": ",".join(s.label for s in structures),
    }
    published = f"model {loaded['model_path']} ({len(loaded['model_m'])} points), {len(structures)} structure(s)"
    if not loaded["structure_errors"]:
        return Diagnostic(OK, LOADER_DIAG_NAME, f"published {published}", values)
    for spec, reason in loaded["structure_errors"]:
        values[f"structure_error.{spec}"] = reason
    reasons = "; ".join(reason for _, reason in loaded["structure_errors"])
    return Diagnostic(ERROR, LOADER_DIAG_NAME, f"bad structure file(s): {reasons}; published {published}", values)


class PreopLoaderWiring:
    """The loader's two steps, mixed into an rclpy Node or LifecycleNode: `_load` reads the files (the
    managed node's configure), `_publish_model` publishes them latched (activate); `_unpublish` removes the
    publishers again (deactivate), so a late joiner no longer gets a model this node does not stand behind."""

    def _declare(self: Any) -> None:
        for name, default in FILE_PARAMETERS:
            self.declare_parameter(name, default)
        # a string array, or one string of comma-separated specs (dynamic typing: a launch argument is a string)
        self.declare_parameter("structures_paths", [], ParameterDescriptor(dynamic_typing=True))
        self._model_publishers: list[Any] = []  # not `_publishers`: rclpy's Node keeps its own list by that name
        self.loaded: dict[str, Any] | None = None

    def _load(self: Any) -> None:
        """Read the model (and fiducials) files now, InputError for a missing or unreadable one; then the
        structure files: a bad one is left out, reported as an ERROR on /diagnostics with its reason."""
        param = {n: self.get_parameter(n).value for n, _ in FILE_PARAMETERS}
        model_m = load_model_m(param["model_path"], param["units"])
        fiducials_path = param["fiducials_path"]
        fiducials_m = load_model_m(fiducials_path, param["units"], "fiducials_path") if fiducials_path else None
        specs = structure_specs(self.get_parameter("structures_paths").value)
        structures, errors = read_structures(specs, to_mm=UNITS_TO_M[param["units"]] * 1e3)
        far = {s.label: far_from_model(s, model_m * 1e3) for s in structures}  # another frame or unit: not published
        errors += [(s.path, far[s.label]) for s in structures if far[s.label]]
        structures = [
            dataclasses.replace(s, label_id=i) for i, s in enumerate(s for s in structures if not far[s.label])
        ]
        stamp_ns = self.get_clock().now().nanoseconds
        # the mesh itself, for viewers (the Slicer bridge, RViz); same stamp as its points: they pair by it
        stamp = Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if param["mesh_path"]:  # a cloud model with its CT mesh beside it (the bag replayed in the demo)
            mesh = mesh_marker(param["mesh_path"], param["units"], param["frame_id"], stamp, required=True)
        else:
            mesh = mesh_marker(param["model_path"], param["units"], param["frame_id"], stamp)
        self.loaded = {**param, "model_m": model_m, "fiducials_m": fiducials_m, "mesh": mesh, "stamp_ns": stamp_ns}
        self.loaded.update(structures=structures, structure_errors=errors)
        for spec, reason in errors:
            self.get_logger().error(f"structure {spec} not published: {reason}")

    def _publish_model(self: Any) -> None:
        loaded, log = self.loaded, self.get_logger()
        frame_id, stamp_ns = loaded["frame_id"], loaded["stamp_ns"]
        if loaded["mesh"] is not None:
            self.mesh_pub = self._latched(Marker, TOPIC_PREOP_MESH)
            self.mesh_pub.publish(loaded["mesh"])
            log.info(f"published the mesh ({len(loaded['mesh'].points) // 3} triangles) on {TOPIC_PREOP_MESH}")
        self.points_pub = self._latched(PointCloud2, TOPIC_PREOP)
        self.points_pub.publish(points_to_cloud(loaded["model_m"], TYPES, frame_id=frame_id, stamp_ns=stamp_ns))
        log.info(
            f"published {len(loaded['model_m'])} preop points from {loaded['model_path']} on {TOPIC_PREOP} ({frame_id})"
        )
        if loaded["fiducials_m"] is not None:
            self.fiducials_pub = self._latched(PointCloud2, TOPIC_PREOP_FIDUCIALS)
            self.fiducials_pub.publish(
                points_to_cloud(loaded["fiducials_m"], TYPES, frame_id=frame_id, stamp_ns=stamp_ns)
            )
            log.info(f"published {len(loaded['fiducials_m'])} fiducials on {TOPIC_PREOP_FIDUCIALS}")
        # the structures, always (none: an empty cloud), so register_node drops another loader's set
        structures = loaded["structures"]
        self._latched(PointCloud2, TOPIC_PREOP_STRUCTURES).publish(
            preop_structures_cloud(structures, TYPES, frame_id, stamp_ns)
        )
        self._latched(String, TOPIC_STRUCTURE_LABELS).publish(String(data=structure_labels_json(structures, stamp_ns)))
        log.info(
            f"published {len(structures)} structure(s) on {TOPIC_PREOP_STRUCTURES}: {[s.label for s in structures]}"
        )
        self.status = loader_status(loaded)
        self.status_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, rclpy_qos(TOPIC_DIAGNOSTICS))
        self._model_publishers.append(self.status_pub)
        # on the steady clock, as register_node's status: a bag's /clock must not stop it
        timer = self.create_timer(STATUS_PERIOD_S, self._publish_status, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._model_publishers.append(timer)
        self._publish_status()

    def _publish_status(self: Any) -> None:
        stamp_ns = self.get_clock().now().nanoseconds
        self.status_pub.publish(diagnostic_array([self.status], stamp_ns, RCLPY_TYPES))

    def _latched(self: Any, msg_type: type, topic: str) -> Any:
        publisher = self.create_publisher(msg_type, topic, rclpy_qos(topic))
        self._model_publishers.append(publisher)
        return publisher

    def _unpublish(self: Any) -> None:
        for entity in self._model_publishers:  # publishers, and the status timer
            (self.destroy_timer if isinstance(entity, Timer) else self.destroy_publisher)(entity)
        self._model_publishers = []


class PreopLoaderNode(PreopLoaderWiring, Node):
    """Loads the preop model once and publishes it latched (reliable + transient local)."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("preop_loader_node", **node_kwargs)  # node_kwargs: e.g. parameter_overrides (tests)
        self._declare()
        self._load()
        self._publish_model()


def main(args: list[str] | None = None) -> int:
    """`ros2 run liver_p2p_reg preop_loader_node --ros-args -p model_path:=liver.stl`; exits the process.

    It spins to keep the latched messages available for late joiners; a missing or unreadable model or
    fiducials file is one fatal line and exit status 1; a bad structure file is an ERROR on /diagnostics
    (the model and the other structures are published).
    """
    return run_node(PreopLoaderNode, "preop_loader_node", args, exit_process=True)


if __name__ == "__main__":
    raise SystemExit(main())
