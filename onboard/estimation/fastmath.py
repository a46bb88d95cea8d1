"""Small numerical kernels of the window solver, without the library wrappers' per-call overhead.

The MAP selection calls them thousands of times per second on small arrays, where numpy's and scipy's
argument handling (``np.cross``'s axis moves, ``scipy.linalg``'s decorators and checks) costs more
than the arithmetic.  Each function computes *bit for bit* what the library call named in its
docstring computes (the same LAPACK routine with the same arguments, or numpy's own component formula
in its operation order), so swapping one for the other changes no result;
``tests/onboard/test_estimator_fast_paths.py`` checks that.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

__all__ = ["cross3", "cho_factor_lower", "cho_solve_lower", "cho_solve_spd_lower", "qr_r", "einsum"]

try:
    #: ``np.einsum`` without its Python layer (argument dispatch, the ``optimize`` branch): the C function it calls
    #: for every contraction the estimator writes (two operands, ``optimize=False``), ~1 us less per call
    from numpy._core.multiarray import c_einsum as einsum
except ImportError:  # numpy 1.26 (no numpy._core): the public function, the same numbers
    einsum = np.einsum

#: cyclic permutations of the three axes: component i of a cross product is a[i+1] b[i+2] - a[i+2] b[i+1]
_NEXT = np.array([1, 2, 0])
_PREV = np.array([2, 0, 1])

#: optimal dgeqrf workspace per matrix shape (the LAPACK query's answer; it depends on the shape only)
_GEQRF_LWORK: dict[tuple[int, int], int] = {}


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` of float64 3-vectors along the last axis (broadcast over the others).

    numpy >= 2 computes ``c0 = a1 b2 - a2 b1``, ``c1 = a2 b0 - a0 b2``, ``c2 = a0 b1 - a1 b0``, one
    rounded product each then one rounded difference; this is that formula for the three components at
    once (``c = a[1, 2, 0] b[2, 0, 1] - a[2, 0, 1] b[1, 2, 0]``), minus the axis handling.
    """
    return a[..., _NEXT] * b[..., _PREV] - a[..., _PREV] * b[..., _NEXT]


def cho_factor_lower(A: np.ndarray) -> tuple[np.ndarray, bool]:
    """``scipy.linalg.cho_factor(A, lower=True, check_finite=False)`` for a float64 matrix: LAPACK dpotrf,
    upper triangle left as it was.  Raises ``np.linalg.LinAlgError`` when A is not positive definite."""
    c, info = lapack.dpotrf(A, lower=1, clean=0)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor of the array is not positive definite")
    if info < 0:
        raise ValueError(f'LAPACK reported an illegal value in {-info}-th argument on entry to "POTRF".')
    return c, True


def cho_solve_lower(c: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``scipy.linalg.cho_solve((c, True), b, check_finite=False)``: LAPACK dpotrs with the lower factor ``c``."""
    x, info = lapack.dpotrs(c, b, lower=1)
    if info != 0:
        raise ValueError(f"illegal value in {-info}th argument of internal potrs")
    return x


def cho_solve_spd_lower(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``cho_solve_lower(cho_factor_lower(A)[0], b)`` in one LAPACK call: dposv, which is dpotrf then dpotrs with
    the same arguments (one wrapper's overhead instead of two, for a solver that needs the solution only).
    Raises ``np.linalg.LinAlgError`` when A is not positive definite, as :func:`cho_factor_lower`."""
    _, x, info = lapack.dposv(A, b, lower=1)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor of the array is not positive definite")
    if info < 0:
        raise ValueError(f'LAPACK reported an illegal value in {-info}-th argument on entry to "POSV".')
    return x


def qr_r(A: np.ndarray) -> np.ndarray:
    """The leading (N, N) block of ``scipy.linalg.qr(A, mode="r", check_finite=False)[0]`` for a float64
    (M, N) matrix with M >= N: the upper-triangular R of LAPACK dgeqrf at the optimal workspace (the
    workspace sets the blocking, so it is the one scipy's query finds)."""
    M, N = A.shape
    lwork = _GEQRF_LWORK.get((M, N))
    if lwork is None:
        lwork = _GEQRF_LWORK[(M, N)] = int(lapack.dgeqrf(A, lwork=-1)[-2][0])
    qr, _, _, info = lapack.dgeqrf(A, lwork=lwork)
    if info < 0:
        raise ValueError(f"illegal value in {-info}th argument of internal geqrf")
    return np.triu(qr[:N])
