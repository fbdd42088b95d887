"""Config: one source of defaults, the generated ROS parameter file, validation errors."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import pytest
import yaml

from liver_p2p_reg import config as config_module
from liver_p2p_reg.cli import main
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


def test_ros_parameter_file_is_generated_from_defaults() -> None:
    text = (ROOT / "config" / "registration.yaml").read_text()
    assert text == Config().to_ros_yaml(), "regenerate: liver-p2p config --ros --write config/registration.yaml --force"
    params = yaml.safe_load(text)["/**"]["ros__parameters"]
    assert Config.from_dict(params) == Config()


# Config's section views and the section each stands for.
VIEWS = {
    "runtime": config_module.RuntimeSection,
    "input_checks": config_module.InputSection,
    "preprocess": config_module.PreprocessSection,
    "features": config_module.FeatureSection,
    "p2p": config_module.P2PSection,
    "icp": config_module.IcpSection,
    "free_space": config_module.FreeSpaceSection,
    "verdict": config_module.VerdictSection,
    "deformation": config_module.DeformSection,
    "stream": config_module.StreamSection,
}


def test_every_field_is_in_one_section_and_the_views_carry_the_config() -> None:
    sections = [c for c in vars(config_module).values() if isinstance(c, type) and c.__name__.endswith("Section")]
    assert set(sections) == set(VIEWS.values()) == set(Config.__bases__)
    names = [f.name for section in sections for f in dataclasses.fields(section)]
    assert len(names) == len(set(names)), "a field declared in two sections (the later one would win silently)"
    assert set(names) == {f.name for f in dataclasses.fields(Config)}
    assert [f.name for f in dataclasses.fields(Config)][0] == "method"  # the sections' fields in pipeline order
    config = Config().replace(k=7, icp_max_iterations=3, mode="once", free_space_warn=0.5)
    for attr, section in VIEWS.items():
        view = getattr(config, attr)
        assert type(view) is section
        assert all(getattr(view, f.name) == getattr(config, f.name) for f in dataclasses.fields(section)), attr
    assert (config.p2p.k, config.icp.icp_max_iterations, config.stream.mode) == (7, 3, "once")
    assert config.verdict.free_space_warn == 0.5
    view = config.p2p
    view.k = 2  # a copy: a stage cannot change the Config
    assert config.k == 7 and config.p2p.k == 7


def test_from_yaml_accepts_plain_and_ros_forms(tmp_path: Path) -> None:
    plain = tmp_path / "plain.yaml"
    plain.write_text(
        "k: 7\nvoxel_size_norm: 0.05\nrefine_dummy_absent: null\n".replace("refine_dummy_absent: null\n", "")
    )
    assert Config.from_yaml(plain).k == 7
    ros = tmp_path / "ros.yaml"
    ros.write_text("register_node:\n  ros__parameters:\n    k: 3\n    mode: once\n")
    cfg = Config.from_yaml(ros)
    assert (cfg.k, cfg.mode) == (3, "once")


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"k": 0}, r"k must be in \[1, 64\]"),
        ({"k": "five"}, "k must be an integer"),
        ({"mode": "sometimes"}, "mode must be one of"),
        ({"selection": "best"}, "selection must be one of"),
        ({"no_such_key": 1}, "unknown configuration key"),
        ({"voxel_size_norm": -1}, "voxel_size_norm must be in"),
        ({"voxel_size_norm": 5}, "voxel_size_norm must be in"),
        ({"confidence_threshold": 1.5}, "confidence_threshold must be in"),
        ({"inlier_radius_norm": 0}, "inlier_radius_norm must be > 0"),
        ({"candidate_proposal": "maybe"}, "must be true or false"),
        ({"refine_candidates": 0}, r"refine_candidates must be in \[1, 256\]"),
        ({"screen_icp_points": 10}, "screen_icp_points must be >= 100"),
        ({"screen_icp_iterations": 0}, r"screen_icp_iterations must be in \[1, 1000\]"),
        ({"consensus_seeds": -1}, r"consensus_seeds must be in \[0, 4096\]"),
        ({"consensus_sigma_norm": 0}, "consensus_sigma_norm must be > 0"),
        ({"seed": -1}, "seed must be >= 0"),
        ({"seed": 2**31}, r"seed must be in \[0, 2147483647\]"),  # Open3D's seed() takes a C int
        ({"expected_extent_min_mm": 700.0}, "expected_extent_min_mm < expected_extent_max_mm"),
        ({"num_threads": 100_000}, r"num_threads must be in \[0, 256\]"),  # a huge pool crashed the process
        ({"num_threads": -4}, r"num_threads must be in \[0, 256\]"),
        ({"k": 100_000}, r"k must be in \[1, 64\]"),
        ({"normal_radius_norm": float("nan")}, r"normal_radius_norm must be in \(0, 2\]"),
        ({"icp_max_corr_norm": 0}, r"icp_max_corr_norm must be in \(0, 2\]"),
        ({"open3d_threads": 1000}, r"open3d_threads must be in \[1, 256\]"),
        ({"ransac_confidence": 2}, r"ransac_confidence must be in \(0, 1\]"),
        ({"icp_max_iterations": -3}, r"icp_max_iterations must be in \[1, 1000\]"),
        ({"ambiguity_residual_ratio": float("nan")}, "ambiguity_residual_ratio must be >= 1"),
        ({"max_input_points": 0}, "max_input_points must be >= 1000"),
        # NaN made a benchmark's OUT folder refuse every later run ("nan then, nan now": NaN != NaN)
        ({"outlier_std_ratio": float("nan")}, "outlier_std_ratio must be >= 0"),
        ({"temperature": float("inf")}, "temperature must be a finite number"),
        # held register_node's worker for minutes (3 GB, ~/reregister unanswered) once set as a parameter
        ({"deform_target_tets": 1_000_000}, r"deform_target_tets must be in \[60, 50000\]"),
        ({"outlier_neighbors": 10**6}, r"outlier_neighbors must be in \[3, 256\]"),
        ({"free_space_weight": float("inf")}, "free_space_weight must be a finite number"),
        # passed `> 0`; survey mode then fused nothing and blamed tracking
        ({"survey_voxel_mm": 1e-300}, r"survey_voxel_mm must be >= 0.1, got 1e-300"),
        ({"survey_voxel_mm": 0}, r"survey_voxel_mm must be >= 0.1"),
        # a YAML list for a path became the path "['a', 'b']", and a deformed bound silently went missing
        ({"deform_error_calibration_path": ["a", "b"]}, "must be a single text value, got a list of 2 items"),
        ({"selection": {"a": 1}}, "selection must be a single text value, got a mapping of 1 keys"),
        ({"deform": [True]}, "deform must be true or false, got a list of 1 items"),
        ({"k": [3]}, "k must be an integer, got a list of 1 items"),
        ({"max_rate_hz": {"x": 1}}, "max_rate_hz must be a number, got a mapping of 1 keys"),
    ],
)
def test_bad_values_are_one_line_errors(values: dict, message: str) -> None:
    with pytest.raises(InputError, match=message) as info:
        Config.from_dict(values)
    assert "\n" not in str(info.value)


def test_int_is_accepted_for_float_fields() -> None:
    assert Config.from_dict({"max_rate_hz": 5}).max_rate_hz == 5.0


def test_the_smallest_survey_voxel_is_accepted() -> None:
    assert Config.from_dict({"survey_voxel_mm": 0.1}).survey_voxel_mm == 0.1


def test_a_long_value_is_cut_short_in_the_error() -> None:
    for values in ({"selection": "x" * 10**6}, {"k": "9" * 10**5}, {"no_such_key_" + "y" * 10**5: 1}):
        with pytest.raises(InputError) as info:
            Config.from_dict(values)
        assert len(str(info.value)) < 200 and "..." in str(info.value), str(info.value)[:300]


def test_config_cli_does_not_overwrite_without_force(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    target = tmp_path / "params.yaml"
    assert main(["config", "--ros", "--write", str(target)]) == 0
    assert target.read_text() == Config().to_ros_yaml()
    target.write_text("mine")
    assert main(["config", "--write", str(target)]) == 2
    assert target.read_text() == "mine"
    assert "exists" in capsys.readouterr().err


def test_bad_yaml_file_is_reported(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("k: [1, 2\n")
    with pytest.raises(InputError, match="not valid YAML"):
        Config.from_yaml(bad)
    with pytest.raises(InputError, match="cannot read config"):
        Config.from_yaml(tmp_path / "missing.yaml")


@pytest.mark.parametrize(
    ("content", "message"),
    [
        # Each used to be an internal error (UnicodeDecodeError, TypeError) or to pass silently.
        pytest.param(
            b"\xff\xfe\x00garbage", r"config .*bad.yaml is not UTF-8 text \(byte 0xff at offset 0\)", id="utf8"
        ),
        pytest.param(
            b"register_node:\n  ros__parameters: 5\n",
            "register_node.ros__parameters must be a mapping .* got 5",
            id="ros-int",
        ),
        pytest.param(b"seed: 1\nk: 3\nseed: 2\n", r"not valid YAML: duplicate key 'seed' \(line 3\)", id="duplicate"),
        pytest.param(
            b"register_node:\n  ros__parameters:\n    k: 3\n    k: 4\n",
            r"duplicate key 'k' \(line 4\)",
            id="ros-duplicate",
        ),
        pytest.param(
            b"register_node:\n  ros__parameters:\n    k: 3\nseed: 4\n",
            "'seed' is not a node's `ros__parameters:` block",
            id="ros-stray-key",
        ),
        pytest.param(b"k: [1, 2\n", r"not valid YAML: expected ',' or '\]', but got .* \(line 2\)", id="syntax"),
    ],
)
def test_malformed_config_files_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture, content: bytes, message: str
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(content)
    with pytest.raises(InputError, match=message) as info:
        Config.from_yaml(bad)
    assert "\n" not in str(info.value)
    assert main(["config", "--config", str(bad)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def _laughs(levels: int) -> str:
    """A YAML "billion laughs": ten 'lol', then each level a list of ten aliases of the one below (10**levels)."""
    parts = ['&a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    parts += [f"&a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, levels)]
    return "[" + ", ".join(parts) + "]"


@pytest.mark.parametrize("key", ["deform", "selection", "k"])
def test_aliases_expanding_a_config_are_refused_at_once(tmp_path: Path, capsys: pytest.CaptureFixture, key) -> None:
    # 524 bytes that stand for 10**9 values: formatting them in the error took 77 s and 6.4 GB, then MemoryError
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(f"{key}: {_laughs(9)}\n")
    start = time.perf_counter()
    with pytest.raises(InputError, match=r"aliases \(\*name\) expand to more than 10000 values") as info:
        Config.from_yaml(bomb)
    assert time.perf_counter() - start < 2 and len(str(info.value)) < 200
    assert main(["config", "--config", str(bomb)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and len(err) < 250


def test_values_nested_a_thousand_deep_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "deep.yaml"
    path.write_text("k: " + "[" * 3000 + "]" * 3000 + "\n")  # was "internal error: RecursionError"
    with pytest.raises(InputError, match="nests its values too deeply"):
        Config.from_yaml(path)


def test_a_few_aliases_are_values_like_any_other(tmp_path: Path) -> None:
    path = tmp_path / "aliases.yaml"
    path.write_text("k: &three 3\nrefine_candidates: *three\n")
    assert (Config.from_yaml(path).k, Config.from_yaml(path).refine_candidates) == (3, 3)
    path.write_text(f"selection: {_laughs(2)}\n")  # 100 values: not a bomb, and not a text value either
    with pytest.raises(InputError, match="selection must be a single text value, got a list of 2 items"):
        Config.from_yaml(path)
    path.write_text("selection: [" + ", ".join(["lol"] * 20_000) + "]\n")  # no aliases: as long as its file
    with pytest.raises(InputError, match="selection must be a single text value, got a list of 20000 items"):
        Config.from_yaml(path)


def test_ros_node_blocks_giving_a_key_two_values_are_refused(tmp_path: Path) -> None:
    # merged silently, the last block winning: `deform` was false with no word
    path = tmp_path / "two_nodes.yaml"
    path.write_text("a:\n  ros__parameters:\n    deform: true\nb:\n  ros__parameters:\n    deform: false\n")
    with pytest.raises(InputError, match="'deform' is True under 'a' but False under 'b'; give it one value"):
        Config.from_yaml(path)
    path.write_text("a:\n  ros__parameters:\n    k: 3\nb:\n  ros__parameters:\n    k: 3.0\n")
    with pytest.raises(InputError, match="'k' is 3 under 'a' but 3.0 under 'b'"):  # written as two settings
        Config.from_yaml(path)
    path.write_text("a:\n  ros__parameters:\n    deform: true\n    k: 3\nb:\n  ros__parameters:\n    deform: true\n")
    assert (Config.from_yaml(path).deform, Config.from_yaml(path).k) == (True, 3)  # the same value twice: one


def test_yaml_merge_keys_may_override_and_empty_ros_blocks_are_defaults(tmp_path: Path) -> None:
    path = tmp_path / "merged.yaml"
    path.write_text("base: &base {k: 3, seed: 1}\nregister_node:\n  ros__parameters:\n    <<: *base\n    k: 5\n")
    with pytest.raises(InputError, match="'base' is not a node's"):  # a ROS file holds node blocks only
        Config.from_yaml(path)
    path.write_text("register_node:\n  ros__parameters:\n    <<: {k: 3, seed: 1}\n    k: 5\n")
    assert (Config.from_yaml(path).k, Config.from_yaml(path).seed) == (5, 1)
    path.write_text("register_node:\n  ros__parameters:\n")
    assert Config.from_yaml(path) == Config()
