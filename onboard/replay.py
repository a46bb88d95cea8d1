"""``python -m onboard.replay``: a stable entry point for :mod:`onboard.app.replay`."""

from onboard.app.replay import main

if __name__ == "__main__":
    raise SystemExit(main())
