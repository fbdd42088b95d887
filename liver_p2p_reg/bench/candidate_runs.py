"""A candidate matcher's validation benchmarks, as the selection scripts run them (resumable `liver-p2p benchmark`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def run_candidate(
    name: str,
    weights: str,
    sets: dict[str, list[str]],
    methods: list[str],
    out_root: str,
    *,
    workers: int,
    data_root: str | None = None,
    threads: int | None = None,
    settings: dict[str, float] | None = None,
) -> None:
    """Benchmark weights `weights` (empty: the bundled ones) on every set into OUT_ROOT/NAME/SET; `settings`: more
    config values for the run (e.g. a threshold a rule chooses).

    Rows already in a run's cases.csv are kept, so an interrupted selection resumes.
    """
    config = Path(out_root) / f"{name}.yaml"
    config.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"weights_path: '{Path(weights).resolve() if weights else ''}'"]
    lines += [f"{key}: {value!r}" for key, value in (settings or {}).items()]
    config.write_text("\n".join(lines) + "\n")
    for dataset, extra in sets.items():
        cmd = [sys.executable, "-m", "liver_p2p_reg", "-q", "benchmark", "--dataset", dataset]
        cmd += ["--methods", ",".join(methods), "--out", str(Path(out_root) / name / dataset)]
        cmd += ["--workers", str(workers), "--config", str(config), *extra]
        if threads is not None:
            cmd += ["--threads", str(threads)]
        if data_root:
            cmd += ["--data-root", data_root]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)


def publish_report(title: str, table: list[str], verdict_line: str, command: str, path: str | None) -> None:
    """A selection's report (title, table, verdict, the command that wrote it): printed, and written to `path`."""
    report = [f"# {title}", "", *table, "", verdict_line, "", f"Command: `{command}`"]
    print("\n".join(report))
    if path:
        Path(path).write_text("\n".join(report) + "\n")
