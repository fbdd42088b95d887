"""Choose the non-rigid stage's defaults on validation sets by the rule in docs/deform/rule.md (never a test set).

Usage (each step resumable; out/deform/ holds the rigid poses and one JSON line per case):
    .venv/bin/python scripts/choose_deform.py rigid real-val-v2          # the default's rigid poses, 2 mm noise
    .venv/bin/python scripts/choose_deform.py grid real-val-v2 [--start I --stop J]   # every grid setting per case
    .venv/bin/python scripts/choose_deform.py summarize real-val-v2 real-val-v2-arap  # -> docs/deform/choice.md
    (amendments 2 and 3 of the rule: the steps `gate` / `summarize-gate` and `holdout` / `summarize-holdout`)

The rigid step registers every second case with visibility in [0.1, 0.3) with `learned-p2p-icp` and the
benchmark's own noise (bench.cases.add_target_noise, 2 mm); the grid step runs the stage from each pose
through `registration.deform.deform_result` with each setting; the summary applies the rule.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from liver_p2p_reg.bench.cases import add_target_noise, case_info, case_seed, with_noise
from liver_p2p_reg.config import Config
from liver_p2p_reg.phantom.casefile import read_case, source_triangles
from liver_p2p_reg.registration.deform import deform_result
from liver_p2p_reg.registration.deform_fit import holdout_gain
from liver_p2p_reg.registration.registrar import Registrar
from liver_p2p_reg.registration.threads import pin_threads
from liver_p2p_reg.result import RegistrationResult

OUT = Path("out/deform")
VISIBILITY = (0.1, 0.3)
GRID = [
    {"deform_modes": m, "deform_regularization": r, "deform_min_gain": 0.0}
    for m in (24, 48, 96)
    for r in (0.001, 0.003, 0.01, 0.03)
]
# Amendment 2 (docs/deform/rule.md): the residual gate `deform_min_gain`, applied after the fit, for these settings.
GATE_GRID = [
    {"deform_modes": m, "deform_regularization": r, "deform_min_gain": 0.0}
    for m, r in ((24, 0.003), (24, 0.01), (48, 0.001), (48, 0.003))
]
GATES = (0.0, 0.02, 0.04, 0.06, 0.08, 0.1)
# Amendment 3: the held-out-half gate (None: off) with these residual gates, for these settings.
HOLDOUT_GRID = [{"deform_modes": 24, "deform_regularization": r, "deform_min_gain": 0.0} for r in (0.01, 0.003)]
HOLDOUT_MIN_GAINS = (0.0, 0.05, 0.1)
HOLDOUT_GATES = (None, 0.0, 0.02, 0.05)
RANGES = ((0.1, 0.2), (0.2, 0.3))
HARM_MM, GOOD_MM, HARM_SHARE = 1.0, 10.0, 0.01


def rms(T: np.ndarray, p: np.ndarray, y: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p @ T[:3, :3].T + T[:3, 3] - y) ** 2, axis=1))))


def rigid(name: str, data: Path) -> None:
    """The default's poses on every second case of the range, with the benchmark's 2 mm noise."""
    infos = [case_info(p) for p in sorted((data / name).glob("*.npz"))]
    infos = [
        i
        for i in with_noise(infos, [2.0], "all")
        if i.added_noise_mm > 0 and VISIBILITY[0] <= i.visibility < VISIBILITY[1]
    ]
    out = {}
    for info in infos[::2]:
        c = read_case(info.path)
        registrar = Registrar(Config(num_threads=2, seed=case_seed(0, info)))
        target = add_target_noise(np.asarray(c["tgt_pcd"], float), info)
        r = registrar.register(
            c["src_pcd"], target, source_fiducials_mm=c["src_marker"], target_fiducials_mm=c["tgt_marker"]
        )
        out[str(info.path)] = dict(
            T=r.T_target_source.tolist(), tre=r.rms_tre_mm, noise=2.0, res=r.residual_mm, ok=r.ok
        )
        print(info.case_id, round(info.visibility, 3), round(r.rms_tre_mm, 2), flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"rigid_{name}.json").write_text(json.dumps(out))


def grid(name: str, start: int, stop: int | None, kind: str = "grid") -> None:
    """Every grid setting from each rigid pose: one JSON line per case (vis, rigid TRE, per-setting TRE)."""
    pin_threads(1)
    settings = {"grid": GRID, "gate": GATE_GRID, "holdout": HOLDOUT_GRID}[kind]
    poses = list(json.loads((OUT / f"rigid_{name}.json").read_text()).items())[start:stop]
    caches: list[dict] = [{} for _ in settings]
    with open(OUT / f"{kind}_{name}_{start}.jsonl", "a") as fh:
        for path, pose in poses:
            c = read_case(path)
            info = dataclasses.replace(case_info(Path(path)), added_noise_mm=pose["noise"])
            target = add_target_noise(np.asarray(c["tgt_pcd"], float), info)
            T0, p, y = np.array(pose["T"]), c["src_marker"], c["tgt_marker"]
            result = RegistrationResult(
                T_target_source=T0, method="learned-p2p-icp", residual_mm=pose["res"], ok=pose["ok"]
            )
            row = {"case": path, "vis": c["visibility"], "rigid": rms(T0, p, y), "out": []}
            for setting, cache in zip(settings, caches, strict=True):
                # the gates are applied to the rows afterwards: the stage runs with the held-out check off
                config = Config(deform=True, deform_holdout_check=False, **setting)
                d = deform_result(result, c["src_pcd"], target, config, cache, source_triangles(c))
                moved = rms(d.T_target_source, p + d.displacement_at(p), y)
                gain = 1.0 - d.residual_after_mm / d.residual_before_mm if d.residual_before_mm > 0 else 0.0
                out = {"tre": moved, "applied": d.applied, "ms": d.runtime_ms, "gain": gain, "u": d.rms_displacement_mm}
                if kind == "holdout" and d.applied:
                    start_s = time.perf_counter()
                    out["holdout"] = holdout_gain(
                        d.model,
                        target,
                        T0,
                        regularization=config.deform_regularization,
                        iterations=config.deform_iterations,
                    )
                    out["holdout_ms"] = 1e3 * (time.perf_counter() - start_s)
                row["out"].append(out)
            fh.write(json.dumps(row) + "\n")
            fh.flush()


def summarize(names: list[str], target: Path) -> None:
    """Apply the rule: no harm in either family, then the lowest mean deformed/rigid ratio; write the table."""
    ratios = np.zeros((len(names), len(RANGES), len(GRID)))
    harm = np.zeros((len(names), len(GRID)))
    lines = ["| set | setting | " + " | ".join(f"ratio {lo}-{hi}" for lo, hi in RANGES) + " | harm | fit p50 (ms) |"]
    lines.append("|---|---|" + "---|" * len(RANGES) + "---|---|")
    p50 = np.zeros((len(names), len(GRID)))
    for s, name in enumerate(names):
        rows = [
            json.loads(line) for f in sorted(OUT.glob(f"grid_{name}_*.jsonl")) for line in f.read_text().splitlines()
        ]
        rigid = np.array([r["rigid"] for r in rows])
        vis = np.array([r["vis"] for r in rows])
        for g in range(len(GRID)):
            tre = np.array([r["out"][g]["tre"] for r in rows])
            good = rigid < GOOD_MM
            harm[s, g] = np.mean((tre - rigid > HARM_MM)[good])
            p50[s, g] = np.median([r["out"][g]["ms"] for r in rows])
            for b, (lo, hi) in enumerate(RANGES):
                sel = (vis >= lo) & (vis < hi)
                ratios[s, b, g] = tre[sel].mean() / rigid[sel].mean()
            cells = " | ".join(f"{ratios[s, b, g]:.3f}" for b in range(len(RANGES)))
            lines.append(
                f"| {name} ({len(rows)} poses) | {_name(GRID[g])} | {cells} | {100 * harm[s, g]:.1f} % | {p50[s, g]:.0f} |"
            )
    score = ratios.mean(axis=(0, 1))
    allowed = np.all(harm <= HARM_SHARE, axis=0)
    best = min(score[allowed]) if allowed.any() else float("nan")
    near = [g for g in range(len(GRID)) if allowed[g] and score[g] <= best + 0.01]
    verdict = f"**No setting passes the harm rule** (<= {100 * HARM_SHARE:g} % of good poses harmed in every set)."
    if near:
        chosen = min(near, key=lambda g: (GRID[g]["deform_modes"], -GRID[g]["deform_regularization"], p50[:, g].mean()))
        verdict = (
            f"**Chosen: {_name(GRID[chosen])}** (mean ratio {score[chosen]:.3f}; settings within 0.01 of the best "
            f"allowed: {', '.join(_name(GRID[g]) for g in near)})."
        )
    text = [
        "# The non-rigid stage's defaults: the rule's result",
        "",
        f"Generated by `.venv/bin/python scripts/choose_deform.py summarize {' '.join(names)}` from the grid rows in",
        "`out/deform/` (rule: [rule.md](rule.md)). Ratio: mean interior RMS-TRE with the stage / without, per",
        f"visibility range; harm: share of poses within {GOOD_MM:g} mm made worse by > {HARM_MM:g} mm. The rows are",
        "not committed (they are made from the real livers); `rigid`, `grid` and `gate` rebuild them (about 2 h on",
        "2 cores). Defaults: `deform_modes`, `deform_regularization` and `deform_min_gain` in `config.py`.",
        "",
        *lines,
        "",
        f"Mean ratio per setting: {', '.join(f'{_name(GRID[g])}: {score[g]:.3f}' for g in range(len(GRID)))}.",
        "",
        verdict,
        "",
    ]
    target.write_text("\n".join(text))
    print("\n".join(text))


def _rows(kind: str, name: str) -> list[dict]:
    return [json.loads(line) for f in sorted(OUT.glob(f"{kind}_{name}_*.jsonl")) for line in f.read_text().splitlines()]


def _gated(rows: list[dict], g: int, use: Callable[[dict], bool]) -> tuple[list[float], float, float]:
    """Setting g's rows with the stage kept where `use(out)`: the ratio per range, the harm and the applied share."""
    rigid = np.array([r["rigid"] for r in rows])
    vis = np.array([r["vis"] for r in rows])
    kept = np.array([use(r["out"][g]) for r in rows])
    tre = np.where(kept, [r["out"][g]["tre"] for r in rows], rigid)
    ratios = [tre[(vis >= lo) & (vis < hi)].mean() / rigid[(vis >= lo) & (vis < hi)].mean() for lo, hi in RANGES]
    return ratios, float(np.mean((tre - rigid > HARM_MM)[rigid < GOOD_MM])), float(kept.mean())


def _judged(rows_of: dict[str, list[dict]], g: int, use: Callable[[dict], bool]) -> tuple[list, list, list]:
    """_gated over every set: the ratios (set by set, range by range), the harms and the applied shares."""
    ratios, harms, applied = [], [], []
    for rows in rows_of.values():
        r, h, a = _gated(rows, g, use)
        ratios += r
        harms.append(h)
        applied.append(a)
    return ratios, harms, applied


def summarize_gate(names: list[str], target: Path) -> None:
    """Amendment 2: each GATE_GRID setting with each residual gate, judged by the same rule; appended to `target`."""
    candidates = [(g, gate) for g in range(len(GATE_GRID)) for gate in GATES]
    score, harm_ok, worst_harm, lines = {}, {}, {}, []
    lines.append(
        "| setting | deform_min_gain | " + " | ".join(f"{n} ratio {lo}-{hi}" for n in names for lo, hi in RANGES)
    )
    lines[-1] += (
        " | " + " | ".join(f"{n} harm" for n in names) + " | " + " | ".join(f"{n} applied" for n in names) + " |"
    )
    lines.append("|---|---|" + "---|" * (len(names) * (len(RANGES) + 2)))
    rows_of = {name: _rows("gate", name) for name in names}
    for g, gate in candidates:
        ratios, harms, applied = _judged(rows_of, g, lambda o, gate=gate: o["applied"] and o["gain"] >= gate)
        score[g, gate], harm_ok[g, gate] = float(np.mean(ratios)), all(h <= HARM_SHARE for h in harms)
        worst_harm[g, gate] = max(harms)
        cells = (
            [f"{x:.3f}" for x in ratios] + [f"{100 * h:.1f} %" for h in harms] + [f"{100 * a:.0f} %" for a in applied]
        )
        lines.append(f"| {_name(GATE_GRID[g])} | {gate:g} | " + " | ".join(cells) + " |")
    allowed = [c for c in candidates if harm_ok[c]]
    worst = min(candidates, key=lambda c: (worst_harm[c], score[c]))
    verdict = (
        f"**No setting and gate pass the harm rule**; the least harmful is {_name(GATE_GRID[worst[0]])}, "
        f"deform_min_gain {worst[1]:g} (worst harm {100 * worst_harm[worst]:.1f} %, mean ratio {score[worst]:.3f})."
    )
    if allowed:
        best = min(score[c] for c in allowed)
        near = [c for c in allowed if score[c] <= best + 0.01]
        g, gate = min(
            near, key=lambda c: (GATE_GRID[c[0]]["deform_modes"], -GATE_GRID[c[0]]["deform_regularization"], -c[1])
        )
        verdict = f"**Chosen: {_name(GATE_GRID[g])}, deform_min_gain {gate:g}** (mean ratio {score[g, gate]:.3f})."
    intro = [
        f"Generated by `.venv/bin/python scripts/choose_deform.py summarize-gate {' '.join(names)}` from the `gate`",
        "rows (the fit does not depend on the gate, so each gate is applied to the same fits afterwards).",
    ]
    _append_section(target, "## Amendment 2: the residual gate", intro, lines, verdict)


def summarize_holdout(names: list[str], target: Path) -> None:
    """Amendment 3: each HOLDOUT_GRID setting x residual gate x held-out gate, by the same rule; appended."""
    candidates = [(g, mg, hg) for g in range(len(HOLDOUT_GRID)) for mg in HOLDOUT_MIN_GAINS for hg in HOLDOUT_GATES]
    score, harms_of, lines = {}, {}, []
    head = [f"{n} ratio {lo}-{hi}" for n in names for lo, hi in RANGES]
    head += [f"{n} harm" for n in names] + [f"{n} applied" for n in names]
    lines.append("| setting | deform_min_gain | deform_min_holdout_gain | " + " | ".join(head) + " |")
    lines.append("|---|---|---|" + "---|" * len(head))
    rows_of = {name: _rows("holdout", name) for name in names}
    for c in candidates:
        g, mg, hg = c

        def use(o: dict, mg: float = mg, hg: float | None = hg) -> bool:
            return o["applied"] and o["gain"] >= mg and (hg is None or o["holdout"] >= hg)

        ratios, harms, applied = _judged(rows_of, g, use)
        score[c], harms_of[c] = float(np.mean(ratios)), harms
        cells = (
            [f"{x:.3f}" for x in ratios] + [f"{100 * h:.1f} %" for h in harms] + [f"{100 * a:.0f} %" for a in applied]
        )
        gate = "off" if hg is None else f"{hg:g}"
        lines.append(f"| {_name(HOLDOUT_GRID[g])} | {mg:g} | {gate} | " + " | ".join(cells) + " |")
    allowed = [c for c in candidates if max(harms_of[c]) <= HARM_SHARE]
    verdict = "**No candidate passes the harm rule.**"
    if allowed:
        best = min(score[c] for c in allowed)
        near = [c for c in allowed if score[c] <= best + 0.01]
        g, mg, hg = min(
            near,
            key=lambda c: (c[2] is not None, -HOLDOUT_GRID[c[0]]["deform_regularization"], -c[1], c[2] or 0.0),
        )
        gate = "off" if hg is None else f"{hg:g}"
        verdict = (
            f"**Chosen: {_name(HOLDOUT_GRID[g])}, deform_min_gain {mg:g}, held-out gate {gate}** "
            f"(mean ratio {score[g, mg, hg]:.3f}; the best allowed: {best:.3f})."
        )
    ms = [o["holdout_ms"] for rows in rows_of.values() for r in rows for o in r["out"] if "holdout_ms" in o]
    intro = [
        f"Generated by `.venv/bin/python scripts/choose_deform.py summarize-holdout {' '.join(names)}` from the",
        "`holdout` rows (each gate applied afterwards to the same fits). The held-out check's own cost (four more",
        f"fits, 1 thread): median {np.median(ms):.0f} ms, p90 {np.percentile(ms, 90):.0f} ms.",
    ]
    _append_section(target, "## Amendment 3: the held-out-half gate", intro, lines, verdict)


def _append_section(target: Path, heading: str, intro: list[str], lines: list[str], verdict: str) -> None:
    """Append one amendment's section (heading, provenance, table, verdict) to the choice page and print it."""
    text = ["", heading, "", *intro, "", *lines, "", verdict, ""]
    with open(target, "a") as fh:
        fh.write("\n".join(text))
    print("\n".join(text))


def _name(setting: dict) -> str:
    return f"modes {setting['deform_modes']}, reg {setting['deform_regularization']:g}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "step", choices=("rigid", "grid", "gate", "holdout", "summarize", "summarize-gate", "summarize-holdout")
    )
    parser.add_argument("sets", nargs="+")
    parser.add_argument("--data", default="data")
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--stop", type=int)
    parser.add_argument("--write", default="docs/deform/choice.md")
    args = parser.parse_args()
    if args.step == "summarize":
        summarize(args.sets, Path(args.write))
        return
    if args.step == "summarize-gate":
        summarize_gate(args.sets, Path(args.write))
        return
    if args.step == "summarize-holdout":
        summarize_holdout(args.sets, Path(args.write))
        return
    for name in args.sets:
        if args.step == "rigid":
            rigid(name, Path(args.data))
        else:
            grid(name, args.start, args.stop, args.step)


if __name__ == "__main__":
    main()
