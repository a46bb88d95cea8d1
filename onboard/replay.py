"""``python -m onboard.replay``: a stable entry point for :mod:`onboard.app.replay`."""

from onboard.app.cli_args import exit_code_of
from onboard.app.replay import main

if __name__ == "__main__":
    raise SystemExit(exit_code_of(main))  # `... | head`: no traceback
