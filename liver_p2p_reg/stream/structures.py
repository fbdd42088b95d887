"""The node core's subsurface structures: the latest set received (points with label ids, and their names)."""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.structures_io import Structure


def fallback_label(label_id: int) -> str:
    """The name of a label id whose name has not arrived (or belongs to another set)."""
    return f"label_{int(label_id)}"


class StructureStore:
    """The structures register_node moves with every pose: the latest set received, whatever the model.

    They come from the loader with its model (same stamp), as two latched messages in any order: the
    points with a label id each (/preop/structures) and the names (/preop/structure_labels, index =
    label id, stamped like the points). The latest points replace the earlier set, and an empty cloud
    clears it: a loader always publishes one, so a new loader's model comes with its own structures or
    none. A model from elsewhere (a bag without structures) keeps the set. Names stamped for another
    set are not used: until its own arrive, a structure is called `label_<id>`.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._structures: list[Structure] = []
        self._stamp_ns: int | None = None  # of the points
        self._names: dict[int, str] = {}  # label id -> name
        self._names_stamp_ns: int | None = None  # None: names that fit any set

    def set_structures(self, structures: Sequence[Structure], stamp_ns: int | None = None) -> None:
        """Structures already named (the command line's --structures, tests); replaces the set."""
        with self._lock:
            self._structures = list(structures)
            self._stamp_ns = None if stamp_ns is None else int(stamp_ns)
            self._names, self._names_stamp_ns = {s.label_id: s.label for s in structures}, self._stamp_ns

    def set_points(self, points_mm: np.ndarray, label_ids: np.ndarray, stamp_ns: int) -> int:
        """The points of a /preop/structures cloud (mm, preop frame) and their label ids; returns the structures."""
        points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        ids = np.asarray(label_ids).reshape(-1)
        if len(ids) != len(points):
            raise InputError(f"{len(points)} structure points but {len(ids)} label ids")
        if not np.isfinite(points).all():
            raise InputError("structure points must all be finite")
        groups = [(int(i), points[ids == i]) for i in np.unique(ids)]
        with self._lock:
            self._structures = [Structure(fallback_label(i), p, i) for i, p in groups]
            self._stamp_ns = int(stamp_ns)
        return len(groups)

    def set_names(self, names: Sequence[str], stamp_ns: int | None = None) -> None:
        """The label names (index = label id) of the set stamped `stamp_ns` (None: whatever set)."""
        with self._lock:
            self._names = {i: str(n) for i, n in enumerate(names)}
            self._names_stamp_ns = None if stamp_ns is None else int(stamp_ns)

    def current(self) -> list[Structure]:
        """The structures to move with the next pose, named as far as their names are known."""
        with self._lock:
            structures, names = self._structures, self._names
            fits = self._names_stamp_ns is None or self._names_stamp_ns == self._stamp_ns
        if not fits:
            return structures
        return [
            Structure(names[s.label_id], s.points_mm, s.label_id, s.path) if s.label_id in names else s
            for s in structures
        ]
