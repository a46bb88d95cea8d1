"""Bayesian Cramer-Rao bound and the efficient-estimator floor of the accuracy table."""

from __future__ import annotations

import numpy as np
import pytest

from groundsim.evaluation.synth import estimator_noise_model, synthesize_scenario
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
from onboard.estimation.crb import bayesian_crb
from onboard.estimation.map_estimator import MapEstimator, MotionPrior

CV_STIFF = MotionPrior(1e-6, 2.5e-7, 0.0)
DRAW_RTOL = 0.05  # Monte-Carlo RMS of 4000 window draws vs the bound they were drawn from
MC_RATIO = (0.7, 1.4)  # 30-seed RMS of an efficient estimator over the bound: chi2(~30) spread, 5-sigma wide


def _p1(seed: int, noise: str = "px0.3"):
    nc = load_noise_cases()[noise]
    truth, obs = synthesize_scenario(load_scenario(reference_scenario_paths()["P1"]), nc, seed)
    return MapEstimator(noise=estimator_noise_model(nc)), truth, obs


def test_bound_is_symmetric_positive_definite_and_shrinks_with_pixel_noise():
    est, truth, obs = _p1(0)
    bound = bayesian_crb(est, obs, truth.p_target_ned_m, CV_STIFF)
    S = bound.covariance
    np.testing.assert_allclose(S, S.T, atol=1e-9 * np.abs(S).max())
    assert np.linalg.eigvalsh(S).min() > 0
    crb = bound.rms_m()
    assert 0.3 < crb < 3.0  # the reference study's 0.85 m for this cell
    from onboard.estimation.map_estimator import NoiseModel

    fine = MapEstimator(noise=NoiseModel(pixel_sigma_px=0.03))
    # the linearised problem scales: pixel noise / 10 with the process noise PSD / 100 is the same problem with
    # every standard deviation / 10 (only the weak, km-scale priors do not scale, which costs < 1 %)
    stiffer = MotionPrior(CV_STIFF.q_horizontal_m2ps3 / 100, CV_STIFF.q_vertical_m2ps3 / 100, 0.0)
    assert bayesian_crb(fine, obs, truth.p_target_ned_m, stiffer).rms_m() == pytest.approx(crb / 10, rel=0.01)
    # with the same prior, the finer pixel still gains, but the process noise now limits it
    assert crb / 10 < bayesian_crb(fine, obs, truth.p_target_ned_m, CV_STIFF).rms_m() < crb / 2


def test_efficient_draws_reproduce_the_bound_they_come_from():
    est, truth, obs = _p1(0)
    bound = bayesian_crb(est, obs, truth.p_target_ned_m, CV_STIFF)
    crb = bound.rms_m()
    pct = bound.efficient_error_range_pct(draws=4000, rng=np.random.default_rng(3))
    assert pct.shape == (4000,) and np.all(pct > 0)
    # mean error / range is ~ RMS error / range for a range-scale error; it cannot exceed the RMS one
    rms_pct = crb / np.mean(truth.range_m) * 100
    assert np.median(pct) < rms_pct * (1 + DRAW_RTOL)
    assert np.median(pct) > 0.3 * rms_pct


def test_map_estimator_is_efficient_on_p1():
    """Our MAP with the true model reaches the bound: RMS over 30 seeds within a chi-square spread of it."""
    sq = []
    for seed in range(30):
        est, truth, obs = _p1(seed)
        res = est.solve(obs, CV_STIFF)
        sq.append(np.mean(np.sum((res.p_ned_m - truth.p_target_ned_m) ** 2, axis=1)))
    est, truth, obs = _p1(0)
    crb = bayesian_crb(est, obs, truth.p_target_ned_m, CV_STIFF).rms_m()
    ratio = float(np.sqrt(np.mean(sq))) / crb
    assert MC_RATIO[0] < ratio < MC_RATIO[1], ratio
