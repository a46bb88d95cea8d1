"""``python -m onboard.fuse``: a stable entry point for :mod:`onboard.app.fuse`."""

import sys

try:  # importing the fusion takes most of a second: a Ctrl-C then is one line too, not a traceback
    from onboard.app.fuse import main
except KeyboardInterrupt:
    print("interrupted while starting: nothing was fused", file=sys.stderr)
    raise SystemExit(130) from None

if __name__ == "__main__":
    raise SystemExit(main())
