"""The observability verdict and the honesty of every published result (a consumer trusts both).

Rates over seeds, not chosen seeds: the bench (``python -m bench.estimator --verdict``, 50 seeds per
cell) prints the full table; these run a few seeds per cell so that a regression shows in CI.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from groundsim.evaluation.synth import estimator_noise_model, synthesize_scenario
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
from onboard.estimation.map_estimator import MapConfig, MapEstimator
from onboard.estimation.sliding import SlidingWindowEstimator

HONEST_BEYOND_3SIGMA = 0.01  # at most 1 % of points beyond 3 sqrt(trace P)
GOOD_ERR = 0.02  # 2 % of range


def _run(name: str, noise: str, seed: int):
    sc = load_scenario(reference_scenario_paths()[name])
    nc = load_noise_cases()[noise]
    truth, obs = synthesize_scenario(sc, nc, seed)
    res = MapEstimator(noise=estimator_noise_model(nc)).solve(obs)
    e = np.linalg.norm(res.p_ned_m - truth.p_target_ned_m, axis=1)
    beyond = float(np.mean(e > 3 * np.sqrt(np.einsum("fii->f", res.cov_p_ned_m2))))
    return res, float(np.mean(e / truth.range_m)), beyond


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, noise, seeds, min_observable",
    [
        ("P3", "RTK", range(6), 5),  # bench: 50/50
        ("P2", "px0.3", range(4), 4),  # bench: 50/50
        ("P2", "RTK", range(6), 3),  # bench: 38/50 (82 % of its good runs)
    ],
)
def test_observable_runs_are_accurate_and_honest_at_a_rate(name, noise, seeds, min_observable):
    got = [_run(name, noise, s) for s in seeds]
    observable = [(err, beyond) for res, err, beyond in got if res.observable]
    assert len(observable) >= min_observable
    assert np.median([err for err, _ in observable]) <= GOOD_ERR  # precision: the median, as the bench states it
    for err, beyond in observable:
        assert err <= 2 * GOOD_ERR
        assert beyond <= HONEST_BEYOND_3SIGMA


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, noise, seeds", [("H3", "RTK", range(4)), ("H3", "px0.3", range(2)), ("H1", "px0.3", range(2))]
)
def test_unobservable_results_are_flagged_and_still_honest(name, noise, seeds):
    """A straight observer (H3) and a figure-eight target (H1, whose solutions collapse towards the camera)
    are never called observable, and the published covariance still covers the error (range floor)."""
    cfg = MapConfig()
    for s in seeds:
        res, err, beyond = _run(name, noise, s)
        assert not res.observable
        assert beyond <= HONEST_BEYOND_3SIGMA, f"{name} {noise} seed {s}: {beyond:.1%} beyond 3 sigma (err {err:.0%})"
        los = res.p_ned_m - res.problem.obs.p_cam_ned_m
        r = np.linalg.norm(los, axis=1)
        u = los / r[:, None]
        sig_r = np.sqrt(np.einsum("fi,fij,fj->f", u, res.cov_p_ned_m2, u))
        floor = np.maximum(cfg.unobservable_range_sigma_floor * r, cfg.unobservable_range_sigma_min_m)
        assert np.all(sig_r >= floor * (1 - 1e-9))


def test_a_far_mirror_mode_is_ambiguity_not_spread():
    """P1 under RTK attitude errors: a target accelerating in mirror of the observer at ~2x the range
    explains the same bearings (P1 RTK seed 13 puts ~60 % of the posterior there).  The reported solution
    stays the constant-velocity one near the truth; the far mass is its ambiguity and does not widen its
    covariance (the old model average gave it a ~45 % range sigma), and the verdict says unobservable."""
    res, err, beyond = _run("P1", "RTK", 13)
    assert res.ambiguity > MapConfig().max_ambiguity
    assert not res.observable
    assert err < GOOD_ERR
    assert beyond <= HONEST_BEYOND_3SIGMA


def _online_confidence(name: str, geometry, noise: str, seed: int, frames: int, cfg: MapConfig) -> tuple[int, int]:
    """(estimates called observable, of them beyond 3 sqrt(trace P)) of the sliding window over ``frames`` 30 Hz
    frames of scenario ``name`` in the campaign's ``geometry`` (range scale, aspect deg, manoeuvre scale)."""
    from groundsim.evaluation.campaign_spec import Geometry, derive_scenario

    sc = derive_scenario(load_scenario(reference_scenario_paths()[name]), Geometry(*geometry))
    nc = load_noise_cases()[noise]
    t = np.arange(frames) / 30.0
    truth, obs = synthesize_scenario(sc, nc, seed, t_s=t)
    sw = SlidingWindowEstimator(noise=estimator_noise_model(nc), map_config=cfg)
    observable = beyond = 0
    for i in range(t.size):
        est = sw.add(t[i], obs.uv_px[i], sc.camera.intrinsics, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i])
        if est is not None and est.observable:
            observable += 1
            e = np.linalg.norm(est.p_ned_m - truth.p_target_ned_m[i])
            beyond += bool(e > 3 * math.sqrt(np.trace(est.cov_p_ned_m2)))
    return observable, beyond


@pytest.mark.parametrize("turn_starts", [True, False])
def test_a_turning_target_is_not_called_observable_at_the_straight_basins_range(turn_starts):
    """P3's circling target with the observer manoeuvring at 4x its reference: over the first 9 s the CT
    posterior's highest mode turns with the target at its true range, while a CT chain started at zero turn
    stays in the straight basin, which explains the bearings with a target 10-17 % closer.  With the turned
    starts (the default) nothing is called observable there that is beyond 3 sigma; without them (the
    contrast, so that the test can fail) the window reports the straight basin's range as observable."""
    cfg = MapConfig() if turn_starts else MapConfig(turn_rate_starts_radps=())
    observable, beyond = _online_confidence("P3", (1.0, 0.0, 4.0), "px0.3", 0, 270, cfg)
    if turn_starts:
        assert beyond == 0
    else:
        assert observable >= 20 and beyond >= 0.9 * observable


@pytest.mark.parametrize("check", [True, False])
def test_a_turn_the_window_cannot_tell_from_none_does_not_make_a_straight_observer_observable(check):
    """H3 (straight constant-velocity observer, range unobservable), a seed whose pixel noise a 0.04-0.05 rad/s
    turn fits: that CT solution pins range by its rigidity alone, its turn 2-4 sigma from zero.  The turn check
    keeps it unobservable; without it (the contrast) the verdict calls a 25 % error observable."""
    sc = load_scenario(reference_scenario_paths()["H3"])
    nc = load_noise_cases()["px0.3"]
    truth, obs = synthesize_scenario(sc, nc, 33)
    cfg = MapConfig() if check else MapConfig(turn_established_z=1e-9)
    res = MapEstimator(config=cfg, noise=estimator_noise_model(nc)).solve(obs)
    err = float(np.mean(np.linalg.norm(res.p_ned_m - truth.p_target_ned_m, axis=1) / truth.range_m))
    assert res.model == "ct" and err > 0.1
    assert res.observable is not check


@pytest.mark.parametrize("rule", [True, False])
def test_a_far_solution_that_pins_range_itself_is_a_rival_not_a_vague_ambiguity(rule):
    """P1 at half the range, its target turned 180 deg and the observer manoeuvring at 3x, RTK, seed 1: a
    turning mode at 1.5x the range holds ~96 % of the posterior while the straight truth, a few per cent, pins
    range itself.  Two confident answers that disagree: never observable (``max_rival_mass``); without the
    rule (the contrast) every observable estimate of the window is beyond 3 sigma."""
    cfg = MapConfig() if rule else MapConfig(max_rival_mass=1.0)
    observable, beyond = _online_confidence("P1", (0.5, 180.0, 3.0), "RTK", 1, 300, cfg)
    if rule:
        assert beyond == 0
    else:
        assert observable >= 20 and beyond == observable


def test_ambiguity_is_zero_when_all_models_agree():
    res, err, _ = _run("P3", "px0.3", 0)
    assert res.ambiguity < 0.01
    assert res.observable and err < GOOD_ERR
    assert 0.5 < res.residual_rms_norm < 1.5  # standardised residuals of a correct model
    assert res.adequacy_p > MapConfig().adequacy_p_min


def test_sliding_estimates_carry_the_diagnostics_and_propagate():
    sc = load_scenario(reference_scenario_paths()["P3"])
    nc = load_noise_cases()["px0.3"]
    t = np.arange(120) / 30.0
    truth, obs = synthesize_scenario(sc, nc, 1, t_s=t)
    sw = SlidingWindowEstimator(noise=estimator_noise_model(nc))
    est = None
    for i in range(t.size):
        est = sw.add(t[i], obs.uv_px[i], sc.camera.intrinsics, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i]) or est
    assert est is not None
    assert math.isfinite(est.residual_rms_norm) and math.isfinite(est.adequacy_p) and math.isfinite(est.ambiguity)
    if not est.observable:  # a 4 s window: unobservable estimates carry the range floor
        assert est.range_sigma_ratio * est.range_m >= MapConfig().unobservable_range_sigma_min_m * (1 - 1e-9)
    later = est.propagated(est.t_s + 0.5)
    assert later.t_s == pytest.approx(est.t_s + 0.5)
    np.testing.assert_allclose(later.p_ned_m, est.p_ned_m + 0.5 * est.v_ned_mps)
    np.testing.assert_allclose(later.cov_p_ned_m2, est.cov_p_ned_m2 + 0.25 * est.cov_v_ned_m2ps2)
    assert later.residual_rms_norm == est.residual_rms_norm  # diagnostics travel with the estimate


def test_residuals_louder_than_the_assumed_noise_fail_the_adequacy_test_and_are_not_observable():
    """P3 with 0.3 px pixel noise, the estimator told 0.15 px: the fit is as good (same geometry, same
    solution) but its standardised residuals are twice the assumed white noise, so the block-whiteness test
    refuses it although the range sigma and the ambiguity alone would pass."""
    sc = load_scenario(reference_scenario_paths()["P3"])
    nc = load_noise_cases()["px0.3"]
    truth, obs = synthesize_scenario(sc, nc, 0)
    cfg = MapConfig()
    honest = MapEstimator(noise=estimator_noise_model(nc)).solve(obs)
    assert honest.observable and honest.adequacy_p > 0.1
    res = MapEstimator(noise=estimator_noise_model(nc, pixel_sigma_px=0.15)).solve(obs)
    assert 1.7 < res.residual_rms_norm < 2.3  # twice the assumed sigma
    assert res.adequacy_p < cfg.adequacy_p_min
    assert res.range_sigma_ratio < cfg.observability_max_sigma_range_ratio  # not what refuses it
    assert res.ambiguity <= cfg.max_ambiguity
    assert not res.observable
    err = np.linalg.norm(res.p_ned_m - truth.p_target_ned_m, axis=1)
    assert float(np.mean(err / truth.range_m)) < GOOD_ERR  # a good fit, refused for its residuals alone


def test_the_adequacy_p_value_is_the_chi_square_survival_of_the_block_means():
    """``m * sum(block mean^2)`` over B blocks of m frames against chi2(2 B) (scipy's, an independent reference)."""
    from scipy.stats import chi2

    est = MapEstimator(config=MapConfig(adequacy_block_frames=5))
    rng = np.random.default_rng(3)
    r_std = rng.standard_normal((23, 2)) + 0.3  # 4 blocks of 5 frames, 3 frames left over
    means = r_std[:20].reshape(4, 5, 2).mean(axis=1)
    stat = 5 * float(np.sum(means**2))
    assert est._adequacy_p(r_std) == pytest.approx(chi2.sf(stat, 8), rel=1e-9)
    assert est._adequacy_p(r_std[:9]) == 1.0  # one block: no test
