"""colcon builds the package (plain and --symlink-install) and the installed executables start."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "liver_p2p_reg"
IGNORED = (
    ".venv",
    ".git",
    "out",
    "build",
    "install",
    "log",
    "__pycache__",
    "*.egg-info",
    ".pytest_cache",
    ".ruff_cache",
)


def colcon() -> str:
    found = shutil.which("colcon", path=str(Path(sys.executable).parent)) or shutil.which("colcon")
    if found is None:
        pytest.skip("colcon not installed (pip install colcon-common-extensions; `make setup` does)")
    return found


def sourced(workspace: Path, command: str, **kwargs) -> subprocess.CompletedProcess:
    """Run `command` in bash after sourcing the workspace's install/setup.sh, as a user would."""
    return subprocess.run(
        ["bash", "-c", f". {workspace}/install/setup.sh && {command}"],
        capture_output=True,
        text=True,
        cwd=workspace,  # not the source checkout: `python -c` would import the package from the cwd
        **kwargs,
    )


@pytest.mark.parametrize("symlink", [False, True], ids=["plain", "symlink-install"])
def test_colcon_build_installs_runnable_executables(tmp_path, symlink):
    exe = colcon()
    shutil.copytree(ROOT, tmp_path / "src" / PACKAGE, ignore=shutil.ignore_patterns(*IGNORED))
    cmd = [exe, "build", "--base-paths", "src"] + (["--symlink-install"] if symlink else [])
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    prefix = tmp_path / "install" / PACKAGE
    for name in ("register_node", "preop_loader_node", "liver-p2p"):
        assert os.access(prefix / "lib" / PACKAGE / name, os.X_OK), f"lib/{PACKAGE}/{name} (for ros2 run)"
    assert os.access(prefix / "bin" / "liver-p2p", os.X_OK), "bin/liver-p2p (on PATH once sourced)"
    assert (prefix / "share" / PACKAGE / "launch" / "registration.launch.py").exists()
    # the sourced workspace's package wins over any other install of it (e.g. the editable one here)
    where = sourced(tmp_path, f"python -c 'import {PACKAGE}; print({PACKAGE}.__file__)'", env=_env())
    assert where.returncode == 0 and str(tmp_path) in where.stdout, where.stdout + where.stderr
    version = sourced(tmp_path, "liver-p2p --version", env=_env())
    assert version.returncode == 0 and "liver-p2p" in version.stdout, version.stderr
    _start_installed_node(tmp_path, prefix / "lib" / PACKAGE / "register_node")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"  # `python` = this venv's
    return env


def _start_installed_node(workspace: Path, exe: Path) -> None:
    """The installed register_node comes up on an isolated domain and stops on SIGINT with status 0."""
    from conftest import require_rclpy

    require_rclpy()
    from liver_p2p_reg.livegraph.graph import isolated_env

    env = {**_env(), **isolated_env(), "RCUTILS_COLORIZED_OUTPUT": "0"}
    log = workspace / "register_node.stderr"
    with open(log, "wb") as err:
        proc = subprocess.Popen(
            ["bash", "-c", f". {workspace}/install/setup.sh && exec {exe} --ros-args -p method:=icp"],
            stdout=subprocess.DEVNULL,
            stderr=err,
            env=env,
        )
        try:
            end = time.monotonic() + 120
            while "register_node ready" not in log.read_text() and proc.poll() is None and time.monotonic() < end:
                time.sleep(0.1)
            assert "register_node ready" in log.read_text(), log.read_text()
            proc.send_signal(signal.SIGINT)
            assert proc.wait(10) == 0, log.read_text()
        finally:
            if proc.poll() is None:
                proc.kill()
