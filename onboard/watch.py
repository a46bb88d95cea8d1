"""``python -m onboard.watch``: a stable entry point for :mod:`onboard.app.watch`."""

import sys

#: what :func:`onboard.app.watch.interrupted_line` says of nothing received, written out here: a Ctrl-C during the
#: imports leaves no module to ask (tests/onboard/test_watch.py holds the two equal)
INTERRUPTED_STARTING = "interrupted: 0 tracks received, 0 with position, 0 observable"
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as onboard.app.watch exits on Ctrl-C


def _interrupted() -> int:
    # the line goes where main puts it: stderr under --json, whose stdout holds payloads only
    print(INTERRUPTED_STARTING, file=sys.stderr if "--json" in sys.argv[1:] else sys.stdout, flush=True)
    return EXIT_INTERRUPTED


# importing numpy and zenoh takes a second or more: a Ctrl-C then is the same one line as later, not a traceback
try:
    from onboard.app.watch import main
except KeyboardInterrupt:
    raise SystemExit(_interrupted()) from None

if __name__ == "__main__":
    try:
        code = main()
    except KeyboardInterrupt:  # before main's own handler is in place (its options, its logging)
        code = _interrupted()
    raise SystemExit(code)
