"""An unobservable position's published covariance: widened across its line of sight for the range it does not
know (:func:`onboard.estimation.map_estimator.across_range_widened`)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.estimation.map_estimator import across_range_widened

finite = st.floats(-1.0, 1.0, allow_nan=False)


def _spd(a: list[float], scales: tuple[float, float, float]) -> np.ndarray:
    L = np.array(a, dtype=float).reshape(3, 3) + 2.0 * np.eye(3)
    P = L @ L.T
    D = np.diag(scales)
    return D @ P @ D


@settings(max_examples=200, deadline=None)
@given(
    st.lists(finite, min_size=9, max_size=9),
    st.tuples(*(st.floats(0.01, 200.0) for _ in range(3))),
    st.tuples(*(st.floats(-1.0, 1.0) for _ in range(3))).filter(lambda v: np.linalg.norm(v) > 1e-3),
    st.floats(1.0, 5000.0),
)
def test_the_range_direction_is_kept_and_the_rest_scaled_by_one_plus_the_range_variance_over_range_squared(
    a, scales, u, range_m
):
    P = _spd(a, scales)
    u = np.array(u) / np.linalg.norm(u)
    W = across_range_widened(P, u, range_m)
    var_r = u @ P @ u
    k = 1.0 + var_r / range_m**2
    Q = np.eye(3) - np.outer(u, u)
    np.testing.assert_allclose(W, W.T, atol=1e-9 * np.abs(P).max())
    assert u @ W @ u == np.float64(var_r) or abs(u @ W @ u - var_r) <= 1e-9 * var_r  # along the line: as it was
    np.testing.assert_allclose(Q @ W @ Q, k * (Q @ P @ Q), rtol=1e-9, atol=1e-9 * np.abs(P).max())
    np.testing.assert_allclose(W @ u, P @ u + (k - 1.0) * (Q @ P @ Q) @ u, atol=1e-9 * np.abs(P).max())
    assert np.linalg.eigvalsh(W - P).min() >= -1e-9 * np.abs(P).max()  # only ever wider


def test_a_solution_collapsed_towards_the_camera_is_honest_about_a_target_farther_along_the_line():
    """40 m out for a target at 180 m, on the same bearing to within 1 mrad: the range floor (150 m) covers the
    range; across the line the solution's 1 mrad at 40 m (4 cm) did not cover 18 cm at 180 m, its widening does."""
    u = np.array([1.0, 0.0, 0.0])
    bearing_rad = 1e-3
    P = np.diag([150.0**2, (40.0 * bearing_rad) ** 2, (40.0 * bearing_rad) ** 2])
    truth = 180.0 * np.array([np.cos(bearing_rad), np.sin(bearing_rad), 0.0])
    e = truth - 40.0 * u

    def nees(C):
        return float(e @ np.linalg.solve(C, e))

    assert nees(P) > 14.156  # beyond its own 3-sigma ellipsoid
    assert nees(across_range_widened(P, u, 40.0)) < 3.0


def test_nothing_to_widen_by_without_a_range():
    P = np.diag([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(across_range_widened(P, np.array([1.0, 0.0, 0.0]), 0.0), P)
