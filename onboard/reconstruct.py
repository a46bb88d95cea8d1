"""``python -m onboard.reconstruct``: a stable entry point for :mod:`onboard.app.reconstruct`."""

from onboard.app.reconstruct import main

if __name__ == "__main__":
    raise SystemExit(main())
