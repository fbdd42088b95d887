"""The learned matches' agreement as a second cue of the screening: the data per case, the composed poses, the rule
(docs/benchmark_real/RULE_feature_agreement.md)."""

from __future__ import annotations

from typing import Any

import numpy as np

from liver_p2p_reg.bench.case_runs import screened_case
from liver_p2p_reg.bench.cases import CaseInfo
from liver_p2p_reg.bench.composed_rule import composed, rule_verdict
from liver_p2p_reg.bench.composed_rule import reproduction_mismatches as own_mismatches
from liver_p2p_reg.metrics import rms_tre_mm

METHOD = "learned-p2p-ransac-icp"
THRESHOLD = 0.2  # ransac_candidate_visibility: the cue applies where the RANSAC candidate does
SETTINGS = {"method": METHOD, "ransac_candidate_visibility": THRESHOLD}
SETS = ("real-val-v2", "real-val-v2-arap", "real-val-camera-v2")
LAMBDAS = (0.1, 0.25, 0.5, 1.0)
AGREE_MM = 10.0  # a confident match agrees with a pose when the pose brings its source point this close
TAG = {"agree_mm": AGREE_MM}  # kept rows hold to the radius their agreements were measured with


def agreement(
    T_mm: np.ndarray, source_mm: np.ndarray, target_mm: np.ndarray, confidence: np.ndarray, radius_mm: float = AGREE_MM
) -> float:
    """The confidence-weighted share of target points whose best source match the pose T brings within `radius_mm`.

    `source_mm[i]` is target point i's best match and `confidence[i]` its dual-softmax confidence; 0 without any.
    """
    moved = source_mm @ T_mm[:3, :3].T + T_mm[:3, 3]
    close = np.linalg.norm(moved - target_mm, axis=1) < radius_mm
    total = float(confidence.sum())
    return float(confidence[close].sum() / total) if total > 0 else 0.0


def keyed_choice(candidates: list[dict[str, Any]], lam: float) -> int:
    """The index of the screened candidate with the lowest residual x (1 + lam x (1 - agreement / the best
    agreement)); the first of equals, as the screening. Without any agreement the residual alone decides."""
    best = max(c["agreement"] for c in candidates)
    keys = [c["short_residual_mm"] * (1 + lam * (1 - (c["agreement"] / best if best > 0 else 1.0))) for c in candidates]
    return int(np.argmin(keys))


def collect_case(info: CaseInfo, config_dict: dict[str, Any]) -> dict[str, Any]:
    """One case registered as the benchmark does; on a view that screened two or more candidates, each one's short
    residual, agreement and RMS-TRE after the full ICP from its own pose."""
    import torch

    from liver_p2p_reg.registration.context import MethodContext
    from liver_p2p_reg.registration.matching import dual_softmax, score_matrix
    from liver_p2p_reg.registration.pipeline import feature_provider
    from liver_p2p_reg.registration.preprocess import preprocess_pair

    data, target, registrar, result, row = screened_case(info, config_dict)
    src_marker, tgt_marker = np.asarray(data["src_marker"], float), np.asarray(data["tgt_marker"], float)
    source, config = data["src_pcd"], registrar.config
    if not result.visibility < config.ransac_candidate_visibility or len(result.screened) < 2:
        return row
    prep = preprocess_pair(source, target, config, registrar.cache)
    provider = feature_provider("learned", config, MethodContext(cache=registrar.cache), source, [])()
    with torch.inference_mode():
        x_src, x_tgt = provider.describe(
            torch.as_tensor(prep.source, dtype=torch.float32),
            torch.as_tensor(prep.target, dtype=torch.float32),
            registrar.cache,  # the source's features the registration just computed
        )
        confidence, match = dual_softmax(score_matrix(x_src, x_tgt), config.temperature).max(dim=0)
    matched_mm = prep.source_norm.invert(prep.source[match.numpy()])
    target_mm = prep.target_norm.invert(prep.target)
    weights = confidence.numpy().astype(np.float64)
    raw = {c.name: c.T_target_source for c in result.candidates}
    chosen = result.candidates[result.chosen].name
    for screened in result.screened:
        refined = registrar.register(source, target, method="track", initial_T_mm=raw[screened.name])
        row["screened"].append(
            {
                "name": screened.name,
                "chosen": screened.name == chosen,
                "short_residual_mm": float(screened.residual_mm),
                "agreement": agreement(screened.T_target_source, matched_mm, target_mm, weights),
                "rms_tre_mm": float(rms_tre_mm(refined.T_target_source, src_marker, tgt_marker)),
            }
        )
    return row


def composed_tre(rows: list[dict[str, Any]], lam: float) -> np.ndarray:
    """Each case's RMS-TRE when the screening's key carries `lam` (the method's own where nothing was screened)."""
    return composed(rows, lambda screened: keyed_choice(screened, lam))


def reproduction_mismatches(rows: list[dict[str, Any]], tolerance_mm: float = 1e-6) -> list[str]:
    """Cases where lambda = 0 does not give the method's own pose (then the composition is not the pipeline's)."""
    return own_mismatches(rows, lambda screened: keyed_choice(screened, 0.0), tolerance_mm)


def verdict(rows_by_set: dict[str, list[dict[str, Any]]]) -> tuple[list[str], str, float | None]:
    """The rule's table (per set: mean / poses >= 20 mm for lambda 0 and each candidate), its verdict line, the
    chosen lambda (None: none)."""
    small = {name: [r for r in rows if 0.05 <= r["visibility"] < 0.2] for name, rows in rows_by_set.items()}
    lams = (0.0, *LAMBDAS)
    tre = {name: {lam: composed_tre(rows, lam) for lam in lams} for name, rows in small.items()}
    table, line, chosen = rule_verdict(tre, 0.0, LAMBDAS, {lam: f"lambda {lam:g}" for lam in lams}, "lambda")
    return table, line, None if chosen is None else float(chosen)
