"""Writing the bundled bags (bags/insilico_*, phantom_sim_*, sweep_*) from their simulated cases, within size budgets."""

from __future__ import annotations

import sys
from pathlib import Path

from liver_p2p_reg.bags.io import bag_size_bytes
from liver_p2p_reg.bags.make import make_case_bag, make_sweep_bag
from liver_p2p_reg.bags.simulate_readme import measure_and_write_readme
from liver_p2p_reg.config import Config
from liver_p2p_reg.errors import LiverP2PError
from liver_p2p_reg.phantom.bundled_cases import PHANTOMS, SWEEPS, insilico_cases, phantom_case, sweep_case

MAX_BAG_BYTES = 3_000_000
MAX_TOTAL_BYTES = 25_000_000
MAX_PREOP_POINTS = 20_000
MAX_INTRAOP_POINTS = 20_000
SWEEP_PERIOD_S = 0.2
MAX_SWEEP_BYTES = 6_000_000


class BagBudgetError(LiverP2PError):
    """A bundled bag, or all of them together, over its size budget."""


def make_bundled_bags(out: Path, config: Config, write_bags: bool, readme: bool, test_frames: int) -> Path | None:
    """Write the bags into OUT (unless not `write_bags`), check their sizes, and (with `readme`) replay them
    into OUT/README.md; returns the README's path (None without `readme`)."""
    if write_bags:
        write_bundled_bags(out)
    bags = sorted(p for p in out.iterdir() if (p / "metadata.yaml").is_file())
    total = sum(bag_size_bytes(p) for p in bags)
    if total > MAX_TOTAL_BYTES:
        raise BagBudgetError(f"bags total {total} bytes > {MAX_TOTAL_BYTES}")
    if not readme:
        return None
    return measure_and_write_readme(bags, config, out, test_frames)


def write_bundled_bags(out: Path) -> None:
    """Simulate every bundled case and write its bag into OUT (overwriting), the sweeps first."""
    for kind, index in SWEEPS:
        name, case = sweep_case(kind, index)
        path = make_sweep_bag(
            out / name,
            case.pop("source_mm"),
            case.pop("frames_mm"),
            overwrite=True,
            seed=len(name),
            frame_period_s=SWEEP_PERIOD_S,
            max_preop_points=MAX_PREOP_POINTS,
            **case,
        )
        _check_size(path, case["info"], MAX_SWEEP_BYTES)
    cases = insilico_cases() + [phantom_case(i, share) for i, share in PHANTOMS]
    for name, case in cases:
        path = make_case_bag(
            out / name,
            case.pop("source_mm"),
            case.pop("target_mm"),
            overwrite=True,
            seed=len(name),
            # full resolution of the generator's clouds: the same point density in source and target
            # keeps the visibility estimate (M/N after voxelization) honest
            max_preop_points=MAX_PREOP_POINTS,
            max_intraop_points=MAX_INTRAOP_POINTS,
            **case,
        )
        _check_size(path, case["info"], MAX_BAG_BYTES)


def _check_size(path: Path, info: dict, limit: int) -> None:
    """Report a written bag on stderr; one over its size budget raises BagBudgetError (the script stops)."""
    size = bag_size_bytes(path)
    print(f"{path.name}: {size / 1e6:.2f} MB {info}", file=sys.stderr)
    if size > limit:
        raise BagBudgetError(f"{path.name} exceeds {limit} bytes")
