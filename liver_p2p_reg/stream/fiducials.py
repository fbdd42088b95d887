"""Ground-truth fiducials of the node core, kept with the preop model and the header stamp they came with."""

from __future__ import annotations

import threading

import numpy as np

MAX_FRAMES = 16  # intraop fiducial sets kept (by stamp) for clouds still to be registered
MAX_MODELS = 4  # preop fiducial sets kept (by stamp) for models that may still arrive


class FiducialStore:
    """Pairs fiducials with their model and cloud by header stamp; never guesses.

    Preop fiducials belong to the preop model with the same header stamp (the loader and the
    bags stamp both alike) and are dropped with it; intraop fiducials belong to the cloud with the same stamp and to
    the current model: a new model forgets them. Without an exact pair the TRE is absent,
    never computed against another frame's or another model's markers.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._preop: dict[int, np.ndarray] = {}  # model stamp -> (F, 3) mm, preop frame
        self._intraop: dict[int, np.ndarray] = {}  # cloud stamp -> (F, 3) mm, sensor frame
        self._model_stamp: int | None = None
        self._paired_once = False  # a cloud of the current model has been paired (or not) already

    def new_model(self, stamp_ns: int) -> None:
        """A new preop model arrived: the old model's markers and earlier intraop fiducials described
        the old one (bags share stamps, so a same-stamp model gets only markers that come after it)."""
        with self._lock:
            if self._model_stamp is not None:
                self._preop.pop(self._model_stamp, None)
            self._model_stamp = int(stamp_ns)
            self._intraop.clear()
            self._paired_once = False

    def forget_frames(self) -> None:
        """The current model came again (same content and stamp): its markers stay, the intraop fiducials
        go, as with a new model (a cloud whose own fiducials never come must not meet an earlier set)."""
        with self._lock:
            self._intraop.clear()
            self._paired_once = False

    def set_preop(self, points_mm: np.ndarray | None, stamp_ns: int | None = None) -> None:
        """Preop fiducials of the model stamped `stamp_ns` (None: the current model)."""
        with self._lock:
            stamp = self._model_stamp if stamp_ns is None else int(stamp_ns)
            stamp = 0 if stamp is None else stamp
            if points_mm is None:
                self._preop.pop(stamp, None)
                return
            self._preop[stamp] = np.asarray(points_mm, float).reshape(-1, 3)
            while len(self._preop) > MAX_MODELS:
                self._preop.pop(next(iter(self._preop)))  # the oldest inserted

    def set_intraop(self, points_mm: np.ndarray, stamp_ns: int) -> None:
        """Intraop fiducials of the cloud stamped `stamp_ns` (sensor frame, mm)."""
        with self._lock:
            self._intraop[int(stamp_ns)] = np.asarray(points_mm, float).reshape(-1, 3)
            while len(self._intraop) > MAX_FRAMES:
                self._intraop.pop(min(self._intraop))

    @property
    def preop_mm(self) -> np.ndarray | None:
        """The current model's fiducials, or None."""
        with self._lock:
            return self._preop.get(0 if self._model_stamp is None else self._model_stamp)

    def status(self) -> dict[str, str]:
        """For the periodic status: how many preop fiducials the current model has (an oracle, a TRE need them)."""
        fid = self.preop_mm
        return {"preop_fiducials": "0" if fid is None else str(len(fid))}

    def expected(self) -> bool:
        """Whether a cloud's own intraop fiducials are likely on their way: the current model has
        markers and either intraop fiducials came for it or no cloud of it has been paired yet."""
        with self._lock:
            model = 0 if self._model_stamp is None else self._model_stamp
            return model in self._preop and (bool(self._intraop) or not self._paired_once)

    def has_frame(self, stamp_ns: int) -> bool:
        with self._lock:
            return int(stamp_ns) in self._intraop

    def pair(self, stamp_ns: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(preop, intraop) fiducials for the cloud stamped `stamp_ns`; (None, None) without an exact,
        same-shaped pair."""
        with self._lock:
            fid_s = self._preop.get(0 if self._model_stamp is None else self._model_stamp)
            fid_t = self._intraop.get(int(stamp_ns))
            self._paired_once = True
        if fid_s is None or fid_t is None or fid_s.shape != fid_t.shape:
            return None, None
        return fid_s, fid_t
