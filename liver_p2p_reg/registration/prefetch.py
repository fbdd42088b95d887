"""Open3D's share of a one-shot registration computed in a child process, so the command imports torch meanwhile.

A `liver-p2p register` process spends most of its time importing torch (for the matcher) and
Open3D (for the ICP's source normals and, on small views, FPFH + RANSAC's candidate pose), one
after the other on one core. Both depend only on the inputs, so the command starts a child that
imports Open3D and computes them with the very same functions (`features.fpfh.local_outward_normals`,
`baselines.fpfh_ransac` after `preprocess.preprocess_pair`) while this process imports torch;
`outward_normals` and `fpfh_ransac` then take the child's result for exactly those points (compared
bit for bit) and settings (the same configuration values). Same functions, same input bits: the same
results. Whatever the child did not deliver (it failed, was not started, took longer than
WAIT_MAX_S) is computed here, as before.

`normals_in_child` is the blocking form, for large clouds: Open3D's normal estimation holds the GIL
(1.5 s for 300 k points), which would stall a node's signal handling and callbacks; waiting on a child's
pipe does not.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from liver_p2p_reg.config import Config

PACKAGE_PARENT = str(Path(__file__).resolve().parents[2])  # the folder holding the package
# The child runs `child_main` of this module. On Linux it dies with the thread that started it, so a node
# stopped mid-warm-up leaves no orphan computing on.
CHILD = """import ctypes, sys
try:
    ctypes.CDLL(None).prctl(1, 9)  # PR_SET_PDEATHSIG, SIGKILL
except (OSError, AttributeError):
    pass
sys.path.insert(0, sys.argv[1])
from liver_p2p_reg.registration.prefetch import child_main
child_main(sys.argv[2:])
"""
POLL_S = 0.002  # how often a waiting lookup looks for the child's next file
# A child slower than this (a hung one) is no longer waited for: the result is computed here. Generous: the
# child's slowest share, RANSAC on a large view, takes seconds.
WAIT_MAX_S = 60.0
_PENDING: list[BackgroundOpen3D] = []
# A job's files live in a temporary folder named for the process that made it; a process killed outright (SIGKILL,
# the OOM killer) cannot remove its own, so the next job removes those whose process is gone. (A process in another
# PID namespace sharing /tmp looks gone: its registration then computes Open3D's share itself, the same result.)
FOLDER_PREFIX = "liver_p2p_open3d_"
MKDTEMP_CHARS = 8  # the random part tempfile.mkdtemp appends to a prefix


def child_command(*argv: str) -> list[str]:
    """The command line of a CHILD running `child_main(argv)`."""
    return [sys.executable, "-c", CHILD, PACKAGE_PARENT, *argv]


def child_main(argv: list[str]) -> None:
    """The child's work: `normals RADIUS MAX_NN` (points on stdin, normals on stdout) or `job FOLDER`
    (BackgroundOpen3D)."""
    if argv[0] == "job":
        _run_job(Path(argv[1]))
        return
    from liver_p2p_reg.registration.features.fpfh import local_outward_normals

    radius, max_nn = argv[1:3]
    normals = local_outward_normals(np.load(io.BytesIO(sys.stdin.buffer.read())), float(radius), int(max_nn))
    out = io.BytesIO()
    np.save(out, normals)
    sys.stdout.buffer.write(out.getvalue())


def digest(points: np.ndarray) -> str:
    """A cloud's identity: its shape and float64 bits."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    return f"{points.shape}:{hashlib.sha256(points.tobytes()).hexdigest()}"


def _save_whole(path: Path, **arrays: np.ndarray) -> None:
    """Write an .npy (one array) or .npz under a temporary name, then rename: a reader never sees half a file."""
    part = path.with_name(f"part_{path.name}")
    if len(arrays) == 1 and path.suffix == ".npy":
        np.save(part, next(iter(arrays.values())))
    else:
        np.savez(part, **arrays)
    os.replace(part, path)


def _run_job(folder: Path) -> None:
    """The ICP's normals first (every `-icp` registration needs them), then RANSAC's pose of each small view."""
    from liver_p2p_reg.registration.features.fpfh import local_outward_normals

    job = json.loads((folder / "job.json").read_text())
    points = np.load(folder / "points.npy")
    _save_whole(folder / "normals.npy", normals=local_outward_normals(points, job["radius"], job["max_nn"]))
    if not job["views"]:
        return
    from liver_p2p_reg.cloud_io import clean_points
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.errors import InputError, RegistrationError
    from liver_p2p_reg.registration.baselines import fpfh_ransac
    from liver_p2p_reg.registration.preprocess import preprocess_pair

    config = Config.from_dict(job["config"])
    cache: dict = {}
    try:  # as the Registrar and the pipeline prepare them
        source = clean_points(np.load(folder / "source.npy"), "source", min_points=config.min_points)
    except InputError:
        return  # the registrations report it
    for i in range(job["views"]):
        try:
            target = clean_points(np.load(folder / f"view{i}.npy"), "target", min_points=config.min_points)
            prep = preprocess_pair(source, target, config, cache)
        except InputError:
            continue  # the registration reports it
        if not prep.visibility < config.ransac_candidate_visibility:
            continue  # no candidate is wanted for this view
        keys = {"source": np.array(digest(prep.source)), "target": np.array(digest(prep.target))}
        try:
            _save_whole(folder / f"ransac{i}.npz", pose=fpfh_ransac(prep.source, prep.target, config, cache), **keys)
        except RegistrationError as exc:
            _save_whole(folder / f"ransac{i}.npz", error=np.array(str(exc)), **keys)


def _alive(pid: int) -> bool:
    """Whether a process with this id exists (one of another user's counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def remove_orphaned_folders(parent: Path | None = None) -> list[Path]:
    """Remove the job folders in `parent` (the temporary directory) whose process no longer exists; those
    removed. Best effort: folders of another naming (an older version's `liver_p2p_open3d_XXXXXXXX`), whose
    owner is alive or that cannot be removed are left alone, and nothing here stops a registration."""
    removed = []
    try:
        for folder in Path(parent or tempfile.gettempdir()).glob(f"{FOLDER_PREFIX}*_*"):
            pid, _, rest = folder.name[len(FOLDER_PREFIX) :].partition("_")
            ours = pid.isascii() and pid.isdigit() and len(pid) <= 9 and len(rest) == MKDTEMP_CHARS
            if ours and folder.is_dir() and not _alive(int(pid)):
                shutil.rmtree(folder, ignore_errors=True)
                if not folder.exists():
                    removed.append(folder)
    except Exception:  # a folder that vanished, a name no process has: never worth a failed registration
        pass
    return removed


class BackgroundOpen3D:
    """`outward_normals(points, radius, max_nn)` and, for each view below `ransac_candidate_visibility`, RANSAC's
    pose (`fpfh_ransac` on the prepared pair), being computed by a child process. `views_mm`: none for the
    normals alone. Raises OSError when the job's files cannot be written or the child cannot start (its
    folder removed): the caller goes on without it."""

    def __init__(
        self,
        points: np.ndarray,
        radius: float,
        max_nn: int = 30,
        *,
        source_mm: np.ndarray | None = None,
        views_mm: list[np.ndarray] = (),
        config: Config | None = None,
    ) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.radius, self.max_nn = float(radius), int(max_nn)
        self.settings = config.to_dict() if views_mm else None  # what the child rebuilds its Config from
        self.poses: dict[tuple[str, str], np.ndarray | str] = {}  # RANSAC's records read so far
        self.read: set[str] = set()
        remove_orphaned_folders()
        self.folder = Path(tempfile.mkdtemp(prefix=f"{FOLDER_PREFIX}{os.getpid()}_"))
        try:
            np.save(self.folder / "points.npy", self.points)
            for i, view in enumerate(views_mm):
                np.save(self.folder / f"view{i}.npy", view)
            if views_mm:
                np.save(self.folder / "source.npy", source_mm)
            job = {"radius": self.radius, "max_nn": self.max_nn, "views": len(views_mm), "config": self.settings}
            (self.folder / "job.json").write_text(json.dumps(job))
            self.child = subprocess.Popen(
                child_command("job", str(self.folder)),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        except OSError:
            shutil.rmtree(self.folder, ignore_errors=True)
            raise
        _PENDING.append(self)

    def matches(self, points: np.ndarray, radius: float, max_nn: int) -> bool:
        points = np.asarray(points)
        return (
            (radius, max_nn) == (self.radius, self.max_nn)
            and points.shape == self.points.shape
            and points.dtype == np.float64
            and np.ascontiguousarray(points).tobytes() == self.points.tobytes()
        )

    def _wait_for(self, found) -> bool:
        """Wait until `found()` holds, the child has ended (then one last look) or WAIT_MAX_S have passed;
        whether it holds."""
        deadline = time.monotonic() + WAIT_MAX_S
        while not found():
            if self.child.poll() is not None:
                return bool(found())
            if time.monotonic() > deadline:
                return False
            time.sleep(POLL_S)
        return True

    def normals(self) -> np.ndarray | None:
        """The child's normals (waits for them), or None when it failed."""
        path = self.folder / "normals.npy"
        if not self._wait_for(path.exists):
            return None
        try:
            normals = np.load(path)
        except (OSError, ValueError):
            return None
        return normals if normals.shape == self.points.shape else None

    def ransac(self, source: np.ndarray, target: np.ndarray) -> np.ndarray | str | None:
        """The child's RANSAC pose for exactly this prepared pair (waits for it), its error message when
        RANSAC found none, or None when the child did not compute it."""
        key = (digest(source), digest(target))

        def found() -> bool:
            for path in sorted(self.folder.glob("ransac*.npz")):
                if path.name in self.read:
                    continue
                try:
                    with np.load(path) as record:
                        value = record["pose"] if "pose" in record else str(record["error"])
                        self.poses[(str(record["source"]), str(record["target"]))] = value
                    self.read.add(path.name)
                except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
                    continue  # not readable: as if the child had not computed it
            return key in self.poses

        if self.settings is None or not self._wait_for(found):
            return None
        value = self.poses[key]
        return value.copy() if isinstance(value, np.ndarray) else value

    def close(self) -> None:
        """Stop the child if it still runs and remove its files (idempotent)."""
        if self.child.poll() is None:
            self.child.kill()
            self.child.wait()
        shutil.rmtree(self.folder, ignore_errors=True)
        if self in _PENDING:
            _PENDING.remove(self)


def take_prefetched(points: np.ndarray, radius: float, max_nn: int) -> np.ndarray | None:
    """The normals a child computed for exactly these points and parameters, else None."""
    for job in list(_PENDING):
        if job.matches(points, radius, max_nn):
            return job.normals()
    return None


def take_prefetched_ransac(source: np.ndarray, target: np.ndarray, config: Config) -> np.ndarray | str | None:
    """`fpfh_ransac(source, target, config, ...)` as a child computed it for exactly this prepared pair and
    these settings: the pose, or the message of its RegistrationError; None when no child did."""
    settings = config.to_dict() if _PENDING else None
    for job in list(_PENDING):
        if job.settings is not None and job.settings == settings:
            ready = job.ransac(source, target)
            if ready is not None:
                return ready
    return None


def normals_in_child(points: np.ndarray, radius: float, max_nn: int = 30) -> np.ndarray | None:
    """`outward_normals(points, radius, max_nn)` computed by a child process and waited for here without
    holding the GIL (through pipes, no files); None when the child fails."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    sent = io.BytesIO()
    np.save(sent, points)
    try:
        done = subprocess.run(
            child_command("normals", repr(float(radius)), str(int(max_nn))),
            input=sent.getvalue(),
            capture_output=True,
            check=False,
        )
        normals = np.load(io.BytesIO(done.stdout)) if done.returncode == 0 else None
    except (OSError, ValueError):
        return None
    return normals if normals is not None and normals.shape == points.shape else None
