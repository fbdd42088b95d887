"""The small views' close contenders judged after the full ICP and the elastic stage: the data per case, the composed
poses, the rule (docs/benchmark_real/RULE_deformed_screening.md)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from liver_p2p_reg.bench.case_runs import NOISE_MM, case_registrar, screened_case
from liver_p2p_reg.bench.cases import CaseInfo
from liver_p2p_reg.bench.composed_rule import GROSS_MM, composed, rule_verdict
from liver_p2p_reg.bench.composed_rule import reproduction_mismatches as own_mismatches
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.registration.contenders import SAME_POSE_MM, probe_points, rms_gap_mm
from liver_p2p_reg.registration.registrar import Registrar

METHOD = "learned-p2p-ransac-icp"
THRESHOLD = 0.2  # ransac_candidate_visibility: the judges apply where the RANSAC candidate does
SETTINGS = {"method": METHOD, "ransac_candidate_visibility": THRESHOLD}
SETS = ("real-val-v2", "real-val-v2-arap", "real-val-camera-v2")
CHECK_SET = "real-val-v2"  # rule 3: the built-in judge's real run must give the composed poses here
TEST_SETS = ("real-test-v2", "real-test-v2-arap", "real-test-camera-v2", "real-test-camera-v2-arap")
CHOSEN = ("deformed", 1.5)  # the selection's verdict (selection_deformed_screening.md)
MARGINS = (0.02, 0.05, 0.10)  # RULE_judge_margin.md's candidates
BINS = ((0.05, 0.10), (0.10, 0.15), (0.15, 0.20), (0.20, 0.30))  # from 0.2 up: a view estimated smaller
JUDGES = ("rigid", "deformed", "predictive")
RATIOS = (1.1, 1.25, 1.5)
TAG = {"max_ratio": max(RATIOS), "same_pose_mm": SAME_POSE_MM}
CANDIDATES = tuple((judge, r) for judge in JUDGES for r in RATIOS)  # the rule's tie order: the cheaper first


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def collect_case(info: CaseInfo, config_dict: dict[str, Any]) -> dict[str, Any]:
    """One case registered as the benchmark does; on a small view that screened two or more candidates, each
    contender's (short residual within max(RATIOS) x the lowest) error and keys after the full ICP and the stage."""
    data, target, registrar, result, row = screened_case(info, config_dict)
    src_marker, tgt_marker = np.asarray(data["src_marker"], float), np.asarray(data["tgt_marker"], float)
    source, config = np.asarray(data["src_pcd"], float), registrar.config
    row["added_ms"] = 0.0
    if not result.visibility < config.ransac_candidate_visibility or len(result.screened) < 2:
        return row
    raw = {c.name: c.T_target_source for c in result.candidates}
    chosen = result.candidates[result.chosen].name
    lowest = min(s.residual_mm for s in result.screened)
    probe = probe_points(source)  # where two refined poses are compared, as the built-in judge does
    done: list[tuple[np.ndarray, dict[str, Any]]] = []
    start, own_icp_ms = time.perf_counter(), 0.0
    for screened in result.screened:
        if not screened.residual_mm <= max(RATIOS) * lowest:
            continue
        icp_start = time.perf_counter()
        refined = registrar.register(source, target, method="track", initial_T_mm=raw[screened.name])
        if screened.name == chosen:  # the pipeline refines its choice anyway
            own_icp_ms = (time.perf_counter() - icp_start) * 1e3
        moved = probe @ refined.T_target_source[:3, :3].T + refined.T_target_source[:3, 3]
        twin = next((k for p, k in done if rms_gap_mm(p, moved) < SAME_POSE_MM), None)
        if twin is None:
            registrar.deform(refined, source, target, data.get("src_triangles"))
            stage = refined.deformation
            twin = {
                "deformed_residual_mm": _finite(stage.residual_after_mm),
                "holdout_gain": _finite(stage.holdout_gain),
                "stage_applied": bool(stage.applied),
            }
            done.append((moved, twin))
        row["screened"].append(
            {
                "name": screened.name,
                "chosen": screened.name == chosen,
                "short_residual_mm": float(screened.residual_mm),
                "rms_tre_mm": float(rms_tre_mm(refined.T_target_source, src_marker, tgt_marker)),
                "full_residual_mm": float(refined.residual_mm),
                **twin,
            }
        )
    # what the judges add: the other contenders' ICP and every stage run
    row["added_ms"] = (time.perf_counter() - start) * 1e3 - own_icp_ms
    return row


def judged_case(info: CaseInfo, config_dict: dict[str, Any]) -> dict[str, Any]:
    """One case registered with the settings and again with the chosen judge built in (`contender_judge_ratio`, on
    the case's preop triangles), beside the rigid bound (ICP from the true pose): each one's RMS-TRE."""
    from liver_p2p_reg.bench.harness import true_pose_mm

    data, target, registrar = case_registrar(info, config_dict)
    markers = np.asarray(data["src_marker"], float), np.asarray(data["tgt_marker"], float)
    source, tris = np.asarray(data["src_pcd"], float), data.get("src_triangles")
    own = registrar.register(source, target)
    judged_registrar = Registrar(registrar.config.replace(contender_judge_ratio=CHOSEN[1]))
    judged_registrar.cache = registrar.cache
    judged = judged_registrar.register(source, target, source_triangles=tris)
    bound = registrar.register(source, target, method="track", initial_T_mm=true_pose_mm(data, info))
    return {
        "case_id": info.case_id,
        "visibility": info.visibility,
        "own_mm": float(rms_tre_mm(own.T_target_source, *markers)),
        "judged_mm": float(rms_tre_mm(judged.T_target_source, *markers)),
        "bound_mm": float(rms_tre_mm(bound.T_target_source, *markers)),
        "judge_ms": float(judged.runtime_ms.get("judge", 0.0)),
    }


def check_mismatches(
    judged_rows: list[dict[str, Any]], kept_rows: list[dict[str, Any]], tolerance_mm: float = 0.01
) -> list[str]:
    """Cases where the built-in judge's pose is not the composed one (beyond `tolerance_mm` of RMS-TRE)."""
    composed = {r["case_id"]: float(composed_tre([r], *CHOSEN)[0]) for r in kept_rows}
    return [r["case_id"] for r in judged_rows if abs(r["judged_mm"] - composed[r["case_id"]]) > tolerance_mm]


def noisy(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The 2 mm noise copies (the protocol's judgement: issue 29's targets are set with 2 mm noise)."""
    return [r for r in rows if r["case_id"].endswith(f"+noise{NOISE_MM:g}mm")]


def judgement_table(rows_by_set: dict[str, list[dict[str, Any]]]) -> list[str]:
    """Per test set and bin below 0.3, the 2 mm noise copies: poses, the method's own and the judged mean /
    success@10 / poses >= 20 mm, the rigid bound's mean, and the judged mean over the bound's."""
    table = [
        "| set | visibility | poses | own: mean (mm) / s@10 / >= 20 mm | judged: mean / s@10 / >= 20 mm | bound mean | judged / bound |",
        "|---|---|---|---|---|---|---|",
    ]

    def cells(tre: np.ndarray) -> str:
        return f"{tre.mean():.2f} / {100 * np.mean(tre < 10):.1f} % / {int((tre >= GROSS_MM).sum())}"

    for name, rows in rows_by_set.items():
        for lo, hi in BINS:
            sel = [r for r in noisy(rows) if lo <= r["visibility"] < hi]
            if not sel:
                continue
            own, judged, bound = (np.array([r[k] for r in sel]) for k in ("own_mm", "judged_mm", "bound_mm"))
            table.append(
                f"| {name} | [{lo:.2f}, {hi:.2f}) | {len(sel)} | {cells(own)} | {cells(judged)} | {bound.mean():.2f} "
                f"| {judged.mean() / bound.mean():.2f}x |"
            )
    return table


def key(contender: dict[str, Any], judge: str) -> float:
    """A contender's key under `judge` (lowest wins); see the rule."""
    rigid = contender["full_residual_mm"]
    if judge == "rigid":
        return rigid
    deformed = contender["deformed_residual_mm"] if contender["deformed_residual_mm"] is not None else rigid
    if judge == "deformed" or contender["holdout_gain"] is None:
        return deformed
    return deformed * (1.0 - contender["holdout_gain"])


def judged_choice(contenders: list[dict[str, Any]], judge: str | None, ratio: float, margin: float = 0.0) -> int:
    """The index of the winner among the contenders within `ratio` x the lowest short residual (judge None: the
    screening's own choice, the lowest short residual); the first of equals. With `margin` another contender wins
    only when its key is below (1 - margin) x the screening's choice's key (RULE_judge_margin.md)."""
    shorts = [c["short_residual_mm"] for c in contenders]
    own = int(np.argmin(shorts))
    if judge is None:
        return own
    keys = [key(c, judge) if c["short_residual_mm"] <= ratio * shorts[own] else np.inf for c in contenders]
    best = int(np.argmin(keys))
    if margin > 0 and not keys[best] < (1.0 - margin) * keys[own]:  # (at 0 the first of equals, as the judge chose)
        return own
    return best


def composed_tre(rows: list[dict[str, Any]], judge: str | None, ratio: float = 1.0, margin: float = 0.0) -> np.ndarray:
    """Each case's RMS-TRE when `judge` picks among its contenders (the method's own where none were kept)."""
    return composed(rows, lambda contenders: judged_choice(contenders, judge, ratio, margin))


def reproduction_mismatches(rows: list[dict[str, Any]], tolerance_mm: float = 1e-6) -> list[str]:
    """Cases where the screening's own choice among the kept contenders is not the method's pose."""
    return own_mismatches(rows, lambda contenders: judged_choice(contenders, None, 1.0), tolerance_mm)


def verdict(rows_by_set: dict[str, list[dict[str, Any]]]) -> tuple[list[str], str, tuple[str, float] | None]:
    """The rule's table (per set: mean / poses >= 20 mm for the method's own and each candidate), its verdict line,
    the chosen (judge, ratio) (None: none)."""
    small = {name: [r for r in rows if 0.05 <= r["visibility"] < 0.2] for name, rows in rows_by_set.items()}
    tre = {
        name: {"own": composed_tre(rows, None), **{c: composed_tre(rows, *c) for c in CANDIDATES}}
        for name, rows in small.items()
    }
    label = {"own": "the method's own", **{c: f"{c[0]} r{c[1]:g}" for c in CANDIDATES}}
    table, line, chosen = rule_verdict(tre, "own", CANDIDATES, label, "judge")
    return table, line, chosen  # type: ignore[return-value]


def margin_verdict(rows_by_set: dict[str, list[dict[str, Any]]]) -> tuple[list[str], str, float | None]:
    """RULE_judge_margin.md: the table (per set: mean / poses >= 20 mm at m = 0 and each margin), the verdict line,
    the chosen margin (None: none)."""
    small = {name: [r for r in rows if 0.05 <= r["visibility"] < 0.2] for name, rows in rows_by_set.items()}
    tre = {name: {m: composed_tre(rows, *CHOSEN, m) for m in (0.0, *MARGINS)} for name, rows in small.items()}
    label = {m: f"margin {m:g}" for m in (0.0, *MARGINS)}
    table, line, chosen = rule_verdict(tre, 0.0, MARGINS, label, "margin")
    return table, line, None if chosen is None else float(chosen)
