"""``python -m onboard``: the daemon (:mod:`onboard.app.main`)."""

import signal

from onboard.app.main import main

if __name__ == "__main__":
    code = main()
    # the daemon has stopped and the interpreter is tearing down (worker, threads, zenoh): a second SIGTERM or
    # Ctrl-C now would end it by the signal's default action (exit 143) instead of the clean stop's code
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    raise SystemExit(code)
