"""A child process that ends with the program that started it: ``IRTRACK_PARENT_PID`` in its environment.

``groundsim demo`` starts the daemon and the simulator as child processes.  A demo ended by SIGKILL (an
out-of-memory kill, ``kill -9``, a CI job's hard limit) runs none of its clean-up, and its children kept running,
holding their ports, until someone found them.  A launcher that wants its child to end with it sets
``IRTRACK_PARENT_PID`` to its own PID; the child then asks Linux for a SIGTERM when its parent dies
(``prctl(PR_SET_PDEATHSIG)``), which it handles as any SIGTERM: a clean stop.  The request is made by the child
itself, after ``exec`` (a ``preexec_fn`` would run between fork and exec, unsafe in a program with threads), so
the parent may already be gone by then: that is checked once, after the request.

Linux sends the signal when the *thread* that forked the child ends: launchers start their children from their
main thread.  The variable is for the direct child (or one ``exec`` wrappers leave in its place): the child
removes it from its own environment, so that a process it starts is not taken for an orphan.  Elsewhere (no
``prctl``) nothing happens, as without the variable.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
from collections.abc import Mapping

__all__ = ["PARENT_PID_ENV", "end_with_parent"]

log = logging.getLogger(__name__)

PARENT_PID_ENV = "IRTRACK_PARENT_PID"
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def end_with_parent(environ: Mapping[str, str] = os.environ) -> bool:
    """When ``environ`` names the parent (``IRTRACK_PARENT_PID``), have this process sent SIGTERM when it dies; True
    when that is arranged.  Call it once SIGTERM is handled as a clean stop.  A parent already gone sends it now."""
    text = environ.get(PARENT_PID_ENV)
    if not text:
        return False
    if environ is os.environ:  # for this process alone: a process it starts has another parent
        os.environ.pop(PARENT_PID_ENV, None)
    try:
        parent = int(text)
    except ValueError:
        log.warning("%s=%r is not a process id: not watching the parent", PARENT_PID_ENV, text)
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        _sigterm_on_parent_death()
    except (OSError, AttributeError) as exc:
        log.warning("%s: cannot ask for a signal when the parent dies (%s): it may outlive it", PARENT_PID_ENV, exc)
        return False
    if os.getppid() != parent:  # gone before the request: its signal will never come
        log.warning("the process that started this one (pid %d) has ended: stopping", parent)
        os.kill(os.getpid(), signal.SIGTERM)
    return True


def _sigterm_on_parent_death() -> None:
    """``prctl(PR_SET_PDEATHSIG, SIGTERM)`` for this process; OSError when refused."""
    libc = ctypes.CDLL(None, use_errno=True)  # the C library this process already has loaded
    if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
