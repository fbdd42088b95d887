"""The preop mesh a bag carries on /preop/mesh: the case's triangles decimated to a bounded count, as a Marker."""

from __future__ import annotations

from typing import Any

import numpy as np

from liver_p2p_reg.errors import InputError

# A bag's /preop/mesh: 72 bytes a triangle (three float64 corners), about 0.58 MB at most. The non-rigid stage fits
# the mesh's vertices to the view, so they must stay about as dense as the view (3-4 mm apart): at 4000 triangles
# the stage was no longer applied on phantom_sim_04 (residual gain 9 % < deform_min_gain), at 8000 it was.
MAX_MESH_TRIANGLES = 8000


def decimated_mesh(
    vertices_mm: np.ndarray, triangles: np.ndarray, max_triangles: int = MAX_MESH_TRIANGLES
) -> tuple[np.ndarray, np.ndarray]:
    """(vertices mm, triangles) with at most `max_triangles`, unused vertices dropped; a mesh small enough is kept.

    Vertex clustering (open3d, deterministic) on the finest cell, of a few multiples of 1/96 of the extent, that
    meets the count: unlike quadric decimation it leaves no long edges, so the surface stays closed for the elastic
    model's voxelization (registration/mechanics/solid.py samples each triangle at most 16 times an edge).
    """
    from liver_p2p_reg.stream.deformation import checked_mesh  # the one check of a preop mesh

    checked = checked_mesh(vertices_mm, triangles, "", 0, max_triangles=None)  # a CT mesh of millions: decimated
    vertices, tris = checked.vertices_mm, checked.triangles
    if max_triangles < 4:
        raise InputError(f"a closed mesh needs at least 4 triangles, max_triangles is {max_triangles}")
    if len(tris) > max_triangles:
        vertices, tris = _clustered(vertices, tris, max_triangles)
    used = np.unique(tris)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[tris]


def _clustered(vertices: np.ndarray, tris: np.ndarray, max_triangles: int) -> tuple[np.ndarray, np.ndarray]:
    """The mesh clustered on the finest cell that leaves at most max_triangles (InputError when none does)."""
    from liver_p2p_reg.o3d import o3d_module

    o3d = o3d_module()

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(tris))
    fine_mm = max(float(np.max(np.ptp(vertices, axis=0))) / 96.0, 1e-6)
    for factor in (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 16.0):
        coarse = mesh.simplify_vertex_clustering(factor * fine_mm)
        coarse.remove_degenerate_triangles()
        coarse.remove_duplicated_triangles()
        coarse.remove_unreferenced_vertices()
        if 4 <= len(coarse.triangles) <= max_triangles:
            return np.asarray(coarse.vertices, dtype=np.float64), np.asarray(coarse.triangles, dtype=np.int64)
    raise InputError(f"the source mesh cannot be decimated to {max_triangles} triangles")


def preop_mesh_marker(vertices_mm: np.ndarray, triangles: np.ndarray, frame_id: str, stamp_ns: int) -> Any:
    """The /preop/mesh Marker (rosbags, metres) of a mesh in mm, as the loader publishes one."""
    from liver_p2p_reg.bags.io import rosbags_marker_types
    from liver_p2p_reg.ros.messages import triangle_list_marker
    from liver_p2p_reg.ros.pointcloud2 import M_PER_MM

    vertices_m = np.asarray(vertices_mm, dtype=np.float64) * M_PER_MM
    return triangle_list_marker(vertices_m, triangles, rosbags_marker_types(), frame_id, stamp_ns)
