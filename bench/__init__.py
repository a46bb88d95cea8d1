"""Benchmarks: print numbers, never assert on time."""

import os


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
