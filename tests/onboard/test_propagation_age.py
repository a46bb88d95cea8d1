"""A carried estimate's covariance knows its age: the motion model's process noise over the time carried."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.estimation.map_estimator import MotionPrior
from onboard.estimation.sliding import TrackEstimate, process_cov_ned_m2

RTOL = 1e-12


def _estimate(prior: MotionPrior | None) -> TrackEstimate:
    return TrackEstimate(
        t_s=10.0,
        p_ned_m=np.array([500.0, 0.0, -100.0]),
        v_ned_mps=np.array([0.0, 20.0, 0.0]),
        cov_p_ned_m2=np.eye(3) * 4.0,
        cov_v_ned_m2ps2=np.eye(3) * 0.25,
        observable=True,
        range_m=510.0,
        range_sigma_ratio=0.004,
        window_frames=300,
        model="cv",
        motion_prior=prior,
    )


@pytest.mark.parametrize(
    "prior, per_axis",
    [
        (MotionPrior(0.1, 0.05, turn_rate_sigma_radps=0.0), lambda q, dt: q * dt**3 / 3.0),
        (MotionPrior(0.1, 0.05, turn_rate_sigma_radps=0.3), lambda q, dt: q * dt**3 / 3.0),
        (MotionPrior(0.1, 0.05, turn_rate_sigma_radps=0.0, jerk=True), lambda q, dt: q * dt**5 / 20.0),
    ],
)
@pytest.mark.parametrize("dt_s", [0.1, 0.7, 2.0])
def test_process_noise_per_axis(prior, per_axis, dt_s):
    Q = process_cov_ned_m2(prior, dt_s)
    expected = np.diag([per_axis(0.1, dt_s), per_axis(0.1, dt_s), per_axis(0.05, dt_s)])
    np.testing.assert_allclose(Q, expected, rtol=RTOL)


def test_no_model_or_no_time_adds_nothing():
    assert not process_cov_ned_m2(None, 1.0).any()
    assert not process_cov_ned_m2(MotionPrior(0.1, 0.1), 0.0).any()


@pytest.mark.parametrize("dt_s", [0.5, -0.5])
def test_propagated_adds_velocity_and_process_noise_for_the_age(dt_s):
    prior = MotionPrior(0.1, 0.05, turn_rate_sigma_radps=0.0)
    est = _estimate(prior)
    out = est.propagated(est.t_s + dt_s)
    expected = est.cov_p_ned_m2 + dt_s**2 * est.cov_v_ned_m2ps2 + process_cov_ned_m2(prior, abs(dt_s))
    np.testing.assert_allclose(out.cov_p_ned_m2, expected, rtol=RTOL)
    np.testing.assert_allclose(out.p_ned_m, est.p_ned_m + dt_s * est.v_ned_mps, rtol=RTOL)
    # grows with the age: an older estimate is never published as more certain
    older = est.propagated(est.t_s + 2 * dt_s)
    assert np.trace(older.cov_p_ned_m2) > np.trace(out.cov_p_ned_m2) > np.trace(est.cov_p_ned_m2)
    assert out.motion_prior is prior


def test_propagated_without_model_is_the_velocity_term_alone():
    est = _estimate(None)
    out = est.propagated(est.t_s + 1.0)
    np.testing.assert_allclose(out.cov_p_ned_m2, est.cov_p_ned_m2 + est.cov_v_ned_m2ps2, rtol=RTOL)
