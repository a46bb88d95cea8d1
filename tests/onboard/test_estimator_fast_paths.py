"""The estimator's fast kernels (onboard.estimation.fastmath) equal the library calls they replace, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from onboard.estimation.fastmath import (
    cho_factor_lower,
    cho_solve_lower,
    cho_solve_spd_lower,
    cross3,
    einsum,
    qr_r,
)

FINITE = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, allow_subnormal=False)


def _vectors(shape):
    return hnp.arrays(np.float64, shape, elements=FINITE)


@settings(max_examples=200, deadline=None)
@given(st.data(), st.integers(1, 40))
def test_cross3_is_np_cross_bit_for_bit(data, n):
    # the estimator's two shapes: one vector against a row pair (per frame), and a single row pair
    a = data.draw(_vectors((n, 1, 3)))
    b = data.draw(_vectors((n, 2, 3)))
    assert np.array_equal(cross3(a, b), np.cross(a, b))
    assert np.array_equal(cross3(a[0], b[0]), np.cross(a[0], b[0]))


@settings(max_examples=60, deadline=None)
@given(st.data(), st.integers(1, 30), st.integers(0, 60), st.floats(1e-6, 1.0))
def test_cholesky_and_qr_are_scipys_bit_for_bit(data, n, extra_rows, ridge):
    A = data.draw(_vectors((n + extra_rows, n)))
    R = qr_r(A)
    R_ref = sla.qr(A, mode="r", check_finite=False)[0][:n]
    assert R.shape == R_ref.shape and np.array_equal(R, R_ref)
    H = A.T @ A + ridge * np.eye(n)
    try:
        c_ref, lower_ref = sla.cho_factor(H, lower=True, check_finite=False)
    except np.linalg.LinAlgError:  # numerically singular: the fast path must refuse it too
        with pytest.raises(np.linalg.LinAlgError):
            cho_factor_lower(H)
        with pytest.raises(np.linalg.LinAlgError):
            cho_solve_spd_lower(H, np.ones(n))
        return
    c, lower = cho_factor_lower(H)
    assert lower is lower_ref is True and np.array_equal(c, c_ref)
    g = data.draw(_vectors((n,)))
    x, x_ref = cho_solve_lower(c, g), sla.cho_solve((c_ref, True), g, check_finite=False)
    assert x.shape == x_ref.shape and np.array_equal(x, x_ref)
    assert np.array_equal(cho_solve_spd_lower(H, g), x_ref)  # factor and solve in one call: the same bits
    E = data.draw(_vectors((n, 3)))
    assert np.array_equal(cho_solve_lower(c, E), sla.cho_solve((c_ref, True), E, check_finite=False))


def test_cho_factor_lower_raises_like_scipy_on_a_matrix_that_is_not_positive_definite():
    H = np.diag([1.0, -1.0, 2.0])
    with pytest.raises(np.linalg.LinAlgError):
        sla.cho_factor(H, lower=True, check_finite=False)
    with pytest.raises(np.linalg.LinAlgError, match="2-th leading minor"):
        cho_factor_lower(H)


@settings(max_examples=60, deadline=None)
@given(st.data(), st.integers(1, 40))
def test_einsum_is_np_einsum_bit_for_bit(data, n):
    # the contractions the window problem writes
    R, w = data.draw(_vectors((3, 3, n))), data.draw(_vectors((3, n)))
    N = data.draw(_vectors((2, 3, n)))
    w0, c = data.draw(_vectors((n, 4))), data.draw(_vectors((n, 4, 3)))
    for subscripts, ops in (
        ("ijf,jf->if", (R, w)),
        ("if,if->f", (w, w)),
        ("akf,alf->kl", (N, N)),
        ("fm,fmk->fk", (w0, c)),
    ):
        assert np.array_equal(einsum(subscripts, *ops), np.einsum(subscripts, *ops))
