"""`liver-p2p register` output: summary vs JSON, -q, several targets in one process, --method track."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.cli import main
from liver_p2p_reg.cloud_io import save_points
from liver_p2p_reg.metrics import transform_points

METHOD = ["--method", "fpfh-p2p-icp"]  # deterministic (no RANSAC) and exact on these clean crops


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A source, two crops of it moved differently (view_a, view_b), one in metres (bad units)."""
    tmp = tmp_path_factory.mktemp("register")
    rng = np.random.default_rng(5)
    source, view_a, T_a, _, _ = partial_case(rng)
    _, crop, _, _, _ = partial_case(np.random.default_rng(5), share=0.3)
    T_b = T_a.copy()
    T_b[:3, 3] += [20.0, -10.0, 5.0]
    view_b = transform_points(T_b @ np.linalg.inv(T_a), crop)
    paths = {name: tmp / name for name in ("source.ply", "view_a.xyz", "view_b.npy", "metres.npy")}
    save_points(paths["source.ply"], source)
    save_points(paths["view_a.xyz"], view_a)
    save_points(paths["view_b.npy"], view_b)
    np.save(paths["metres.npy"], view_a / 1000.0)
    return {"T_a": T_a, "T_b": T_b, **{k: str(v) for k, v in paths.items()}}


def _run(argv: list[str], capsys: pytest.CaptureFixture) -> tuple[int, str, str]:
    rc = main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_json_on_stdout_without_output_and_the_summary_on_stderr(case: dict, capsys: pytest.CaptureFixture) -> None:
    rc, out, err = _run(["register", case["source.ply"], case["view_a.xyz"], *METHOD], capsys)
    assert rc == 0
    result = json.loads(out)  # stdout is the JSON alone: `| jq` works
    assert result["status"] in ("OK", "WARN") and result["source"] == case["source.ply"]
    assert np.abs(np.array(result["transform"]) - case["T_a"]).max() < 0.5
    summary = [line for line in err.splitlines() if not line.startswith("liver-p2p: WARNING")]
    assert len(summary) == 1 and summary[0].startswith("view_a.xyz: ") and "JSON on stdout" in summary[0]


def test_quiet_prints_nothing_but_the_asked_for_json(case: dict, tmp_path: Path, capsys) -> None:
    out_json = tmp_path / "r.json"
    rc, out, err = _run(
        ["-q", "register", case["source.ply"], case["view_a.xyz"], *METHOD, "-o", str(out_json)], capsys
    )
    assert (rc, out, err) == (0, "", "") and json.loads(out_json.read_text())["transform"]
    # -q after the subcommand too; without --output the JSON is the result, so it is still printed
    rc, out, err = _run(["register", case["source.ply"], case["view_a.xyz"], *METHOD, "-q"], capsys)
    assert rc == 0 and err == "" and json.loads(out)["method"] == METHOD[1]


def test_several_targets_in_one_process(case: dict, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    folder = tmp_path / "results"
    argv = ["register", case["source.ply"], case["view_a.xyz"], case["view_b.npy"], *METHOD, "-o", str(folder)]
    rc, out, _ = _run(argv, capsys)
    assert rc == 0
    lines = out.splitlines()
    assert [line.split(":")[0] for line in lines] == ["view_a.xyz", "view_b.npy"]
    assert sorted(p.name for p in folder.iterdir()) == ["view_a.json", "view_b.json"]
    for name, T in (("view_a", case["T_a"]), ("view_b", case["T_b"])):
        written = json.loads((folder / f"{name}.json").read_text())
        assert written["target"].endswith(name + (".xyz" if name == "view_a" else ".npy"))
        assert np.abs(np.array(written["transform"]) - T).max() < 0.5
    # The same numbers as one target per process: the shared source preparation changes nothing.
    rc, single, _ = _run(["register", case["source.ply"], case["view_b.npy"], *METHOD], capsys)
    assert json.loads(single)["transform"] == json.loads((folder / "view_b.json").read_text())["transform"]
    # Nothing is overwritten without --force, and that is found before any registration.
    before = {p: p.stat().st_mtime_ns for p in folder.iterdir()}
    rc, out, err = _run(argv, capsys)
    assert rc == 2 and out == "" and err.startswith("liver-p2p: error:") and "exists; pass --force" in err
    assert {p: p.stat().st_mtime_ns for p in folder.iterdir()} == before
    # Without --output: one JSON object per line.
    rc, out, _ = _run(argv[:-2], capsys)
    assert rc == 0 and [json.loads(line)["target"] for line in out.splitlines()] == argv[2:4]


def test_several_targets_refuse_ambiguous_outputs(case: dict, tmp_path: Path, capsys) -> None:
    twin = tmp_path / "other"
    twin.mkdir()
    (twin / "view_a.xyz").write_bytes(Path(case["view_a.xyz"]).read_bytes())
    two = ["register", case["source.ply"], case["view_a.xyz"], case["view_b.npy"], *METHOD]
    rc, _, err = _run([*two, "-o", str(tmp_path / "all.json")], capsys)
    assert rc == 2 and "with several targets, give a folder" in err
    rc, _, err = _run(
        ["register", case["source.ply"], case["view_a.xyz"], str(twin / "view_a.xyz"), "-o", str(tmp_path)], capsys
    )
    assert rc == 2 and "would both write" in err
    rc, _, err = _run(
        [*two, "--source-fiducials", case["view_b.npy"], "--target-fiducials", case["view_b.npy"]], capsys
    )
    assert rc == 2 and "single TARGET" in err


def test_a_bad_target_in_a_batch_does_not_stop_the_others(case: dict, tmp_path: Path, capsys) -> None:
    folder = tmp_path / "batch"
    argv = ["register", case["source.ply"], case["metres.npy"], case["view_a.xyz"], *METHOD, "-o", str(folder)]
    rc, out, err = _run(argv, capsys)
    assert rc == 2
    assert err.splitlines()[0].startswith(f"liver-p2p: error: {case['metres.npy']}: target extent")
    assert out.startswith("view_a.xyz: ") and sorted(p.name for p in folder.iterdir()) == ["view_a.json"]


def test_track_refines_an_initial_transform(case: dict, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    prior = case["T_a"].copy()
    prior[:3, 3] += [2.0, -1.5, 1.0]  # an earlier pose, a few millimetres off
    as_text = tmp_path / "prior.txt"
    np.savetxt(as_text, prior)
    rc, out, _ = _run(
        ["register", case["source.ply"], case["view_a.xyz"], "--method", "track", "--initial-transform", str(as_text)],
        capsys,
    )
    assert rc == 0
    tracked = json.loads(out)
    assert tracked["method"] == "track" and tracked["status"] == "OK"
    assert np.abs(np.array(tracked["transform"])[:3, 3] - case["T_a"][:3, 3]).max() < 1.0  # pulled back in
    # An earlier result's JSON is a prior too (the command's own output).
    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps(tracked))
    rc, out, _ = _run(
        ["register", case["source.ply"], case["view_a.xyz"], "--method", "track", "--initial-transform", str(earlier)],
        capsys,
    )
    assert rc == 0 and np.allclose(json.loads(out)["transform"], tracked["transform"], atol=0.2)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--method", "track"], "give it with --initial-transform"),
        (["--method", "fpfh-p2p", "--initial-transform", "T.txt"], "used by --method track and --method evaluate only"),
        (["--method", "track", "--initial-transform", "missing.txt"], "file not found"),
        (["--method", "track", "--initial-transform", "T3.txt"], "expected a 4x4 matrix"),
    ],
)
def test_track_argument_errors_are_one_line(case: dict, tmp_path: Path, capsys, monkeypatch, extra, message) -> None:
    monkeypatch.chdir(tmp_path)
    np.savetxt("T.txt", np.eye(4))
    np.savetxt("T3.txt", np.eye(3))
    rc, out, err = _run(["register", case["source.ply"], case["view_a.xyz"], *extra], capsys)
    assert rc == 2 and out == "" and len(err.splitlines()) == 1 and message in err
