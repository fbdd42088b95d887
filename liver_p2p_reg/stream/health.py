"""The intraop stream's health as diagnostic_updater users read it: frequency, stamp delay, silence -> STALE."""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from liver_p2p_reg.stream.outputs import DIAG_NAME, OK, STALE, WARN, Diagnostic

STREAM_DIAG_NAME = "liver_p2p_reg: intraop stream"
WINDOW_S = 5.0  # frequency and delay are measured over the clouds of the last WINDOW_S seconds
MAX_DELAY_WARN_MS = 1000.0  # a cloud older than this on arrival (its stamp vs the node's clock) -> WARN


class StreamHealth:
    """Arrival times and stamp delays of the intraop clouds; thread-safe (callbacks vs. the status timer)."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self.window_s = window_s
        self._lock = threading.Lock()
        self._arrivals: deque[tuple[float, float]] = deque()  # (monotonic s on arrival, stamp delay ms)
        self._last_s: float | None = None

    def on_cloud(self, now_s: float, stamp_ns: int, clock_ns: int) -> None:
        """A cloud arrived at monotonic `now_s`; `clock_ns` is the node's clock (ROS time) then."""
        delay_ms = (clock_ns - stamp_ns) * 1e-6 if stamp_ns > 0 else float("nan")
        with self._lock:
            self._arrivals.append((now_s, delay_ms))
            self._last_s = now_s
            self._forget(now_s)

    def silent_for_s(self, now_s: float) -> float | None:
        """Seconds since the last cloud, None before the first."""
        with self._lock:
            return None if self._last_s is None else now_s - self._last_s

    def status(self, now_s: float, stale_after_s: float, publishers: int | None = None) -> Diagnostic:
        """The stream's status: STALE before the first cloud and after `stale_after_s` of silence; WARN when
        clouds arrive older than MAX_DELAY_WARN_MS (a clock or a transport problem); else OK.

        `publishers`: how many publishers the node's subscription has matched, where known. A silence with one
        matched is a publisher that sends nothing or data that do not arrive (a publisher that ran before this
        node was killed and started again: docs/limitations.md), not a camera that is gone (a killed one stays
        matched until its discovery lease ends); the message says so.
        """
        with self._lock:
            self._forget(now_s)
            times = [t for t, _ in self._arrivals]
            delays = np.array([d for _, d in self._arrivals if np.isfinite(d)])
            last_s = self._last_s
        values = {"window_s": f"{self.window_s:.1f}", "clouds_in_window": str(len(times))}
        # frequency over the window, from the spacing of its clouds (one cloud: no rate yet)
        values["frequency_hz"] = (
            f"{(len(times) - 1) / (times[-1] - times[0]):.2f}" if len(times) > 1 and times[-1] > times[0] else "0.00"
        )
        if len(delays):
            values["delay_ms_mean"], values["delay_ms_max"] = f"{delays.mean():.1f}", f"{delays.max():.1f}"
        matched = ""
        if publishers is not None:
            values["publishers"] = str(publishers)
            if publishers > 0:
                matched = f"; {publishers} publisher{'s' if publishers > 1 else ''} matched, nothing arrives"
        if last_s is None:
            return Diagnostic(STALE, STREAM_DIAG_NAME, f"no intraop data yet (/intraop/points){matched}", values)
        silent_s = now_s - last_s
        values["silent_s"] = f"{silent_s:.1f}"
        if silent_s > stale_after_s:
            return Diagnostic(STALE, STREAM_DIAG_NAME, f"no intraop data for {silent_s:.1f} s{matched}", values)
        if len(delays) and delays.max() > MAX_DELAY_WARN_MS:
            message = f"intraop clouds arrive up to {delays.max():.0f} ms after their stamp"
            return Diagnostic(WARN, STREAM_DIAG_NAME, message, values)
        return Diagnostic(OK, STREAM_DIAG_NAME, f"intraop stream at {values['frequency_hz']} Hz", values)

    def _forget(self, now_s: float) -> None:
        while self._arrivals and self._arrivals[0][0] < now_s - self.window_s:
            self._arrivals.popleft()


def stale_when_silent(status: Diagnostic, silent_s: float | None, stale_after_s: float) -> Diagnostic:
    """The registration status, STALE when no cloud came for `stale_after_s` (its last values kept): a pose
    that old describes an organ that may have moved since."""
    if status.name != DIAG_NAME or status.level == STALE or silent_s is None or silent_s <= stale_after_s:
        return status
    message = f"no intraop data for {silent_s:.1f} s; last: {status.message}"
    return Diagnostic(STALE, status.name, message, {**status.values, "silent_s": f"{silent_s:.1f}"})
