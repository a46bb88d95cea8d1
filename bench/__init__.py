"""Benchmarks: print numbers, never assert on time.

Each ``python -m bench.<name>`` ends with :func:`run_benchmark`: Ctrl-C (or SIGTERM) stops it through its
own clean-up (its daemon, simulator or pool is stopped), and it prints one line ``interrupted: bench.<name>
stopped part-way; <what was kept>`` and exits 130 (143 for SIGTERM).  ``python -m bench`` runs them in turn
and prints that one line itself (:data:`SUITE_ENV` tells a benchmark so).
"""

import json
import os
import signal

from groundsim.io.stop_signals import EXIT_INTERRUPTED, print_interrupted

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
    says it for the whole suite) and the signal's exit code."""
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
    return int(rc or 0)


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
