"""`bag make` refuses, in one line and before writing, what would give a bag the node cannot use or one
missing what the case holds: an invalid frame id, preop triangles that do not index the preop points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.bags.make import make_sweep_bag
from liver_p2p_reg.cli import main
from liver_p2p_reg.errors import InputError


def _blob(n: int = 400) -> np.ndarray:
    """A liver-sized ellipsoid surface (mm)."""
    d = np.random.default_rng(3).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * [80.0, 55.0, 40.0]


@pytest.mark.parametrize("frame_id", ["", " ", "/camera", "my camera"])
def test_an_invalid_frame_id_is_refused_before_writing(tmp_path: Path, capsys, frame_id: str) -> None:
    np.savetxt(tmp_path / "src.xyz", _blob())
    np.savetxt(tmp_path / "tgt.xyz", _blob()[:200])
    out = tmp_path / "bag"
    rc = main(["bag", "make", str(out), "--source", str(tmp_path / "src.xyz"), "--target", str(tmp_path / "tgt.xyz"),
               "--frame-id", frame_id])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2 and f"frame id {frame_id!r} is not a ROS frame id" in err and err.count("\n") == 1
    assert not out.exists()
    with pytest.raises(InputError, match="preop frame id '' is not a ROS frame id"):
        make_sweep_bag(tmp_path / "sweep", _blob(), [_blob()[:200]], preop_frame="")


def test_case_triangles_out_of_range_are_refused_not_dropped(tmp_path: Path, capsys) -> None:
    source = _blob()
    triangles = np.array([[0, 1, 2], [2, 3, 400]], dtype=np.int32)  # 400: one past the last point
    case = tmp_path / "case.npz"
    np.savez(case, src_pcd=source, tgt_pcd=source[:200], src_triangles=triangles)
    out = tmp_path / "bag"
    assert main(["bag", "make", str(out), "--case", str(case)]) == 2
    err = capsys.readouterr().err
    assert "src_triangles index vertices 0..400, but src_pcd has 400 (valid: 0..399)" in err
    assert err.count("\n") == 1 and not out.exists()
    np.savez(case, src_pcd=source, tgt_pcd=source[:200], src_triangles=triangles[:, :2])
    assert main(["bag", "import", str(case), str(out)]) == 2
    assert "src_triangles must be an (F, 3) index array" in capsys.readouterr().err
