"""``python -m groundsim <command>``: the ground simulator's entry point (commands in groundsim.cli)."""

import sys

from groundsim.cli import main

if __name__ == "__main__":
    sys.exit(main())
