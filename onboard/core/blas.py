"""One BLAS thread per process: the environment every entry point sets before numpy is imported.

The pipeline, the simulator and the evaluation are single-threaded by design: the estimator's matrices
are small, so OpenBLAS's worker threads buy nothing there, and on a loaded 2-core machine their spinning
made solves many times slower.  The variables only take effect if they are set before numpy (and
scipy) load their BLAS, so an entry point calls :func:`single_thread_blas_env` before its other
imports, and a parent passes the same variables to the children it starts.  Importing this module
imports nothing but :mod:`os`.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_thread_blas_env(env: MutableMapping[str, str] | None = None, n: int = 1) -> MutableMapping[str, str]:
    """Set every BLAS thread variable to ``n`` unless already set; ``env`` None = this process's
    environment (call it before numpy is imported), else a child's environment dict.  Returns it."""
    target: MutableMapping[str, str] = os.environ if env is None else env
    for var in BLAS_THREAD_VARS:
        target.setdefault(var, str(n))
    return target
