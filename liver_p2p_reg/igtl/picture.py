"""Draw what a Slicer peer received: PreopModel under CTToSensor over IntraopCloud, RegistrationStatus as the title."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from liver_p2p_reg.igtl.wire import Message, decode_polydata, decode_string, decode_transform


@dataclass
class Arrived:
    """The latest message of each device as a peer decoded it, and how many came."""

    model_ras: np.ndarray  # the cloud or mesh vertices, Slicer RAS of the CT (mm)
    model_triangles: int  # of the mesh (0: the model came as points)
    cloud: np.ndarray  # sensor frame = Slicer's scene (mm)
    transform: np.ndarray  # CTToSensor
    status: str
    counts: dict[str, tuple[str, int, int]]  # device -> (type, messages, bytes of the last body)


def points_of(body: bytes) -> tuple[np.ndarray, int]:
    """(points, mesh triangles) of a POLYDATA: a points POLYDATA of N triangles carries its cloud first."""
    points, polygons = decode_polydata(body)
    if len(points) == 3 * len(polygons) and all(cell[0] == i for i, cell in enumerate(polygons[:16])):
        return points[: len(polygons)], 0
    return points, len(polygons)


def collect(messages: list[Message], model: str, cloud: str, transform: str, status: str) -> Arrived:
    """The latest message of each named device (KeyError if one never came) and the count per device."""
    latest: dict[str, Message] = {}
    counts: dict[str, tuple[str, int, int]] = {}
    for m in messages:
        latest[m.device] = m
        _, n, _ = counts.get(m.device, (m.type_name, 0, 0))
        counts[m.device] = (m.type_name, n + 1, len(m.body))
    model_ras, triangles = points_of(latest[model].body)
    cloud_points, _ = points_of(latest[cloud].body)
    return Arrived(
        model_ras,
        triangles,
        cloud_points,
        decode_transform(latest[transform].body),
        decode_string(latest[status].body),
        counts,
    )


def draw(arrived: Arrived, path: str | Path, title: str = "") -> Path:
    """Three orthographic views of Slicer's scene: the model moved by CTToSensor (grey), the cloud (blue)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    M = arrived.transform
    model = arrived.model_ras @ M[:3, :3].T + M[:3, 3]
    cloud = arrived.cloud
    rng = np.random.default_rng(0)
    shown_model = model[rng.permutation(len(model))[:6000]]
    views = (("R", "A", 0, 1), ("R", "S", 0, 2), ("A", "S", 1, 2))
    fig, axes = plt.subplots(1, 4, figsize=(19, 5.2), gridspec_kw={"width_ratios": [1, 1, 1, 0.8]})
    for ax, (h, v, i, j) in zip(axes[:3], views, strict=True):
        ax.scatter(shown_model[:, i], shown_model[:, j], s=1, c="0.6", label="PreopModel under CTToSensor")
        ax.scatter(cloud[:, i], cloud[:, j], s=1, c="tab:blue", label="IntraopCloud")
        ax.set_xlabel(f"{h} (mm)")
        ax.set_ylabel(f"{v} (mm)")
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].legend(loc="upper left", markerscale=8, fontsize=8)
    axes[3].axis("off")
    lines = ["received over OpenIGTLink:", "device              type      messages  last body", ""]
    for device, (kind, n, size) in arrived.counts.items():
        lines.append(f"{device:<19} {kind:<9} {n:>8}  {_size(size):>9}")
    kind = f"a mesh of {arrived.model_triangles} triangles" if arrived.model_triangles else "a cloud"
    lines += ["", f"PreopModel: {len(model)} points, {kind}", f"IntraopCloud: {len(cloud)} points", "CTToSensor:"]
    lines += ["  " + " ".join(f"{v:9.3f}" for v in row) for row in M[:3]]
    axes[3].text(0, 1, "\n".join(lines), va="top", family="monospace", fontsize=9.5)
    fig.suptitle(f"{title}\n{arrived.status}" if title else arrived.status, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def _size(n_bytes: int) -> str:
    return f"{n_bytes} B" if n_bytes < 10240 else f"{n_bytes / 1024:.0f} KiB"
