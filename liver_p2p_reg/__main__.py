"""`python -m liver_p2p_reg` runs the `liver-p2p` command line."""

import sys

from liver_p2p_reg.cli import main

if __name__ == "__main__":
    sys.exit(main())
