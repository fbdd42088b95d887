"""The settings of the OpenIGTLink link to 3D Slicer (slicer_bridge_node, `register --slicer`, `replay --slicer`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from liver_p2p_reg.config_io import from_mapping
from liver_p2p_reg.errors import InputError

SLICER_ROLES = ("server", "client")
CT_CONVENTIONS = ("LPS", "RAS")
IGTL_DEVICE_NAME_BYTES = 20  # OpenIGTLink header field


@dataclass
class SlicerConfig:
    """Settings of the OpenIGTLink link to 3D Slicer, with defaults (msg_docs/parameters_slicer_bridge.md)."""

    # server: Slicer's OpenIGTLinkIF connector connects to us (its type "Client");
    # client: we connect to a connector of type "Server" and reconnect when it goes away
    role: str = "server"
    host: str = "0.0.0.0"  # server: the address to listen on (all interfaces); client: Slicer's host
    port: int = 18944  # OpenIGTLink's registered port; 0 (server only) picks a free one
    # anatomical convention of the ct frame's coordinates: LPS (DICOM, and Slicer's own model
    # files) or RAS; Slicer's scene is RAS, so LPS coordinates get x and y negated on the way
    ct_convention: str = "LPS"
    transform_device: str = "CTToSensor"  # TRANSFORM: Slicer RAS of the CT -> sensor frame (mm)
    model_device: str = "PreopModel"  # POLYDATA: the preop model in Slicer RAS of the CT (mm)
    # POLYDATA: the preop model after the non-rigid stage, sensor frame (mm): the mesh's triangles when it came on one
    deformed_model_device: str = "DeformedModel"
    cloud_device: str = "IntraopCloud"  # POLYDATA: the registered intraop cloud, sensor frame (mm)
    status_device: str = "RegistrationStatus"  # STRING: "LEVEL: message" of each registration
    max_model_points: int = 20000  # a preop model without mesh is decimated to at most this many points
    max_cloud_points: int = 5000  # the intraop cloud is decimated to at most this many points
    # the intraop cloud is sent at most this often (the transform always); 0: no cloud (the bridge
    # then does not even subscribe to the clouds, which costs a copy of each one)
    cloud_rate_hz: float = 5.0
    point_size_mm: float = 1.5  # each point is drawn as a triangle of this leg length
    max_queue_messages: int = 16  # per client: older unsent messages beyond this are dropped
    max_queue_mb: float = 64.0  # per client: ... and beyond this many megabytes
    reconnect_period_s: float = 1.0  # client role: time between connection attempts

    def validate(self) -> SlicerConfig:
        """Check ranges and choices; raise InputError with a one-line message if bad."""
        if self.role not in SLICER_ROLES:
            raise InputError(f"role must be one of {SLICER_ROLES}, got {self.role!r}")
        if self.ct_convention not in CT_CONVENTIONS:
            raise InputError(f"ct_convention must be one of {CT_CONVENTIONS}, got {self.ct_convention!r}")
        lowest_port = 0 if self.role == "server" else 1
        if not lowest_port <= self.port <= 65535:
            raise InputError(f"port must be in {lowest_port}..65535 for role {self.role}, got {self.port}")
        if not self.host:
            raise InputError("host must not be empty")
        devices = self.devices()
        for name in devices:
            if not name or not name.isascii() or not name.isprintable() or len(name) > IGTL_DEVICE_NAME_BYTES:
                raise InputError(f"device name {name!r} must be 1-{IGTL_DEVICE_NAME_BYTES} printable ASCII characters")
        if len(set(devices)) != len(devices):
            raise InputError(f"device names must differ, got {devices}")
        for name in ("max_model_points", "max_cloud_points", "max_queue_messages"):
            if not getattr(self, name) >= 1:
                raise InputError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.cloud_rate_hz >= 0:
            raise InputError(f"cloud_rate_hz must be >= 0 (0: no cloud), got {self.cloud_rate_hz}")
        for name in ("point_size_mm", "max_queue_mb", "reconnect_period_s"):
            if not getattr(self, name) > 0:  # `not >` also catches NaN
                raise InputError(f"{name} must be > 0, got {getattr(self, name)}")
        return self

    def devices(self) -> list[str]:
        """The bridge's own device names (structures get theirs from their labels, never one of these)."""
        return [
            self.transform_device,
            self.model_device,
            self.deformed_model_device,
            self.cloud_device,
            self.status_device,
        ]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> SlicerConfig:
        return SlicerConfig.from_dict({**self.to_dict(), **changes})

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> SlicerConfig:
        """Build from a mapping (ROS parameters, CLI options) with the same coercion as Config; validate."""
        return from_mapping(cls, values, "Slicer link setting")
