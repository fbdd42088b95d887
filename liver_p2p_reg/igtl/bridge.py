"""Registration outputs (mm) as Slicer's OpenIGTLink messages: model, cloud, CTToSensor transform, status."""

from __future__ import annotations

import time

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.igtl import scene, wire
from liver_p2p_reg.igtl.endpoint import Endpoint, IgtlClient, IgtlServer, LogFn
from liver_p2p_reg.slicer_config import IGTL_DEVICE_NAME_BYTES, SlicerConfig


def open_endpoint(config: SlicerConfig, log: LogFn | None = None) -> Endpoint:
    """The server or client the configuration asks for, already running."""
    limits = {
        "max_queue_messages": config.max_queue_messages,
        "max_queue_bytes": int(config.max_queue_mb * (1 << 20)),
        "log": log,
    }
    if config.role == "server":
        return IgtlServer(config.host, config.port, **limits)
    return IgtlClient(config.host, config.port, config.reconnect_period_s, **limits)


class SlicerBridge:
    """Encodes each output once and publishes it under its device; the endpoint does the rest.

    Every method returns at once: encoding is a few array copies and a checksum, and sending
    happens on the endpoint's own thread.
    """

    def __init__(self, config: SlicerConfig, endpoint: Endpoint) -> None:
        self.config = config.validate()
        self.endpoint = endpoint
        wire.crc64(b"")  # a missing checksum library is one clear error now, not one per message later

    def send_model(self, points_ct_mm: np.ndarray, triangles: np.ndarray | None = None, stamp_ns: int = 0) -> int:
        """The preop model (ct frame, mm): the mesh if triangles are given, else its points; returns points sent."""
        ras = scene.ct_to_slicer(points_ct_mm, self.config.ct_convention)
        sent, body = self._surface_body(ras, triangles, "preop")
        self._publish("POLYDATA", self.config.model_device, body, stamp_ns)
        return sent

    def send_deformed_model(
        self, points_sensor_mm: np.ndarray, triangles: np.ndarray | None = None, stamp_ns: int = 0
    ) -> int:
        """The deformed preop model, sensor frame (mm; not under CTToSensor): a mesh or points; returns points sent."""
        sent, body = self._surface_body(points_sensor_mm, triangles, "deformed preop")
        self._publish("POLYDATA", self.config.deformed_model_device, body, stamp_ns)
        return sent

    def _surface_body(self, points_mm: np.ndarray, triangles: np.ndarray | None, what: str) -> tuple[int, bytes]:
        """(points sent, POLYDATA body) of a model in Slicer's coordinates: the mesh, or points decimated and splatted."""
        if triangles is not None and len(triangles):
            points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
            if not np.isfinite(points).all():  # triangles index every vertex: none can be dropped
                raise InputError(f"{what} mesh has non-finite vertices")
            return len(points), wire.polydata_body(points, triangles)
        points = scene.decimate(_finite(points_mm, f"{what} model"), self.config.max_model_points)
        return len(points), wire.polydata_body(*scene.splat(points, self.config.point_size_mm))

    def send_cloud(self, points_sensor_mm: np.ndarray, stamp_ns: int = 0) -> int:
        """The intraop cloud (sensor frame, mm), decimated; returns points sent."""
        points = scene.decimate(_finite(points_sensor_mm, "intraop cloud"), self.config.max_cloud_points)
        body = wire.polydata_body(*scene.splat(points, self.config.point_size_mm))
        self._publish("POLYDATA", self.config.cloud_device, body, stamp_ns)
        return len(points)

    def send_structure(self, device: str, points_sensor_mm: np.ndarray, stamp_ns: int = 0) -> int:
        """One structure moved into the sensor frame (mm), under its own device (`structure_device`), its points
        drawn as the cloud's are (each a small triangle; the first N points of the POLYDATA are the structure's);
        returns points sent."""
        points = _finite(points_sensor_mm, f"structure {device}")
        body = wire.polydata_body(*scene.splat(points, self.config.point_size_mm))
        self._publish("POLYDATA", device, body, stamp_ns)
        return len(points)

    def structure_devices(self, labels: list[str]) -> list[str]:
        """The device names of structures with these labels: each label as it is when it is a valid device
        name, else made one (non-ASCII and unprintable characters as '_', cut to 20 bytes), never one of the
        bridge's own devices nor another structure's (a clash gets a '~2', '~3', ... suffix)."""
        taken = set(self.config.devices())
        return [_device_name(label, taken) for label in labels]

    def send_pose(self, T_sensor_ct_mm: np.ndarray, stamp_ns: int = 0) -> np.ndarray:
        """The CTToSensor TRANSFORM of a pose T_sensor_ct (mm); returns the matrix sent."""
        matrix = scene.slicer_transform(T_sensor_ct_mm, self.config.ct_convention)
        self._publish("TRANSFORM", self.config.transform_device, wire.transform_body(matrix), stamp_ns)
        return matrix

    def send_status(self, level_name: str, message: str, stamp_ns: int = 0) -> str:
        """A STRING 'LEVEL: message' (OK, WARN, ERROR); returns the text sent."""
        text = f"{level_name}: {message}"
        # every verdict counts (a WARN must not be replaced by the next OK before it is seen): not coalesced
        self._publish("STRING", self.config.status_device, wire.string_body(text), stamp_ns, replace=False)
        return text

    def _publish(self, type_name: str, device: str, body: bytes, stamp_ns: int, replace: bool = True) -> None:
        stamp_ns = stamp_ns or time.time_ns()  # no stamp (a file on the command line): now
        message = wire.pack_message(type_name, device, body, stamp_ns)
        self.endpoint.publish(f"{type_name}:{device}", message, replace)


def _device_name(label: str, taken: set[str]) -> str:
    """A valid, unused device name for a label (adds it to `taken`)."""
    name = "".join(ch if ch.isascii() and ch.isprintable() else "_" for ch in label)[:IGTL_DEVICE_NAME_BYTES] or "_"
    candidate, n = name, 1
    while candidate in taken:
        n += 1
        suffix = f"~{n}"
        candidate = name[: IGTL_DEVICE_NAME_BYTES - len(suffix)] + suffix
    taken.add(candidate)
    return candidate


def _finite(points: np.ndarray, what: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) == 0:
        raise InputError(f"{what} has no finite points")
    return points
