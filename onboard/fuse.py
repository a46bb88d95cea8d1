"""``python -m onboard.fuse``: a stable entry point for :mod:`onboard.app.fuse`."""

from onboard.app.fuse import main

if __name__ == "__main__":
    raise SystemExit(main())
