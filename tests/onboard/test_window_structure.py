"""WindowProblem's structured normal equations: J^T J and J^T r built from the Jacobian's knot-interval structure
(normal_matrix, gradient) are the dense products of the Jacobian evaluate() returns, for every parameter layout."""

from __future__ import annotations

import numpy as np
import pytest

from groundsim.evaluation.synth import synthesize_scenario
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
from onboard.estimation.map_estimator import MapEstimator
from onboard.estimation.window_problem import NoiseModel

#: the structured sums run in another order than the dense products: agreement to rounding, relative to the
#: column scales (the Cholesky factorisation sees H / (d d^T))
SCALED_RTOL = 1e-13

NOISE_LAYOUTS = {
    "pixels only": NoiseModel(),
    "attitude bias": NoiseModel(attitude_bias_sigma_rad=0.005),
    "offset and drift": NoiseModel(camera_position_offset_sigma_m=1.0, camera_position_drift_sigma_mps=0.1),
    "every nuisance": NoiseModel(
        attitude_bias_sigma_rad=0.005,
        attitude_white_sigma_rad=0.001,
        camera_position_white_sigma_m=0.3,
        camera_position_offset_sigma_m=1.0,
        camera_position_drift_sigma_mps=0.1,
    ),
}


@pytest.fixture(scope="module")
def window():
    """P2 under RTK errors, every third frame of its 10 s, with a 1.5 s gap: one knot interval without a row and
    uneven counts in its neighbours (the zero padding of the interval sums)."""
    sc = load_scenario(reference_scenario_paths()["P2"])
    t = sc.frame_times_s()[::3]
    t = t[(t < 4.0) | (t > 5.5)]
    _, obs = synthesize_scenario(sc, load_noise_cases()["RTK"], 0, t_s=t)
    return obs


def _problem(obs, noise: NoiseModel, family: str):
    est = MapEstimator(noise=noise)
    prob = est.problem(obs, est.config.motion_prior(family, 1e-3))
    theta = est.initial_guesses(prob)[2]
    # every nuisance and the turn rate away from zero, so that their columns and cross terms are exercised
    theta[prob.nc :] = np.linspace(0.02, -0.03, prob.n_params - prob.nc)
    return prob, theta


@pytest.mark.parametrize("family", ["cv", "ct", "ca"])
@pytest.mark.parametrize("layout", sorted(NOISE_LAYOUTS))
def test_structured_normal_equations_are_the_dense_products(window, layout, family):
    prob, theta = _problem(window, NOISE_LAYOUTS[layout], family)
    per_interval = np.bincount(prob.rows.index[:, 0], minlength=prob.count - 3)
    assert per_interval.min() == 0 and per_interval.max() > 2  # the gap, and the padding of the others
    r, J, valid = prob.evaluate(theta)
    assert valid
    J = J.copy()
    H_dense, g_dense = J.T @ J, J.T @ r
    H, g = prob.normal_matrix(), prob.gradient(r)
    d = np.sqrt(np.diag(H_dense))
    assert np.all(d > 0)
    np.testing.assert_array_less(np.abs(H - H_dense), SCALED_RTOL * np.outer(d, d))
    np.testing.assert_array_less(np.abs(g - g_dense), SCALED_RTOL * d * np.linalg.norm(r))
    # the linearisation the solver runs (no dense Jacobian) leaves the same pieces behind
    r2, _ = prob.linearise(theta)
    np.testing.assert_array_equal(r2, r)
    np.testing.assert_array_equal(prob.normal_matrix(), H)


def test_a_rejected_linearisation_without_jacobian_keeps_the_last_ones_pieces(window):
    prob, theta = _problem(window, NOISE_LAYOUTS["attitude bias"], "ct")
    prob.linearise(theta)
    H = prob.normal_matrix()
    far = theta.copy()
    far[: prob.nc] *= 1.1
    prob.linearise(far, jacobian=False)
    np.testing.assert_array_equal(prob.normal_matrix(), H)


def test_the_range_hypotheses_are_the_line_of_sight_fits_and_shared_by_a_windows_problems(window):
    est = MapEstimator(noise=NOISE_LAYOUTS["pixels only"])
    cv = est.problem(window, est.config.motion_prior("cv", 1e-3))
    ct = est.problem(window, est.config.motion_prior("ct", 1e-3))
    for r0 in est.config.init_ranges_m:
        expected = cv.theta_from_positions(window.p_cam_ned_m + r0 * window.bearings_ned())
        np.testing.assert_array_equal(cv.theta_along_lines_of_sight(r0), expected)
        on_ct = ct.theta_along_lines_of_sight(r0)
        np.testing.assert_array_equal(on_ct[: ct.nc], expected[: cv.nc])
        assert on_ct[ct.i_omega] == 0.0


def test_the_observations_point_covariances_by_knot_interval_are_the_per_row_ones(window):
    prob, theta = _problem(window, NOISE_LAYOUTS["attitude bias"], "ct")
    _, J, _ = prob.evaluate(theta)
    Sigma = prob.covariance(prob.factor(J))
    by_interval = prob.point_covariances(Sigma)
    per_row = prob.point_covariances(Sigma, rows=prob.rows)  # rows given: the general path
    assert by_interval.shape == (prob.F, 3, 3)
    scale = np.sqrt(np.einsum("fii->fi", per_row))
    np.testing.assert_array_less(np.abs(by_interval - per_row), 1e-12 * scale[:, :, None] * scale[:, None, :])


@pytest.mark.parametrize("family", ["cv", "ct", "ca"])
def test_the_factor_from_the_normal_equations_is_the_qr_ones(window, family):
    est = MapEstimator(noise=NOISE_LAYOUTS["attitude bias"])
    prob = est.problem(window, est.config.motion_prior(family, 1e-3))
    sol = prob.solve(est.initial_guesses(prob)[2], max_iterations=20, want_factor=False, dense_jacobian=False)
    assert prob.last_jacobian is None  # not formed
    R, d = prob.normal_factor()
    _, J, _ = prob.evaluate(sol.theta)
    R_qr, d_qr = prob.factor(J)
    # R^T R is the scaled normal matrix either way; the rows' signs are the QR's own
    np.testing.assert_allclose(np.abs(np.diag(R)), np.abs(np.diag(R_qr)), rtol=1e-6)
    np.testing.assert_allclose(d, d_qr, rtol=1e-12)
    assert prob.log_evidence(sol.theta, sol.cost, (R, d)) == pytest.approx(
        prob.log_evidence(sol.theta, sol.cost, (R_qr, d_qr)), abs=1e-5
    )
    Sigma, Sigma_qr = prob.covariance((R, d)), prob.covariance((R_qr, d_qr))
    scale = np.sqrt(np.diag(Sigma_qr))
    np.testing.assert_array_less(np.abs(Sigma - Sigma_qr), 1e-6 * np.outer(scale, scale))


def test_an_ill_conditioned_normal_factor_falls_back_to_the_qr(window, monkeypatch):
    from onboard.estimation import window_problem

    est = MapEstimator(noise=NOISE_LAYOUTS["attitude bias"])
    prob = est.problem(window, est.config.motion_prior("cv", 1e-3))
    theta = prob.solve(est.initial_guesses(prob)[2], max_iterations=20, want_factor=False).theta
    J = prob.last_jacobian.copy()
    prob.linearise(theta)
    monkeypatch.setattr(window_problem, "_NORMAL_FACTOR_MAX_SPAN", 1.0)  # every factor "ill-conditioned"
    R, d = prob.normal_factor()
    R_qr, d_qr = prob.factor(J)
    np.testing.assert_array_equal(R, R_qr)
    np.testing.assert_array_equal(d, d_qr)
