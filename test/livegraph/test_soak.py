"""`liver-p2p soak`: the criteria on hand-made minutes, and a short real run through the live graph."""

import csv
import math
import os
import subprocess
import sys
from pathlib import Path

from conftest import require_rclpy

from liver_p2p_reg.livegraph.soak_report import MinuteRow, evaluate, read_csv, write_csv

BAG = Path(__file__).resolve().parents[2] / "bags" / "phantom_sim_04_vis0.36"


def minute(number: int, rss_mb: float, p95_ms: float) -> MinuteRow:
    return MinuteRow(number, 60.0 * number, rss_mb, rss_mb - 5, 50.0, 600, 600, 480, 120,
                     p95_ms / 3, p95_ms, p95_ms * 1.5, 0, 13)  # fmt: skip


def test_criteria_pass_when_memory_and_latency_stay_flat_after_minute_2():
    rows = [minute(1, 400, 900), minute(2, 500, 200), minute(3, 510, 230), minute(4, 520, 210)]
    c = evaluate(rows)
    assert (c.reference, c.last) == (2, 4)
    assert math.isclose(c.rss_growth_pct, 4.0) and c.rss_pass is True  # minute 1 (start-up) is left out
    assert math.isclose(c.p95_ratio, 1.15) and c.p95_worst_minute == 3 and c.p95_pass is True
    assert c.passed


def test_criteria_miss_on_growing_memory_or_a_slow_minute():
    c = evaluate([minute(1, 400, 200), minute(2, 500, 200), minute(3, 530, 250), minute(4, 526, 200)])
    assert math.isclose(c.rss_growth_pct, 5.2) and c.rss_pass is False  # the last minute against minute 2
    assert math.isclose(c.p95_ratio, 1.25) and c.p95_pass is False and not c.passed


def test_criteria_need_a_minute_2():
    c = evaluate([minute(1, 400, 200)])
    assert c.rss_pass is None and c.p95_pass is None and not c.passed


def test_csv_round_trip(tmp_path):
    rows = [minute(1, 400.5, 200.25), minute(2, 401.0, float("nan"))]
    write_csv(rows, tmp_path / "soak.csv")
    back = read_csv(tmp_path / "soak.csv")
    assert back[0] == rows[0] and back[1].minute == 2 and math.isnan(back[1].latency_ms_p95)


def test_a_short_soak_through_the_live_graph_writes_csv_png_and_md(tmp_path):
    require_rclpy()
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\n<!-- SOAK:START -->\nold\n<!-- SOAK:END -->\n")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "liver_p2p_reg", "soak", "--minutes", "0.25", "--minute-s", "5",
           "--bags", str(BAG), "--out", str(out), "--readme", str(readme)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ), timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with open(out / "soak.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["minute"]) for r in rows] == [1, 2, 3]
    assert all(int(r["published"]) >= 40 and float(r["rss_mb_max"]) > 50 for r in rows)  # 10 Hz for 5 s
    timed = [r for r in rows if int(r["poses"]) > 0 and math.isfinite(float(r["latency_ms_p95"]))]
    assert timed and all(0 < float(r["latency_ms_p50"]) <= float(r["latency_ms_max"]) for r in timed)
    assert all(int(r["errors"]) == 0 for r in rows)
    assert (out / "soak.png").stat().st_size > 10_000
    report = (out / "soak.md").read_text()
    assert "RSS growth, minute 2 -> minute 3" in report and ("PASS" in report or "MISS" in report)
    page = tmp_path / "docs" / "results" / "soak.md"
    assert "](../soak/soak.png)" in page.read_text() and (tmp_path / "docs" / "soak" / "soak.png").is_file()
    block = readme.read_text()
    assert "old" not in block and "**Soak**" in block and "](docs/results/soak.md)" in block


def children(pid: int) -> list[int]:
    """The processes whose parent is `pid`."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            continue  # ended meanwhile
    return found


def test_a_soak_ended_by_sigterm_stops_its_node(tmp_path):
    """SIGTERM (a supervisor's, `timeout`'s) ends a command as Ctrl-C does: the soak stops the register_node it
    started instead of leaving it running on its domain."""
    import signal
    import time

    require_rclpy()
    cmd = [sys.executable, "-m", "liver_p2p_reg", "soak", "--minutes", "1", "--minute-s", "60",
           "--bags", str(BAG), "--out", str(tmp_path / "out")]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    nodes: list[int] = []
    try:
        deadline = time.monotonic() + 60
        log = tmp_path / "out" / "logs" / "register_node.stderr"
        while not (log.is_file() and children(proc.pid)) and time.monotonic() < deadline:
            time.sleep(0.2)
        nodes = children(proc.pid)
        assert nodes, "the soak started no node"
        time.sleep(3.0)  # the node is up (or coming up); the soak is waiting or publishing
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode != -signal.SIGTERM, err  # not killed on the spot: it ran its cleanup
        assert not any(Path(f"/proc/{pid}").exists() for pid in nodes), err  # its node is gone too
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in nodes:  # a failed run must not leave its node answering on the domain
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
