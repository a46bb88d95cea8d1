"""``python -m onboard.record_recover``: a stable entry point for :mod:`onboard.app.record_recover`."""

from onboard.app.record_recover import main

if __name__ == "__main__":
    raise SystemExit(main())
