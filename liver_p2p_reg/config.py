"""The one typed configuration object shared by the CLI, bag replay and ROS nodes.

Defaults live here and only here. `config/registration.yaml` (the ROS parameter file) is
generated from these defaults with `liver-p2p config --ros` and a test checks that it matches.

Flat outside, sectioned inside: users write flat names (`Config(k=5)`, YAML keys, ROS parameters); each field is
declared once, with its default, in the section of the stage that reads it, Config inherits all sections, and a
stage takes its section's view (`config.p2p`, a copy), so no stage keeps defaults of its own.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, TypeVar

import yaml

from liver_p2p_reg.config_io import from_mapping, quoted, read_yaml_mapping

# Choices and ranges validated in `Config.validate` (a module of their own: the CLI lists the choices in --help)
from liver_p2p_reg.config_ranges import (  # noqa: E402
    CLOSED,
    DEVICES,
    FINITE,
    HALF_OPEN,
    MAX_SEED,
    MINIMUMS,
    NODE_MODES,
    SELECTION_RULES,
)
from liver_p2p_reg.errors import InputError


@dataclass
class RuntimeSection:
    """What runs and where."""

    # Default: the method the latest benchmarks favour (README "Default method" gives the numbers).
    method: str = "learned-p2p-icp"
    device: str = "cpu"
    num_threads: int = 0  # torch CPU threads per registration; 0: OMP_NUM_THREADS, else the usable CPUs
    # Linux/glibc: keep freed large buffers in the process heap (alloc.py); faster frames on large
    # views, identical results, the process keeps its peak memory
    reuse_freed_memory: bool = True
    seed: int = 0


@dataclass
class InputSection:
    """Input checks: what a cloud must look like to be registered at all."""

    min_points: int = 100  # fewer valid intraop points than this is an error
    max_input_points: int = 1_000_000  # clouds this large are voxelized before anything else (bounded memory)
    expected_extent_min_mm: float = 20.0  # clouds smaller than this look like wrong units
    expected_extent_max_mm: float = 600.0  # clouds larger than this look like wrong units


@dataclass
class PreprocessSection:
    """Preprocessing: outlier removal, normalization, voxelization."""

    # intraop cloud: drop points whose mean distance to their neighbours is above mean + this
    # many std (flying pixels, specks); 0 disables
    outlier_std_ratio: float = 2.0
    outlier_neighbors: int = 20
    voxel_size_norm: float = 0.04  # voxel edge in normalized (unit-sphere) units
    # a target may voxelize to at most this many times the source's voxels: a full view with
    # sensor noise occupies a few percent more voxels than the model; swapped files are ~2-5x
    max_target_ratio: float = 1.25


@dataclass
class FeatureSection:
    """Point features (FPFH, the learned matcher's weights) and the FPFH+RANSAC baseline."""

    normal_radius_norm: float = 0.1  # normal estimation radius (normalized units)
    fpfh_radius_norm: float = 0.25  # FPFH feature radius (normalized units)
    weights_path: str = ""  # empty: the weights bundled with the package
    ransac_max_corr_norm: float = 0.05  # FPFH+RANSAC max correspondence distance (paper)
    ransac_max_iterations: int = 100000
    ransac_confidence: float = 0.999
    # OpenMP threads of Open3D's RANSAC, FGR and ICP (methods fpfh-ransac*, fgr*, icp, and the
    # default's RANSAC candidate on small views). RANSAC's threads
    # draw from one shared generator, so on more than 1 the same seed can give another pose run to run;
    # 1 is reproducible (RANSAC ~8 % slower, docs/results/speed.md)
    open3d_threads: int = 1


@dataclass
class P2PSection:
    """Dual-softmax matching and the P2P module: patch candidates, their fits, the selection."""

    temperature: float = 0.1  # dual-softmax temperature applied to the score matrix
    confidence_threshold: float = 0.0  # minimum dual-softmax confidence of a kept match
    mutual_only: bool = False  # True: strict mutual-NN matches (the paper); False: each row's best, confidence-weighted
    k: int = 5  # number of P2P patch candidates
    selection: str = "closest-point"  # P2P candidate selection rule
    inlier_radius_norm: float = 0.05  # tau of the inlier-count rule (normalized units)
    candidate_proposal: bool = True  # False: patch nodes by FPS over the whole source
    max_patch_rows: int = 1024  # P2P matches an even subsample of about this many rows per patch; 0: all (the paper)
    refit_iterations: int = 6  # robust re-fits of each candidate on its own consistent matches; 0: off (the paper)
    refit_radius_start_norm: float = 0.3  # first re-fit radius (normalized units) ...
    refit_radius_end_norm: float = 0.04  # ... shrinking geometrically to this one
    # each P2P candidate also gets a fit started from a pairwise-distance consensus among its
    # this many most confident matches (an extra candidate; robust when wrong matches are the
    # majority); 0: off (the paper)
    consensus_seeds: int = 64
    consensus_sigma_norm: float = 0.1  # pairwise-distance mismatch at which two matches stop being compatible


@dataclass
class IcpSection:
    """ICP: the screening of P2P's candidates and the refinement of the chosen one."""

    # `-icp` feature pipelines: a short ICP screens up to this many distinct P2P candidates and the
    # one that fits best after it is refined (small smooth views fit several poses almost equally
    # well before ICP); 1: refine only the candidate P2P chose
    refine_candidates: int = 6
    screen_icp_points: int = 400  # screening ICP: intraop points ...
    screen_icp_iterations: int = 15  # ... and iterations per candidate
    # learned-p2p-icp: the FPFH + RANSAC pose is screened beside P2P's candidates when the view's estimated
    # visibility (intraop / preop voxels) is below this (0: never, the default before the switch bit for bit;
    # 0.2 was chosen by docs/benchmark_real/RULE_ransac_candidate_threshold.md; 1: always)
    ransac_candidate_visibility: float = 0.2
    # learned-p2p-icp: the poses of a search of the whole preop surface (registration/surface_search.py) are
    # screened beside those when the view's estimated visibility is below this (0: never, the default until
    # docs/benchmark_real/RULE_surface_search.md chooses; 1: always)
    surface_search_visibility: float = 0.0
    # learned-p2p-icp on those small views: the screened candidates whose short residual is within this factor
    # of the lowest are each refined by the full ICP and the one the elastic stage fits best wins (0: off; 1.5 chosen
    # on validation sets, docs/benchmark_real/RULE_deformed_screening.md; needs the preop model's elastic model)
    contender_judge_ratio: float = 0.0
    icp_max_iterations: int = 50
    icp_max_corr_norm: float = 0.1  # ICP correspondence gate (normalized units)
    icp_trim_ratio: float = 0.8  # robust ICP keeps this share of closest pairs
    icp_max_points: int = 1000  # ICP uses an even subsample of at most this many target points (speed)


@dataclass
class FreeSpaceSection:
    """Free space: used when the target's sensor origin is known (node, --sensor-origin, camera crops)."""

    # intraop clouds arrive in their sensor's own frame (the ROS convention), so the sensor sits at
    # (0, 0, 0) there and free space is checked; false for clouds transformed into another frame
    sensor_at_frame_origin: bool = True
    # moved preop surface this far in front of the observed one along the rays violates free space (freespace.py)
    free_space_band_mm: float = 10.0
    # selection, screening and the ambiguity test rank hypotheses by residual x (1 + this x violation), violation =
    # share of the view's footprint the pose contradicts; chosen on validation camera crops (docs/freespace/rule.md)
    free_space_weight: float = 0.5


@dataclass
class VerdictSection:
    """Confidence and verdict: when a registration is reported WARN or ambiguous."""

    residual_warn_mm: float = 4.0  # mean closest-point residual above this -> WARN
    # pose uncertainty (expected organ-point displacement under the fit's misfit, confidence.py) above this -> WARN;
    # chosen on validation livers (scripts/calibrate_confidence.py; README "Confidence" has the test-set effect)
    uncertainty_warn_mm: float = 15.0
    free_space_warn: float = 0.1  # a pose contradicting more than this share of the view's footprint -> WARN
    # a rival hypothesis (after ICP screening if the method screens), residual within this factor of the best ...
    ambiguity_residual_ratio: float = 1.2
    ambiguity_pose_mm: float = 15.0  # ... and a pose differing by this much -> ambiguous
    # per-point error bounds (error_bound.py), calibrated by `liver-p2p calibrate-bound` on validation sets:
    error_coverage: float = 0.9  # the share of true positions each bound contains (one the calibration holds)
    structure_error_warn_mm: float = 10.0  # a structure's (no structures: the interior's) bound above this -> WARN
    error_calibration_path: str = ""  # empty: the calibrations bundled with the package (single views; survey frames)


@dataclass
class DeformSection:
    """The non-rigid stage after the rigid pose (deform.py): the preop model's elastic modes pulled onto the view."""

    deform: bool = False  # run the stage after every registration (the rigid pose is published first)
    # modes, regularization and gain chosen on validation sets of both deformation families (docs/deform/choice.md)
    deform_modes: int = 24  # lowest non-rigid elastic modes of the preop model kept as the deformation basis
    deform_target_tets: int = 6000  # tetrahedra of the preop model's mesh (built once per model)
    deform_regularization: float = 0.01  # strain-energy weight: mm^2 of mean squared residual per mm^2 of mode 1
    deform_iterations: int = 15  # Gauss-Newton steps (the pairs are recomputed each step)
    deform_min_points: int = 200  # fewer view points than this: no deformation ("too little overlap")
    deform_max_residual_mm: float = 5.0  # rigid residual above this: a gross pose is not deformed
    deform_min_gain: float = 0.0  # the residual must fall by this share, else the rigid result stands
    # the held-out-half check (deform_fit.holdout_gain): fitted on each half of the view, does the deformation
    # predict the other half better than the rigid correction alone, by this share? Four more fits. Chosen with
    # deform_min_gain by amendment 3 of docs/deform/rule.md: a deformation must predict, not only fit
    deform_holdout_check: bool = True
    deform_min_holdout_gain: float = 0.0
    deform_max_displacement_mm: float = 25.0  # a larger displacement anywhere is implausible: rigid result
    # the error bound of the deformed positions (`liver-p2p calibrate-bound --deformed`); empty: the bundled ones (of
    # single-frame fits, and of survey mode's fused-survey fits: scripts/calibrate_survey_bound.py)
    deform_error_calibration_path: str = ""


@dataclass
class StreamSection:
    """The node logic (register_node, bag replay): mode, rate, tracking, survey."""

    mode: str = "continuous"
    max_rate_hz: float = 2.0  # continuous mode: at most this many registrations per s
    stale_after_s: float = 5.0  # register_node: status STALE ("no intraop data") after this long without a cloud
    # continuous mode: refine the last good pose by ICP on the next cloud (method `track`) and
    # keep it if it fits as well as the last full registration; else run the full method
    track_previous_pose: bool = True
    track_residual_ratio: float = 1.2  # a tracked pose is kept if its residual <= this x the full registration's
    track_max_frames: int = 10  # a full registration at least every this many frames
    # survey mode (survey.py): frames tracked and fused into one surface in the preop frame, which is
    # registered globally again each time its visibility has grown by survey_step
    survey_step: float = 0.05
    survey_voxel_mm: float = 2.0  # fused surface: one mean point per voxel of this edge ...
    survey_max_points: int = 20000  # ... doubled whenever it would hold more points than this
    # survey mode with `deform`: the non-rigid stage fits the fused surface (in the current frame), not the frame
    # alone: the deformation is underdetermined by one view of 20-30 % (docs/deform/ceiling.md)
    survey_deform_fused: bool = True
    record_path: str = ""  # flight recorder (bags/recorder.py): an MCAP file of every input, change and pose; "": off
    record_max_mb: float = 0.0  # the recorder starts a new numbered file beyond this size; 0: one file


S = TypeVar("S")


def _view(config: Config, section: type[S]) -> S:
    """A copy of one section's fields: the stage reading it cannot change the Config."""
    return section(**{f.name: getattr(config, f.name) for f in fields(section)})


# The sections last stage first: a dataclass takes its bases' fields from the last base to the
# first, so Config's fields (and `liver-p2p config`, the ROS parameter file) run in pipeline order.
@dataclass
class Config(
    StreamSection,
    DeformSection,
    VerdictSection,
    FreeSpaceSection,
    IcpSection,
    P2PSection,
    FeatureSection,
    PreprocessSection,
    InputSection,
    RuntimeSection,
):
    """Every tunable of the registration pipeline and of the node logic: the sections above, flat."""

    @property
    def runtime(self) -> RuntimeSection:
        return _view(self, RuntimeSection)

    @property
    def input_checks(self) -> InputSection:
        return _view(self, InputSection)

    @property
    def preprocess(self) -> PreprocessSection:
        return _view(self, PreprocessSection)

    @property
    def features(self) -> FeatureSection:
        return _view(self, FeatureSection)

    @property
    def p2p(self) -> P2PSection:
        return _view(self, P2PSection)

    @property
    def icp(self) -> IcpSection:
        return _view(self, IcpSection)

    @property
    def free_space(self) -> FreeSpaceSection:
        return _view(self, FreeSpaceSection)

    @property
    def verdict(self) -> VerdictSection:
        return _view(self, VerdictSection)

    @property
    def deformation(self) -> DeformSection:
        return _view(self, DeformSection)

    @property
    def stream(self) -> StreamSection:
        return _view(self, StreamSection)

    def validate(self) -> Config:
        """Check ranges and choices; raise InputError with a one-line message if bad."""
        for name, minimum in MINIMUMS.items():
            value = getattr(self, name)
            if not value >= minimum:  # `not >=` also catches NaN
                raise InputError(f"{name} must be >= {minimum}, got {value}")
        for name, (low, high) in CLOSED.items():  # a huge thread pool segfaulted; 100000 patches took a minute
            if not low <= getattr(self, name) <= high:
                raise InputError(f"{name} must be in [{low}, {high}], got {getattr(self, name)}")
        for name, (low, high) in HALF_OPEN.items():
            if not low < getattr(self, name) <= high:
                raise InputError(f"{name} must be in ({low}, {high}], got {getattr(self, name)}")
        for name in FINITE:
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"{name} must be a finite number, got {getattr(self, name)}")
        if not self.seed <= MAX_SEED:
            raise InputError(f"seed must be in [0, {MAX_SEED}] (Open3D takes a 32-bit seed), got {self.seed}")
        if not self.max_target_ratio >= 1:  # below 1 would refuse a full view of an undeformed liver
            raise InputError(f"max_target_ratio must be >= 1, got {self.max_target_ratio}")
        if not 0 <= self.confidence_threshold <= 1:  # a dual-softmax confidence is below 1 (1 rejects all)
            raise InputError(f"confidence_threshold must be in [0, 1], got {self.confidence_threshold}")
        if not self.inlier_radius_norm > 0:
            raise InputError(f"inlier_radius_norm must be > 0, got {self.inlier_radius_norm}")
        if not self.consensus_sigma_norm > 0:
            raise InputError(f"consensus_sigma_norm must be > 0, got {self.consensus_sigma_norm}")
        if not self.temperature > 0:
            raise InputError(f"temperature must be > 0, got {self.temperature}")
        if self.selection not in SELECTION_RULES:
            raise InputError(f"selection must be one of {SELECTION_RULES}, got {quoted(self.selection)}")
        if self.mode not in NODE_MODES:
            raise InputError(f"mode must be one of {NODE_MODES}, got {quoted(self.mode)}")
        if self.device not in DEVICES:
            raise InputError(f"device must be one of {DEVICES}, got {quoted(self.device)}")
        if not 0 < self.refit_radius_end_norm <= self.refit_radius_start_norm:
            raise InputError(
                "need 0 < refit_radius_end_norm <= refit_radius_start_norm, got "
                f"{self.refit_radius_end_norm} and {self.refit_radius_start_norm}"
            )
        if not 0 <= self.deform_min_gain < 1:
            raise InputError(f"deform_min_gain must be in [0, 1), got {self.deform_min_gain}")
        if not -1 <= self.deform_min_holdout_gain < 1:
            raise InputError(f"deform_min_holdout_gain must be in [-1, 1), got {self.deform_min_holdout_gain}")
        if not (self.contender_judge_ratio == 0 or 1 <= self.contender_judge_ratio < float("inf")):
            raise InputError(
                f"contender_judge_ratio must be 0 (off) or a finite factor >= 1, got {self.contender_judge_ratio}"
            )
        if not 0 <= self.ransac_candidate_visibility <= 1:
            raise InputError(f"ransac_candidate_visibility must be in [0, 1], got {self.ransac_candidate_visibility}")
        if not 0 <= self.surface_search_visibility <= 1:
            raise InputError(f"surface_search_visibility must be in [0, 1], got {self.surface_search_visibility}")
        if not 0 <= self.expected_extent_min_mm < self.expected_extent_max_mm:
            raise InputError(
                "need 0 <= expected_extent_min_mm < expected_extent_max_mm, got "
                f"{self.expected_extent_min_mm} and {self.expected_extent_max_mm}"
            )
        if not 0 < self.survey_step <= 1:
            raise InputError(f"survey_step must be in (0, 1] (a visibility increase), got {self.survey_step}")
        if not self.max_rate_hz > 0:
            raise InputError(f"max_rate_hz must be > 0, got {self.max_rate_hz}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of all fields (YAML/JSON/ROS-parameter friendly)."""
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> Config:
        """Copy with some fields changed (unknown names and bad types are errors)."""
        return Config.from_dict({**self.to_dict(), **changes})

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> Config:
        """Build from a mapping, coercing ints to floats where needed; validate."""
        return from_mapping(cls, values, "configuration key")

    @classmethod
    def from_yaml(cls, path: str | Path) -> Config:
        """Load a plain mapping or a ROS 2 parameter file (`<node>: ros__parameters: ...`)."""
        return cls.from_dict(read_yaml_mapping(path))

    def to_ros_yaml(self) -> str:
        """The ROS 2 parameter file text for both nodes (wildcard node name)."""
        header = (
            "# Generated by `liver-p2p config --ros` from liver_p2p_reg/config.py; do not edit by hand.\n"
            "# Parameters of register_node (ROS 2 parameter-file format). Units: *_mm millimetres,\n"
            "# *_norm normalized units (source scaled into the unit sphere), *_hz hertz.\n"
        )
        body = yaml.safe_dump({"/**": {"ros__parameters": self.to_dict()}}, sort_keys=False)
        return header + body
