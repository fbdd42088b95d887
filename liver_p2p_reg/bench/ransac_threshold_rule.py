"""The RANSAC candidate's threshold rule (docs/benchmark_real/RULE_ransac_candidate_threshold.md), from composed rows."""

from __future__ import annotations

from pathlib import Path

from liver_p2p_reg.bench.cases_csv import CASES_CSV, read_rows
from liver_p2p_reg.bench.ransac_candidate_rule import CANDIDATE, GROUPS, REFERENCE, RUN, SETS, TIME_LIMIT_MS, median_ms
from liver_p2p_reg.bench.small_view_rule import SLACK_MM, tre_stats

THRESHOLDS = (0.15, 0.20, 0.25)  # the candidates for `ransac_candidate_visibility`
RUN_THRESHOLD = 0.3  # the candidate's runs were made with this value (its default until the rule says otherwise)
TIE_MM = 0.01  # pooled small-view means this close: the smaller threshold wins (RANSAC on fewer views)
SPEED_BLOCK = "SPEED-RANSAC-THRESHOLD"  # the speed.md block bench_paths.py writes for the chosen threshold


def _key(row: dict) -> tuple[str, float]:
    return row["case_id"], row["added_noise_mm"]


def _by_method(rows: list[dict], method: str) -> dict[tuple[str, float], dict]:
    return {_key(r): r for r in rows if r["method"] == method}


def row_tre(row: dict) -> float:
    """A benchmark row's RMS-TRE, infinite for a failed registration."""
    return float("inf") if row["failed"] else row["rms_tre_mm"]


def composed_rows(rows: list[dict], threshold: float) -> list[dict]:
    """Each case's row with RANSAC's pose where its M/N is below `threshold` (<= RUN_THRESHOLD), else the default's.

    Exact, not an estimate: below the threshold the candidate's path is the one it ran at RUN_THRESHOLD, above it
    the RANSAC hypothesis returns before any work and the path is the default's (`shared_path_mismatches` checks it).
    """
    if not 0 < threshold <= RUN_THRESHOLD:
        raise ValueError(f"a threshold is composed from runs at {RUN_THRESHOLD}; {threshold} is outside (0, it]")
    ref, cand = _by_method(rows, REFERENCE), _by_method(rows, CANDIDATE)
    if ref.keys() != cand.keys():
        raise ValueError(f"the two runs hold other cases: {len(ref)} {REFERENCE} rows, {len(cand)} {CANDIDATE} rows")
    return [cand[k] if cand[k]["method_visibility"] < threshold else ref[k] for k in sorted(ref)]


def shared_path_mismatches(rows: list[dict]) -> list[str]:
    """Cases where the two runs should agree bit for bit and do not: M/N differs, or M/N >= RUN_THRESHOLD (no
    RANSAC pose) and the RMS-TRE or the failure differs."""
    return path_mismatches(_by_method(rows, REFERENCE), _by_method(rows, CANDIDATE), RUN_THRESHOLD, "no RANSAC pose")


def path_mismatches(reference: dict, candidate: dict, threshold: float, without: str) -> list[str]:
    """Of two runs' rows by case, the cases that must agree bit for bit and do not: M/N differs, or M/N >= `threshold`
    (the candidate's extra work, `without`, did not run) and the RMS-TRE or the failure differs."""
    bad = []
    for k in sorted(reference.keys() & candidate.keys()):
        a, b = reference[k], candidate[k]
        if a["method_visibility"] != b["method_visibility"]:
            bad.append(f"{k[0]} (+{k[1]} mm): M/N {a['method_visibility']} vs {b['method_visibility']}")
        elif a["method_visibility"] >= threshold and row_tre(a) != row_tre(b):
            bad.append(f"{k[0]} (+{k[1]} mm): RMS-TRE {row_tre(a)} vs {row_tre(b)} with {without}")
    return bad


def real_run_mismatches(composed: list[dict], run_rows: list[dict]) -> list[str]:
    """Cases where a real run of the chosen threshold (its CANDIDATE rows) differs from the composed rows."""
    return run_differences(composed, _by_method(run_rows, CANDIDATE))


def run_differences(composed: list[dict], real: dict) -> list[str]:
    """Cases where a real run's rows (by case) are missing or differ from the composed rows."""
    bad = [f"{k[0]} (+{k[1]} mm): missing from the real run" for k in map(_key, composed) if k not in real]
    bad += [
        f"{_key(r)[0]} (+{_key(r)[1]} mm): composed {row_tre(r)} vs run {row_tre(real[_key(r)])}"
        for r in composed
        if _key(r) in real and row_tre(r) != row_tre(real[_key(r)])
    ]
    return bad


def set_rows(out_root: str, dataset: str) -> list[dict]:
    """One validation set's rows of both methods (the earlier rule's runs)."""
    return read_rows(Path(out_root) / RUN / dataset / CASES_CSV)


def threshold_verdict(out_root: str) -> tuple[list[str], str, float | None]:
    """The rule's table, its verdict line and the chosen threshold (None: none passes or a check failed)."""
    table = [
        "| set | `ransac_candidate_visibility` | bins | poses | mean RMS-TRE (mm) | success@10 mm | >= 20 mm |"
        " views with M/N below it |",
        "|---|---|---|---|---|---|---|---|",
    ]
    checks, passing, small_rows = [], set(THRESHOLDS), {t: [] for t in THRESHOLDS}
    for dataset in SETS:
        rows = set_rows(out_root, dataset)
        checks += [f"{dataset}: {m}" for m in shared_path_mismatches(rows)]
        ref = [r for r in rows if r["method"] == REFERENCE]
        options = {"default (none)": ref, **{f"{t:.2f}": composed_rows(rows, t) for t in THRESHOLDS}}
        stats = {}
        for label, chosen in options.items():
            stats[label] = {
                g: tre_stats([r for r in chosen if lo <= r["visibility"] < hi]) for g, (lo, hi) in GROUPS.items()
            }
            for g, s in stats[label].items():
                lo, hi = GROUPS[g]
                given = sum(r["method"] == CANDIDATE and lo <= r["visibility"] < hi for r in chosen)
                table.append(
                    f"| {dataset} | {label} | {g} | {s['n']} | {s['mean']:.2f} | {100 * s['s10']:.1f} % | "
                    f"{s['gross']} | {given} |"
                )
        small, above = GROUPS
        base = stats["default (none)"]
        for t in THRESHOLDS:
            s = stats[f"{t:.2f}"]
            ok1 = s[small]["mean"] < base[small]["mean"] and s[small]["s10"] >= base[small]["s10"]
            ok2 = s[above]["mean"] <= base[above]["mean"] + SLACK_MM and s[above]["gross"] <= base[above]["gross"]
            if not (ok1 and ok2):
                passing.discard(t)
            lo, hi = GROUPS[small]
            small_rows[t] += [r for r in options[f"{t:.2f}"] if lo <= r["visibility"] < hi]
    pooled = {t: tre_stats(small_rows[t])["mean"] for t in THRESHOLDS}
    table += ["", pooled_line(pooled, passing, "1-2")]
    if checks:
        return table + ["", *checks[:20]], f"The composition check failed on {len(checks)} case(s): no verdict.", None
    if not passing:
        return table, "No threshold passes rules 1 and 2 on all three sets: the value stays 0.3.", None
    chosen = lowest_pooled(pooled, passing, TIE_MM)
    return table, f"Threshold {chosen:.2f} passes rules 1 and 2 on all three sets and is chosen (rule 3 next).", chosen


def pooled_line(pooled: dict[float, float], passing: set[float], rules: str) -> str:
    """The table's last line: each threshold's pooled small-view mean, marked where it passes `rules`."""
    marks = (f"{t:.2f}: {mean:.2f}" + (f" (passes {rules})" if t in passing else "") for t, mean in pooled.items())
    return "Mean RMS-TRE (mm) of the three sets' [0.05, 0.2) poses pooled, per threshold: " + ", ".join(marks)


def lowest_pooled(pooled: dict[float, float], passing: set[float], tie_mm: float) -> float:
    """The passing threshold with the lowest pooled mean; within `tie_mm` of it, the smallest threshold."""
    best = min(pooled[t] for t in passing)
    return min(t for t in passing if pooled[t] <= best + tie_mm)


def timed_method(threshold: float) -> str:
    """The method spec `scripts/bench_paths.py` times the candidate at `threshold` by (its row name there)."""
    return f"{CANDIDATE}:ransac_candidate_visibility={threshold:g}"


def time_verdict(speed_md: Path, threshold: float) -> tuple[str, bool]:
    """Rule 3 for the chosen threshold: its line and whether it passes (NaN: not measured, fails)."""
    ms = median_ms(speed_md, timed_method(threshold), SPEED_BLOCK)
    ok = ms <= TIME_LIMIT_MS
    return (
        f"Rule 3: median time {ms:.1f} ms per registration (limit {TIME_LIMIT_MS:.0f} ms), {'met' if ok else 'missed'}.",
        ok,
    )
