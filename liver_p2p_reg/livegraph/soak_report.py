"""The soak benchmark's results without rclpy: per-minute rows, the two criteria, the CSV, the plot, the Markdown."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from liver_p2p_reg.bags.replay import fmt, markdown_table
from liver_p2p_reg.plotting import pyplot

REFERENCE_MINUTE = 2  # minute 1 holds the start-up: imports, the first model, the allocator's growth
RSS_GROWTH_MAX_PCT = 5.0  # the targets, minute 2 -> the last minute
P95_RATIO_MAX = 1.2


@dataclass
class MinuteRow:
    """One minute of the soak: register_node's memory and CPU, what it answered and how fast."""

    minute: int  # 1-based
    end_s: float  # end of the minute, s since the first cloud
    rss_mb_max: float  # the largest VmRSS sample of the minute (what the criterion uses)
    rss_mb_mean: float
    cpu_percent: float  # register_node's CPU time over the minute, % of one core
    published: int  # clouds published on /intraop/points
    received: int  # the node's received_clouds counter, this minute's increase (/diagnostics)
    dropped: int  # the node's dropped_clouds counter (superseded before registered, latest-only)
    poses: int  # /registration/pose received this minute (matched to a published cloud)
    latency_ms_p50: float  # publish -> pose received, over this minute's poses
    latency_ms_p95: float
    latency_ms_max: float
    errors: int  # diagnostics at level ERROR (registration attempts and preop models)
    models: int  # preop models published this minute (bag changes)


CSV_FIELDS = [f.name for f in fields(MinuteRow)]


@dataclass
class Criteria:
    """The issue's two criteria over minutes `reference`..`last`; `*_pass` is None where not evaluable."""

    reference: int
    last: int
    rss_ref_mb: float
    rss_last_mb: float
    rss_growth_pct: float
    rss_pass: bool | None
    p95_ref_ms: float
    p95_worst_ms: float
    p95_worst_minute: int
    p95_ratio: float
    p95_pass: bool | None

    @property
    def passed(self) -> bool:
        return bool(self.rss_pass) and bool(self.p95_pass)


def evaluate(
    rows: Sequence[MinuteRow],
    reference: int = REFERENCE_MINUTE,
    rss_growth_max_pct: float = RSS_GROWTH_MAX_PCT,
    p95_ratio_max: float = P95_RATIO_MAX,
) -> Criteria:
    """RSS growth from minute `reference` to the last minute (%, the minutes' max RSS) and the worst p95
    latency of minutes `reference`..last over the reference minute's; PASS within the limits."""
    nan = float("nan")
    ref = next((r for r in rows if r.minute == reference), None)
    if ref is None:  # too short a run: nothing to compare
        return Criteria(reference, rows[-1].minute if rows else 0, nan, nan, nan, None, nan, nan, 0, nan, None)
    later = [r for r in rows if r.minute >= reference]
    last = later[-1]
    growth = (last.rss_mb_max - ref.rss_mb_max) / ref.rss_mb_max * 100 if ref.rss_mb_max > 0 else nan
    timed = [r for r in later if math.isfinite(r.latency_ms_p95)]
    worst = max(timed, key=lambda r: r.latency_ms_p95) if timed else None
    ratio = worst.latency_ms_p95 / ref.latency_ms_p95 if worst and ref.latency_ms_p95 > 0 else nan
    return Criteria(
        reference=reference,
        last=last.minute,
        rss_ref_mb=ref.rss_mb_max,
        rss_last_mb=last.rss_mb_max,
        rss_growth_pct=growth,
        rss_pass=None if not math.isfinite(growth) else growth <= rss_growth_max_pct,
        p95_ref_ms=ref.latency_ms_p95,
        p95_worst_ms=worst.latency_ms_p95 if worst else nan,
        p95_worst_minute=worst.minute if worst else 0,
        p95_ratio=ratio,
        p95_pass=None if not math.isfinite(ratio) else ratio <= p95_ratio_max,
    )


def verdict(passed: bool | None) -> str:
    return "n/a" if passed is None else ("PASS" if passed else "MISS")


def write_csv(rows: Sequence[MinuteRow], path: Path) -> None:
    """One row per minute, the fields of MinuteRow."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: round(v, 3) if isinstance(v, float) else v for k, v in asdict(row).items()})


def read_csv(path: Path) -> list[MinuteRow]:
    """The rows `write_csv` wrote."""
    kinds = {f.name: f.type for f in fields(MinuteRow)}
    with open(path, newline="") as fh:
        return [
            MinuteRow(**{k: int(v) if kinds[k] == "int" else float(v) for k, v in item.items()})
            for item in csv.DictReader(fh)
        ]


def plot(rows: Sequence[MinuteRow], path: Path, criteria: Criteria | None = None) -> None:
    """RSS (max and mean) and latency (p95 and p50) against the minute; the limits as dashed lines."""
    plt = pyplot()
    minutes = [r.minute for r in rows]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.5, 6), sharex=True)
    top.plot(minutes, [r.rss_mb_max for r in rows], "o-", label="RSS, max of the minute")
    top.plot(minutes, [r.rss_mb_mean for r in rows], ".--", alpha=0.6, label="RSS, mean of the minute")
    bottom.plot(minutes, [r.latency_ms_p95 for r in rows], "o-", color="C3", label="latency p95")
    bottom.plot(minutes, [r.latency_ms_p50 for r in rows], ".--", color="C2", alpha=0.7, label="latency p50")
    if criteria is not None and math.isfinite(criteria.rss_ref_mb):
        top.axhline(
            criteria.rss_ref_mb * (1 + RSS_GROWTH_MAX_PCT / 100),
            color="grey",
            ls=":",
            label=f"minute {criteria.reference} + {RSS_GROWTH_MAX_PCT:g} %",
        )
    if criteria is not None and math.isfinite(criteria.p95_ref_ms):
        bottom.axhline(
            criteria.p95_ref_ms * P95_RATIO_MAX,
            color="grey",
            ls=":",
            label=f"{P95_RATIO_MAX:g} x minute {criteria.reference}'s p95",
        )
    top.set_ylabel("register_node RSS (MB)")
    bottom.set_ylabel("publish -> pose (ms)")
    bottom.set_xlabel("minute")
    from matplotlib.ticker import MaxNLocator  # matplotlib is loaded by now

    bottom.xaxis.set_major_locator(MaxNLocator(integer=True))
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    top.set_title("Soak: the live ROS 2 graph, per minute")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def minutes_table(rows: Sequence[MinuteRow]) -> str:
    header = [
        "minute",
        "RSS MB max",
        "RSS MB mean",
        "CPU %",
        "poses",
        "latency ms p50",
        "p95",
        "max",
        "clouds sent",
        "received",
        "dropped",
        "errors",
        "models",
    ]
    body = [
        [
            str(r.minute),
            fmt(r.rss_mb_max, 1),
            fmt(r.rss_mb_mean, 1),
            fmt(r.cpu_percent, 0),
            str(r.poses),
            fmt(r.latency_ms_p50, 0),
            fmt(r.latency_ms_p95, 0),
            fmt(r.latency_ms_max, 0),
            str(r.published),
            str(r.received),
            str(r.dropped),
            str(r.errors),
            str(r.models),
        ]
        for r in rows
    ]
    return markdown_table(header, body)


def criteria_table(c: Criteria) -> str:
    header = ["criterion", "target", "measured", "met"]
    span = f"minute {c.reference} -> minute {c.last}"
    body = [
        [
            f"RSS growth, {span} (max RSS of each minute)",
            f"<= {RSS_GROWTH_MAX_PCT:g} %",
            f"{c.rss_growth_pct:+.1f} % ({fmt(c.rss_ref_mb, 1)} -> {fmt(c.rss_last_mb, 1)} MB)"
            if math.isfinite(c.rss_growth_pct)
            else "-",
            verdict(c.rss_pass),
        ],
        [
            f"worst p95 latency of minutes {c.reference}..{c.last} / minute {c.reference}'s",
            f"<= {P95_RATIO_MAX:g}x",
            f"{c.p95_ratio:.2f}x (minute {c.p95_worst_minute}: {fmt(c.p95_worst_ms, 0)} ms; "
            f"minute {c.reference}: {fmt(c.p95_ref_ms, 0)} ms)"
            if math.isfinite(c.p95_ratio)
            else "-",
            verdict(c.p95_pass),
        ],
    ]
    return markdown_table(header, body)


def overall(rows: Sequence[MinuteRow], values: Sequence[float]) -> str:
    """p50 / p95 of the poses of all minutes (the latencies themselves, not the minutes' percentiles)."""
    if not len(values):
        return "no pose arrived"
    p50, p95 = np.percentile(values, [50, 95])
    return f"{sum(r.poses for r in rows)} poses, latency p50 {p50:.0f} ms, p95 {p95:.0f} ms over all minutes"


def report_markdown(rows: Sequence[MinuteRow], c: Criteria, info: dict, png_link: str) -> str:
    """The whole results page: how it was run, the criteria, the plot, the per-minute table."""
    bags = info["bags"]
    lines = [
        "# Soak: the live ROS 2 graph for many minutes",
        "",
        f"Generated by `{info['command']}` ({info['date']}); {info['machine']}; load average (1 min) "
        f"{fmt(info.get('load_start', float('nan')))} at the start, {fmt(info.get('load_end', float('nan')))} at "
        "the end (other work on the machine makes the latency noisy). Do not edit: rerun the command.",
        "",
        f"`register_node` ran as a process on an isolated domain ({info['node']}). The probe published the "
        f"intraop clouds of {len(bags)} bundled bag{'s' if len(bags) != 1 else ''} at {info['rate_hz']:g} Hz "
        f"({', '.join(f'`{b}`' for b in bags)}), each bag {info['bag_s']:.1f} s per minute with its own "
        "`/preop/points` model (a new model when the bag changes, the clouds going on while it warms up), "
        "every minute the same bags in the same order, each cloud and its fiducials stamped with the wall clock when sent. RSS: VmRSS sampled every "
        f"{info['sample_s']:g} s, the minute's max and mean; latency: cloud published -> its "
        "`/registration/pose` received; received/dropped: the node's own counters on `/diagnostics` "
        f"(continuous mode registers at most `max_rate_hz` = {info['max_rate_hz']:g} clouds/s, latest only).",
        "",
        f"{len(rows)} minutes of {info['minute_s']:g} s{' (interrupted)' if info.get('interrupted') else ''}; "
        f"{info['overall']}; register_node peak RSS (VmHWM) {fmt(info.get('rss_peak_mb', float('nan')), 1)} MB; "
        f"process start -> first model warmed up {fmt(info.get('ready_s', float('nan')), 1)} s.",
        "",
        "## Criteria",
        "",
        criteria_table(c),
        "",
        f"![register_node RSS and latency per minute]({png_link})",
        "",
        "## Per minute",
        "",
        minutes_table(rows),
        "",
        "## Errors",
        "",
        *error_lines(info.get("errors", {})),
        "",
    ]
    return "\n".join(lines)


def error_lines(messages: dict[str, int]) -> list[str]:
    """One line per distinct ERROR diagnostic (or the soak's own complaint), with its count."""
    if not messages:
        return ["None."]
    return [f"- {n} x {text}" for text, n in sorted(messages.items(), key=lambda kv: -kv[1])]


def readme_block(rows: Sequence[MinuteRow], c: Criteria, info: dict, link: str) -> str:
    """The README's SOAK block: one paragraph, the numbers in the results page."""
    rss = f"{c.rss_growth_pct:+.1f} %" if math.isfinite(c.rss_growth_pct) else "-"
    ratio = f"{c.p95_ratio:.2f}x" if math.isfinite(c.p95_ratio) else "-"
    return (
        f"**Soak** (`{info['command']}`): the live graph for {len(rows)} minutes, {len(info['bags'])} bundled "
        f"bags at {info['rate_hz']:g} Hz; register_node's RSS minute {c.reference} -> {c.last} {rss} "
        f"(<= {RSS_GROWTH_MAX_PCT:g} %: {verdict(c.rss_pass)}), worst p95 latency {ratio} minute "
        f"{c.reference}'s (<= {P95_RATIO_MAX:g}x: {verdict(c.p95_pass)}); {info['overall']}. "
        f"Per minute, plot and machine: [{Path(link).name}]({link})."
    )
