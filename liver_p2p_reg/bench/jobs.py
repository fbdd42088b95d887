"""What a benchmark run runs: its spec and recorded settings, the method variants and the (case, variant) jobs."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from liver_p2p_reg.bench.cases import CaseInfo, first_per_bin
from liver_p2p_reg.bench.cases_csv import CASES_CSV
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import InputError
from liver_p2p_reg.files import write_text_atomic

SETTINGS_JSON = "settings.json"
ORACLE = "procrustes"
# The rigid surface bound: the configured refinement (`track`, trimmed ICP) started from the case's
# true pose. No rigid method that ends in the same ICP can do better on the surface it sees; a row
# of the benchmark only (it needs the ground truth), not a registration method.
BOUND = "bound"
ABLATION_K = tuple(range(1, 9))  # the paper's Fig. 8: K = 1 ... 8
ABLATION_CASES_PER_BIN = 10
# Settings that may differ between runs into one OUT: they add rows and never change existing ones.
ADDITIVE_SETTINGS = ("noise_levels_mm", "ablation_cases_per_bin", "sensor_aware")
# `METHOD+deform`: the method with the non-rigid stage after it (rows of their own, TRE at the deformed positions)
DEFORM_SUFFIX = "+deform"
SENSOR_AWARE_TAG = "[fs]"  # label suffix of the rows registered with the case's sensor origin (free space)


@dataclass(frozen=True)
class Variant:
    """One way of running a method: its name plus Config overrides (empty for the main run), and
    whether the case's sensor origin is given (a main run of its own, labelled `method[fs]`)."""

    method: str
    overrides: tuple[tuple[str, Any], ...] = ()
    sensor_aware: bool = False
    # A named main-table method built on `method` (e.g. `prepared`: per-liver prepared weights in
    # `overrides`); its rows count as a method of their own, not as an ablation variant.
    tag: str = ""

    @property
    def label(self) -> str:
        base = self.method + SENSOR_AWARE_TAG if self.sensor_aware else self.method
        if self.tag == DEFORM_SUFFIX:
            return base + DEFORM_SUFFIX
        if self.tag:
            return f"{base}[{self.tag}]"
        if not self.overrides:
            return base
        return f"{base}[{self.variant}]"

    @property
    def variant(self) -> str:
        """The ablation's overrides ("" for a main run, with or without the sensor origin or a tag)."""
        return "" if self.tag else ",".join(f"{k}={v}" for k, v in self.overrides)


@dataclass
class BenchmarkSpec:
    """Everything that defines a benchmark run (the parts that must not change within one OUT)."""

    out: Path
    dataset_id: str
    cases: list[CaseInfo]
    methods: list[str]
    config: Config = field(default_factory=Config)
    preset: str = "full"
    limit: int | None = None
    ablations: bool = False
    ablation_cases_per_bin: int = ABLATION_CASES_PER_BIN
    workers: int = 1
    noise_levels_mm: tuple[float, ...] = ()
    noise_bins: str = "lowest"  # which cases get the noisy copies (cases.with_noise)
    # case_id -> patient-prepared weights of its liver (`--prepare-minutes`): adds `<method>[prepared]`
    # rows for the learned methods
    prepared: dict[str, str] = field(default_factory=dict)
    prepare_minutes: float = 0.0
    sensor_aware: bool = False  # also run every method with the case's sensor origin (`method[fs]` rows)
    visibility_range: tuple[float, float] | None = None  # only cases with visibility in [lo, hi)

    def settings(self) -> dict[str, Any]:
        """The settings recorded in OUT/settings.json; a rerun must match them."""
        from liver_p2p_reg.bench.cases import fingerprint

        clean = [c for c in self.cases if c.added_noise_mm == 0]  # noisy copies are additive
        return {
            "dataset": self.dataset_id,
            "cases_fingerprint": fingerprint(clean),
            "n_cases": len(clean),
            "preset": self.preset,
            "limit": self.limit,
            "ablation_cases_per_bin": self.ablation_cases_per_bin,
            "noise_levels_mm": list(self.noise_levels_mm),
            "noise_bins": self.noise_bins,
            "prepare_minutes": self.prepare_minutes,
            "sensor_aware": self.sensor_aware,
            "config": self.config.to_dict(),
            **({"visibility_range": list(self.visibility_range)} if self.visibility_range else {}),
        }


def benchmark_methods() -> list[str]:
    """What `--methods` may name: every registration method and the bound row."""
    from liver_p2p_reg.registration.methods import method_names

    return sorted([*method_names(), BOUND])


def is_p2p(method: str) -> bool:
    """Methods whose P2P module the ablations vary (plain `X-p2p`, not the refined `X-p2p-icp`)."""
    return method.endswith("-p2p")


def main_variant(name: str) -> Variant:
    """The variant a `--methods` name runs: the method itself, or `METHOD+deform` with the non-rigid stage."""
    if name.endswith(DEFORM_SUFFIX):
        return Variant(name.removesuffix(DEFORM_SUFFIX), (("deform", True),), tag=DEFORM_SUFFIX)
    return Variant(name)


def build_jobs(spec: BenchmarkSpec) -> list[tuple[CaseInfo, Variant]]:
    """All (case, variant) pairs of the run, cases outermost so partial runs cover whole cases."""
    main = [main_variant(m) for m in spec.methods]
    if spec.sensor_aware:  # the same cases with the sensor origin, next to each method's plain run
        # the oracle and the bound start from the truth: a sensor origin changes nothing of theirs
        main += [replace(main_variant(m), sensor_aware=True) for m in spec.methods if m not in (ORACLE, BOUND)]
    ablation: list[Variant] = []
    if spec.ablations:
        cfg = spec.config
        for m in spec.methods:
            if m.endswith("-p2p-icp"):  # the ICP screening of the candidates, on or off
                ablation.append(Variant(m, (("refine_candidates", 1 if cfg.refine_candidates > 1 else 6),)))
            if not is_p2p(m):
                continue
            ablation += [Variant(m, (("k", k),)) for k in ABLATION_K if k != cfg.k]
            other_rule = "inlier-count" if cfg.selection == "closest-point" else "closest-point"
            ablation.append(Variant(m, (("selection", other_rule),)))
            ablation.append(Variant(m, (("candidate_proposal", not cfg.candidate_proposal),)))
            # this project's additions to the paper's module: row-best matches, the robust re-fit
            # and the consensus-started twin candidates
            ablation.append(Variant(m, (("mutual_only", not cfg.mutual_only),)))
            ablation.append(Variant(m, (("refit_iterations", 0 if cfg.refit_iterations else 6),)))
            ablation.append(Variant(m, (("consensus_seeds", 0 if cfg.consensus_seeds else 64),)))
    clean = [c for c in spec.cases if c.added_noise_mm == 0]  # ablations run on the noise-free cases
    ablation_ids = {c.case_id for c in first_per_bin(clean, spec.ablation_cases_per_bin)}
    jobs = []
    for case in spec.cases:
        jobs += [(case, v) for v in main]
        weights = spec.prepared.get(case.case_id.split("+")[0])  # noisy copies share their case's liver
        if weights:
            jobs += [
                (case, Variant(m, (("weights_path", weights),), tag="prepared"))
                for m in spec.methods
                if m.startswith("learned")
            ]
        if case.case_id in ablation_ids:
            jobs += [(case, v) for v in ablation]
    return jobs


def read_json(path: Path) -> dict[str, Any]:
    """A JSON object a benchmark run recorded in its OUT; InputError naming the file when it is damaged."""
    try:
        value = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path} is not readable JSON ({exc}); use a new --out or delete it") from None
    if not isinstance(value, dict):
        raise InputError(f"{path} holds no JSON object; use a new --out or delete it")
    return value


def _write_settings(path: Path, settings: dict[str, Any]) -> None:
    """settings.json in one step: a run cut short never leaves a half-written one that locks the OUT."""
    write_text_atomic(path, json.dumps(settings, indent=2, sort_keys=True) + "\n")


def check_settings(out: Path, settings: dict[str, Any]) -> None:
    """Refuse to mix runs with different settings in one OUT; record the settings of a new OUT."""
    path = out / SETTINGS_JSON
    if path.exists():
        old = read_json(path)
        diffs = _diff(old, settings)
        if diffs:
            raise InputError(
                f"{out} holds a run with other settings ({'; '.join(diffs[:3])}); use a new --out or delete it"
            )
        for key in ADDITIVE_SETTINGS:  # record what was added (union of noise levels, largest ablation set)
            if key == "noise_levels_mm":
                settings[key] = sorted(set(old.get(key, [])) | set(settings[key]))
            elif key == "sensor_aware":
                settings[key] = bool(old.get(key, False) or settings[key])
            else:
                settings[key] = max(old.get(key, 0), settings[key])
        _write_settings(path, settings)
        return
    if (out / CASES_CSV).exists():
        raise InputError(f"{out / CASES_CSV} exists without {SETTINGS_JSON}; use a new --out")
    out.mkdir(parents=True, exist_ok=True)
    _write_settings(path, settings)


def _diff(old: Any, new: Any, prefix: str = "") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in sorted(set(old) | set(new)):
            if prefix == "config." and (key not in old or key not in new):
                continue  # a Config field added or removed since: the rows' settings did not change
            if not prefix and key in ADDITIVE_SETTINGS:
                continue  # these only add rows (noisy copies, ablation cases); existing rows stay valid
            out += _diff(old.get(key), new.get(key), f"{prefix}{key}.")
        return out
    return [] if old == new else [f"{prefix.rstrip('.')}: {old!r} then, {new!r} now"]
