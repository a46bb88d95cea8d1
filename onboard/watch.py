"""``python -m onboard.watch``: a stable entry point for :mod:`onboard.app.watch`."""

from onboard.app.watch import main

if __name__ == "__main__":
    raise SystemExit(main())
