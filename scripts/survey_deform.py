"""The non-rigid stage on one view against the stage on a fused survey of several views, on real-anatomy sets.

    .venv/bin/python scripts/survey_deform.py [--sets real-test-camera-v2,real-test-camera-v2-arap] \
        [--views 1,2,4,8] [--noise-mm 2] [--readme docs/results/survey_deform.md]
    .venv/bin/python scripts/survey_deform.py --bags bags/sweep_* [--readme docs/results/survey_deform.md]

A camera set holds, for each liver and deformation, up to 16 laparoscope views of the same deformed organ from
different camera poses, their visibility bins cycling [0.05, 0.1), [0.1, 0.15), [0.15, 0.2), [0.2, 0.3) (so the
first view sees 5-10 %). For each (liver, deformation) with at least the largest k views, the first k views
(k in --views) are fused into the sensor frame of the first one with their true relative poses (the perfect
tracking survey mode approaches; each view gets its own --noise-mm of Gaussian noise), and then:
- the rigid pose is ICP started from the true pose on that fused surface (method `track`, where survey mode's
  global registrations end: bags/README.md, the survey table);
- the stage (`deform`, its defaults) runs from that pose once on the first view alone and once on the fused
  surface (`survey_deform_fused`).
With --bags: each sweep bag replayed through the node core in survey mode with the stage, fitting the frame and
fitting the fused survey (`survey_deform_fused` false / true).
Reported: mean interior RMS-TRE of the Procrustes oracle, the rigid pose, each stage's result (the rigid
result where the stage was not applied), how often it was applied, how often the fused stage's error lies within
its deformed-position bound (calibrated on single views, 90 %), and survey mode's own path: the first view
that the default registers without warnings (free space from its camera; survey mode waits for one), the fused
views fitted by ICP from that pose (survey mode's tracking, here perfect, and its correction), then the stage on
the fused views. Nothing here is tuned: the stage's
settings are the defaults chosen on the validation livers (docs/deform/choice.md).
"""

from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from liver_p2p_reg.bench.cases import list_case_paths, read_case, resolve_dataset, sensor_origin_mm
from liver_p2p_reg.bench.readme import write_headline
from liver_p2p_reg.config import Config
from liver_p2p_reg.metrics import rms_tre_mm
from liver_p2p_reg.registration.baselines import kabsch_np
from liver_p2p_reg.registration.confidence import pose_bound_warnings
from liver_p2p_reg.registration.registrar import Registrar

MARK, BAGS_MARK = "SURVEY-DEFORM", "SURVEY-BAGS"
VIEW_NAME = re.compile(r"case_L(\d+)_D(\d+)_T(\d+)$")


def organ_views(dataset: str) -> dict[tuple[int, int], list[Path]]:
    """The set's case files grouped by (liver, deformation), each group in view order."""
    folder, _ = resolve_dataset(dataset, None)
    groups: dict[tuple[int, int], list[tuple[int, Path]]] = defaultdict(list)
    for path in list_case_paths(folder):
        match = VIEW_NAME.match(path.stem)
        if match:  # density twins and other variants are not separate views
            liver, deformation, view = (int(g) for g in match.groups())
            groups[(liver, deformation)].append((view, path))
    return {key: [p for _, p in sorted(views)] for key, views in sorted(groups.items())}


def to_first_view(case: dict, first: dict, rng: np.random.Generator, noise_mm: float) -> np.ndarray:
    """A view's points, noised, moved into the first view's sensor frame by the two true poses."""
    points = np.asarray(case["tgt_pcd"], float)
    points = points + rng.normal(0.0, noise_mm, points.shape) if noise_mm > 0 else points
    in_ct = (points - case["t_gt"]) @ np.asarray(case["R_gt"], float)  # R^T (x - t), row vectors
    return in_ct @ np.asarray(first["R_gt"], float).T + first["t_gt"]


def stage_tre_mm(registrar: Registrar, rigid, source, view, triangles, fid_s, fid_t) -> tuple[float, bool, float]:
    """Interior RMS-TRE after the stage fitted `view` from the rigid pose (the rigid one when not applied), whether
    it was applied, and whether that error lies within the deformed positions' bound (1/0; NaN when not applied)."""
    registrar.deform(rigid, source, view, triangles, fid_s, fid_t)
    if not rigid.deformation.applied:
        return rms_tre_mm(rigid.T_target_source, fid_s, fid_t), False, float("nan")
    return rigid.deformed_rms_tre_mm, True, float(rigid.deformed_rms_tre_mm <= rigid.deformed_error_bound_mm)


def survey_start(registrar: Registrar, source: np.ndarray, cases: list[dict], first: dict) -> np.ndarray:
    """Survey mode's first pose, in the first view's sensor frame: the default on each view in turn (free space from
    its own camera, no added noise) until one registers without warnings, as survey mode waits for (else the last)."""
    config = registrar.config
    for case in cases:
        result = registrar.register(source, case["tgt_pcd"], sensor_origin_mm=sensor_origin_mm(case))
        if not pose_bound_warnings(result, config):  # survey mode's gate
            break
    # sensor i -> ct (the truth) -> sensor of the first view
    R_i, t_i, R_0, t_0 = (np.asarray(x, float) for x in (case["R_gt"], case["t_gt"], first["R_gt"], first["t_gt"]))
    to_first = np.eye(4)
    to_first[:3, :3] = R_0 @ R_i.T
    to_first[:3, 3] = t_0 - R_0 @ R_i.T @ t_i
    return to_first @ np.asarray(result.T_target_source, float)


def run_set(dataset: str, counts: list[int], noise_mm: float, registrar: Registrar) -> dict[int, np.ndarray]:
    """Per view count, one row per organ: oracle, rigid, stage on one view, stage on the fused views, applied on one,
    applied on the fused, the fused stage within its bound, survey mode's own pose (survey_start, then ICP), that + stage, harm."""
    rows: dict[int, list] = defaultdict(list)
    # the same organs for every count: those with at least the largest count of views (a camera pose that could
    # not reach its visibility bin was skipped when the set was made)
    organs = {key: paths for key, paths in organ_views(dataset).items() if len(paths) >= max(counts)}
    for (liver, deformation), paths in tqdm(organs.items(), desc=dataset, unit="organ"):
        cases = [read_case(p) for p in paths[: max(counts)]]
        first = cases[0]
        rng = np.random.default_rng([liver, deformation, int(noise_mm * 1000)])
        views = [to_first_view(c, first, rng, noise_mm) for c in cases]
        source = np.asarray(first["src_pcd"], float)
        triangles = first.get("src_triangles")
        fid_s, fid_t = np.asarray(first["src_marker"], float), np.asarray(first["tgt_marker"], float)
        truth = kabsch_np(fid_s, fid_t)
        oracle = rms_tre_mm(truth, fid_s, fid_t)  # the same for every count of fused views
        start_T = survey_start(registrar, source, cases, first)
        for k in counts:
            fused = np.concatenate(views[:k])
            rigid = registrar.register(source, fused, method="track", initial_T_mm=truth)
            rigid_tre = rms_tre_mm(rigid.T_target_source, fid_s, fid_t)
            one, one_applied, _ = stage_tre_mm(registrar, rigid, source, views[0], triangles, fid_s, fid_t)
            many, many_applied, covered = stage_tre_mm(registrar, rigid, source, fused, triangles, fid_s, fid_t)
            # survey mode's own path: its first pose, then the fused views fitted by ICP from it (its tracking and
            # correction; tracking perfect here)
            surveyed = registrar.register(source, fused, method="track", initial_T_mm=start_T)
            found_tre = rms_tre_mm(surveyed.T_target_source, fid_s, fid_t)
            found_many = stage_tre_mm(registrar, surveyed, source, fused, triangles, fid_s, fid_t)[0]
            harmed = found_tre < 10.0 and found_many > found_tre + 1.0  # a good pose made worse by > 1 mm
            rows[k].append(
                (oracle, rigid_tre, one, many, one_applied, many_applied, covered, found_tre, found_many, harmed)
            )
    return {k: np.asarray(v, float) for k, v in rows.items()}


def table_lines(results: dict[str, dict[int, np.ndarray]], noise_mm: float) -> list[str]:
    """The markdown table: one row per set and view count."""
    lines = [
        f"Mean interior RMS-TRE (mm), {noise_mm:g} mm noise per view; the stage's result is the rigid one where it "
        "was not applied; `applied`: on one view / on the fused views.",
        "",
        "| set | views fused | organs | oracle | rigid (ICP from the true pose on the fused views) | stage on the first "
        "view | stage on the fused views | fused / oracle | applied | within the deformed bound | survey: the "
        "default on the first view without warnings, ICP on the fused views from it | that + stage on the fused views "
        "| harmed (that < 10 mm, > 1 mm worse) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, by_count in results.items():
        for k, r in sorted(by_count.items()):
            oracle, rigid, one, many = (r[:, i].mean() for i in range(4))
            applied = f"{100 * r[:, 4].mean():.0f} % / {100 * r[:, 5].mean():.0f} %"
            covered = r[:, 6][np.isfinite(r[:, 6])]
            within = f"{100 * covered.mean():.0f} % of {len(covered)}" if len(covered) else "-"
            lines.append(
                f"| {name} | {k} | {len(r)} | {oracle:.2f} | {rigid:.2f} | {one:.2f} | {many:.2f} | "
                f"{many / oracle:.2f} | {applied} | {within} | {r[:, 7].mean():.2f} | {r[:, 8].mean():.2f} | "
                f"{int(r[:, 9].sum())} |"
            )
    return lines


def final_tre_mm(frame: dict) -> float:
    """A replayed frame's interior RMS-TRE after the stage: the deformed one where it was applied, else the rigid one."""
    deformed = frame.get("deformed_rms_tre_mm")
    return float(frame["rms_tre_mm"] if deformed is None else deformed)


def bag_lines(bags: list[str]) -> list[str]:
    """Each sweep bag replayed in survey mode with the stage on the frame and on the fused surface."""
    from liver_p2p_reg.bags.replay import replay_bag

    lines = [
        f"Command: `.venv/bin/python scripts/survey_deform.py --bags {' '.join(bags)}` (no other option)",
        "",
        "Interior RMS-TRE (mm) per frame after the stage (the rigid one where it was not applied), mean over all "
        "frames, over the last 10, and at the last frame; the rigid survey's last frame beside it:",
        "",
        "| sweep bag | stage fits | frames applied | mean, all frames | mean, last 10 | last frame | rigid, last frame "
        "| stage p50 (ms) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for bag in bags:
        for fused in (False, True):
            row = replay_bag(bag, Config(mode="survey", deform=True, survey_deform_fused=fused))
            tre = [final_tre_mm(f) for f in row.per_frame]
            rigid_last = row.per_frame[-1]["rms_tre_mm"]
            lines.append(
                f"| `{Path(bag).name}` | {'the fused survey' if fused else 'the frame'} | "
                f"{row.deform_applied}/{row.registered} | {np.mean(tre):.2f} | {np.mean(tre[-10:]):.2f} | "
                f"{tre[-1]:.2f} | {rigid_last:.2f} | {np.median([f['deform_ms'] for f in row.per_frame]):.0f} |"
            )
    return lines


def rule_lines(runs: dict[float, dict[str, np.ndarray]], reference: float) -> list[str]:
    """docs/deform/RULE_survey.md applied: per candidate and set, the survey path's mean after the stage and its harm."""
    sets = list(runs[reference])
    lines = [
        "| regularization | "
        + " | ".join(f"{name}: mean after the stage (mm), harmed" for name in sets)
        + " | passes |",
        "|---|" + "---|" * len(sets) + "---|",
    ]
    passing = {}
    for value, by_set in runs.items():
        ok = value != reference
        cells = []
        for name in sets:
            mean, harm = by_set[name][:, 8].mean(), int(by_set[name][:, 9].sum())
            ref_mean, ref_harm = runs[reference][name][:, 8].mean(), int(runs[reference][name][:, 9].sum())
            ok &= mean <= ref_mean - 0.05 and harm <= ref_harm
            cells.append(f"{mean:.3f}, {harm}")
        if ok:
            passing[value] = np.mean([by_set[name][:, 8].mean() for name in sets])
        lines.append(
            f"| {value:g} | "
            + " | ".join(cells)
            + f" | {'yes' if ok else 'no' if value != reference else '(reference)'} |"
        )
    chosen = min(passing, key=passing.get) if passing else reference
    verdict = f"**Chosen: {chosen:g}**" + (
        " (no candidate passes; the fused survey keeps the default)" if not passing else ""
    )
    return [*lines, "", verdict]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="real-test-camera-v2,real-test-camera-v2-arap")
    parser.add_argument("--views", default="1,2,4,8")
    parser.add_argument("--noise-mm", type=float, default=2.0)
    parser.add_argument(
        "--regularization", type=float, help="the stage's deform_regularization (default: the config's)"
    )
    parser.add_argument("--bags", nargs="+", help="instead: replay these sweep bags in survey mode, frame vs fused")
    parser.add_argument(
        "--rule", help="regularizations to judge by docs/deform/RULE_survey.md, the first the reference"
    )
    parser.add_argument("--runs", default="out/survey_rule", help="with --rule: one JSON of rows per value (resumable)")
    parser.add_argument("--readme", help="write the block into this markdown file")
    args = parser.parse_args(argv)
    if args.rule:
        return judge(args)
    if args.bags:
        lines = bag_lines(args.bags)
        write_headline(lines[0], lines[2:], args.readme, BAGS_MARK)
        return 0
    counts = sorted({int(v) for v in args.views.split(",")})
    config = Config() if args.regularization is None else Config(deform_regularization=args.regularization)
    registrar = Registrar(config)  # the stage is called on its own after each rigid pose
    results = {name: run_set(name, counts, args.noise_mm, registrar) for name in args.sets.split(",")}
    command = (
        f"Command: `.venv/bin/python scripts/survey_deform.py --sets {args.sets} --views {args.views} "
        f"--noise-mm {args.noise_mm:g}"
        + ("" if args.regularization is None else f" --regularization {args.regularization:g}")
        + "`"
    )
    lines = [command, "", *table_lines(results, args.noise_mm)]
    write_headline(lines[0], lines[2:], args.readme, MARK)
    return 0


def judge(args: argparse.Namespace) -> int:
    """--rule: run (or read back) each regularization on the sets at --views, then apply the rule."""
    import json

    counts = sorted({int(v) for v in args.views.split(",")})
    runs: dict[float, dict[str, np.ndarray]] = {}
    for value in (float(v) for v in args.rule.split(",")):
        path = Path(args.runs) / f"regularization_{value:g}.json"
        if not path.exists():
            registrar = Registrar(Config(deform_regularization=value))
            rows = {name: run_set(name, counts, args.noise_mm, registrar)[counts[-1]] for name in args.sets.split(",")}
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({name: r.tolist() for name, r in rows.items()}))
        runs[value] = {name: np.asarray(r, float) for name, r in json.loads(path.read_text()).items()}
    command = (
        f"Command: `.venv/bin/python scripts/survey_deform.py --sets {args.sets} --views {counts[-1]} "
        f"--noise-mm {args.noise_mm:g} --rule {args.rule}`"
    )
    lines = [command, "", *rule_lines(runs, float(args.rule.split(",")[0]))]
    write_headline(lines[0], lines[2:], args.readme, "SURVEY-RULE")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
