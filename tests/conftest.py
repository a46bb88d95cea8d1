"""Suite-wide fixtures."""

from __future__ import annotations

import pytest

try:  # BLAS threads contend badly on small shared machines (a MAP solve ran ~9x slower with them)
    from threadpoolctl import threadpool_limits
except ImportError:  # a dev dependency; without it the tests only run slower
    threadpool_limits = None


@pytest.fixture(scope="session", autouse=True)
def _one_blas_thread():
    """Every test in-process on one BLAS thread, as the daemon and the benchmarks run."""
    if threadpool_limits is None:
        yield
        return
    with threadpool_limits(limits=1):
        yield
