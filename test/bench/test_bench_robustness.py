"""`liver-p2p benchmark` on damaged input: a cut cases.csv, a damaged case or settings file, bad options, a README
without its markers. Each is one line (or a warning and a rerun), never a traceback nor a silently kept bad row."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.bench.cases_csv import read_rows
from liver_p2p_reg.cli import main
from liver_p2p_reg.phantom.casefile import write_case


def _case(rng: np.random.Generator, visibility: float) -> dict:
    """A small case: a moved cloud with its interior markers (the oracle registers it from the markers)."""
    source = rng.normal(size=(400, 3)) * [60.0, 45.0, 30.0]
    markers = source[:12] * 0.5
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R, t = q * np.sign(np.linalg.det(q)), rng.uniform(-50, 50, 3)
    keep = source[: int(400 * visibility)]
    return {
        "src_pcd": source,
        "tgt_pcd": keep @ R.T + t,
        "src_marker": markers,
        "tgt_marker": markers @ R.T + t + rng.normal(scale=1.0, size=markers.shape),
        "R_gt": R,
        "t_gt": t,
        "visibility": visibility,
        "liver_id": 0,
        "seed": 1,
        "crop_mode": "random",
    }


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    folder = tmp_path / "cases"
    rng = np.random.default_rng(5)
    for i, visibility in enumerate((0.25, 0.45, 0.65)):
        write_case(folder / f"case_L{i}_D00_T000.npz", _case(rng, visibility))
    return folder


def _bench(dataset: Path, out: Path, *extra: str, quiet: bool = True) -> int:
    argv = ["benchmark", "--dataset", str(dataset), "--methods", "procrustes", "--out", str(out), *extra]
    return main(["-q", *argv] if quiet else argv)


def _one_line_error(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("liver-p2p: error: "), err
    return err


def _numbers(out: Path) -> list[tuple]:
    """The rows of OUT/cases.csv but wall-clock runtimes."""
    rows = read_rows(out / "cases.csv")
    return [tuple((k, repr(v)) for k, v in r.items() if not k.startswith("runtime_")) for r in rows]  # repr: NaN == NaN


def test_a_cut_or_damaged_row_is_registered_again(dataset: Path, tmp_path: Path, caplog) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out) == 0
    first, path = _numbers(out), out / "cases.csv"
    lines = path.read_text().splitlines(keepends=True)
    fields = lines[-1].split(",")
    for damaged in (
        "".join(lines[:-1]) + ",".join(fields[:10]) + "," + fields[10][:1],  # cut mid-row: rms "1"
        "".join(lines) + "case_L0",  # cut in the first field of an appended row
        "".join(lines[:-1]) + ",".join([*fields[:10], "abc", *fields[11:]]),  # a whole line, an unparsable number
    ):
        path.write_text(damaged)
        assert _bench(dataset, out, quiet=False) == 0  # not -q: it silences warnings
        assert _numbers(out) == first  # the damaged row run again, not kept
        assert "damaged row" in caplog.text
        caplog.clear()
    assert path.read_text().endswith("\n")


@pytest.mark.parametrize("minutes", ["nan", "inf", "-1"])
def test_prepare_minutes_must_be_a_finite_number(dataset: Path, tmp_path: Path, capsys, minutes: str) -> None:
    assert _bench(dataset, tmp_path / "out", "--prepare-minutes", minutes) == 2
    assert "--prepare-minutes must be a finite number >= 0" in _one_line_error(capsys)
    assert not (tmp_path / "out").exists()  # no settings.json recording NaN, which no later run could match


def _damage_crc(path: Path) -> None:
    """Write the case uncompressed and change one byte of its cloud: the archive's CRC no longer matches."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(path, **arrays)
    data = bytearray(path.read_bytes())
    at = data.index(b"src_pcd.npy") + 400  # inside the cloud's bytes
    data[at] ^= 0xFF
    path.write_bytes(bytes(data))


def test_a_damaged_case_is_one_line_naming_it(dataset: Path, tmp_path: Path, capsys) -> None:
    case = sorted(dataset.iterdir())[1]
    _damage_crc(case)
    assert _bench(dataset, tmp_path / "o1") == 2
    assert f"{case.name}: not a readable case NPZ" in _one_line_error(capsys)
    rng = np.random.default_rng(2)
    bad_markers = {**_case(rng, 0.5), "tgt_marker": rng.normal(size=(5, 3))}  # 12 source markers, 5 target ones
    write_case(case, bad_markers)
    assert _bench(dataset, tmp_path / "o2") == 2
    assert f"{case.name}: src_marker (12, 3) and tgt_marker (5, 3)" in _one_line_error(capsys)
    write_case(case, _case(rng, 3.0))  # a share of the surface above 1
    assert _bench(dataset, tmp_path / "o3") == 2
    assert f"{case.name}: visibility must lie in [0, 1], got 3" in _one_line_error(capsys)
    assert not any((tmp_path / o).exists() for o in ("o1", "o2", "o3"))  # refused before the run


def test_a_damaged_settings_file_is_one_line_naming_it(dataset: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out) == 0
    (out / "settings.json").write_text('{"dataset": ')  # cut short
    assert _bench(dataset, out) == 2
    assert "settings.json is not readable JSON" in _one_line_error(capsys)
    summary_only = ["-q", "benchmark", "--dataset", "x", "--out", str(out), "--summary-only"]
    assert main(summary_only) == 2
    assert "settings.json is not readable JSON" in _one_line_error(capsys)
    (out / "settings.json").write_text(json.dumps([1]))
    assert main(summary_only) == 2
    assert "settings.json holds no JSON object" in _one_line_error(capsys)


def test_the_readme_is_checked_before_the_run(dataset: Path, tmp_path: Path, capsys) -> None:
    readme = tmp_path / "README.md"
    readme.write_text("# no block here\n")
    assert _bench(dataset, tmp_path / "out", "--readme", str(readme)) == 2
    assert "lacks the <!-- BENCHMARK:START -->" in _one_line_error(capsys)
    assert not (tmp_path / "out").exists()
    readme.write_text("<!-- OTHER:START -->\n<!-- OTHER:END -->\n")
    assert _bench(dataset, tmp_path / "out", "--readme", str(readme), "--readme-block", "OTHER") == 0
    assert "Dataset `" in readme.read_text() and readme.read_text().startswith("<!-- OTHER:START -->")
    with open(tmp_path / "out" / "cases.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 3
