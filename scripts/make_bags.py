"""Generate the bundled bags (bags/insilico_*, bags/phantom_sim_*) and bags/README.md's expected-results table.

    .venv/bin/python scripts/make_bags.py            # cases -> bags -> replay -> README table
    .venv/bin/python scripts/make_bags.py --readme-only   # re-measure the existing bags only

The cases are liver_p2p_reg/phantom/bundled_cases.py's (test-set cases, simulated in vitro phantoms,
sweeps); liver_p2p_reg/bags/simulate.py writes their bags and simulate_readme.py the README.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from liver_p2p_reg.bags.simulate import BagBudgetError, make_bundled_bags
from liver_p2p_reg.config import Config

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "bags")
    parser.add_argument("--readme-only", action="store_true", help="do not regenerate the bags")
    parser.add_argument("--method", help="registration method for the expected results (default: Config's)")
    parser.add_argument("--bags-only", action="store_true", help="write the bags, skip the replay and README")
    parser.add_argument("--test-frames", type=int, default=1, help="frames the bundled-bag test replays")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    config = Config() if not args.method else Config(method=args.method)
    try:
        readme = make_bundled_bags(args.out, config, not args.readme_only, not args.bags_only, args.test_frames)
    except BagBudgetError as exc:  # a bag over its size budget: one line and exit status 1, no traceback
        raise SystemExit(str(exc)) from None
    if readme is not None:
        print(readme.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
