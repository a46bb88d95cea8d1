"""numba's ``njit`` for the onboard service's compiled kernels (the estimator's, the image chain's).

numba is a declared runtime dependency (pyproject): without it the kernels' import raises an ImportError that names
it and how it is installed, rather than a bare traceback or a silent fallback to numpy at several times the CPU.
"""

from __future__ import annotations

try:
    from numba import njit
except ImportError as exc:
    raise ImportError(
        "the onboard service's compiled kernels need numba (a runtime dependency: `pip install .` installs it); "
        f"it could not be imported: {exc}"
    ) from exc

__all__ = ["njit"]
