"""The P2P ablation section of a benchmark report (paper Fig. 8, Table VI form): K curves and setting twins."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from liver_p2p_reg.bench import plots
from liver_p2p_reg.bench.cases import BIN_LABELS, PAPER_FIRST_BIN
from liver_p2p_reg.bench.jobs import ABLATION_K
from liver_p2p_reg.bench.markdown import DASH, fmt, md_table, pct, pm
from liver_p2p_reg.bench.stats import Row, by_bin, in_bin, success_rate
from liver_p2p_reg.bench.tables import Tables


def ablation_cases(tables: Tables, method: str) -> set[str]:
    """The cases on which `method` ran ablation variants."""
    return {r["case_id"] for r in tables.rows if r["base_method"] == method and r["variant"]}


def _variant_rows(tables: Tables, method: str, variant: str) -> list[Row]:
    """Rows of `method` with `variant` on the ablation cases; the default setting is the main run."""
    ids = ablation_cases(tables, method)
    if variant == "":
        return [r for r in tables.main if r["method"] == method and r["case_id"] in ids]
    return [r for r in tables.rows if r["base_method"] == method and r["variant"] == variant]


def k_curves(tables: Tables) -> dict[str, dict[int, tuple[float, float]]]:
    """Per `-p2p` method with ablations: K -> mean RMS-TRE (lowest bin, all ablation cases)."""
    k_default = int(tables.settings["config"]["k"])
    curves: dict[str, dict[int, tuple[float, float]]] = {}
    for m in tables.methods:
        if not m.endswith("-p2p") or not ablation_cases(tables, m):
            continue
        per_k = {}
        for k in ABLATION_K:
            rows = _variant_rows(tables, m, "" if k == k_default else f"k={k}")
            if rows:
                low = [r["rms_tre_mm"] for r in rows if in_bin(PAPER_FIRST_BIN)(r)]
                per_k[k] = (
                    float(np.mean(low)) if low else math.nan,
                    float(np.mean([r["rms_tre_mm"] for r in rows])),
                )
        curves[m] = per_k
    return curves


def ablation_section(tables: Tables, out: Path) -> list[str]:
    curves = k_curves(tables)
    screened = [m for m in tables.methods if m.endswith("-p2p-icp") and ablation_cases(tables, m)]
    if not curves and not screened:
        return []
    cfg = tables.settings["config"]
    ids = set().union(*(ablation_cases(tables, m) for m in [*curves, *screened]))
    counts = by_bin([r for r in tables.main if r["case_id"] in ids and r["method"] == tables.methods[0]])
    sizes = sorted({g.size for g in counts if g.size})
    per_bin = str(sizes[0]) if len(sizes) == 1 else f"{sizes[0]}–{sizes[-1]}" if sizes else "0"
    lines = [
        "## P2P ablations (Fig. 8, Table VI form)",
        "",
        f"On {len(ids)} noise-free cases ({per_bin} per visibility bin, spread over livers); "
        f"every other setting as in the main run (K={cfg['k']}, selection {cfg['selection']}, "
        f"candidate proposal {cfg['candidate_proposal']}). Mean RMS-TRE (mm): lowest bin / all ablation cases.",
        "",
    ]
    if curves:
        header = ["method", *(f"K={k}" for k in ABLATION_K)]
        rows = [
            [m, *(f"{fmt(per_k[k][0])} / {fmt(per_k[k][1])}" if k in per_k else DASH for k in ABLATION_K)]
            for m, per_k in curves.items()
        ]
        lines += md_table(header, rows)
        plots.k_ablation(curves, out / "ablation_k.png")
        lines += ["", "![mean RMS-TRE vs K](ablation_k.png)", ""]
    refit_values = (cfg["refit_iterations"], 0) if cfg["refit_iterations"] else (0, 6)
    seeds = cfg.get("consensus_seeds", 0)  # absent from runs made before the option existed
    consensus_values = (seeds, 0) if seeds else (0, 64)
    screen_values = (cfg.get("refine_candidates", 1), 1) if cfg.get("refine_candidates", 1) > 1 else (1, 6)
    for field, values, methods in (
        ("selection", ("closest-point", "inlier-count"), list(curves)),
        ("candidate_proposal", (True, False), list(curves)),
        ("mutual_only", (False, True), list(curves)),  # True: the paper's strict mutual nearest neighbours
        ("refit_iterations", refit_values, list(curves)),  # 0: the paper's single weighted Procrustes fit
        ("consensus_seeds", consensus_values, list(curves)),  # 0: no consensus-started twin candidates
        ("refine_candidates", screen_values, screened),  # 1: ICP refines only P2P's choice
    ):
        if not methods:
            continue
        header = ["method"]
        for v in values:
            header += [f"{field}={v} {BIN_LABELS[PAPER_FIRST_BIN]}", f"{field}={v} all", f"success {field}={v}"]
        rows = []
        for m in methods:
            cells = []
            for v in values:
                variant = "" if str(cfg.get(field)) == str(v) else f"{field}={v}"
                sub = _variant_rows(tables, m, variant)
                low = np.array([r["rms_tre_mm"] for r in sub if in_bin(PAPER_FIRST_BIN)(r)], float)
                cells += [pm(low), pm(np.array([r["rms_tre_mm"] for r in sub], float)), pct(success_rate(sub))]
            rows.append([m, *cells])
        lines += md_table(header, rows) + [""]
    return lines
