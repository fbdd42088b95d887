"""Intake and scheduling of intraop clouds: the pending cloud (latest only), the mode, the rate limit, the fiducial wait."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from liver_p2p_reg.config import Config
from liver_p2p_reg.stream.fiducials import FiducialStore

# A cloud arriving at exactly max_rate_hz is due although its arrival jitters this share of a period early.
RATE_TOLERANCE = 0.05
# While ground truth is expected, a cloud waits at most this long for its own same-stamp fiducials
# (published just before it, on another topic) so its TRE is not lost to delivery order. The wait
# counts from the first cloud the pending slot held: a newer cloud replacing it does not restart it
# (else a stream faster than 1 / FIDUCIAL_WAIT_S without fiducials was never registered).
FIDUCIAL_WAIT_S = 0.3

# () -> (the cloud's finite points in mm, its raw point count); raises InputError for an unreadable
# cloud. Called only when the cloud is registered, so intake stays O(1) (ROS messages: ros.messages).
Decoder = Callable[[], tuple[np.ndarray, int]]


def finite_rows(points: np.ndarray) -> np.ndarray:
    """The rows of an (N, 3) array without NaN/inf."""
    return points[np.isfinite(points).all(axis=1)]


def points_decoder(points_mm: np.ndarray, n_raw: int | None = None) -> Decoder:
    """The Decoder of a cloud given as plain (N, 3) millimetre points (`n_raw`: the count it came with)."""
    count = len(points_mm) if n_raw is None else n_raw
    return lambda: (finite_rows(points_mm), count)


@dataclass
class IntraopCloud:
    """An intraop cloud as received: its header and how to get its points."""

    frame_id: str
    stamp_ns: int
    decode: Decoder
    received_s: float | None = None  # arrival on the caller's clock (None: not given)
    waiting_since_s: float | None = None  # arrival of the first cloud in the pending slot (fiducial wait)


class Intake:
    """Which cloud is registered when: latest only, per the mode and the rate limit; thread-safe.

    One cloud is pending at a time (a newer one replaces it: `dropped`); the rate limit counts
    from the arrival of the last registered cloud (its start time when no arrival is known):
    counting from start times let waits creep up frame after frame.
    """

    def __init__(self, fiducials: FiducialStore) -> None:
        self._lock = threading.Lock()
        self._fiducials = fiducials
        self._pending: IntraopCloud | None = None
        self._latest: IntraopCloud | None = None  # the last cloud registered, decoded (~/reregister)
        self._rate_ref_s: float | None = None
        self._have_model = False  # a preop model is there to register against
        self._once_done = False
        self.received = 0
        self.dropped = 0  # clouds superseded before they were registered (latest-only)

    def new_model(self) -> None:
        """A preop model arrived: clouds can be registered, and `once` mode registers once more."""
        with self._lock:
            self._have_model = True
            self._once_done = False

    def mark_once_done(self) -> None:
        """`once` mode gave its pose: no cloud is due by itself until the next model."""
        self._once_done = True

    def receive(self, cloud: IntraopCloud) -> bool:
        """Make `cloud` the pending one (the older is dropped); whether a model is there to register against."""
        with self._lock:
            self.received += 1
            cloud.waiting_since_s = cloud.received_s
            if self._pending is not None:
                self.dropped += 1  # latest-only: the older cloud is never registered
                if cloud.received_s is not None and self._pending.waiting_since_s is not None:
                    cloud.waiting_since_s = min(cloud.received_s, self._pending.waiting_since_s)
            self._pending = cloud
            return self._have_model

    def keep_latest(self, cloud: IntraopCloud) -> None:
        """The cloud now being registered, decoded: what ~/reregister takes when nothing is pending."""
        with self._lock:
            self._latest = cloud

    def next_due_s(self, config: Config) -> float | None:
        """When the pending cloud becomes due (the caller's clock; -inf: now), None if it never will
        by itself (nothing pending, no model, on_demand, once already done)."""
        with self._lock:
            cloud = self._pending
            if cloud is None or not self._have_model or config.mode == "on_demand":
                return None
            if config.mode == "once" and self._once_done:
                return None
            due_s = -np.inf
            if config.mode == "continuous" and self._rate_ref_s is not None:
                due_s = self._rate_ref_s + (1.0 - RATE_TOLERANCE) / config.max_rate_hz
        waiting_since_s = cloud.waiting_since_s
        if waiting_since_s is not None and self._fiducials.expected() and not self._fiducials.has_frame(cloud.stamp_ns):
            due_s = max(due_s, waiting_since_s + FIDUCIAL_WAIT_S)
        return due_s

    def due(self, config: Config, now_s: float) -> bool:
        """Whether the pending cloud is due at `now_s`."""
        due_s = self.next_due_s(config)
        return due_s is not None and now_s >= due_s - 1e-9

    def take_due(self, config: Config, now_s: float) -> IntraopCloud | None:
        """The pending cloud if it is due at `now_s` (the rate limit then counts from its arrival), else None."""
        if not self.due(config, now_s):
            return None
        with self._lock:
            cloud, self._pending = self._pending, None
            if cloud is not None:
                self._rate_ref_s = now_s if cloud.received_s is None else cloud.received_s
        return cloud

    def take_latest(self, now_s: float) -> IntraopCloud | None:
        """The pending cloud, else the last registered one, whatever the mode (~/reregister); None if none came."""
        with self._lock:
            cloud = self._pending or self._latest
            self._pending = None
            self._rate_ref_s = now_s
        return cloud

    def release(self) -> None:
        """Lift the rate limit and the fiducial wait of the pending cloud (the end of a replayed bag)."""
        with self._lock:
            self._rate_ref_s = None
            if self._pending is not None:
                self._pending.received_s = None  # no fiducials are coming after the bag's end
                self._pending.waiting_since_s = None
