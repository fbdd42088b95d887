"""Benchmark harness end to end: `liver-p2p benchmark` on small synthetic cases through the public API."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import write_cases

from liver_p2p_reg.bench.cases_csv import read_rows
from liver_p2p_reg.cli import main
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import RegistrationError
from liver_p2p_reg.metrics import mean_closest_point_mm
from liver_p2p_reg.registration.context import MethodContext
from liver_p2p_reg.registration.methods import Method, add_method, remove_method
from liver_p2p_reg.registration.registrar import Registrar, available_methods
from liver_p2p_reg.result import RegistrationResult


def kabsch_rms_mm(source_mm: np.ndarray, target_mm: np.ndarray) -> float:
    """RMS residual of the best rigid fit of source onto target (least squares, SVD)."""
    cs, ct = source_mm.mean(0), target_mm.mean(0)
    u, _, vt = np.linalg.svd((source_mm - cs).T @ (target_mm - ct))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    moved = (source_mm - cs) @ R.T + ct
    return float(np.sqrt(np.mean(np.sum((moved - target_mm) ** 2, axis=1))))


# --- methods that exist only in this test: a broken one, a failing one, a config probe ---------------
def _identity(source: np.ndarray, target: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Deliberately broken: never moves the source."""
    return RegistrationResult(np.eye(4), "identity-test", mean_closest_point_mm(target, source))


def _raise(source: np.ndarray, target: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    raise RegistrationError("too few matches (test)")


def _probe(source: np.ndarray, target: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """Ground-truth fit shifted along x by k mm (+30 mm for inlier-count, +60 mm without proposal)."""
    s, t = ctx.source_fiducials_mm, ctx.target_fiducials_mm
    cs, ct = s.mean(0), t.mean(0)
    u, _, vt = np.linalg.svd((s - cs).T @ (t - ct))
    R = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, ct - R @ cs
    T[0, 3] += config.k + 30.0 * (config.selection == "inlier-count") + 60.0 * (not config.candidate_proposal)
    return RegistrationResult(T, "probe-test-p2p", 0.0, runtime_ms={"match": 1.0, "select": 0.5})


def _probe_icp(source: np.ndarray, target: np.ndarray, config: Config, ctx: MethodContext) -> RegistrationResult:
    """The probe 2 mm off with the ICP screening of candidates, 10 mm off without it."""
    result = _probe(source, target, config.replace(k=2 if config.refine_candidates > 1 else 10), ctx)
    result.method = "probe-test-p2p-icp"
    return result


TEST_METHODS = {
    "identity-test": _identity,
    "raise-test": _raise,
    "probe-test-p2p": _probe,
    "probe-test-p2p-icp": _probe_icp,
}


@pytest.fixture(scope="module", autouse=True)
def test_methods() -> Iterator[None]:
    """Register the test-only methods for this module and remove them afterwards (other tests list methods)."""
    for name, fn in TEST_METHODS.items():
        add_method(name, Method(doc=fn.__doc__ or name, run=fn))
    yield
    for name in TEST_METHODS:
        remove_method(name)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("cases")
    write_cases(folder, per_bin=2)
    return folder


def _bench(dataset: Path, out: Path, methods: str, *extra: str) -> int:
    return main(["-q", "benchmark", "--dataset", str(dataset), "--methods", methods, "--out", str(out), *extra])


def _numbers(path: Path) -> list[tuple]:
    """Everything in cases.csv but wall-clock runtimes."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return [tuple((k, v) for k, v in r.items() if not k.startswith("runtime_")) for r in rows]


def test_smoke_run_writes_schema_and_tells_good_from_bad(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out, "identity-test,raise-test,probe-test-p2p", "--preset", "smoke") == 0
    with open(out / "cases.csv", newline="") as fh:
        header = next(csv.reader(fh))
    for column in (
        "case_id", "method", "visibility", "noise_mm", "crop_mode", "deformation_rms_mm", "rms_tre_mm",
        "max_tre_mm", "residual_mm", "runtime_ms", "runtime_match_ms", "runtime_select_ms",
        "chosen_candidate", "failed", "reason", "ambiguous",
    ):  # fmt: skip
        assert column in header
    rows = read_rows(out / "cases.csv")
    assert len(rows) == 16 * 3  # smoke keeps up to 3 cases per bin; this set has 2 per bin
    identity = [r for r in rows if r["method"] == "identity-test"]
    probe = [r for r in rows if r["method"] == "probe-test-p2p"]
    failed = [r for r in rows if r["method"] == "raise-test"]
    # The broken method keeps the initial pose: its error is the initial misalignment, tens of mm.
    assert all(r["rms_tre_mm"] == pytest.approx(r["initial_rms_tre_mm"]) for r in identity)
    assert np.mean([r["rms_tre_mm"] for r in identity]) > 50
    # The probe is the best rigid fit moved 5 mm (default k): a few mm, never near the identity's error.
    assert max(r["rms_tre_mm"] for r in probe) < 25
    assert all(r["failed"] and r["reason"] == "RegistrationError: too few matches (test)" for r in failed)
    assert all(r["rms_tre_mm"] == pytest.approx(r["initial_rms_tre_mm"]) for r in failed)  # documented rule
    assert not any(r["failed"] for r in identity + probe)
    summary = (out / "summary.md").read_text()
    for heading in ("Table I form", "relative to the oracle", "Success rate", "Wilcoxon", "Runtime", "Machine"):
        assert heading in summary
    assert "| raise-test | 0.0 % |" in summary
    assert "| probe-test-p2p | 100.0 % |" in summary
    for png in ("success_vs_tau.png", "tre_vs_visibility.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_reruns_give_identical_numbers(dataset: Path, tmp_path: Path) -> None:
    for name in ("a", "b"):
        assert _bench(dataset, tmp_path / name, "identity-test,probe-test-p2p", "--noise-levels", "2,4") == 0
    first, second = _numbers(tmp_path / "a" / "cases.csv"), _numbers(tmp_path / "b" / "cases.csv")
    assert first == second and len(first) == 2 * (16 + 2 * 2)  # 2 noisy copies of the 2 lowest-bin cases


def test_noise_levels_add_noisy_low_visibility_cases(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out, "identity-test", "--noise-levels", "2,4") == 0
    rows = {r["case_id"]: r for r in read_rows(out / "cases.csv")}
    noisy = [r for r in rows.values() if r["added_noise_mm"] > 0]
    assert sorted(r["noise_mm"] for r in noisy) == [2.0, 2.0, 4.0, 4.0]
    assert all(r["visibility"] < 0.3 for r in noisy)
    for r in noisy:  # the target really changed: the identity's residual moves, its TRE does not
        clean = rows[r["case_id"].split("+")[0]]
        assert r["residual_mm"] != clean["residual_mm"]
        assert r["rms_tre_mm"] == clean["rms_tre_mm"]
    summary = (out / "summary.md").read_text()
    assert "Sensor noise at visibility [0.2,0.3)" in summary and "noise 4 mm" in summary
    # The main table keeps the clean cases only: 2 per bin.
    assert "| *cases* | 2 | 2 | 2 | 2 | 2 | 2 | 2 | 2 | 16 |" in summary


def test_resume_skips_done_rows_and_reruns_missing_ones(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out, "probe-test-p2p", "--limit", "4") == 0
    path = out / "cases.csv"
    rows = list(csv.DictReader(open(path, newline="")))
    rows[0]["rms_tre_mm"] = "12345.0"  # a done row: must be kept as is, not recomputed
    removed = rows.pop(1)  # a missing row: must be run again
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    assert _bench(dataset, out, "probe-test-p2p", "--limit", "4") == 0
    again = read_rows(path)
    assert len(again) == 4
    assert again[0]["rms_tre_mm"] == 12345.0
    redone = next(r for r in again if r["case_id"] == removed["case_id"])
    assert redone["rms_tre_mm"] == pytest.approx(float(removed["rms_tre_mm"]))
    # Adding a method to the same OUT runs only the new rows and summarizes both.
    assert _bench(dataset, out, "probe-test-p2p,identity-test", "--limit", "4") == 0
    final = read_rows(path)
    assert len(final) == 8
    # Noise levels only add (noisy copies of) cases: allowed into the same OUT, old rows kept.
    assert _bench(dataset, out, "probe-test-p2p,identity-test", "--limit", "4", "--noise-levels", "2") == 0
    final = read_rows(path)
    assert len(final) == 8 + 2 * 2  # the 4 first cases hold 2 from [0.2,0.3): one noisy copy each, 2 methods
    assert [r["rms_tre_mm"] for r in final if r["method"] == "probe-test-p2p"][0] == 12345.0


def test_refuses_to_mix_settings_in_one_out(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out, "identity-test", "--limit", "2") == 0
    assert _bench(dataset, out, "identity-test", "--limit", "2", "--seed", "3") == 2
    assert "holds a run with other settings (config.seed: 0 then, 3 now)" in capsys.readouterr().err
    assert _bench(dataset, out, "identity-test", "--limit", "3") == 2
    # A Config field added to the code after the first run does not block adding methods later.
    settings = json.loads((out / "settings.json").read_text())
    del settings["config"]["icp_trim_ratio"]
    (out / "settings.json").write_text(json.dumps(settings))
    assert _bench(dataset, out, "identity-test,probe-test-p2p", "--limit", "2") == 0


def test_bad_arguments_are_one_line_errors(dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert _bench(dataset, tmp_path / "o1", "nope") == 2
    assert "unknown method(s) nope" in capsys.readouterr().err
    assert _bench(tmp_path / "missing/dir", tmp_path / "o2", "identity-test") == 2
    assert "does not exist" in capsys.readouterr().err
    assert _bench(dataset, tmp_path / "o3", "identity-test", "--noise-levels", "a") == 2
    assert "--noise-levels must be" in capsys.readouterr().err
    assert _bench(tmp_path / "missing/dir", tmp_path / "o5", "identity-test", "--workers", "0") == 2
    assert "--workers must be >= 1" in capsys.readouterr().err  # before the data are looked at
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _bench(empty, tmp_path / "o4", "identity-test") == 2
    assert "no case files" in capsys.readouterr().err


def test_ablations_reach_the_method_through_config(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out, "probe-test-p2p", "--ablations", "--ablation-cases-per-bin", "1") == 0
    rows = read_rows(out / "cases.csv")
    variants = {r["method"] for r in rows}
    assert variants == {
        "probe-test-p2p",
        *(f"probe-test-p2p[k={k}]" for k in (1, 2, 3, 4, 6, 7, 8)),
        "probe-test-p2p[selection=inlier-count]",
        "probe-test-p2p[candidate_proposal=False]",
        "probe-test-p2p[mutual_only=True]",
        "probe-test-p2p[refit_iterations=0]",
        "probe-test-p2p[consensus_seeds=0]",
    }
    assert sum(r["method"] == "probe-test-p2p[k=1]" for r in rows) == 8  # one case per bin
    by = {(r["case_id"], r["method"]): r for r in rows}
    case = next(r["case_id"] for r in rows if r["method"] == "probe-test-p2p[k=1]")
    tre = [by[case, "probe-test-p2p" if k == 5 else f"probe-test-p2p[k={k}]"]["rms_tre_mm"] for k in range(1, 9)]
    assert tre == sorted(tre) and tre[-1] > tre[0] + 3  # the offset grows with k: k reached the method
    assert by[case, "probe-test-p2p[selection=inlier-count]"]["rms_tre_mm"] > 25
    summary = (out / "summary.md").read_text()
    assert "P2P ablations" in summary and "K=8" in summary and (out / "ablation_k.png").is_file()
    assert "mutual_only=True" in summary and "refit_iterations=0" in summary and "consensus_seeds=0" in summary


def test_oracle_error_equals_best_rigid_fit_of_the_fiducials(dataset: Path, tmp_path: Path) -> None:
    if "procrustes" not in available_methods():
        pytest.skip("the procrustes method is not part of this build yet")
    out = tmp_path / "out"
    assert _bench(dataset, out, "procrustes") == 0
    rows = read_rows(out / "cases.csv")
    assert len(rows) == 16
    for r in rows:
        with np.load(dataset / f"{r['case_id']}.npz") as case:
            expected = kabsch_rms_mm(case["src_marker"], case["tgt_marker"])
        assert not r["failed"]
        assert r["rms_tre_mm"] == pytest.approx(expected, rel=1e-6, abs=1e-6)
        assert expected > 0.5  # the deformation leaves a residual a rigid fit cannot remove
    assert not math.isnan(rows[0]["max_tre_mm"])


def test_bound_row_is_track_from_the_true_pose(dataset: Path, tmp_path: Path) -> None:
    """The rigid surface bound: the configured ICP (`track`) started from each case's R_gt, t_gt."""
    out = tmp_path / "out"
    assert _bench(dataset, out, "procrustes,bound", "--preset", "smoke") == 0
    rows = read_rows(out / "cases.csv")
    bound = {r["case_id"]: r for r in rows if r["method"] == "bound"}
    assert len(bound) == 16 and not any(r["failed"] for r in bound.values())
    for case_id, r in list(bound.items())[:4]:
        with np.load(dataset / f"{case_id}.npz") as case:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = case["R_gt"], case["t_gt"]
            direct = Registrar(Config(seed=r["seed"])).register(
                case["src_pcd"],
                case["tgt_pcd"],
                method="track",
                initial_T_mm=T,
                source_fiducials_mm=case["src_marker"],
                target_fiducials_mm=case["tgt_marker"],
            )
        assert r["rms_tre_mm"] == direct.rms_tre_mm and r["max_tre_mm"] == direct.max_tre_mm
    summary = (out / "summary.md").read_text()
    assert "bound (ICP from the true pose)" in summary and "mean / bound" in summary


def test_readme_option_regenerates_the_benchmark_block(dataset: Path, tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text("# x\n<!-- BENCHMARK:START -->\nstale\n<!-- BENCHMARK:END -->\ntail\n")
    out = tmp_path / "docs" / "benchmark"
    assert _bench(dataset, out, "probe-test-p2p", "--limit", "3", "--readme", str(readme)) == 0
    text = readme.read_text()
    assert (
        "stale" not in text and text.startswith("# x\n<!-- BENCHMARK:START -->\n") and text.endswith("END -->\ntail\n")
    )
    assert "| probe-test-p2p |" in text and "[docs/benchmark/summary.md](docs/benchmark/summary.md)" in text
    assert "--readme" in text  # the command that regenerates it is quoted
    # --summary-only rewrites the reports from cases.csv, running nothing, with the recorded command.
    readme.write_text("<!-- BENCHMARK:START -->\n<!-- BENCHMARK:END -->\n")
    (out / "summary.md").unlink()
    assert (
        main(["-q", "benchmark", "--dataset", "unused", "--out", str(out), "--summary-only", "--readme", str(readme)])
        == 0
    )
    assert (
        (out / "summary.md").is_file()
        and "--limit 3" in readme.read_text()
        and "| probe-test-p2p |" in readme.read_text()
    )
    assert main(["-q", "benchmark", "--dataset", "x", "--out", str(tmp_path / "none"), "--summary-only"]) == 2


def test_two_workers_give_the_same_rows_as_one(dataset: Path, tmp_path: Path) -> None:
    if "procrustes" not in available_methods():
        pytest.skip("the procrustes method is not part of this build yet")
    for workers in ("1", "2"):
        assert _bench(dataset, tmp_path / workers, "procrustes", "--limit", "3", "--workers", workers) == 0
    assert _numbers(tmp_path / "1" / "cases.csv") == _numbers(tmp_path / "2" / "cases.csv")


def test_screening_ablation_reaches_the_icp_method(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert _bench(dataset, out, "probe-test-p2p-icp", "--ablations", "--ablation-cases-per-bin", "1") == 0
    rows = read_rows(out / "cases.csv")
    assert {r["method"] for r in rows} == {"probe-test-p2p-icp", "probe-test-p2p-icp[refine_candidates=1]"}
    off = [r["rms_tre_mm"] for r in rows if r["variant"] == "refine_candidates=1"]
    on = [
        r["rms_tre_mm"]
        for r in rows
        if r["variant"] == "" and r["case_id"] in {x["case_id"] for x in rows if x["variant"]}
    ]
    assert len(off) == len(on) == 8 and np.mean(off) > np.mean(on) + 5
    summary = (out / "summary.md").read_text()
    assert "refine_candidates=6" in summary and "refine_candidates=1" in summary
