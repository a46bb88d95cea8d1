"""Benchmarks: print numbers, never assert on time.

Each ``python -m bench.<name>`` ends with :func:`run_benchmark`: Ctrl-C (or SIGTERM) stops it through its
own clean-up (its daemon, simulator or pool is stopped), and it prints one line ``interrupted: bench.<name>
stopped part-way; <what was kept>`` and exits 130 (143 for SIGTERM).  ``python -m bench`` runs them in turn
and prints that one line itself (:data:`SUITE_ENV` tells a benchmark so).  A file the run reads and refuses (a
configuration, a scenario: the project's :class:`InputError` or :class:`ConfigError`) is one line
``bench.<name>: <why>``, exit code 2; any other :class:`IrtrackError` (a failure part-way through a measurement) is
that line and exit code 1.
"""

import argparse
import json
import os
import signal
import sys

from groundsim.io.stop_signals import EXIT_INTERRUPTED, print_interrupted
from onboard.app.cli_args import EXIT_USAGE  # a file an option names, refused once read, is a bad option value too
from onboard.core.errors import ConfigError, InputError, IrtrackError

#: set by ``python -m bench`` for the benchmarks it runs: the suite prints the one "interrupted" line
SUITE_ENV = "BENCH_SUITE"
EXIT_SIGNALLED = {signal.SIGINT: EXIT_INTERRUPTED, signal.SIGTERM: 128 + signal.SIGTERM}  # as a shell reports it


def write_json(path: str, document, **dump_options) -> None:
    """``document`` as JSON in ``path`` (its folder made first): a benchmark's ``--json`` file.  ``dump_options``
    go to :func:`json.dump` (e.g. ``indent=2, default=float`` for numpy numbers)."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "w") as fh:
        json.dump(document, fh, **dump_options)


def run_benchmark(name: str, main, kept: str = "the figures printed above are kept") -> int:
    """``main()`` of ``bench.<name>`` as a command: its exit code (None counts as 0).  The first SIGINT or
    SIGTERM raises KeyboardInterrupt in ``main`` (its ``finally`` blocks stop what it started); then
    ``interrupted: bench.<name> stopped part-way; <kept>`` on stderr (not under ``python -m bench``, which
    says it for the whole suite) and the signal's exit code.  An :class:`IrtrackError` out of ``main`` is
    ``bench.<name>: <message>`` on stderr; exit code 2 for a refused input or configuration (a file, a value:
    :class:`InputError`, :class:`ConfigError`), 1 for a failure part-way through a measurement."""
    received: list[int] = []
    pid = os.getpid()

    def on_signal(signum, _frame):
        if os.getpid() != pid:  # a forked pool worker: its pool's terminate() SIGTERMs it, to die silently
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        # later signals (a terminal's Ctrl-C and the suite's forwarded one, an impatient second Ctrl-C) must
        # not cut the clean-up of the first one short: it stops daemons and pools, bounded in time
        for sig in EXIT_SIGNALLED:
            signal.signal(sig, signal.SIG_IGN)
        received.append(signum)
        raise KeyboardInterrupt

    for sig in EXIT_SIGNALLED:
        signal.signal(sig, on_signal)
    try:
        rc = main()
    except KeyboardInterrupt:
        for sig in EXIT_SIGNALLED:
            signal.signal(sig, signal.SIG_IGN)
        if not os.environ.get(SUITE_ENV):
            print_interrupted(f"bench.{name} stopped part-way; {kept}")
        return EXIT_SIGNALLED[received[0] if received else signal.SIGINT]
    except IrtrackError as exc:  # its message names the file, the field and what was expected
        print(f"bench.{name}: {' '.join(str(exc).splitlines())}", file=sys.stderr)
        # a file or value refused is the caller's to fix (2); a failure part-way through a measurement is not
        return EXIT_USAGE if isinstance(exc, InputError | ConfigError) else 1
    return int(rc or 0)


def parse_flags(prog: str, description: str, flags: dict[str, str] | None = None):
    """The command line of a benchmark that takes no option but on/off ``flags`` (name -> help): ``--help``
    prints them, anything else is refused by name (exit 2) rather than ignored while the default run starts."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    for name, text in (flags or {}).items():
        ap.add_argument(name, action="store_true", help=text)
    return ap.parse_args()


def pin_to_one_cpu(unpinned: str = "not pinned") -> str:
    """Pin this process to the lowest CPU it may run on; says which ("pinned to CPU N") or ``unpinned``
    where the platform cannot (no ``sched_setaffinity``) or refuses."""
    try:
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
    except (AttributeError, OSError):
        return unpinned
    return f"pinned to CPU {cpu}"


def machine_speed_ms(repeats: int = 3) -> float:
    """This machine's speed right now: CPU ms of this thread for a fixed pure-Python loop (the kind of code
    the daemon's per-frame and per-message paths run), the fastest of ``repeats``.  Printed beside CPU
    figures so that runs on a VM whose speed drifts (+-25 % between minutes here) can be compared."""
    import time

    best = float("inf")
    for _ in range(repeats):
        c0 = time.thread_time()
        acc = 0
        for i in range(300_000):
            acc += (i * i) % 7
        best = min(best, time.thread_time() - c0)
    return best * 1e3


def frame_speed_ms(repeats: int = 5) -> float:
    """This machine's speed right now at the image chain's kind of work: CPU ms of this thread for a fixed
    sequence of whole-frame passes over a 640 x 512 float32 frame (a 3 x 3 box mean, an absolute difference, an area
    resize to a quarter and a comparison, as the detector's statistics run them), the fastest of ``repeats``.  The
    Python loop of :func:`machine_speed_ms` did not see a day on which this VM ran the same chain ~30 % slower (its
    loop at 14-15 ms throughout): that slowness was in memory-bound work, which this probe times."""
    import time

    import cv2
    import numpy as np

    if repeats < 1:
        raise ValueError(f"frame_speed_ms: repeats must be >= 1, got {repeats}")
    frame = np.random.default_rng(0).normal(130.0, 3.0, (512, 640)).astype(np.float32)
    box, dev, mask = np.empty_like(frame), np.empty_like(frame), np.empty(frame.shape, np.bool_)
    best = float("inf")
    for _ in range(repeats):
        c0 = time.thread_time()
        for _ in range(4):
            cv2.blur(frame, (3, 3), dst=box, borderType=cv2.BORDER_REPLICATE)
            np.subtract(frame, box, out=dev)
            np.abs(dev, out=dev)
            cells = cv2.resize(dev, (160, 128), interpolation=cv2.INTER_AREA)
            np.greater_equal(dev, cv2.resize(cells, (640, 512), interpolation=cv2.INTER_LINEAR), out=mask)
        best = min(best, time.thread_time() - c0)
    return best * 1e3


def _pacing_work(a, n_loop: int) -> float:
    """A fixed mix of the daemon's kinds of work: a pure-Python loop and small-array numpy calls."""
    s = 0.0
    for i in range(n_loop):
        s += i * 0.5
    for _ in range(60):
        s += float((a * 2.0 + 1.0).sum())
    return s


def pacing_factor(rate_hz: float = 30.0, calls: int = 150) -> tuple[float, float]:
    """This machine's CPU cost of running at a rate: CPU ms of this thread per call of a fixed ~0.4 ms
    workload back to back, and the ratio of its cost when called ``rate_hz`` times a second with sleeps in
    between (medians of ``calls`` calls each).  On this VM the ratio is 1.2-2 (it moves between minutes): a daemon that does its work 30
    times a second pays that much more than the work costs in a tight loop, whatever the work."""
    import time

    import numpy as np

    if not rate_hz > 0 or calls < 1:
        raise ValueError(f"pacing_factor: rate_hz must be > 0 and calls >= 1, got {rate_hz} and {calls}")
    a = np.random.default_rng(0).random((84, 84))

    def per_call_ms(paced: bool) -> float:
        cpu = []
        nxt = time.monotonic()
        for _ in range(calls):
            c0 = time.thread_time()
            _pacing_work(a, 2000)
            cpu.append(time.thread_time() - c0)
            if paced:
                nxt += 1.0 / rate_hz
                time.sleep(max(nxt - time.monotonic(), 0.0))
        return float(np.median(cpu)) * 1e3

    tight = per_call_ms(False)
    return tight, per_call_ms(True) / tight
