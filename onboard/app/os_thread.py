"""The daemon's threads and processes by name in the OS, so that ``top -H``, ``ps -L``, py-spy and
``/proc/<pid>/task/<tid>/comm`` say which is the pipeline, the estimator, the recorder (Linux; a no-op
elsewhere).  Python 3.11 names its threads only inside Python."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["name_os_thread"]

_PR_SET_NAME = 15  # <linux/prctl.h>
_libc = None


def name_os_thread(name: str) -> bool:
    """Name the calling thread (the process, when called from its main thread) ``name``, cut to the
    kernel's 15 bytes.  Returns whether it took; never raises."""
    global _libc
    if not sys.platform.startswith("linux"):
        return False
    try:
        if _libc is None:
            _libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        return _libc.prctl(_PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
