"""Coasting an estimate through a navigation gap (onboard.pipeline.coast): pure maths, checked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.estimation.sliding import TrackEstimate
from onboard.pipeline.coast import OBSERVABLE_MAX_RANGE_SIGMA_RATIO, coast_estimate

ATOL_M = 1e-9


def _estimate(observable: bool = True) -> TrackEstimate:
    p = np.array([100.0, 0.0, -50.0])
    return TrackEstimate(
        10.0, p, np.array([0.0, 5.0, 0.0]), np.diag([1.0, 1.0, 1.0]), np.diag([0.04, 0.04, 0.04]),
        observable, float(np.linalg.norm(p)), 0.01, 100, "cv",
    )  # fmt: skip


def test_propagation_adds_velocity_and_acceleration_variance_and_leaves_the_input_alone():
    est = _estimate()
    cov0 = est.cov_p_ned_m2.copy()
    out = coast_estimate(est, 12.0, np.zeros(3), cam_sigma_m=5.0, accel_sigma_mps2=1.0)
    np.testing.assert_allclose(out.p_ned_m, [100.0, 10.0, -50.0], atol=ATOL_M)
    # P + dt^2 V + (a dt^2 / 2)^2 I = 1 + 4 * 0.04 + (0.5 * 4)^2 = 5.16 per axis
    np.testing.assert_allclose(out.cov_p_ned_m2, np.eye(3) * 5.16, atol=1e-12)
    assert out.t_s == 12.0 and out.range_m == pytest.approx(math.sqrt(100**2 + 10**2 + 50**2))
    np.testing.assert_array_equal(est.cov_p_ned_m2, cov0)
    assert est.t_s == 10.0


def test_a_bearing_narrows_across_the_ray_only_and_the_camera_sigma_limits_it():
    est = _estimate()
    cam = np.zeros(3)
    t = 13.0
    prior = coast_estimate(est, t, cam, cam_sigma_m=0.0, accel_sigma_mps2=1.0)
    u = prior.p_ned_m / np.linalg.norm(prior.p_ned_m)  # the bearing through the propagated point
    sharp = coast_estimate(est, t, cam, cam_sigma_m=0.0, u_ned=u, bearing_sigma_rad=1e-3, accel_sigma_mps2=1.0)
    blurred = coast_estimate(est, t, cam, cam_sigma_m=20.0, u_ned=u, bearing_sigma_rad=1e-3, accel_sigma_mps2=1.0)
    along = lambda e: float(u @ e.cov_p_ned_m2 @ u)  # noqa: E731
    across = lambda e: float(np.trace(e.cov_p_ned_m2)) - along(e)  # noqa: E731
    assert along(sharp) == pytest.approx(along(prior), rel=1e-9)  # range is left to the window
    assert across(sharp) < 0.05 * across(prior)
    assert across(sharp) < across(blurred) < across(prior)  # a dead-reckoned camera is worth less


def test_the_verdict_holds_only_while_the_coasted_range_sigma_stays_small():
    est = _estimate()
    near = coast_estimate(est, 10.5, np.zeros(3), cam_sigma_m=1.0, accel_sigma_mps2=1.0)
    far = coast_estimate(est, 25.0, np.zeros(3), cam_sigma_m=1.0, accel_sigma_mps2=1.0)
    assert near.observable and near.range_sigma_ratio < OBSERVABLE_MAX_RANGE_SIGMA_RATIO
    assert not far.observable and far.range_sigma_ratio > OBSERVABLE_MAX_RANGE_SIGMA_RATIO
    assert not coast_estimate(_estimate(observable=False), 10.5, np.zeros(3), 1.0).observable


def test_an_unobservable_estimate_is_put_on_the_frames_ray_at_its_last_range():
    est = _estimate(observable=False)
    u = np.array([0.0, 0.3, -0.1]) + est.p_ned_m / np.linalg.norm(est.p_ned_m)
    u /= np.linalg.norm(u)  # a bearing some degrees off the estimate's ray
    cam = np.array([1.0, 2.0, 0.0])
    out = coast_estimate(est, 11.0, cam, 1.0, u_ned=u, bearing_sigma_rad=1e-3, accel_sigma_mps2=1.0)
    np.testing.assert_allclose(out.p_ned_m, cam + est.range_m * u, atol=ATOL_M)
    r = est.range_m
    along = (0.01 * r) ** 2 + 1.0 * 0.04 + 0.5**2  # window's range sigma, dt^2 V, (a dt^2 / 2)^2
    across = (r * 1e-3) ** 2 + 1.0 + 0.5**2
    assert float(u @ out.cov_p_ned_m2 @ u) == pytest.approx(along, rel=1e-9)
    assert float(np.trace(out.cov_p_ned_m2)) == pytest.approx(along + 2 * across, rel=1e-9)
    assert not out.observable
