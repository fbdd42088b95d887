"""The surface search's rule (docs/benchmark_real/RULE_surface_search.md), from rows composed by the cases' M/N."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.cases_csv import CASES_CSV, read_rows
from liver_p2p_reg.bench.ransac_threshold_rule import lowest_pooled, path_mismatches, pooled_line
from liver_p2p_reg.bench.ransac_threshold_rule import row_tre as tre
from liver_p2p_reg.bench.small_view_rule import NOISE, SLACK_MM, tre_stats

METHOD = "learned-p2p-icp"
SETTING = "surface_search_visibility"
THRESHOLDS = (0.10, 0.15, 0.20)  # the candidates for `surface_search_visibility`
RUN_THRESHOLD = 0.20  # the candidate's run is made at this value; each smaller T is composed from it
REFERENCE_RUN, CANDIDATE_RUN = "reference", "search-0.20"  # the runs' folders under the out root
TEST_REFERENCE_RUN = "test-reference"  # the default on the test sets, this machine (the published rows: another CPU)
VAL_SETS = {
    name: [*NOISE, "--visibility", "0.05,0.3"] for name in ("real-val-v2", "real-val-v2-arap", "real-val-camera-v2")
}
TEST_SETS = {
    name: [*NOISE, "--visibility", "0.05,0.3"]
    for name in ("real-test-v2", "real-test-v2-arap", "real-test-camera-v2", "real-test-camera-v2-arap")
}
# the published default's rows of each test set (the protocol's benchmark folders)
PUBLISHED = {
    "real-test-v2": "docs/benchmark_real_test_v2",
    "real-test-v2-arap": "docs/benchmark_real_test_v2_arap",
    "real-test-camera-v2": "docs/benchmark_real_test_camera_v2",
    "real-test-camera-v2-arap": "docs/benchmark_real_test_camera_v2_arap",
}
BINS = {"[0.05, 0.10)": (0.05, 0.10), "[0.10, 0.15)": (0.10, 0.15), "[0.15, 0.20)": (0.15, 0.20)}
POOLED, ABOVE = "[0.05, 0.2)", "[0.2, 0.3)"
GROUPS = {POOLED: (0.05, 0.2), **BINS, ABOVE: (0.2, 0.3)}
TIE_MM = 0.01  # pooled small-view means this close: the smaller threshold wins (the search on fewer views)
TIME_LIMIT_MS = 150.0  # the limit on the default's median time per registration


def key(row: dict) -> tuple[str, float]:
    """A benchmark row's case: its id and its added noise."""
    return row["case_id"], row["added_noise_mm"]


def method_rows(path: Path) -> dict[tuple[str, float], dict]:
    """The default's rows of one benchmark folder's cases.csv, by case."""
    return {key(r): r for r in read_rows(path / CASES_CSV) if r["method"] == METHOD}


def compose(reference: dict, candidate: dict, threshold: float) -> list[dict]:
    """Each case's candidate row where its M/N is below `threshold` (<= RUN_THRESHOLD), else the reference's.

    Exact, not an estimate: below the threshold the search's path is the one the candidate ran, above it the search
    returns before any work (`mismatches` checks the second half)."""
    if not 0 < threshold <= RUN_THRESHOLD:
        raise ValueError(f"a threshold is composed from a run at {RUN_THRESHOLD}; {threshold} is outside (0, it]")
    missing = sorted(set(candidate) - set(reference))
    if missing:
        raise ValueError(f"{len(missing)} candidate case(s) have no reference row, e.g. {missing[0]}")
    return [candidate[k] if candidate[k]["method_visibility"] < threshold else reference[k] for k in sorted(candidate)]


def mismatches(reference: dict, candidate: dict, threshold: float = RUN_THRESHOLD) -> list[str]:
    """Cases the two runs must agree on bit for bit and do not: M/N differs, or M/N >= `threshold` (no search)
    and the RMS-TRE or the failure differs."""
    return path_mismatches(reference, candidate, threshold, "no search")


def group_stats(rows: list[dict]) -> dict[str, dict[str, float]]:
    """tre_stats of each group of GROUPS."""
    return {g: tre_stats([r for r in rows if lo <= r["visibility"] < hi]) for g, (lo, hi) in GROUPS.items()}


def passes(stats: dict[str, dict[str, float]], base: dict[str, dict[str, float]], bins: bool = True) -> bool:
    """Rules 1 and 3 (and 2 with `bins`) of a candidate's group statistics against the reference's."""
    pooled, above = stats[POOLED], base[POOLED]
    ok = pooled["mean"] < above["mean"] and pooled["s10"] >= above["s10"]
    groups = [ABOVE, *BINS] if bins else [ABOVE]
    return ok and all(
        stats[g]["mean"] <= base[g]["mean"] + SLACK_MM and stats[g]["gross"] <= base[g]["gross"] for g in groups
    )


def table_rows(name: str, label: str, stats: dict[str, dict[str, float]], searched: dict[str, int]) -> list[str]:
    """One option's markdown rows, one per group."""
    return [
        f"| {name} | {label} | {g} | {s['n']} | {s['mean']:.2f} | {100 * s['s10']:.1f} % | {s['gross']} | "
        f"{searched.get(g, 0)} |"
        for g, s in stats.items()
    ]


TABLE_HEAD = [
    "| set | `surface_search_visibility` | bins | poses | mean RMS-TRE (mm) | success@10 mm | >= 20 mm |"
    " views searched |",
    "|---|---|---|---|---|---|---|---|",
]


def searched_counts(rows: list[dict], threshold: float) -> dict[str, int]:
    """Per group, the views whose M/N is below `threshold` (the search ran on them)."""
    return {
        g: sum(lo <= r["visibility"] < hi and r["method_visibility"] < threshold for r in rows)
        for g, (lo, hi) in GROUPS.items()
    }


def validation_verdict(out_root: str) -> tuple[list[str], str, float | None]:
    """The rule's table on the validation runs, its verdict line and the chosen threshold (None: none passes)."""
    table, checks, passing = list(TABLE_HEAD), [], set(THRESHOLDS)
    pooled = {t: [] for t in THRESHOLDS}
    for name in VAL_SETS:
        ref = method_rows(Path(out_root) / REFERENCE_RUN / name)
        cand = method_rows(Path(out_root) / CANDIDATE_RUN / name)
        checks += [f"{name}: {m}" for m in mismatches(ref, cand)]
        base = group_stats(list(ref.values()))
        table += table_rows(name, "reference (0)", base, {})
        for t in THRESHOLDS:
            rows = compose(ref, cand, t)
            stats = group_stats(rows)
            table += table_rows(name, f"{t:.2f}", stats, searched_counts(rows, t))
            if not passes(stats, base):
                passing.discard(t)
            pooled[t] += [r for r in rows if GROUPS[POOLED][0] <= r["visibility"] < GROUPS[POOLED][1]]
    means = {t: tre_stats(rows)["mean"] for t, rows in pooled.items()}
    table += ["", pooled_line(means, passing, "1-3")]
    if checks:
        return table + ["", *checks[:20]], f"The composition check failed on {len(checks)} case(s): no verdict.", None
    if not passing:
        return table, "No threshold passes rules 1-3 on all three sets: the search stays off (0).", None
    chosen = lowest_pooled(means, passing, TIE_MM)
    return table, f"Threshold {chosen:.2f} passes rules 1-3 on all three sets and is chosen (time next).", chosen


def judged_on_test_sets(
    out_root: str, threshold: float, name: str, reference: str = ""
) -> tuple[list[str], str, bool, list[str]]:
    """The test sets' judgement of `threshold`: table, verdict line, whether it passes, and a line per set comparing
    the reference with the published default's rows where no search ran (their largest RMS-TRE difference).

    The candidate's test runs are in OUT_ROOT/NAME/SET, made at the threshold itself, so its rows at M/N >= it must
    equal the reference's: the default's rows of OUT_ROOT/REFERENCE/SET, or the published ones without `reference`.
    """
    table, checks, ok, published = list(TABLE_HEAD), [], True, []
    for dataset, folder in PUBLISHED.items():
        ref = method_rows(Path(out_root) / reference / dataset) if reference else method_rows(Path(folder))
        cand = method_rows(Path(out_root) / name / dataset)
        checks += [f"{dataset}: {m}" for m in mismatches(ref, cand, threshold)]
        base = group_stats([ref[k] for k in sorted(cand.keys() & ref.keys())])
        rows = [cand[k] for k in sorted(cand)]  # run at the threshold itself: no composition
        stats = group_stats(rows)
        label = "default (0), this run" if reference else "published default (0)"
        table += table_rows(dataset, label, base, {})
        table += table_rows(dataset, f"{threshold:.2f}", stats, searched_counts(rows, threshold))
        ok = ok and passes(stats, base, bins=False)
        if reference:
            published.append(published_difference(dataset, method_rows(Path(folder)), ref))
    if checks:
        line = f"The composition check failed on {len(checks)} case(s): no verdict."
        return table + ["", *checks[:20]], line, False, published
    line = (
        f"Threshold {threshold:.2f} keeps rules 1 and 3 on all four test sets (no veto; it ships only where the "
        "validation's rules and time passed too: selection_surface_search.md)."
        if ok
        else f"Threshold {threshold:.2f} fails rule 1 or 3 on a test set: vetoed, the search stays off (0)."
    )
    return table, line, ok, published


def published_difference(dataset: str, published: dict, reference: dict) -> str:
    """How far this machine's default rows are from the published ones, case by case (another CPU's arithmetic)."""
    shared = sorted(published.keys() & reference.keys())
    pairs = [(tre(published[k]), tre(reference[k])) for k in shared]
    diffs = [abs(a - b) for a, b in pairs if np.isfinite(a) and np.isfinite(b)]  # (a failure on one side: not counted)
    moved = sum(d > 0.01 for d in diffs)
    return (
        f"{dataset}: {len(shared)} rows beside the published ones, {sum(d > 0 for d in diffs)} differing, "
        f"{moved} by more than 0.01 mm, the largest by {max(diffs, default=0.0):.2g} mm"
    )
