"""`liver-p2p soak`: the bundled bags looped through the live ROS 2 graph for minutes; RSS and latency per minute."""

from __future__ import annotations

import argparse
import math
import os
import shutil
import time
from pathlib import Path

from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError

RESULTS_PAGE = Path("docs/results/soak.md")  # under the README's folder, with --readme
PLOT_DIR = Path("docs/soak")
OUTPUT_FILES = ("soak.csv", "soak.png", "soak.md")  # what OUT holds after a run (and logs/)
# Depth cameras stream at up to ~90 frames per second; far above that the player and the latency probe starve
# (10^6 Hz: 0 clouds received, a report of nothing, exit 0), measuring them instead of the node.
MAX_RATE_HZ = 100.0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "soak",
        help="soak benchmark: the bundled bags looped at a fixed rate through the live ROS 2 graph, RSS and "
        "latency per minute",
    )
    p.add_argument("--minutes", type=float, default=30.0, help="how long, in whole minutes (default: 30)")
    p.add_argument("--rate-hz", type=float, default=10.0, help="intraop clouds per second (default: 10)")
    p.add_argument(
        "--bags",
        nargs="+",
        metavar="DIR_OR_BAG",
        help="bags, or folders of bags, to play in turn (default: every bundled bag)",
    )
    p.add_argument("--out", default="out/soak", help="soak.csv, soak.png, soak.md and node logs (default: out/soak)")
    p.add_argument("--force", action="store_true", help="replace an earlier soak's soak.csv, soak.png and soak.md")
    p.add_argument(
        "--readme",
        nargs="?",
        const="README.md",
        metavar="README",
        help="also write docs/results/soak.md, docs/soak/ (next to README) and README's SOAK block "
        "(default README: ./README.md)",
    )
    p.add_argument("--method", help="registration method of register_node (default: the configured default)")
    p.add_argument("--config", help="YAML configuration file for register_node")
    p.add_argument("--minute-s", type=float, default=60.0, help=argparse.SUPPRESS)  # the tests' short minutes
    p.add_argument("--sample-s", type=float, default=2.0, help=argparse.SUPPRESS)  # RSS sample period
    p.set_defaults(func=run)


def resolve_bags(items: list[str] | None) -> list[Path]:
    """Bag directories / .mcap files, a folder standing for the bags in it (sorted); default the bundled ones."""
    from liver_p2p_reg.cli.demo_cmd import bundled_bags_dir

    if not items:
        bundled = bundled_bags_dir()
        if bundled is None:
            raise InputError("no bundled bags found (expected a bags/ folder next to the package); give --bags")
        items = [str(bundled)]
    out: list[Path] = []
    for item in items:
        path = Path(item)
        if _is_bag(path):
            out.append(path)
        elif path.is_dir() and (inner := sorted(p for p in path.iterdir() if _is_bag(p))):
            out.extend(inner)
        else:
            raise InputError(f"--bags: {item} is neither a bag nor a folder of bags")
    return out


def _is_bag(path: Path) -> bool:
    return (path / "metadata.yaml").is_file() or (path.suffix == ".mcap" and path.is_file())


def run(args: argparse.Namespace) -> int:
    config = Config.from_yaml(args.config) if args.config else Config()
    if args.method:
        config = config.replace(method=args.method)
    config.validate()
    minute_s = float(args.minute_s)
    if not (math.isfinite(minute_s) and minute_s > 0):
        raise InputError(f"--minute-s must be a finite number of seconds > 0 (got {args.minute_s})")
    if not math.isfinite(args.minutes):
        raise InputError(f"--minutes must be a finite number of minutes (got {args.minutes})")
    minutes = int(math.floor(args.minutes * 60.0 / minute_s + 1e-9))
    if minutes < 1 or not 0 < args.rate_hz <= MAX_RATE_HZ:
        raise InputError(
            f"--minutes must be at least one minute and --rate-hz in (0, {MAX_RATE_HZ:g}] "
            f"(got {args.minutes}, {args.rate_hz})"
        )
    if not (math.isfinite(args.sample_s) and args.sample_s > 0):
        raise InputError(f"--sample-s must be a finite number of seconds > 0 (got {args.sample_s})")
    if args.readme:  # checked now, not after half an hour
        from liver_p2p_reg.bench.readme import readme_markers

        readme = Path(args.readme)
        text = readme.read_text() if readme.is_file() else None
        if text is None or not all(m in text for m in readme_markers("SOAK")):
            raise InputError(
                f"--readme {readme}: no such file, or it lacks the {' ... '.join(readme_markers('SOAK'))} markers"
            )
    bags = resolve_bags(args.bags)
    out = _check_out(Path(args.out), bags, args.force)
    try:
        from liver_p2p_reg.livegraph import soak  # the rclpy adapter: importable only where rclpy is
        from liver_p2p_reg.livegraph.demo import node_params
    except ImportError as exc:
        raise InputError(f"the soak needs the live ROS 2 graph, and rclpy is not importable ({exc})") from None
    from tqdm import tqdm

    info = _info(args, config, bags, minute_s)
    quiet = getattr(args, "quiet", False)
    print(
        f"Soak: {len(bags)} bags at {args.rate_hz:g} Hz through register_node for {minutes} x {minute_s:g} s "
        f"(method {config.method}; node logs in {out}/logs) ...",
        flush=True,
    )
    total_s = minutes * minute_s
    bar_format = "{l_bar}{bar}| {n_fmt}/{total_fmt} s [{elapsed}<{remaining}]{postfix}"
    with tqdm(total=round(total_s), desc="soak", bar_format=bar_format, disable=quiet) as bar:

        def on_sample(elapsed_s: float, row) -> None:
            bar.update(max(0, min(round(elapsed_s), round(total_s)) - bar.n))
            if row is not None:
                line = _minute_line(row)
                bar.set_postfix_str(
                    f"minute {row.minute}: RSS {row.rss_mb_max:.0f} MB, p95 {row.latency_ms_p95:.0f} ms"
                )
                bar.write(line)

        result = soak.run_soak(
            bags,
            out,
            minutes=minutes,
            rate_hz=args.rate_hz,
            minute_s=minute_s,
            sample_s=args.sample_s,
            params=node_params(config),
            on_sample=on_sample,
        )
    info.update(interrupted=result.interrupted, rss_peak_mb=result.rss_peak_mb, errors=dict(result.error_messages))
    info["ready_s"] = result.ready_s
    info["load_end"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    if not result.rows:
        print(f"liver-p2p soak: no minute completed{': ' + result.failure if result.failure else ''}; nothing written")
        return 130 if result.interrupted else 1
    _write(result, info, out, args.readme)
    if result.interrupted:
        print(f"interrupted: the {len(result.rows)} minutes done are written")
        return 130
    if result.failure:
        print(f"liver-p2p soak: {result.failure}; the {len(result.rows)} minutes done are written")
        return 1
    if not result.latency_ms:  # nothing measured is no pass: the rows are written, the run failed
        print(f"liver-p2p soak: no pose arrived in {len(result.rows)} minutes (see {out}/logs)")
        return 1
    if result.exit_status != 0:  # a node that does not end cleanly on SIGINT failed the soak
        print(f"liver-p2p soak: register_node ended with status {result.exit_status} after SIGINT (see {out}/logs)")
        return 1
    return 0


def _check_out(out: Path, bags: list[Path], force: bool) -> Path:
    """--out checked before the node starts: a folder outside the bags it plays, an earlier soak's files replaced
    only with --force (a 30-minute run's results are not lost to a rerun)."""
    from liver_p2p_reg.cli.output_paths import output_folder

    output_folder(out, "--out", inputs=bags, bag_folders=True)
    taken = [out / name for name in OUTPUT_FILES if (out / name).exists() or (out / name).is_symlink()]
    for path in taken:  # never replaced, --force or not
        if path.is_dir():
            raise InputError(f"--out {out}: {path} is a folder; choose another --out")
    if taken and not force:
        raise InputError(f"{taken[0]} exists (an earlier soak); pass --force to replace it, or choose another --out")
    return out


def _info(args: argparse.Namespace, config: Config, bags: list[Path], minute_s: float) -> dict:
    from liver_p2p_reg.bench.sysinfo import code_version, cpu_model

    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    parts = [f"--minutes {args.minutes:g}", f"--rate-hz {args.rate_hz:g}"]
    if args.bags:
        parts.append("--bags " + " ".join(args.bags))
    for flag, value in (("--method", args.method), ("--config", args.config)):
        if value:
            parts.append(f"{flag} {value}")
    if minute_s != 60.0:
        parts.append(f"--minute-s {minute_s:g}")
    if args.readme:
        parts.append("--readme" if args.readme == "README.md" else f"--readme {args.readme}")
    omp = os.environ.get("OMP_NUM_THREADS")
    return {
        "command": ("" if omp is None else f"OMP_NUM_THREADS={omp} ") + "liver-p2p soak " + " ".join(parts),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        # the nodes inherit this process's environment; importing the ROS adapters set the wait policy's default
        "machine": f"{cpu_model()}, {usable} usable cores, OMP_NUM_THREADS={omp or 'unset'}, "
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}, "
        + (f"GOMP_SPINCOUNT={spin}, " if (spin := os.environ.get("GOMP_SPINCOUNT")) else "")
        + f"liver_p2p_reg {code_version()}",
        "load_start": load,
        "node": f"method `{config.method}`",
        "bags": [b.name.removesuffix(".mcap") for b in bags],
        "rate_hz": float(args.rate_hz),
        "minute_s": minute_s,
        "bag_s": minute_s / len(bags),
        "sample_s": float(args.sample_s),
        "max_rate_hz": config.max_rate_hz,
    }


def _minute_line(row) -> str:
    from liver_p2p_reg.bags.replay import fmt

    return (
        f"minute {row.minute}: RSS {fmt(row.rss_mb_max, 1)} MB (max), latency p50/p95/max "
        f"{fmt(row.latency_ms_p50, 0)}/{fmt(row.latency_ms_p95, 0)}/{fmt(row.latency_ms_max, 0)} ms, "
        f"{row.poses} poses, {row.dropped} dropped, {row.errors} errors, CPU {fmt(row.cpu_percent, 0)} %"
    )


def _write(result, info: dict, out: Path, readme: str | None) -> None:
    from liver_p2p_reg.bench.readme import relative_link, replace_readme_block
    from liver_p2p_reg.livegraph import soak_report as report

    rows = result.rows
    criteria = report.evaluate(rows)
    info["overall"] = report.overall(rows, result.latency_ms)
    csv_path, png_path, md_path = out / "soak.csv", out / "soak.png", out / "soak.md"
    report.write_csv(rows, csv_path)
    report.plot(rows, png_path, criteria)
    md_path.write_text(report.report_markdown(rows, criteria, info, png_path.name))
    print(report.minutes_table(rows))
    print(report.criteria_table(criteria))
    for line in report.error_lines(info["errors"]) if info["errors"] else []:
        print(f"errors: {line[2:]}")
    print(f"{info['overall']}; written: {csv_path}, {png_path}, {md_path}")
    if readme:
        readme_path = Path(readme)
        root = readme_path.parent
        page, plots = root / RESULTS_PAGE, root / PLOT_DIR
        plots.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(png_path, plots / "soak.png")
        shutil.copyfile(csv_path, plots / "soak.csv")
        page.parent.mkdir(parents=True, exist_ok=True)
        page.write_text(report.report_markdown(rows, criteria, info, relative_link(plots / "soak.png", page.parent)))
        block = report.readme_block(rows, criteria, info, relative_link(page, root))
        replace_readme_block(readme_path, block, "SOAK")
        print(f"written: {page}, {plots}/soak.png, {plots}/soak.csv and the SOAK block of {readme_path}")
