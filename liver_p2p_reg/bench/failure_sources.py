"""Where a method's poses beyond the rigid bound come from: a wrong pick, too few screened, no candidate, ambiguity.

For each pose the method's error is set beside the bound's (the configured ICP from the true pose). A pose more
than `MARGIN_MM` worse than the bound is a failure of the method, and the full ICP is then run from each of its
candidates:
- "pick": a screened candidate reaches the bound's basin (within the margin), and the screening (by the residual
  after its short ICP) chose another pose;
- "screening": only a candidate that was not screened (beyond `refine_candidates`, or skipped as a near-duplicate
  of a screened one) reaches it;
- "search": none reaches it, and the bound's residual is below `RESIDUAL_RATIO` x the chosen pose's: a wider
  search scored by the residual would prefer the true basin;
- "ambiguous": none reaches it, and the residual does not prefer the true basin (deformation or a symmetric patch):
  geometry alone cannot tell, other evidence must (features, free space, more views).
The rows keep the numbers (each candidate's error after ICP, both residuals), and the table classifies them, so a
label is never older than the thresholds. The thresholds sort failures and choose nothing; an exploratory pass
before this module used the same 5 mm margin.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from liver_p2p_reg.bench.case_runs import case_registrar
from liver_p2p_reg.bench.cases import (
    BIN_EDGES,
    BIN_LABELS,
    CaseInfo,
    sensor_origin_mm,
    visibility_bin,
)
from liver_p2p_reg.bench.harness import true_pose_mm
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.metrics import rms_tre_mm

MARGIN_MM = 5.0  # a pose this much worse than the bound is the method's failure, not the deformation's
RESIDUAL_RATIO = 0.9  # the residual "prefers" the true basin when the bound's is below this share of the chosen one's
SOURCES = ("pick", "screening", "search", "ambiguous")


def classify(
    final_mm: float, final_res_mm: float, bound_mm: float, bound_res_mm: float, reached: Iterable[tuple[bool, float]]
) -> str:
    """The source of one pose's excess over the bound: "" (within the margin) or one of SOURCES.

    `reached`: (screened, RMS-TRE after ICP from the candidate) for every candidate of the registration.
    """
    if not final_mm > bound_mm + MARGIN_MM:
        return ""
    good = [screened for screened, tre in reached if tre <= bound_mm + MARGIN_MM]
    if any(good):
        return "pick"
    if good:
        return "screening"
    return "search" if bound_res_mm < RESIDUAL_RATIO * final_res_mm else "ambiguous"


def run_case(info: CaseInfo, config_dict: dict[str, Any], sensor_aware: bool = False) -> dict[str, Any]:
    """Register one case as the benchmark does, ICP from the true pose beside it and, on a failure, from every
    candidate; the row names the failure's source. A method's error becomes the row's `error`.

    `sensor_aware`: the registration gets the case's sensor origin (free space), as the benchmark's `[fs]` rows.
    """
    data, target, registrar = case_registrar(info, config_dict)
    src_marker, tgt_marker = np.asarray(data["src_marker"], float), np.asarray(data["tgt_marker"], float)
    source = data["src_pcd"]
    row: dict[str, Any] = {
        "case_id": info.case_id,
        "method": config_dict["method"],
        "visibility": info.visibility,
        "added_noise_mm": info.added_noise_mm,
    }

    def from_pose(T: np.ndarray) -> tuple[float, float]:
        refined = registrar.register(source, target, method="track", initial_T_mm=T)
        return float(rms_tre_mm(refined.T_target_source, src_marker, tgt_marker)), float(refined.residual_mm)

    try:
        origin = sensor_origin_mm(data) if sensor_aware else None
        if sensor_aware and origin is None:
            raise InputError(f"case {info.case_id} stores no sensor origin (only camera crops do)")
        result = registrar.register(
            source, target, source_fiducials_mm=src_marker, target_fiducials_mm=tgt_marker, sensor_origin_mm=origin
        )
        final = float(rms_tre_mm(result.T_target_source, src_marker, tgt_marker))
        bound, bound_res = from_pose(true_pose_mm(data, info))
        reached: list[tuple[bool, float]] = []
        if final > bound + MARGIN_MM:
            # without a screening (one candidate, or refine_candidates 1) the chosen one is all that was weighed
            chosen = {result.candidates[result.chosen].name} if result.chosen is not None else set()
            screened = {c.name for c in result.screened} or chosen
            reached = [(c.name in screened, from_pose(c.T_target_source)[0]) for c in result.candidates if c.ok]
    except LiverP2PError as exc:
        return {**row, "error": f"{type(exc).__name__}: {exc}"}
    return {
        **row,
        "method_visibility": float(result.visibility),
        "rms_tre_mm": final,
        "residual_mm": float(result.residual_mm),
        "bound_rms_tre_mm": bound,
        "bound_residual_mm": bound_res,
        "chosen": result.candidates[result.chosen].name if result.chosen is not None else "",
        "n_candidates": len(result.candidates),
        "reached": reached,  # (screened, RMS-TRE after ICP from it) per candidate; only for a pose beyond its bound
        "error": "",
    }


def source_of(row: dict[str, Any]) -> str:
    """A kept row's failure source ("" within the margin), by `classify` from its numbers."""
    reached = [(bool(screened), float(tre)) for screened, tre in row["reached"]]
    return classify(row["rms_tre_mm"], row["residual_mm"], row["bound_rms_tre_mm"], row["bound_residual_mm"], reached)


def summary_table(rows_by_set: dict[str, list[dict[str, Any]]], top_bin: float = 0.3) -> list[str]:
    """Markdown: per set and visibility bin below `top_bin`, the mean error beside the bound's, the failures by
    source, and each source's share of the bin's mean (its excess over the bound, per pose of the bin)."""
    head = (
        "| set | bin | poses | mean / bound (mm) | failures | " + " | ".join(SOURCES) + " | excess of the mean (mm) |"
    )
    lines = [head, "|" + "---|" * (6 + len(SOURCES))]
    for name, rows in rows_by_set.items():
        for index, label in enumerate(BIN_LABELS):
            members = [r for r in rows if not r["error"] and visibility_bin(r["visibility"]) == index]
            if not members or BIN_EDGES[index] >= top_bin:
                continue
            final = np.array([r["rms_tre_mm"] for r in members])
            bound = np.array([r["bound_rms_tre_mm"] for r in members])
            sources = [source_of(r) for r in members]
            failed = [(r, s) for r, s in zip(members, sources, strict=True) if s]
            excess = {s: sum(r["rms_tre_mm"] - r["bound_rms_tre_mm"] for r, t in failed if t == s) for s in SOURCES}
            counts = " | ".join(f"{sum(t == s for _, t in failed)}" for s in SOURCES)
            shares = ", ".join(f"{s} {excess[s] / len(members):.2f}" for s in SOURCES if excess[s])
            lines.append(
                f"| {name} | {label} | {len(members)} | {final.mean():.2f} / {bound.mean():.2f} | {len(failed)} | "
                f"{counts} | {shares or '-'} |"
            )
    return lines
