"""The Slicer link of the command line: `register --slicer HOST:PORT` (client) and `replay --slicer PORT` (server)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.slicer_config import SlicerConfig

LOG = logging.getLogger("liver_p2p_reg")
CONNECT_TIMEOUT_S = 5.0
FLUSH_TIMEOUT_S = 10.0


def parse_address(text: str) -> tuple[str, int]:
    """'HOST:PORT', '[IPv6]:PORT' or 'PORT' (this machine) -> (host, port)."""
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host, port_text = "localhost", text
    host = host.strip("[]") or "localhost"  # ':18944' is this machine, as a bare port is
    try:
        port = int(port_text)
    except ValueError:
        raise InputError(f"--slicer {text!r}: expected HOST:PORT, e.g. localhost:18944") from None
    if not 1 <= port <= 65535 or not host:
        raise InputError(f"--slicer {text!r}: expected HOST:PORT with a port in 1..65535")
    return host, port


def connect_to_slicer(address: str, config: SlicerConfig | None = None) -> SlicerBridge:
    """A bridge connected to Slicer's OpenIGTLink server connector; one clear error if there is none."""
    host, port = parse_address(address)
    config = (config or SlicerConfig()).replace(role="client", host=host, port=port)
    endpoint = open_endpoint(config, log=lambda level, text: None)  # the error below says it in one line
    end = time.monotonic() + CONNECT_TIMEOUT_S
    while not endpoint.peer_count() and not endpoint.last_error and time.monotonic() < end:
        time.sleep(0.01)
    if not endpoint.peer_count():
        endpoint.close()
        reason = endpoint.last_error or f"no answer within {CONNECT_TIMEOUT_S:g} s"
        raise InputError(
            f"cannot connect to 3D Slicer at {host}:{port} ({reason}): is an OpenIGTLinkIF connector "
            "of type Server active on that port?"
        )
    return SlicerBridge(config, endpoint)


def send_registration(
    bridge: SlicerBridge,
    source_path: str | Path,
    source_mm: np.ndarray,
    target_mm: np.ndarray,
    result: Any,
    warnings: list[str],
    structures: list[Any] | None = None,
    mesh: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Model (the file's mesh if it has one), intraop cloud, CTToSensor, the deformed model when the non-rigid
    stage was applied, each structure (`PlacedStructure`s, moved into the target's frame, deformed when the stage
    was applied, a POLYDATA named by its label) and the verdict; returns once sent.

    Call it once per registration on the same connection; close `bridge.endpoint` at the end.
    """
    from liver_p2p_reg.cloud_io import MESH_FORMATS, load_mesh

    vertices, triangles = source_mm, None
    if Path(source_path).suffix.lower() in MESH_FORMATS:
        mesh_vertices, mesh_triangles = mesh if mesh is not None else load_mesh(source_path)  # read once
        if len(mesh_triangles):
            vertices, triangles = mesh_vertices, mesh_triangles
    bridge.send_model(vertices, triangles)
    bridge.send_cloud(target_mm)
    bridge.send_pose(result.T_target_source)
    placed = structures or []
    deformation = getattr(result, "deformation", None)
    if deformation is not None and deformation.applied:  # the model where the non-rigid stage put it (sensor frame)
        bridge.send_deformed_model(deformation.deformed_position_mm(vertices), triangles)
    for device, structure in zip(bridge.structure_devices([s.label for s in placed]), placed, strict=True):
        bridge.send_structure(device, structure.current_position_mm)
    message = f"registered: residual {result.residual_mm:.2f} mm"
    if result.rms_tre_mm is not None:
        message += f", RMS-TRE {result.rms_tre_mm:.2f} mm"
    if warnings:
        message += " (" + "; ".join(warnings) + ")"
    bridge.send_status("WARN" if warnings else "OK", message)
    if not bridge.endpoint.flush(FLUSH_TIMEOUT_S):
        bridge.endpoint.close()
        raise InputError(f"3D Slicer did not take the result within {FLUSH_TIMEOUT_S:g} s (connection stalled)")
    LOG.info("sent to 3D Slicer: %s, %s, %s, %s", *_devices(bridge.config))


def serve_replay(port: int, wait_s: float, config: SlicerConfig | None = None) -> Any:
    """A SlicerLink serving on `port` (the replay's observer); waits up to wait_s for Slicer to connect."""
    from liver_p2p_reg.igtl.link import SlicerLink

    config = (config or SlicerConfig()).replace(role="server", port=port)
    endpoint = open_endpoint(config)
    LOG.info("OpenIGTLink server on port %d: waiting up to %g s for 3D Slicer to connect", endpoint.port, wait_s)
    if not endpoint.wait_for_peers(1, wait_s):
        LOG.warning("no OpenIGTLink client connected within %g s; replaying anyway", wait_s)
    return SlicerLink(SlicerBridge(config, endpoint))


def finish_replay(link: Any, wait_s: float) -> None:
    """Let the last messages leave (the last pose's cloud too), then stop serving."""
    link.tick(force=True)
    if not link.bridge.endpoint.flush(wait_s):
        LOG.warning("a Slicer client did not take the last messages within %g s", wait_s)
    link.bridge.endpoint.close()


def _devices(config: SlicerConfig) -> tuple[str, ...]:
    return (config.model_device, config.cloud_device, config.transform_device, config.status_device)
