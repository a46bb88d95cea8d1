"""``python -m onboard.reconstruct``: a stable entry point for :mod:`onboard.app.reconstruct`."""

from onboard.app.cli_args import exit_code_of
from onboard.app.reconstruct import main

if __name__ == "__main__":
    raise SystemExit(exit_code_of(main))  # `... | head`: no traceback
