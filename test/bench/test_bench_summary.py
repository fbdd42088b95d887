"""Benchmark report arithmetic: bins, oracle ratios, success rates, rank-sum marks, slow flags, README block."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import ranksums

from liver_p2p_reg.bench.cases import BIN_LABELS, PAPER_FIRST_BIN, visibility_bin
from liver_p2p_reg.bench.readme import readme_markers, replace_readme_block
from liver_p2p_reg.bench.summary import Summary
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError

README_START, README_END = readme_markers()


def _row(case: int, method: str, vis: float, tre: float, runtime_ms: float = 10.0, failed: bool = False) -> dict:
    return {
        "case_id": f"c{case:03d}",
        "method": method,
        "base_method": method,
        "variant": "",
        "visibility": vis,
        "noise_mm": 0.0,
        "added_noise_mm": 0.0,
        "crop_mode": "random",
        "deformation_rms_mm": 3.0,
        "rms_tre_mm": tre,
        "max_tre_mm": tre * 1.5,
        "initial_rms_tre_mm": 100.0,
        "residual_mm": 1.0,
        "runtime_ms": runtime_ms,
        "failed": failed,
        "reason": "RegistrationError: x" if failed else "",
        "ambiguous": False,
    }


def _settings() -> dict:
    return {
        "dataset": "synthetic",
        "preset": "full",
        "limit": None,
        "ablation_cases_per_bin": 10,
        "config": Config().to_dict(),
    }


def _summary(rows: list[dict]) -> Summary:
    return Summary(rows, _settings(), {"cpu": "test cpu", "usable_cores": 2, "torch": "x", "device": "cpu"})


def test_visibility_bins_follow_the_paper_and_reach_down_to_the_laparoscope() -> None:
    # the laparoscope's range below the paper's bins, then the paper's Table I bins unchanged
    assert BIN_LABELS[:3] == ("[0.05,0.10)", "[0.10,0.15)", "[0.15,0.20)")
    assert BIN_LABELS[PAPER_FIRST_BIN] == "[0.2,0.3)" and BIN_LABELS[-1] == "[0.9,1.0]" and len(BIN_LABELS) == 11
    assert BIN_LABELS[visibility_bin(0.12)] == "[0.10,0.15)" and visibility_bin(0.05) == 0
    assert visibility_bin(0.19) == 2 and visibility_bin(0.2) == PAPER_FIRST_BIN and visibility_bin(0.2999) == 3
    assert visibility_bin(0.3) == 4 and visibility_bin(0.95) == 10 and visibility_bin(1.0) == 10
    assert visibility_bin(0.049) is None and visibility_bin(1.01) is None and visibility_bin(float("nan")) is None


def test_tables_ratios_success_and_significance() -> None:
    rng = np.random.default_rng(3)
    rows = []
    low_p2p, low_base = rng.normal(6, 1, 20), rng.normal(12, 2, 20)
    high_p2p, high_base = rng.normal(3.5, 0.3, 20), rng.normal(3.5, 0.3, 20)
    for i in range(20):
        rows += [
            _row(i, "procrustes", 0.25, 2.0),
            _row(i, "x-p2p", 0.25, low_p2p[i]),
            _row(i, "x", 0.25, low_base[i], 9000.0),
        ]
        j = 100 + i
        rows += [_row(j, "procrustes", 0.95, 3.0), _row(j, "x-p2p", 0.95, high_p2p[i])]
        rows += [_row(j, "x", 0.95, high_base[i], runtime_ms=9000.0, failed=i < 5)]
    s = _summary(rows)
    assert s.bins == [PAPER_FIRST_BIN, 10] and s.methods == ["procrustes", "x", "x-p2p"]
    assert s.slow == {"x"}  # median 9 s per case
    table = "\n".join(s.table_tre())
    assert "| procrustes (oracle) | 2.00 ± 0.00 | 3.00 ± 0.00 | 2.50 ± 0.50 |" in table
    assert f"| x-p2p | {np.mean(low_p2p):.2f} ± {np.std(low_p2p):.2f} |" in table
    ratio = "\n".join(s.table_ratio())
    assert f"| x-p2p | {np.mean(low_p2p) / 2:.2f} | {np.mean(high_p2p) / 3:.2f} |" in ratio
    success = "\n".join(s.table_success())
    low_rate = 100 * np.mean(low_base < 20)
    # At [0.9,1.0] 5 of 20 runs failed: they never count as successes, whatever their TRE.
    assert f"| x (slow) | {low_rate:.1f} % | 75.0 % | {(low_rate + 75) / 2:.1f} % |" in success
    wilcoxon = "\n".join(s.table_wilcoxon())
    p_low = ranksums(low_p2p, low_base).pvalue
    p_high = ranksums(high_p2p, high_base).pvalue
    assert p_low < 0.05 < p_high
    assert f"p={p_low:.3g} **\\***" in wilcoxon and f"p={p_high:.3g} (" in wilcoxon
    runtime = "\n".join(s.table_runtime())
    assert "| x (slow) |" in runtime


def test_readme_block_is_replaced_and_nothing_else(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text(f"# Title\n\nintro\n\n{README_START}\nold numbers\n{README_END}\n\n## After\ntext\n")
    replace_readme_block(readme, "new table\n| a | b |")
    text = readme.read_text()
    assert text == f"# Title\n\nintro\n\n{README_START}\nnew table\n| a | b |\n{README_END}\n\n## After\ntext\n"
    replace_readme_block(readme, "again")  # idempotent markers: a second run replaces the first
    assert text.replace("new table\n| a | b |", "again") == readme.read_text()
    bare = tmp_path / "bare.md"
    bare.write_text("no markers here\n")
    with pytest.raises(InputError, match="lacks the"):
        replace_readme_block(bare, "x")
    assert bare.read_text() == "no markers here\n"


def test_readme_block_holds_the_main_tables() -> None:
    rows = [_row(i, m, 0.25, 2.0 + i) for i in range(3) for m in ("procrustes", "x")]
    block = _summary(rows).readme_block("docs/benchmark/summary.md")
    assert "| procrustes (oracle) | 3.00 ± 0.82 | 3.00 ± 0.82 |" in block
    assert "Success rate" in block and "median total (ms)" in block
    assert "[docs/benchmark/summary.md](docs/benchmark/summary.md)" in block and "test cpu" in block


def test_tables_cover_only_cases_every_method_ran_on() -> None:
    rows = [_row(i, m, 0.25, 2.0 + i) for i in range(4) for m in ("procrustes", "x")]
    rows.append(_row(9, "procrustes", 0.25, 50.0))  # an interrupted run: case 9 lacks "x"
    s = _summary(rows)
    assert s.n_cases() == 4 and s.incomplete == 1
    assert "| procrustes (oracle) | 3.50 ± 1.12 | 3.50 ± 1.12 |" in "\n".join(s.table_tre())
    assert "cover the 4 cases that every method ran on, of the ? selected" in "\n".join(s.header_lines())
    s.settings["n_cases"] = 10
    assert "**Partial run:** the tables cover the 4 cases that every method ran on, of the 10 selected (1 more" in (
        "\n".join(s.header_lines())
    )


def test_confidence_table_counts_the_warnings_on_bad_and_good_poses() -> None:
    rows = [_row(i, "procrustes", 0.25, 3.0) for i in range(5)]
    mine = [_row(i, "x", 0.25, tre) for i, tre in enumerate((3.0, 4.0, 30.0, 50.0, 60.0))]
    mine[1]["uncertainty_mm"] = Config().uncertainty_warn_mm + 1  # a false alarm on a good pose
    mine[2]["uncertainty_mm"] = math.inf  # nothing constrained the pose
    mine[3]["residual_mm"] = Config().residual_warn_mm + 1
    mine[4]["ambiguous"] = True
    mine[0]["uncertainty_mm"] = 1.0
    summary = _summary(rows + mine)
    table = "\n".join(summary.table_confidence(summary.main))
    assert "| x | 3 | 3 | 1 / 2 | 4 / 5 | 1 / 1 / 2 |" in table
    assert "procrustes" not in table  # the oracle is never warned about
    mine[4]["ambiguous"] = False  # a bad pose nothing flags is counted as missed
    table = "\n".join(summary.table_confidence(summary.main))
    assert "| x | 3 | 2 | 1 / 2 | 3 / 5 | 1 / 0 / 2 |" in table


def test_rows_from_before_the_density_column_count_as_uniform() -> None:
    """A resumed run mixes rows without a density (written before the column existed) and `uniform` ones."""
    rows = [
        _row(i, m, 0.25, 5.0) | {"density": "" if i < 2 else "uniform"} for i in range(4) for m in ("procrustes", "a")
    ]
    assert _summary(rows).table_density() is None
    rows += [
        _row(i, m, 0.25, 6.0) | {"case_id": f"d{i}", "density": "mesh-vertices"}
        for i in range(4)
        for m in ("procrustes", "a")
    ]
    header = _summary(rows).table_density()[0]
    assert "| mesh-vertices | uniform |" in header and "|  |" not in header


def test_bootstrap_intervals_resample_livers_not_cases() -> None:
    from liver_p2p_reg.bench.headline import bootstrap_mean, liver_of

    assert liver_of("case_L0900003_D01_T004+noise2mm") == "0900003" and liver_of("odd") == "odd"
    # 100 cases of one liver at 0 mm and one case of another at 10 mm: the cases alone would give a
    # narrow interval about 0.1 mm; as two livers, a resample can be either liver alone
    values = np.array([0.0] * 100 + [10.0])
    livers = ["a"] * 100 + ["b"]
    mean, lo, hi = bootstrap_mean(values, livers)
    assert mean == pytest.approx(10 / 101) and lo == 0.0 and hi == 10.0
    assert bootstrap_mean(values, livers) == (mean, lo, hi)  # a fixed seed: the same interval every time
    single = bootstrap_mean(np.array([1.0, 2.0]), ["a", "a"])
    assert single[0] == 1.5 and np.isnan(single[1]) and np.isnan(single[2])
    rng = np.random.default_rng(0)
    many = rng.normal(5.0, 1.0, 400)
    mean, lo, hi = bootstrap_mean(many, [str(i // 10) for i in range(400)])
    assert lo < mean < hi and hi - lo < 1.0
