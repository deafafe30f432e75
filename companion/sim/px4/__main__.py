"""``python -m companion.sim.px4``: see companion/sim/px4/cli.py."""

import sys

from companion.sim.px4.cli import main

if __name__ == "__main__":
    sys.exit(main())
