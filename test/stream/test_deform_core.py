"""The node core's non-rigid stage: /preop/mesh markers into welded meshes, the rigid pose first, a stage that never
changes the pose or the verdict, the mesh paired with its model by stamp, the elastic model built at warm-up."""

from __future__ import annotations

import numpy as np
import pytest

from liver_p2p_reg.bags.io import rosbags_types, typestore
from liver_p2p_reg.cloud_io import sample_mesh_surface
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom.anatomy import make_liver
from liver_p2p_reg.phantom.dataset import make_case
from liver_p2p_reg.phantom.simulate import simulate_liver
from liver_p2p_reg.registration.deform import Deformation
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.ros.messages import (
    MARKER_TRIANGLE_LIST,
    feed_preop_mesh_msg,
    mesh_marker_mm,
    registered_structures_cloud,
)
from liver_p2p_reg.ros.pointcloud2 import cloud_to_structures
from liver_p2p_reg.stream.core import NodeCore
from liver_p2p_reg.stream.deformation import rigid_registrar, stage_values
from liver_p2p_reg.stream.outputs import ERROR, OK, PREOP_DIAG_NAME, WARN
from liver_p2p_reg.structures_io import Structure

# a small elastic model: built in well under a second
SMALL = dict(method="procrustes", mode="on_demand", deform_modes=12, deform_target_tets=1500)
DEFORM_KEYS = set(stage_values(Deformation(True, "", np.eye(4)), None, 1.0, 1.0, 1.0, "note"))
TYPES = typestore().types


def marker(corners_m: np.ndarray, marker_type: int = MARKER_TRIANGLE_LIST, frame_id: str = "ct", stamp_ns: int = 5):
    """A visualization_msgs/Marker (rosbags classes) whose `points` are these corners (metres)."""
    t = TYPES
    sec, nanosec = divmod(stamp_ns, 10**9)
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )
    color = t["std_msgs/msg/ColorRGBA"](r=0.8, g=0.45, b=0.35, a=1.0)
    return t["visualization_msgs/msg/Marker"](
        header=header,
        ns="preop",
        id=0,
        type=marker_type,
        action=0,
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        scale=t["geometry_msgs/msg/Vector3"](x=1.0, y=1.0, z=1.0),
        color=color,
        lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=True,
        points=[t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)) for x, y, z in corners_m],
        colors=[],
        texture_resource="",
        texture=t["sensor_msgs/msg/CompressedImage"](header=header, format="", data=np.zeros(0, np.uint8)),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )


def octahedron_mm() -> tuple[np.ndarray, np.ndarray]:
    vertices = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * 40.0 + 7.5
    faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    return vertices, np.array(faces)


def test_a_mesh_marker_becomes_welded_vertices_and_the_same_triangles() -> None:
    vertices, faces = octahedron_mm()
    out_vertices, out_faces = mesh_marker_mm(marker(vertices[faces.reshape(-1)] * 1e-3))
    assert out_vertices.shape == (6, 3) and out_faces.shape == (8, 3) and out_faces.dtype == np.int64
    np.testing.assert_allclose(out_vertices[out_faces], vertices[faces], rtol=0, atol=1e-9)  # same corners, same order
    assert len({tuple(sorted(f)) for f in out_faces.tolist()}) == 8  # no triangle collapsed by the welding


@pytest.mark.parametrize(
    "corners, marker_type, reason",
    [
        (np.zeros((0, 3)), MARKER_TRIANGLE_LIST, "0 points"),
        (np.ones((4, 3)), MARKER_TRIANGLE_LIST, "4 points (a positive multiple of 3"),
        (np.array([[0.0, 0.0, np.nan], [1, 0, 0], [0, 1, 0]]), MARKER_TRIANGLE_LIST, "non-finite"),
        (np.eye(3), 8, "marker type 8 is not TRIANGLE_LIST"),
    ],
)
def test_a_malformed_mesh_marker_is_one_error_and_changes_nothing(corners, marker_type, reason) -> None:
    with pytest.raises(InputError, match=reason.replace("(", r"\(")):
        mesh_marker_mm(marker(corners, marker_type))
    core = NodeCore(Config(**SMALL, deform=True))
    vertices, faces = octahedron_mm()
    assert feed_preop_mesh_msg(core, marker(vertices[faces.reshape(-1)] * 1e-3)).level == OK
    kept = core.mesh.for_model("ct", 5)
    diag = feed_preop_mesh_msg(core, marker(corners, marker_type))
    assert diag.level == ERROR and diag.name == PREOP_DIAG_NAME
    assert diag.message.startswith("bad /preop/mesh: ") and reason in diag.message and "\n" not in diag.message
    assert core.mesh.for_model("ct", 5) is kept  # the good mesh stands


@pytest.fixture(scope="module")
def case():
    """A small procedural liver: its mesh, the points a loader samples from it, a deformed partial view, a tumour."""
    sim = simulate_liver(7, 1, target_tets=1500, liver=make_liver(7, spacing_mm=5.0))
    c = make_case(sim, 0, 0.35, seed=1)
    vertices, triangles = c["src_pcd"], c["src_triangles"]
    d = np.random.default_rng(8).normal(size=(30, 3))
    tumour = vertices.mean(axis=0) + 4.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    return {
        "vertices": vertices,
        "triangles": triangles,
        "points": sample_mesh_surface(vertices, triangles, seed=0),
        "view": c["tgt_pcd"],
        "fid_s": c["src_marker"],
        "fid_t": c["tgt_marker"],
        "structures": [Structure("tumour", tumour, 0)],
    }


def registered(case, mesh_stamp: int | None = 5, **cfg):
    """(core, what on_pose got, the final output, the warm-up's diagnostic, the elastic models it built) of one
    registration of the case, as register_node runs it."""
    core = NodeCore(Config(**{**SMALL, **cfg}))
    if mesh_stamp is not None:
        early = core.set_preop_mesh(case["vertices"], case["triangles"], "ct", mesh_stamp)
        # before its model: kept, and register_node builds nothing for it yet (the model's warm-up will)
        assert early.level == OK and early.values["for_current_model"] == "false"
    warm = core.set_preop(case["points"], "ct", 5)
    assert warm.level == OK, warm.message
    built = elastic_models(core)  # what the warm-up built
    core.set_preop_fiducials(case["fid_s"], 5)
    core.structures.set_structures(case["structures"])
    core.set_intraop_fiducials(case["fid_t"], 6)
    core.on_intraop_points(case["view"], "camera", 6)
    first = []
    output = core.reregister(on_pose=first.append)
    assert len(first) == 1 and output.pose is not None
    return core, first[0], output, warm, built


def elastic_models(core: NodeCore) -> list[str]:
    return [k for k in core.registrar.cache if str(k).startswith("elastic:")]


def published_structures_mm(output) -> tuple[np.ndarray, np.ndarray]:
    """(points, bounds) in mm of the /registration/structures message register_node makes of this output."""
    points_m, _, bounds_m = cloud_to_structures(
        registered_structures_cloud(output.structures, rosbags_types(), "camera", 6)
    )
    return points_m * 1e3, bounds_m * 1e3


def comparable(values: dict[str, str]) -> dict[str, str]:
    """A diagnostic's values without timings and the stage's own keys."""
    return {k: v for k, v in values.items() if not k.startswith("runtime_ms.") and k not in DEFORM_KEYS}


def test_the_rigid_pose_goes_out_first_then_the_stage_adds_its_surface_and_values(case) -> None:
    core, rigid, output, warm, built = registered(case, deform=True)
    assert warm.values["deform_model"] == "ready" and warm.values["deform_surface"] == "mesh"  # built at warm-up
    assert float(warm.values["deform_model_ms"]) > 0 and len(built) == 1
    assert not DEFORM_KEYS & set(rigid.diagnostics[0].values) and rigid.deformed_preop_mm is None
    assert output.pose is rigid.pose  # the same pose, the same verdict
    diag, rigid_diag = output.diagnostics[0], rigid.diagnostics[0]
    assert (diag.level, diag.message) == (rigid_diag.level, rigid_diag.message)
    assert DEFORM_KEYS <= set(diag.values) and comparable(diag.values) == comparable(rigid_diag.values)
    assert diag.values["deform_applied"] == "true" and diag.values["deform_reason"] == ""
    assert diag.values["deform_surface"] == "mesh"
    assert float(diag.values["deform_residual_after_mm"]) < float(diag.values["deform_residual_before_mm"])
    deformation = output.result.deformation
    assert deformation.applied and np.array_equal(output.result.T_target_source, rigid.pose.T_sensor_ct_mm)
    # on the mesh: its vertices, in their order (a holder of /preop/mesh pairs them with its triangles)
    assert len(output.deformed_preop_mm) == len(case["vertices"]) != len(case["points"])
    np.testing.assert_array_equal(output.deformed_preop_mm, deformation.deformed_position_mm(case["vertices"]))
    rigid_vertices = case["vertices"] @ rigid.pose.T_sensor_ct_mm[:3, :3].T + rigid.pose.T_sensor_ct_mm[:3, 3]
    shift = np.linalg.norm(output.deformed_preop_mm - rigid_vertices, axis=1)
    assert 0.01 < shift.max() < core.config.deform_max_displacement_mm
    (tumour,) = output.structures  # the structures where the stage put them; the rigid positions kept beside
    np.testing.assert_array_equal(tumour.position_mm, rigid.structures[0].position_mm)
    np.testing.assert_array_equal(
        tumour.deformed_position_mm, deformation.deformed_position_mm(case["structures"][0].points_mm)
    )
    np.testing.assert_array_equal(tumour.error_bound_mm, rigid.structures[0].error_bound_mm)
    points, bounds = published_structures_mm(output)  # /registration/structures: the deformed positions
    np.testing.assert_allclose(points, tumour.deformed_position_mm, rtol=0, atol=1e-3)
    # ... and the bounds of those positions: the deformed-position calibration's, not the rigid pose's
    assert tumour.deformed_error_bound_mm is not None and np.all(np.isfinite(tumour.deformed_error_bound_mm))
    assert not np.allclose(tumour.deformed_error_bound_mm, tumour.error_bound_mm)
    np.testing.assert_allclose(bounds, tumour.deformed_error_bound_mm, rtol=1e-6)
    assert core.status().values["deform_applied"] == "true"  # the periodic status carries them too
    assert elastic_models(core) == built  # the frame built nothing: the warm-up did


def test_a_stage_not_applied_changes_neither_the_pose_nor_the_verdict(case) -> None:
    off = registered(case, deform=False)[2]
    refused = registered(case, deform=True, deform_max_displacement_mm=0.01)[2]
    assert not DEFORM_KEYS & set(off.diagnostics[0].values) and off.deformed_preop_mm is None
    diag = refused.diagnostics[0]
    assert diag.values["deform_applied"] == "false" and "implausible deformation" in diag.values["deform_reason"]
    assert refused.deformed_preop_mm is None and refused.structures[0].deformed_position_mm is None
    assert np.array_equal(refused.pose.T_sensor_ct_mm, off.pose.T_sensor_ct_mm)
    assert (diag.level, diag.message) == (off.diagnostics[0].level, off.diagnostics[0].message)
    assert comparable(diag.values) == comparable(off.diagnostics[0].values)
    np.testing.assert_array_equal(refused.structures[0].position_mm, off.structures[0].position_mm)
    np.testing.assert_array_equal(published_structures_mm(refused)[0], published_structures_mm(off)[0])


def test_the_mesh_serves_the_model_of_its_stamp_and_a_late_one_rebuilds_the_elastic_model(case) -> None:
    core, _, output, warm, _ = registered(case, mesh_stamp=99, deform=True)  # another model's mesh: not used
    assert warm.values["deform_surface"] == "points" and output.diagnostics[0].values["deform_surface"] == "points"
    assert output.diagnostics[0].values["deform_applied"] == "true"  # on the rebuilt surface: the points, in order
    np.testing.assert_array_equal(
        output.deformed_preop_mm, output.result.deformation.deformed_position_mm(case["points"])
    )
    assert core.prepare_deformation() is None  # already built for this model and surface
    late = core.set_preop_mesh(case["vertices"], case["triangles"], "ct", 5)
    assert late.level == OK and "kept for the model of its stamp" not in late.message
    assert late.values["mesh_triangles"] == str(len(case["triangles"])) and late.values["for_current_model"] == "true"
    rebuilt = core.prepare_deformation()
    assert rebuilt.level == OK and "elastic model built on its mesh" in rebuilt.message, rebuilt.message
    assert rebuilt.values["deform_surface"] == "mesh" and core.prepare_deformation() is None
    assert core.reregister().diagnostics[0].values["deform_surface"] == "mesh"
    # a mesh that cannot be an elastic model's surface (a hole): the preop status says why; frames still register
    v, t = case["vertices"], case["triangles"]
    holed = t[np.argsort(np.linalg.norm(v[t].mean(axis=1) - v[0], axis=1))[len(t) // 50 :]]
    core.set_preop_mesh(v, holed, "ct", 5)
    unusable = core.prepare_deformation()
    assert unusable.level == WARN and "non-rigid stage unavailable" in unusable.message
    again = core.reregister()
    assert again.pose is not None and again.diagnostics[0].values["deform_applied"] == "false"
    assert again.diagnostics[0].values["deform_reason"]


def test_deform_turned_on_later_builds_then_and_the_rigid_registrar_never_deforms(case) -> None:
    core = NodeCore(Config(**SMALL))
    core.set_preop(case["points"], "ct", 5)
    assert core.prepare_deformation() is None  # deform off: nothing to build
    core.reconfigure({"deform": True})
    assert core.config.deform and not core.registrar.config.deform
    built = core.prepare_deformation()
    assert built is not None and built.values["deform_model"] == "ready" and built.values["deform_surface"] == "points"
    given = Registrar(Config(**SMALL, deform=True))
    rigid = rigid_registrar(given.config, given)
    assert not rigid.config.deform and rigid.cache is given.cache
    plain = Registrar(Config(**SMALL))
    assert rigid_registrar(plain.config, plain) is plain


def test_a_mesh_of_the_same_stamp_that_is_not_the_models_surface_is_not_used(case) -> None:
    """Every bundled bag stamps its model alike: another liver's mesh (or this one's 5 m away) under the model's
    frame and stamp was deformed as this model's surface, and published at OK."""
    core, _, _, _, _ = registered(case, deform=True)
    for moved, cut in ((case["vertices"] + 50.0, slice(None)), (case["vertices"], slice(len(case["triangles"]) // 4))):
        core.set_preop_mesh(moved, case["triangles"][cut], "ct", 5)
        said = core.prepare_deformation()
        assert said.level == WARN and "not this model's surface, not used" in said.message, said.message
        assert said.values["deform_surface"] == "points" and said.values["deform_model"] == "ready"
        assert core.prepare_deformation() is None  # said once
        output = core.reregister()
        assert output.diagnostics[0].values["deform_surface"] == "points"
        assert output.deformed_preop_mm is None or len(output.deformed_preop_mm) == len(case["points"])
    core.set_preop_mesh(case["vertices"], case["triangles"], "ct", 5)  # its own mesh again: taken
    assert core.prepare_deformation().values["deform_surface"] == "mesh"
    # a mesh for the next model does not replace the current model's
    core.set_preop_mesh(case["vertices"] + 50.0, case["triangles"], "ct", 6)
    assert core.mesh.for_model("ct", 5, core.preop_mm) is not None
    assert core.reregister().diagnostics[0].values["deform_surface"] == "mesh"


def test_meshes_beyond_the_triangle_limit_are_refused() -> None:
    from liver_p2p_reg.stream.deformation import MAX_MESH_TRIANGLES, checked_mesh

    vertices, faces = octahedron_mm()
    many = np.tile(faces, (MAX_MESH_TRIANGLES // len(faces) + 1, 1))
    with pytest.raises(InputError, match="decimate"):
        checked_mesh(vertices, many, "ct", 5)


JUDGE = dict(method="learned-p2p-icp", ransac_candidate_visibility=1.0, contender_judge_ratio=100.0)


def test_the_contenders_judge_uses_the_one_elastic_model_of_the_mesh(case) -> None:
    """With the judge on (deform off) the warm-up builds the mesh's model and a judged registration uses it: no
    model rebuilt from the points."""
    core, _, output, warm, built = registered(case, **JUDGE)
    assert warm.values["deform_model"] == "ready" and warm.values["deform_surface"] == "mesh"
    assert len(built) == 1 and built[0].endswith("True)")  # the mesh's, built at the model's warm-up
    assert "judge" in output.result.runtime_ms, output.diagnostics[0].message
    assert elastic_models(core) == built  # the registration judged on it: nothing rebuilt


def test_survey_modes_global_registration_judges_on_the_mesh_too(case) -> None:
    core = NodeCore(Config(**{**SMALL, **JUDGE, "mode": "survey"}))
    assert core.set_preop_mesh(case["vertices"], case["triangles"], "ct", 5).level == OK
    assert core.set_preop(case["points"], "ct", 5).level == OK
    built = elastic_models(core)
    core.on_intraop_points(case["view"], "camera", 6)
    output = core.process_pending(1.0)
    assert output is not None and output.result is not None and "survey_state" in output.diagnostics[0].values
    assert "judge" in output.result.runtime_ms, output.diagnostics[0].message  # the survey's first, global one
    assert len(built) == 1 and elastic_models(core) == built
