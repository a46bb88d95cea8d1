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
