"""rclpy adapter: `liver-p2p soak`: the bundled bags looped at a fixed rate through register_node for minutes, per-minute rows."""

from __future__ import annotations

import math
import signal
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.player import read_raw
from liver_p2p_reg.errors import InputError, LiverP2PError
from liver_p2p_reg.livegraph.graph import (
    GraphProbe,
    NodeProcess,
    Received,
    level_of,
    set_isolated_environment,
    stamp_ns,
    values_of,
)
from liver_p2p_reg.livegraph.soak_report import MinuteRow
from liver_p2p_reg.ros.topics import (
    TOPIC_DIAGNOSTICS,
    TOPIC_INTRAOP,
    TOPIC_INTRAOP_FIDUCIALS,
    TOPIC_POSE,
    TOPIC_PREOP,
    TOPIC_PREOP_FIDUCIALS,
)
from liver_p2p_reg.stream.outputs import DIAG_NAME, PREOP_DIAG_NAME

ERROR_LEVEL = 2  # DiagnosticStatus.ERROR
POLL_S = 0.02  # how often the probe's records are read between two clouds
START_TIMEOUT_S = 120.0  # node start, and the first model's warm-up


class NodeDied(LiverP2PError):
    """register_node ended during the soak."""


@dataclass
class SoakBag:
    """A bag as the soak plays it: its model (CDR bytes) and its frames (cloud, fiducials or None)."""

    name: str
    preop: bytes
    preop_fiducials: bytes | None
    frames: list[tuple[bytes, bytes | None]]


def load_bag(path: Path) -> SoakBag:
    """The bag's /preop/* (first message each) and its /intraop/points paired with same-stamp fiducials."""
    topics = [TOPIC_PREOP, TOPIC_PREOP_FIDUCIALS, TOPIC_INTRAOP, TOPIC_INTRAOP_FIDUCIALS]
    first: dict[str, bytes] = {}
    clouds: list[tuple[int, bytes]] = []
    fiducials: dict[int, bytes] = {}
    for topic, _, _, raw in read_raw(path, topics):
        first.setdefault(topic, raw)
        if topic == TOPIC_INTRAOP:
            clouds.append((header_stamp_ns(raw), raw))
        elif topic == TOPIC_INTRAOP_FIDUCIALS:
            fiducials[header_stamp_ns(raw)] = raw
    if TOPIC_PREOP not in first or not clouds:
        raise InputError(f"{path} needs {TOPIC_PREOP} and {TOPIC_INTRAOP} messages for the soak")
    name = path.name.removesuffix(".mcap")
    frames = [(raw, fiducials.get(stamp)) for stamp, raw in clouds]
    return SoakBag(name, first[TOPIC_PREOP], first.get(TOPIC_PREOP_FIDUCIALS), frames)


def _byte_order(raw: bytes) -> str:
    return "little" if raw[1] == 1 else "big"  # CDR encapsulation: 0x0001 little-endian


def header_stamp_ns(raw: bytes) -> int:
    """The header stamp of a PointCloud2's CDR bytes (sec, nanosec lead the message)."""
    order = _byte_order(raw)
    return int.from_bytes(raw[4:8], order, signed=True) * 1_000_000_000 + int.from_bytes(raw[8:12], order)


def restamped(raw: bytes, stamp_ns: int) -> bytes:
    """The same message with another header stamp: looped frames stay tellable apart, as a camera's are."""
    order = _byte_order(raw)
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return raw[:4] + sec.to_bytes(4, order, signed=True) + nanosec.to_bytes(4, order) + raw[12:]


def drain(probe: GraphProbe) -> dict[str, list[Received]]:
    """Everything the probe recorded since the last drain, removed from it (a soak would hoard clouds)."""
    with probe.lock:
        taken = {topic: items for topic, items in probe.received.items() if items}
        for topic in taken:
            probe.received[topic] = []
    return taken


@dataclass
class _Minute:
    """What one minute gathered so far."""

    rss: list[float] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)
    published: int = 0
    errors: int = 0
    models: int = 0


@dataclass
class SoakRun:
    """The finished (or interrupted) soak: its rows and what the report says about the run."""

    rows: list[MinuteRow] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)  # every pose's, all minutes
    interrupted: bool = False
    failure: str = ""  # why it ended early (the node died), else ""
    error_messages: Counter = field(default_factory=Counter)  # "name: message" of each ERROR, all minutes
    rss_peak_mb: float = float("nan")
    ready_s: float = float("nan")  # process start -> first model warmed up
    exit_status: int | None = None


class Soak:
    """The loop: clouds at a fixed rate, the node's RSS every `sample_s`, a row every `minute_s`."""

    def __init__(
        self,
        probe: GraphProbe,
        node: NodeProcess,
        bags: Sequence[SoakBag],
        *,
        rate_hz: float,
        minute_s: float,
        sample_s: float,
        on_sample: Callable[[float, MinuteRow | None], None],
    ) -> None:
        self.probe, self.node, self.bags = probe, node, list(bags)
        self.period_s, self.minute_s, self.sample_s = 1.0 / rate_hz, minute_s, sample_s
        self.on_sample = on_sample  # (seconds since minute 1 began, the row just closed or None)
        self.run = SoakRun()
        self.minute = _Minute()
        self.sent: dict[int, float] = {}  # stamp -> when published, until its pose arrives
        self.counters: dict[str, int] = {}  # the node's latest *_clouds counters
        self.counters_then: dict[str, int] = {}  # ... at the start of this minute
        self.preop_answers = self.models_sent = 0  # warmed-up models the node reported, models published
        self.t0 = self.next_sample_s = self.cpu_then_s = self.minute_start_s = 0.0

    # ---------------------------------------------------------------- reading the probe
    def poll(self) -> None:
        taken = drain(self.probe)
        now = time.monotonic()
        for item in taken.get(TOPIC_POSE, []):
            sent_s = self.sent.pop(stamp_ns(item.msg), None)
            if sent_s is not None:
                self.minute.latency_ms.append((item.received_s - sent_s) * 1e3)
        for item in taken.get(TOPIC_DIAGNOSTICS, []):
            for status in item.msg.status:
                values = values_of(status)
                if status.name == DIAG_NAME and "received_clouds" in values:  # the periodic status
                    self.counters = {k: int(v) for k, v in values.items() if k.endswith("_clouds")}
                    continue
                error = level_of(status) == ERROR_LEVEL
                # an answer: warmed up, refused, or the same model as the one the node holds (bags of one liver)
                answered = "warm_up_ms" in values or values.get("unchanged") == "true" or error
                self.preop_answers += status.name == PREOP_DIAG_NAME and answered
                if error:
                    self.error(f"{status.name}: {status.message[:160]}")
        if len(self.sent) > 1000:  # clouds that got no pose (dropped, latest-only): forget the old ones
            self.sent = {s: t for s, t in self.sent.items() if now - t < 60.0}
        if now >= self.next_sample_s and self.t0:
            self.minute.rss.append(_rss_mb(self.node))
            self.next_sample_s += self.sample_s
            self.on_sample(now - self.t0, None)
        if not self.node.alive():
            raise NodeDied(f"register_node exited with status {self.node.proc.returncode} (see its logs)")

    def error(self, message: str) -> None:
        self.minute.errors += 1
        self.run.error_messages[message] += 1

    def wait_until(self, end_s: float, done: Callable[[], bool] = lambda: False) -> bool:
        """Keep reading the probe until `done()` or `end_s`; whether `done()` came true."""
        while not done():
            now = time.monotonic()
            if now >= end_s:
                return False
            time.sleep(min(POLL_S, end_s - now))
            self.poll()
        return True

    # ---------------------------------------------------------------- talking to the node
    def send_model(self, bag: SoakBag) -> None:
        """Publish the bag's model (and fiducials); the node answers with a preop diagnostic once warm."""
        self.probe.publish(TOPIC_PREOP, bag.preop)
        if bag.preop_fiducials is not None:
            self.probe.publish(TOPIC_PREOP_FIDUCIALS, bag.preop_fiducials)
        self.models_sent += 1
        self.minute.models += 1

    def stream(self, bag: SoakBag, end_s: float) -> None:
        """The bag's frames in a loop at the rate until `end_s`, each (with its fiducials) freshly stamped."""
        next_s = time.monotonic()
        index = 0
        while next_s < end_s:
            self.wait_until(next_s)
            cloud, fiducials = bag.frames[index % len(bag.frames)]
            stamp = time.time_ns()
            if fiducials is not None:
                self.probe.publish(TOPIC_INTRAOP_FIDUCIALS, restamped(fiducials, stamp))
            self.sent[stamp] = self.probe.publish(TOPIC_INTRAOP, restamped(cloud, stamp))
            self.minute.published += 1
            index += 1
            next_s += self.period_s
            if next_s < time.monotonic() - self.period_s:  # fell behind (a busy machine): no burst
                next_s = time.monotonic()
        self.wait_until(end_s)

    # ---------------------------------------------------------------- the minutes
    def close_minute(self, number: int) -> MinuteRow:
        m, now, cpu_s = self.minute, time.monotonic(), _cpu_s(self.node)
        lat = np.asarray(m.latency_ms, float)

        def delta(key: str) -> int:
            return self.counters.get(key, 0) - self.counters_then.get(key, 0)

        def pct(q: float) -> float:
            return float(np.percentile(lat, q)) if len(lat) else float("nan")

        rss = [v for v in m.rss if math.isfinite(v)]
        row = MinuteRow(
            minute=number,
            end_s=now - self.t0,
            rss_mb_max=max(rss, default=float("nan")),
            rss_mb_mean=float(np.mean(rss)) if rss else float("nan"),
            cpu_percent=(cpu_s - self.cpu_then_s) / max(now - self.minute_start_s, 1e-9) * 100,
            published=m.published,
            received=delta("received_clouds"),
            dropped=delta("dropped_clouds"),
            poses=len(lat),
            latency_ms_p50=pct(50),
            latency_ms_p95=pct(95),
            latency_ms_max=float(lat.max()) if len(lat) else float("nan"),
            errors=m.errors,
            models=m.models,
        )
        self.run.rows.append(row)
        self.run.latency_ms.extend(m.latency_ms)
        self.minute, self.counters_then = _Minute(), dict(self.counters)
        self.cpu_then_s, self.minute_start_s = cpu_s, now
        self.on_sample(now - self.t0, row)
        return row

    def play(self, minutes: int) -> None:
        """Minute 1 starts once the first model is warm; every minute then plays every bag once, for the
        same share of the minute, so the minutes compare like with like. The clouds keep coming while the
        node warms a new model up, as a camera's would."""
        self.send_model(self.bags[0])
        if not self.wait_until(time.monotonic() + START_TIMEOUT_S, lambda: self.preop_answers >= self.models_sent):
            raise InputError("register_node reported no preop model for the first bag (see its logs)")
        self.run.ready_s = time.monotonic() - self.node.started_s
        self.minute = _Minute()  # the first model's warm-up is before minute 1
        self.t0 = self.next_sample_s = self.minute_start_s = time.monotonic()
        self.counters_then, self.cpu_then_s = dict(self.counters), _cpu_s(self.node)
        share_s = self.minute_s / len(self.bags)
        for number in range(1, minutes + 1):
            for i, bag in enumerate(self.bags):
                start_s = self.t0 + (number - 1) * self.minute_s + i * share_s
                if len(self.bags) > 1 and (number, i) != (1, 0):
                    self.send_model(bag)
                self.stream(bag, start_s + share_s)
                if self.preop_answers < self.models_sent:  # counted, and on to the next bag
                    self.error(f"{bag.name}'s model not warmed up within its share of the minute")
            self.close_minute(number)


def _rss_mb(node: NodeProcess, name: str = "VmRSS") -> float:
    try:
        return node.rss_mb(name)
    except OSError:  # the process is gone
        return float("nan")


def _cpu_s(node: NodeProcess) -> float:
    try:
        return node.cpu_s()
    except OSError:
        return float("nan")


def run_soak(
    bags: Sequence[Path],
    out_dir: Path,
    *,
    minutes: int,
    rate_hz: float = 10.0,
    minute_s: float = 60.0,
    sample_s: float = 2.0,
    params: dict | None = None,
    on_sample: Callable[[float, MinuteRow | None], None] = lambda s, row: None,
) -> SoakRun:
    """Start register_node on an isolated domain and soak it; Ctrl-C ends it with the minutes done so
    far. Node logs go to out_dir/logs."""
    if not rate_hz > 0 or not minute_s > 0 or not sample_s > 0 or minutes < 1:
        raise InputError("--rate-hz, --minute-s and the sample period must be > 0, and at least one minute run")
    loaded = [load_bag(Path(b)) for b in bags]
    env = set_isolated_environment()
    log_dir = out_dir / "logs"
    node = NodeProcess("register_node", params or {}, env=env, log_dir=log_dir)
    probe = GraphProbe()
    soak = Soak(probe, node, loaded, rate_hz=rate_hz, minute_s=minute_s, sample_s=sample_s, on_sample=on_sample)
    try:
        intraop = probe.publishers[TOPIC_INTRAOP]
        probe.wait_for(lambda: intraop.get_subscription_count() > 0 or not node.alive(), START_TIMEOUT_S)
        if not node.alive() or intraop.get_subscription_count() == 0:
            last = (node.stderr().strip().splitlines() or ["no output"])[-1]
            raise InputError(f"register_node did not come up ({last}; see {log_dir}/register_node.stderr)")
        soak.play(minutes)
    except KeyboardInterrupt:
        soak.run.interrupted = True
    except NodeDied as exc:
        try:  # a Ctrl-C reaches the node too, and may end it before this process sees its KeyboardInterrupt
            time.sleep(0.5)
            soak.run.failure = f"{exc} in {log_dir}"
        except KeyboardInterrupt:
            soak.run.interrupted = True
    finally:
        soak.run.rss_peak_mb = _rss_mb(node, "VmHWM")
        soak.run.exit_status, _ = node.stop(signal.SIGINT)
        try:
            probe.close()
        except Exception:  # a Ctrl-C has already shut the probe's context down
            pass
    return soak.run
