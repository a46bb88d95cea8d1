"""``python -m onboard.track_video``: a stable entry point for :mod:`onboard.app.track_video`."""

from onboard.app.cli_args import exit_code_of
from onboard.app.track_video import main

if __name__ == "__main__":
    raise SystemExit(exit_code_of(main))  # `... | head`: no traceback
