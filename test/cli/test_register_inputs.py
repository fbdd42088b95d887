"""The register command's optional inputs refuse what would give a wrong result: a projective prior pose,
fiducials in metres, a seed Open3D cannot take; weights a method ignores are named once."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.cli import main
from liver_p2p_reg.cli.register_inputs import load_fiducials, load_initial_transform, warn_unused_weights
from liver_p2p_reg.cloud_io import save_points
from liver_p2p_reg.errors import InputError

FIDUCIALS_MM = np.array([[10.0, -40.0, 250.0], [55.0, 20.0, 260.0], [-30.0, 35.0, 240.0], [5.0, 0.0, 300.0]])


@pytest.fixture
def clouds(tmp_path: Path) -> tuple[str, str]:
    """A liver-sized blob (mm) as SOURCE and TARGET files: the checks under test run before any registration."""
    d = np.random.default_rng(0).normal(size=(500, 3))
    points = d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0]
    save_points(tmp_path / "src.ply", points)
    save_points(tmp_path / "tgt.ply", points[points[:, 2] > 0])
    return str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply")


def _run(args: list, capsys: pytest.CaptureFixture) -> tuple[int, str]:
    rc = main([str(a) for a in args])
    return rc, capsys.readouterr().err


def test_a_projective_initial_transform_is_refused(clouds, tmp_path: Path, capsys) -> None:
    pose = np.eye(4)
    pose[3] = [1.0, 2.0, 3.0, 4.0]  # rotation block fine, last row projective
    np.savetxt(tmp_path / "proj.txt", pose)
    rc, err = _run(["register", *clouds, "--method", "track", "--initial-transform", tmp_path / "proj.txt"], capsys)
    assert rc == 2 and "not a rigid transform (bottom row is 1 2 3 4" in err
    assert err.count("\n") == 1 and "Traceback" not in err
    pose[3] = [0.0, 0.0, 1e-9, 1.0]  # printed round-off is not a projective row
    np.savetxt(tmp_path / "near.txt", pose)
    assert load_initial_transform(tmp_path / "near.txt")[3, 3] == 1.0
    np.save(tmp_path / "complex.npy", np.eye(4) * (1 + 1j))  # its imaginary part was dropped with a warning
    with pytest.raises(InputError, match="holds complex128 values, not real numbers"):
        load_initial_transform(tmp_path / "complex.npy")


@pytest.mark.parametrize("method", ["fpfh-ransac", "fgr"])
def test_a_seed_open3d_cannot_take_is_one_line(clouds, tmp_path: Path, capsys, method: str) -> None:
    rc, err = _run(["register", *clouds, "--method", method, "--seed", 2**31], capsys)
    assert rc == 2 and err == "liver-p2p: error: seed must be in [0, 2147483647] (Open3D takes a 32-bit seed), got 2147483648\n"  # fmt: skip
    (tmp_path / "c.yaml").write_text("seed: 99999999999\n")
    rc, err = _run(["register", *clouds, "--method", method, "--config", tmp_path / "c.yaml"], capsys)
    assert rc == 2 and "seed must be in [0, 2147483647]" in err and err.count("\n") == 1


def test_fiducials_in_metres_are_refused(tmp_path: Path) -> None:
    np.savetxt(tmp_path / "mm.xyz", FIDUCIALS_MM)
    assert np.allclose(load_fiducials(tmp_path / "mm.xyz", "--source-fiducials", 600.0), FIDUCIALS_MM)
    np.savetxt(tmp_path / "m.xyz", FIDUCIALS_MM / 1000.0)  # ~0.1-0.3: every coordinate below 1 mm
    with pytest.raises(
        InputError, match=r"--source-fiducials .*m\.xyz: every coordinate is below 1 mm .*metres"
    ) as info:
        load_fiducials(tmp_path / "m.xyz", "--source-fiducials", 600.0)
    assert "\n" not in str(info.value)
    shifted = FIDUCIALS_MM / 1000.0 + [0.0, 0.0, 5.0]  # metres far from the origin: their spread gives them away
    np.savetxt(tmp_path / "far.xyz", shifted)
    with pytest.raises(InputError, match=r"--target-fiducials .*their extent .* below 1 mm.*metres"):
        load_fiducials(tmp_path / "far.xyz", "--target-fiducials", 600.0)


def test_weights_a_method_ignores_are_named_once(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="liver_p2p_reg"):
        warn_unused_weights("fpfh-ransac-icp", "nope.safetensors")
        warn_unused_weights("learned-p2p-icp", "nope.safetensors")  # read by the learned matcher: no warning
        warn_unused_weights("fgr", "")  # none given: nothing to say
    assert [r.getMessage() for r in caplog.records] == [
        "method 'fpfh-ransac-icp' does not use weights: --weights nope.safetensors is ignored"
    ]
