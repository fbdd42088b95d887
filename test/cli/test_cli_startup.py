"""A fast, quiet start: what each command imports, errors before heavy work, one-line argparse errors."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from synthetic_cases import partial_case

from liver_p2p_reg.cli import main
from liver_p2p_reg.cloud_io import save_points

HEAVY = ("torch", "open3d", "scipy", "matplotlib", "sklearn")
# Runs the command line in a fresh interpreter and reports what it imported and how it exited.
PROBE = f"""import sys
from liver_p2p_reg.cli import main
try:
    rc = main(sys.argv[1:])
except SystemExit as exc:
    rc = exc.code
heavy = sorted(m for m in {HEAVY} if m in sys.modules)
print("PROBE", rc, ",".join(heavy), file=sys.stderr)
"""


def probe(*argv: str, cwd: Path | None = None) -> tuple[int, set[str], list[str]]:
    """(exit status, heavy modules imported, other stderr lines) of `liver-p2p ARGV` in a new process."""
    proc = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, timeout=300, cwd=cwd)
    lines = proc.stderr.splitlines()
    tag = [line for line in lines if line.startswith("PROBE ")]
    assert tag, proc.stderr
    _, rc, heavy = (tag[-1].split(" ") + [""])[:3]
    return int(rc), set(filter(None, heavy.split(","))), [line for line in lines if not line.startswith("PROBE ")]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("startup")
    source, target, *_ = partial_case(np.random.default_rng(3))
    save_points(tmp / "source.ply", source)
    save_points(tmp / "target.ply", target)
    return {"dir": tmp, "source": str(tmp / "source.ply"), "target": str(tmp / "target.ply")}


def test_help_imports_no_heavy_library() -> None:
    for argv in (["--help"], ["register", "--help"], ["benchmark", "--help"], ["bag", "make", "--help"]):
        rc, heavy, _ = probe(*argv)
        assert (rc, heavy) == (0, set()), argv


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["register", "{source}", "{target}", "--seed", "abc"], "argument --seed: invalid int value: 'abc'"),
        (["register", "{source}"], "the following arguments are required: TARGET"),
        (["register", "{dir}/missing.ply", "{target}"], "file not found"),
        (["register", "{source}", "{dir}/missing.ply"], "file not found"),
        (["register", "{source}", "{target}", "--method", "magic"], "unknown method 'magic'"),
        (["register", "{source}", "{target}", "--k", "0"], "k must be in [1, 64]"),
        (["register", "{source}", "{target}", "-o", "{source}"], "is an input of this command"),
        (["register", "{source}", "{target}", "--method", "track"], "--initial-transform"),
        (["bogus"], "invalid choice: 'bogus'"),
    ],
)
def test_argument_errors_are_one_line_before_any_heavy_import(files: dict, argv: list[str], message: str) -> None:
    rc, heavy, err = probe(*(a.format(**files) for a in argv))
    assert rc == 2 and heavy == set()
    assert len(err) == 1 and err[0].startswith("liver-p2p") and ": error: " in err[0] and message in err[0], err


def test_seed_abc_is_one_line_in_process(files: dict, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["register", files["source"], files["target"], "--seed", "abc"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "usage:" not in err and "see `liver-p2p register --help`" in err


def test_swapped_clouds_are_refused_before_torch_is_imported(files: dict) -> None:
    """The default (learned) method: the complete/partial check comes before torch and the weights."""
    rc, heavy, err = probe("register", files["target"], files["source"])
    assert rc == 2 and "more than 1.25x the source" in err[-1]
    assert "torch" not in heavy and "open3d" not in heavy


def test_learned_method_on_ply_files_needs_no_open3d(files: dict) -> None:
    """PLY/PCD are read without Open3D; only the `-icp` refinement (normals) and the Open3D methods import it."""
    rc, heavy, _ = probe("-q", "register", files["source"], files["target"], "--method", "learned-p2p")
    assert rc == 0 and "torch" in heavy and "open3d" not in heavy
    rc, heavy, _ = probe("-q", "register", files["source"], files["target"], "--method", "fpfh-ransac")
    assert rc == 0 and "open3d" in heavy and "torch" not in heavy and "sklearn" not in heavy


def test_default_method_gets_the_icp_normals_from_a_child_and_the_same_pose(files: dict) -> None:
    """learned-p2p-icp: Open3D (the ICP's source normals) is imported by a child process while this one
    imports torch (prefetch.py); the pose is bit for bit the one computed in one process."""
    out = files["dir"] / "default.json"
    rc, heavy, _ = probe("-q", "register", files["source"], files["target"], "-o", str(out), "--force")
    assert rc == 0 and "torch" in heavy and "open3d" not in heavy
    from liver_p2p_reg import Config, Registrar
    from liver_p2p_reg.cloud_io import load_points

    alone = Registrar(Config()).register(load_points(files["source"]), load_points(files["target"]))
    written = json.loads(out.read_text())
    assert written["transform"] == alone.T_target_source.tolist()
    assert written["screened"] == [c.to_json_dict() for c in alone.screened]


def test_prefetched_normals_are_the_in_process_ones(files: dict) -> None:
    from liver_p2p_reg.cloud_io import load_points
    from liver_p2p_reg.registration.features.fpfh import outward_normals
    from liver_p2p_reg.registration.prefetch import BackgroundOpen3D, take_prefetched

    points = load_points(files["source"]) / 100.0
    job = BackgroundOpen3D(points, 0.1)
    assert take_prefetched(points + 0.0, 0.2, 30) is None  # other parameters: not this job
    child = take_prefetched(points.copy(), 0.1, 30)
    job.close()
    assert child is not None and child.tobytes() == outward_normals(points, 0.1).tobytes()
    assert not job.folder.exists()  # cleaned up once closed


def test_a_job_folder_left_by_a_killed_process_is_removed_by_the_next_job(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGKILL leaves a job's temporary folder behind; the next job removes those whose process is gone, and only
    those (a live process's folder, another program's folder stay)."""
    import tempfile

    from liver_p2p_reg.registration.prefetch import FOLDER_PREFIX, BackgroundOpen3D, remove_orphaned_folders

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(gone.stdout)  # a process that has ended
    orphan = tmp_path / f"{FOLDER_PREFIX}{dead_pid}_abcdefgh"
    live = tmp_path / f"{FOLDER_PREFIX}{os.getppid()}_abcdefgh"
    # an older version's names (8 random characters, some looking like a pid), names no process can have
    others = [f"{FOLDER_PREFIX}{n}" for n in ("abcdefgh", "42_k3j9a", "99999999999_abcdefgh", "\u00b2_abcdefgh")]
    for folder in (orphan, live, *(tmp_path / n for n in others)):
        folder.mkdir()
        (folder / "points.npy").write_bytes(b"x")
    assert remove_orphaned_folders(tmp_path) == [orphan]
    assert not orphan.exists() and live.exists() and all((tmp_path / n).exists() for n in others)
    # a job sweeps the temporary directory before it names its own folder for this process
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    orphan.mkdir()
    job = BackgroundOpen3D(np.zeros((40, 3)), 0.1)
    try:
        assert not orphan.exists() and live.exists()
        assert job.folder.parent == tmp_path and job.folder.name.startswith(f"{FOLDER_PREFIX}{os.getpid()}_")
    finally:
        job.close()


@pytest.fixture(scope="module")
def small_view(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A 15 % crop: below the default's `ransac_candidate_visibility`, so its registration wants RANSAC's pose."""
    tmp = tmp_path_factory.mktemp("small_view")
    source, target, *_ = partial_case(np.random.default_rng(5), share=0.15)
    save_points(tmp / "source.ply", source)
    save_points(tmp / "target.ply", target)
    return {"dir": tmp, "source": str(tmp / "source.ply"), "target": str(tmp / "target.ply")}


def test_prefetched_ransac_pose_is_the_in_process_one(small_view: dict) -> None:
    """A child computes FPFH + RANSAC's pose of each small view from the raw clouds; `fpfh_ransac` takes it for
    exactly that prepared pair and those settings (bit for bit its own), and for anything else computes its own."""
    from liver_p2p_reg import Config
    from liver_p2p_reg.cloud_io import load_points
    from liver_p2p_reg.registration.baselines import fpfh_ransac
    from liver_p2p_reg.registration.prefetch import BackgroundOpen3D, take_prefetched_ransac
    from liver_p2p_reg.registration.preprocess import preprocess_pair, source_normalization

    config = Config()
    source, target = load_points(small_view["source"]), load_points(small_view["target"])
    prep = preprocess_pair(source, target, config, {})
    assert prep.visibility < config.ransac_candidate_visibility
    here = fpfh_ransac(prep.source, prep.target, config, {})
    half = preprocess_pair(source, target[: len(target) // 2], config, {})  # another view, not in the job
    full = source_normalization(source).apply(source)
    job = BackgroundOpen3D(full, config.normal_radius_norm, source_mm=source, views_mm=[target], config=config)
    try:
        assert take_prefetched_ransac(prep.source, prep.target, config.replace(seed=1)) is None  # other settings
        child = take_prefetched_ransac(prep.source, prep.target, config)
        assert isinstance(child, np.ndarray) and child.tobytes() == here.tobytes()
        assert take_prefetched_ransac(half.source, half.target, config) is None  # waits for the child, then None
        assert job.child.poll() == 0
    finally:
        job.close()
    # a child that died before it wrote anything: nothing is taken from it, nothing waits for it
    job = BackgroundOpen3D(full, config.normal_radius_norm, source_mm=source, views_mm=[target], config=config)
    try:
        job.child.kill()
        job.child.wait()
        assert take_prefetched_ransac(prep.source, prep.target, config) is None
        assert fpfh_ransac(prep.source, prep.target, config, {}).tobytes() == here.tobytes()  # computed here
    finally:
        job.close()


def test_default_method_on_a_small_view_needs_no_open3d_here_and_gives_the_same_pose(small_view: dict) -> None:
    """The default on a view below `ransac_candidate_visibility`: FPFH + RANSAC's candidate pose comes from the
    child that imports Open3D (with the ICP normals) while this process imports torch; this process never imports
    Open3D, and the result is bit for bit the one computed in one process."""
    out = small_view["dir"] / "default.json"
    rc, heavy, _ = probe("-q", "register", small_view["source"], small_view["target"], "-o", str(out), "--force")
    assert rc == 0 and "torch" in heavy and "open3d" not in heavy
    from liver_p2p_reg import Config, Registrar
    from liver_p2p_reg.cloud_io import load_points

    alone = Registrar(Config()).register(load_points(small_view["source"]), load_points(small_view["target"]))
    written = json.loads(out.read_text())
    assert "ransac" in written["runtime_ms"] and "fpfh-ransac" in [c["name"] for c in written["candidates"]]
    assert written["transform"] == alone.T_target_source.tolist()
    assert written["screened"] == [c.to_json_dict() for c in alone.screened]


def test_a_large_clouds_normals_come_from_a_child_and_leave_the_gil_free() -> None:
    """Open3D holds the GIL while it estimates normals: for a node's warm-up of a large model that stalled its
    signal handling (a SIGTERM waited for it). From OFF_PROCESS_POINTS up a child computes them: bit for bit the
    in-process normals, while another thread of this process keeps running."""
    import threading

    from liver_p2p_reg.registration.features.fpfh import OFF_PROCESS_POINTS, local_outward_normals, outward_normals

    d = np.random.default_rng(0).normal(size=(OFF_PROCESS_POINTS, 3))
    points = d / np.linalg.norm(d, axis=1, keepdims=True) * [1.0, 0.7, 0.5]

    def largest_gap_s(work) -> tuple[float, float, np.ndarray]:
        """(the longest a ticking thread waited between ticks, the work's duration, its result) while `work` runs
        on another thread."""
        out, gaps, done = [], [0.0], threading.Event()
        worker = threading.Thread(target=lambda: (out.append(work()), done.set()))
        start = last = time.perf_counter()
        worker.start()
        while not done.is_set():
            time.sleep(0.002)
            now = time.perf_counter()
            gaps.append(now - last)
            last = now
        worker.join()
        return max(gaps), last - start, out[0]

    gap_local_s, local_s, here = largest_gap_s(lambda: local_outward_normals(points, 0.1))
    gap_child_s, _, child = largest_gap_s(lambda: outward_normals(points, 0.1))
    assert child.tobytes() == here.tobytes()
    assert gap_local_s > 0.5 * local_s  # the stall this avoids: in process, the ticks wait for Open3D
    assert gap_child_s < 0.5 * local_s, (gap_child_s, local_s)


def test_the_method_table_is_explicit_and_plugins_are_added_by_a_call() -> None:
    from liver_p2p_reg.errors import InputError
    from liver_p2p_reg.registration.methods import METHODS, Method, add_method, method_names, remove_method
    from liver_p2p_reg.registration.registrar import available_methods

    assert method_names() == available_methods() == sorted(METHODS)
    for name, row in METHODS.items():  # each row runs one pipeline
        assert sum((bool(row.features), bool(row.estimate), row.prior, row.oracle)) == 1, name
        assert not (row.p2p and not row.features), name
    with pytest.raises(InputError, match="built in"):
        add_method("icp", Method(doc="x", run=lambda *a: None))
    add_method("plugin-test", Method(doc="a plug-in", run=lambda *a: None))
    assert "plugin-test" in available_methods()
    remove_method("plugin-test")
    assert "plugin-test" not in available_methods()


def test_one_loaded_network_serves_every_registrar(files: dict) -> None:
    from liver_p2p_reg import Config, Registrar
    from liver_p2p_reg.cloud_io import load_points

    source, target = load_points(files["source"]), load_points(files["target"])
    registrars = [Registrar(Config(method="learned")) for _ in range(2)]
    for registrar in registrars:
        registrar.register(source, target)
    models = [next(v for k, v in r.cache.items() if k.startswith("learned_provider:")).model for r in registrars]
    assert models[0] is models[1]


def test_cli_logging_keeps_other_libraries_below_warning() -> None:
    """scikit-fem's INFO lines would interleave with the dataset/benchmark progress bars."""
    assert main(["config"]) == 0
    assert logging.getLogger("skfem").getEffectiveLevel() >= logging.WARNING
    assert logging.getLogger("liver_p2p_reg.phantom.testset").getEffectiveLevel() == logging.INFO


def test_open3d_core_import_is_quiet_and_leaves_its_other_parts_importable() -> None:
    code = (
        "import sys\n"
        "from liver_p2p_reg.o3d import o3d_module\n"
        "o3d = o3d_module()\n"
        "assert 'sklearn' not in sys.modules and 'dash' not in sys.modules\n"
        "assert o3d.utility.get_verbosity_level() == o3d.utility.VerbosityLevel.Error\n"
        "import open3d.ml, open3d.visualization\n"
        "assert callable(open3d.visualization.draw_plotly)\n"
        "print('ok')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.stdout.strip() == "ok", proc.stderr


def test_readme_names_only_bags_that_exist_and_the_formats_the_reader_takes() -> None:
    import re

    from liver_p2p_reg.cloud_io import POINT_FORMATS

    root = Path(__file__).resolve().parents[2]
    readme = (root / "README.md").read_text()
    named = set(re.findall(r"bags/([A-Za-z0-9_.]+[A-Za-z0-9])", readme)) - {"README.md"}
    assert named and all((root / "bags" / name).is_dir() for name in named), named
    sentence = readme[readme.index("Inputs are ") :].split(" (meshes")[0]
    assert re.findall(r"\.[a-z]+", sentence) == list(POINT_FORMATS)


def test_every_phony_make_target_has_a_rule() -> None:
    makefile = (Path(__file__).resolve().parents[2] / "Makefile").read_text()
    phony = next(line for line in makefile.splitlines() if line.startswith(".PHONY:")).split(":")[1].split()
    for target in phony:
        assert f"\n{target}:" in makefile, target


def test_every_method_has_its_own_colour_and_the_default_is_not_the_oracles() -> None:
    from liver_p2p_reg.bench.plots import method_style
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.registration.methods import method_names

    colours = {m: method_style(m)["color"] for m in method_names()}
    assert len(set(colours.values())) == len(colours)
    oracle, default = method_style("procrustes"), method_style(Config().method)
    assert oracle["linestyle"] == "--" and default["linestyle"] == "-" and oracle["color"] != default["color"]


def test_json_result_keeps_its_keys(files: dict, capsys: pytest.CaptureFixture) -> None:
    """Scripts read these keys; the new ones (source, target, status, warnings) are additions."""
    assert main(["register", files["source"], files["target"], "--method", "fpfh-p2p"]) == 0
    keys = set(json.loads(capsys.readouterr().out))
    assert {"transform", "method", "residual_mm", "runtime_ms", "candidates", "uncertainty_mm", "ambiguous"} <= keys
    assert {"source", "target", "status", "warnings"} <= keys


def test_overlay_labels_what_each_distance_is() -> None:
    """The residual line and the histogram measure different things: both say which; far points are counted."""
    from liver_p2p_reg.overlay import HISTOGRAM_MAX_MM, draw_registration
    from liver_p2p_reg.plotting import pyplot
    from liver_p2p_reg.result import RegistrationResult

    source, target, *_ = partial_case(np.random.default_rng(2))
    far = target[:7] + [0.0, 0.0, 80.0]  # seven points far off the surface
    result = RegistrationResult(np.eye(4), "track", residual_mm=2.5, uncertainty_mm=3.0)
    fig = draw_registration(source, np.vstack([source[: len(target)], far]), result, residual_warn_mm=4.0)
    labels = fig.axes[3].get_legend_handles_labels()[1]
    assert any(label.startswith("residual_mm 2.50 (voxelized, outliers removed)") for label in labels)
    assert any(label.startswith("mean of these") for label in labels)
    assert f"\u2265 {HISTOGRAM_MAX_MM:g} mm: 7 points" in labels
    assert "track = ICP refinement of the previous pose" in fig._suptitle.get_text()
    pyplot().close(fig)
