"""Named test sets: the smoke preset end to end (generation, manifest, reuse, stats CLI)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import pytest

from liver_p2p_reg.cli import dataset_cmd
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.phantom import testset
from liver_p2p_reg.phantom.casefile import read_case
from liver_p2p_reg.phantom.manifest import read_manifest
from liver_p2p_reg.phantom.testset import TESTSETS, ensure_testset


def test_smoke_testset_generates_once_and_is_balanced(tmp_path, monkeypatch, capsys, caplog) -> None:
    monkeypatch.setenv("LIVER_P2P_DATA", str(tmp_path / "root"))
    caplog.set_level(logging.INFO, logger="liver_p2p_reg")
    # First only the liver a small benchmark preset needs, announced with its size ...
    path = ensure_testset("insilico-smoke", progress=False, livers=[1])
    assert "building test set insilico-smoke" in caplog.text and "1 of the 2 livers, 8 cases, about 3 MB" in caplog.text
    first = sorted(path.glob("case_*.npz"))
    assert (
        len(first) == 8
        and all("L9010001" in p.name for p in first)
        and not testset.is_complete(path, TESTSETS["insilico-smoke"])
    )
    first_mtimes = [p.stat().st_mtime_ns for p in first]
    caplog.clear()
    assert ensure_testset("insilico-smoke", progress=False, livers=[1]) == path and caplog.text == ""  # done: nothing
    # ... then the rest: the first liver's cases are kept, not rebuilt.
    path = ensure_testset("insilico-smoke", progress=False)
    assert "all livers, 16 cases" in caplog.text
    assert [p.stat().st_mtime_ns for p in first] == first_mtimes
    assert path == tmp_path / "root" / "insilico-smoke"
    cases = testset.testset_cases(path)
    assert cases == sorted(cases) and len(cases) == 16
    rows = read_manifest(path)
    bins = np.floor(np.array([r["visibility"] for r in rows]) * 10).clip(2, 9)
    assert np.array_equal(np.bincount(bins.astype(int), minlength=10)[2:], np.full(8, 2))
    assert all(r["split"] == "test" for r in rows)
    # Test livers come from the reserved seeds, never from a training seed.
    assert {r["liver_id"] // 10_000 for r in rows} == {TESTSETS["insilico-smoke"].seed}
    case = read_case(cases[0])
    assert np.allclose(case["tgt_marker"], read_case(cases[0])["tgt_marker"])
    # Present and complete: a second call regenerates nothing.
    mtimes = [p.stat().st_mtime_ns for p in cases]
    assert ensure_testset("insilico-smoke", progress=False) == path
    assert [p.stat().st_mtime_ns for p in cases] == mtimes

    parser = argparse.ArgumentParser()
    dataset_cmd.add_parser(parser.add_subparsers())
    args = parser.parse_args(["dataset", "stats", str(path), "--png", str(tmp_path / "h.png")])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "16 cases, 2 livers" in out and "[0.9,1.0] 2" in out
    assert (tmp_path / "h.png").stat().st_size > 10_000


def test_unknown_testset_is_input_error(tmp_path) -> None:
    with pytest.raises(InputError, match="unknown test set"):
        ensure_testset("insilico-test-v0", root=tmp_path)


def test_a_set_from_another_generator_version_is_rebuilt(tmp_path) -> None:
    import json

    path = ensure_testset("insilico-smoke", root=tmp_path, progress=False)
    meta = json.loads((path / "dataset.json").read_text())
    first = read_case(testset.testset_cases(path)[0])
    meta["generator_version"] = 0
    (path / "dataset.json").write_text(json.dumps(meta))
    (path / "case_L0000000_D00_T000.npz").write_bytes(b"stale")
    assert ensure_testset("insilico-smoke", root=tmp_path, progress=False) == path
    assert not (path / "case_L0000000_D00_T000.npz").exists()
    again = read_case(testset.testset_cases(path)[0])
    assert np.array_equal(first["tgt_pcd"], again["tgt_pcd"])  # rebuilt identically


def test_validation_sets_use_livers_no_test_set_or_training_store_can_have() -> None:
    """Defaults are chosen on the val sets: their livers must be unseen by training and by the tests."""
    val = {name: spec for name, spec in TESTSETS.items() if spec.split == "val"}
    test_seeds = {spec.seed for spec in TESTSETS.values() if spec.split == "test"}
    assert set(val) == {
        f"insilico-val{crop}-{version}" for crop in ("", "-camera") for version in ("v1", "v2", "v2-arap")
    }
    for name, spec in val.items():
        assert spec.seed not in test_seeds, name
        # a reserved seed: `dataset generate --store/--seed` refuses it, so no training store holds these livers
        with pytest.raises(InputError, match="reserved"):
            testset.DatasetSpec(livers=1, deformations=1, targets=1, seed=spec.seed).validate()
        assert testset.testset_spec(name).seed == spec.seed


def test_smoke_preset_picks_its_cases_from_the_design_and_needs_few_livers() -> None:
    from liver_p2p_reg.bench.cases import (
        BIN_LABELS,
        PAPER_FIRST_BIN,
        CaseInfo,
        first_per_bin,
        planned_cases,
        visibility_bin,
    )

    v1_bins = range(PAPER_FIRST_BIN, len(BIN_LABELS))  # the paper's bins: v1 holds no case below 0.2
    livers, names = planned_cases("insilico-test-v1", "smoke", None)
    assert livers == [0, 6, 11] and len(names) == 3 * len(v1_bins)
    design = testset.expected_cases("insilico-test-v1")
    bins = {name: visibility_bin(v) for _, name, v in design}
    assert sorted(bins[n] for n in names) == sorted(list(v1_bins) * 3)
    # The same cases `first_per_bin` picks from the whole set when none is skipped (test-v1 skips none).
    infos = [CaseInfo(Path(n).stem, Path(n), v, 0.0, "", 0.0, 0) for _, n, v in design]
    assert sorted(c.case_id + ".npz" for c in first_per_bin(infos, 3)) == sorted(names)
    assert planned_cases("insilico-test-v1", "full", 5) == ([0], [n for _, n, _ in design[:5]])
    assert planned_cases("/no/such/folder", "smoke", None) is None
