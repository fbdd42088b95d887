"""`liver-p2p benchmark`: run methods on a test set; write cases.csv, summary.md and PNG curves."""

from __future__ import annotations

import argparse
import json
import math
import shlex
from pathlib import Path

from liver_p2p_reg.config import DEVICES, Config
from liver_p2p_reg.errors import InputError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "benchmark",
        help="compare registration methods on a test set (tables, curves, statistics, timing)",
        description=(
            "Runs every method on every case through the public Registrar API. Resumable: rows already in "
            "OUT/cases.csv are skipped, so rerunning (or adding --methods) only runs what is missing. "
            "The summary covers every method in OUT/cases.csv."
        ),
    )
    p.add_argument("--dataset", required=True, help="folder of case NPZs, or a named test set such as insilico-test-v1")
    p.add_argument("--methods", help="comma-separated method names (default: all registered methods)")
    p.add_argument("--out", required=True, help="output folder (cases.csv, summary.md, PNGs)")
    p.add_argument("--limit", type=int, help="only the first N cases (after the preset)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--device", choices=DEVICES, help="compute device for learned methods (default: config)")
    p.add_argument(
        "--preset", choices=("smoke", "full"), default="full", help="smoke: first 3 cases per visibility bin"
    )
    p.add_argument("--ablations", action="store_true", help="also run the P2P ablations (K, selection, proposal)")
    p.add_argument("--ablation-cases-per-bin", type=int, default=10, help="cases per bin used by the ablations")
    p.add_argument("--config", help="start from this YAML config instead of the defaults")
    p.add_argument("--seed", type=int, help="base seed (each case derives its own from it)")
    p.add_argument("--threads", type=int, help="torch CPU threads per worker (config num_threads)")
    p.add_argument(
        "--noise-levels",
        help="comma-separated sensor-noise levels in mm (e.g. 2,4) added to the [0.2,0.3) cases as extra cases (Table II)",
    )
    p.add_argument(
        "--noise-bins",
        choices=("lowest", "all"),
        default="lowest",
        help="which cases get the --noise-levels copies: the lowest visibility bin (default) or all",
    )
    p.add_argument(
        "--visibility",
        metavar="LO,HI",
        help="only the cases whose visibility lies in [LO, HI), e.g. 0.1,0.3 (where a laparoscope looks)",
    )
    p.add_argument(
        "--prepare-minutes",
        type=float,
        default=0.0,
        help="also run the learned methods with patient-prepared weights (`liver-p2p prepare`, this many "
        "minutes per liver, each test liver once, cached under DATA_ROOT/prepared): rows `<method>[prepared]`",
    )
    p.add_argument(
        "--sensor-aware",
        action="store_true",
        help="also run every method with each case's stored camera position (free-space scoring), "
        "as rows `METHOD[fs]` beside the plain ones; needs camera crops (e.g. insilico-camera-v1)",
    )
    p.add_argument("--data-root", help="where named test sets live (default: $LIVER_P2P_DATA or ./data)")
    p.add_argument("--readme", help="replace the README's BENCHMARK block with the main tables")
    p.add_argument(
        "--readme-block",
        default="BENCHMARK",
        metavar="NAME",
        help="with --readme: the block between <!-- NAME:START --> and <!-- NAME:END --> (default: %(default)s)",
    )
    p.add_argument(
        "--summary-only", action="store_true", help="run nothing: rewrite summary.md (and --readme) from OUT/cases.csv"
    )
    p.set_defaults(func=run)


def _visibility_range(text: str | None) -> tuple[float, float] | None:
    """`LO,HI` -> (LO, HI) with 0 <= LO < HI; a bad value is one InputError line."""
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--visibility must be LO,HI (two numbers, e.g. 0.1,0.3), got {text!r}") from None
    if not 0 <= lo < hi:
        raise InputError(f"--visibility needs 0 <= LO < HI, got {text!r}")
    return lo, hi


def _command_line(args: argparse.Namespace, methods: list[str]) -> str:
    """The canonical command that reproduces this run (shown in the summary and the README)."""
    parts = ["liver-p2p", "benchmark", "--dataset", args.dataset, "--methods", ",".join(methods), "--out", args.out]
    for flag, value in (
        ("--preset", args.preset if args.preset != "full" else None),
        ("--limit", args.limit),
        ("--workers", args.workers if args.workers != 1 else None),
        ("--device", args.device),
        ("--config", args.config),
        ("--seed", args.seed),
        ("--threads", args.threads),
        ("--noise-levels", args.noise_levels),
        ("--noise-bins", args.noise_bins if args.noise_bins != "lowest" else None),
        ("--visibility", args.visibility),
        ("--prepare-minutes", args.prepare_minutes or None),
    ):
        if value is not None:
            parts += [flag, str(value)]
    if args.ablations:
        parts += ["--ablations", "--ablation-cases-per-bin", str(args.ablation_cases_per_bin)]
    if args.sensor_aware:
        parts += ["--sensor-aware"]
    if args.readme:
        parts += ["--readme", args.readme]
        if args.readme_block != "BENCHMARK":
            parts += ["--readme-block", args.readme_block]
    return " ".join(shlex.quote(p) for p in parts)


def _check_readme(args: argparse.Namespace) -> None:
    """--readme names a README holding the block's markers: checked before the run, not after it."""
    from liver_p2p_reg.bench.readme import check_readme

    if args.readme:
        check_readme(args.readme, getattr(args, "readme_block", "BENCHMARK"))


def _cuda_available() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def _noise_levels(text: str | None) -> list[float]:
    if not text:
        return []
    try:
        levels = sorted({float(x) for x in text.split(",") if x.strip()})
    except ValueError:
        raise InputError(f"--noise-levels must be comma-separated numbers in mm, got {text!r}") from None
    if any(not 0 <= lv <= 50 for lv in levels):
        raise InputError(f"--noise-levels must lie in [0, 50] mm, got {text!r}")
    return levels


def run(args: argparse.Namespace) -> int:
    from liver_p2p_reg.bench.cases import (
        case_info,
        list_case_paths,
        planned_cases,
        resolve_dataset,
        select_cases,
        with_noise,
    )
    from liver_p2p_reg.bench.harness import run_benchmark
    from liver_p2p_reg.bench.jobs import (
        DEFORM_SUFFIX,
        BenchmarkSpec,
        benchmark_methods,  # the table and `bound`: no torch or Open3D
        check_settings,
    )
    from liver_p2p_reg.bench.sysinfo import machine_info

    if args.summary_only:
        return _summary_only(args)
    config = Config.from_yaml(args.config) if args.config else Config()
    overrides = {
        k: v for k, v in (("device", args.device), ("seed", args.seed), ("num_threads", args.threads)) if v is not None
    }
    config = config.replace(**overrides) if overrides else config
    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else benchmark_methods()
    if not methods:
        raise InputError("no methods to run (--methods is empty)")
    unknown = [m for m in methods if m.removesuffix(DEFORM_SUFFIX) not in benchmark_methods()]
    if unknown:  # before a named test set is generated, which can take minutes
        raise InputError(f"unknown method(s) {', '.join(unknown)}; choose from: {', '.join(benchmark_methods())}")
    if config.device == "cuda" and not _cuda_available():
        raise InputError("--device cuda: no CUDA device is available to torch here")
    _check_readme(args)
    if args.ablation_cases_per_bin < 1:
        raise InputError(f"--ablation-cases-per-bin must be >= 1, got {args.ablation_cases_per_bin}")
    if args.workers < 1:  # here too (the harness checks it), before the test set is generated
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    from liver_p2p_reg.cli.output_paths import given_paths, output_folder

    output_folder(args.out, "--out", inputs=given_paths(args.config, args.dataset))
    noise_levels = _noise_levels(args.noise_levels)
    # NaN would be recorded in settings.json, and NaN != NaN refuses every later run into that OUT
    if not (math.isfinite(args.prepare_minutes) and args.prepare_minutes >= 0):
        raise InputError(f"--prepare-minutes must be a finite number >= 0, got {args.prepare_minutes}")
    plan = planned_cases(args.dataset, args.preset, args.limit)  # a named set: only the livers these cases need
    root = Path(args.data_root) if args.data_root else None
    folder, dataset_id = resolve_dataset(args.dataset, root, livers=plan[0] if plan else None)
    paths = list_case_paths(folder) if plan is None else [folder / n for n in plan[1] if (folder / n).is_file()]
    cases = select_cases([case_info(p) for p in paths], args.preset, args.limit)
    visibility_range = _visibility_range(args.visibility)
    if visibility_range is not None:
        cases = [c for c in cases if visibility_range[0] <= c.visibility < visibility_range[1]]
        if not cases:
            raise InputError(f"no case of {args.dataset} has a visibility in [{args.visibility})")
    cases = with_noise(cases, noise_levels, args.noise_bins)
    if args.sensor_aware:
        lacking = [c.case_id for c in cases if not c.has_sensor_origin]
        if lacking:
            raise InputError(
                f"--sensor-aware: {len(lacking)} of {len(cases)} cases store no sensor origin (e.g. {lacking[0]}); "
                "only camera crops do (a camera set made before the origin was stored is brought up to date by "
                "`liver-p2p dataset generate --testset NAME`)"
            )
    prepared: dict[str, str] = {}
    if args.prepare_minutes > 0:
        from liver_p2p_reg.bench.patient import prepare_test_livers
        from liver_p2p_reg.phantom.testset import default_root

        prepared = prepare_test_livers(
            cases,
            args.prepare_minutes,
            (root or default_root()) / "prepared",
            progress=not getattr(args, "quiet", False),
        )
    out = Path(args.out)
    spec = BenchmarkSpec(
        out=out,
        dataset_id=dataset_id,
        cases=cases,
        methods=methods,
        config=config,
        preset=args.preset,
        limit=args.limit,
        ablations=args.ablations,
        ablation_cases_per_bin=args.ablation_cases_per_bin,
        workers=args.workers,
        noise_levels_mm=tuple(noise_levels),
        noise_bins=args.noise_bins,
        prepared=prepared,
        prepare_minutes=args.prepare_minutes,
        sensor_aware=args.sensor_aware,
        visibility_range=visibility_range,
    )
    check_settings(out, spec.settings())  # refuse a mismatching OUT before touching it
    machine = machine_info(config.device)
    machine["workers"] = args.workers
    command = _command_line(args, methods)
    # Written before the run, so an interrupted run can still be summarized with --summary-only.
    (out / "machine.json").write_text(json.dumps({**machine, "command": command}, indent=2) + "\n")
    rows = run_benchmark(spec, progress=not getattr(args, "quiet", False))
    _write_reports(args, out, rows, machine, command)
    return 0


def _write_reports(args: argparse.Namespace, out: Path, rows: list, machine: dict, command: str) -> None:
    from liver_p2p_reg.bench.jobs import SETTINGS_JSON, read_json
    from liver_p2p_reg.bench.readme import relative_link, replace_readme_block
    from liver_p2p_reg.bench.summary import write_summary

    settings = read_json(out / SETTINGS_JSON)
    summary = write_summary(out, rows, settings, machine, command)
    if args.readme:
        readme = Path(args.readme)
        block = summary.readme_block(relative_link(out / "summary.md", readme.parent))
        replace_readme_block(readme, block, getattr(args, "readme_block", "BENCHMARK"))
    if not getattr(args, "quiet", False):
        n_failed = sum(r["failed"] for r in rows)
        print(f"{len(rows)} rows ({n_failed} failed) in {out / 'cases.csv'}; summary: {out / 'summary.md'}")


def _summary_only(args: argparse.Namespace) -> int:
    """Rewrite the reports of an existing OUT; machine and command are those recorded by its last run."""
    from liver_p2p_reg.bench.cases_csv import CASES_CSV, read_rows
    from liver_p2p_reg.bench.jobs import SETTINGS_JSON, read_json

    out = Path(args.out)
    if not (out / CASES_CSV).is_file() or not (out / SETTINGS_JSON).is_file():
        raise InputError(f"--summary-only: {out} holds no benchmark run ({CASES_CSV}, {SETTINGS_JSON})")
    _check_readme(args)
    machine_path = out / "machine.json"
    if machine_path.is_file():
        machine = read_json(machine_path)
    else:  # a run from before machine.json existed: describe this machine, as the run likely used it
        from liver_p2p_reg.bench.sysinfo import machine_info

        settings = read_json(out / SETTINGS_JSON)
        machine = {**machine_info(settings.get("config", {}).get("device", "cpu")), "note": "recorded at summary time"}
    command = machine.pop("command", "")
    _write_reports(args, out, read_rows(out / CASES_CSV), machine, command)
    return 0
