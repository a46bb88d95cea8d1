"""``python -m onboard.health``: a stable entry point for :mod:`onboard.app.health`."""

from onboard.app.health import main

if __name__ == "__main__":
    raise SystemExit(main())
