"""``python -m onboard``: the daemon (:mod:`onboard.app.main`)."""

from onboard.app.main import main

if __name__ == "__main__":
    raise SystemExit(main())
