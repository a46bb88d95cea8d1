"""The window problem's compiled kernels (onboard.estimation.kernels) against their numpy references, over random
windows and parameter layouts; and that the estimator compiles them at its construction, never in a step."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.evaluation.synth import estimator_noise_model, synthesize_scenario
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
from onboard.estimation import kernels, window_problem
from onboard.estimation.map_estimator import MapEstimator
from onboard.estimation.sliding import SlidingConfig, SlidingWindowEstimator

REPO = Path(__file__).resolve().parents[2]

#: the kernels sum in index order where numpy handed the sums to BLAS: agreement to rounding, relative to the
#: largest magnitude of the compared array (what a Cholesky factorisation or a residual norm sees)
RTOL = 1e-12

LAYOUTS = st.tuples(st.booleans(), st.booleans(), st.booleans())  # attitude bias, offset, drift


def _close(actual, expected, rtol=RTOL):
    scale = max(float(np.max(np.abs(expected))), 1e-300)
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rtol * scale)


def _window(rng, F, count):
    """A random window: sorted knot intervals, B-spline-like positive weights summing to one, controls ahead of
    cameras looking roughly at them (most rows valid, some not), random weights and measurements."""
    seg = np.sort(rng.integers(0, count - 3, F))
    index = (seg[:, None] + np.arange(4)).astype(np.int64)
    w0 = rng.uniform(0.01, 1.0, (F, 4))
    w0 /= w0.sum(axis=1, keepdims=True)
    c = rng.normal(0.0, 50.0, (count, 3)) + [300.0, 20.0, -40.0]
    p_cam_T = np.ascontiguousarray(rng.normal(0.0, 5.0, (F, 3)).T)
    # cameras whose optical axis (row 2 of R_cn) points north, tilted at random
    R_T = np.empty((3, 3, F))
    for f in range(F):
        q, rr = np.linalg.qr(np.eye(3) + 0.2 * rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(rr))  # near the identity
        R_T[:, :, f] = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]) @ q
    xy_T = rng.normal(0.0, 0.2, (2, F))
    sT = rng.uniform(500.0, 5000.0, (2, F))
    dt = np.linspace(-5.0, 5.0, F)
    return index, w0, c, p_cam_T, R_T, xy_T, sT, dt


def _nuisances(rng, layout):
    phi, beta, gamma = layout
    Rphi = window_problem._rodrigues(rng.normal(0.0, 0.02, 3)) if phi else np.zeros((0, 0))
    b = rng.normal(0.0, 2.0, 3) if beta else np.zeros(0)
    g = rng.normal(0.0, 0.2, 3) if gamma else np.zeros(0)
    return Rphi, b, g


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.integers(4, 12), LAYOUTS, st.booleans())
def test_linearise_measurements_is_the_numpy_formulation(seed, F, count, layout, jacobian):
    rng = np.random.default_rng(seed)
    index, w0, c, p_cam_T, R_T, xy_T, sT, dt = _window(rng, F, count)
    Rphi, beta, gamma = _nuisances(rng, layout)
    u = 3 + 3 * sum(layout)
    outs = []
    for fn in (kernels.linearise_measurements, kernels.linearise_measurements_reference):
        X, los, r, U = np.full((3, F), np.nan), np.full((3, F), np.nan), np.full(2 * F, np.nan), np.zeros((2, u, F))
        valid = fn(c, index, w0, p_cam_T, beta, gamma, dt, Rphi, R_T, xy_T, sT, jacobian, X, los, r, U)
        outs.append((valid, X, los, r, U))
    (valid, X, los, r, U), (valid_ref, X_ref, los_ref, r_ref, U_ref) = outs
    assert valid == valid_ref
    _close(X, X_ref)
    _close(los, los_ref)
    _close(r, r_ref)
    _close(U, U_ref)
    if not jacobian:
        assert not U.any()  # the last linearisation's pieces stay as they were


def test_an_invalid_row_is_found_and_the_others_still_written():
    rng = np.random.default_rng(3)
    index, w0, c, p_cam_T, R_T, xy_T, sT, dt = _window(rng, 10, 6)
    c[:, 0] = -300.0  # every control behind the north-looking cameras
    X, los, r, U = np.empty((3, 10)), np.empty((3, 10)), np.empty(20), np.zeros((2, 3, 10))
    valid = kernels.linearise_measurements(
        c, index, w0, p_cam_T, np.zeros(0), np.zeros(0), dt, np.zeros((0, 0)), R_T, xy_T, sT, True, X, los, r, U
    )
    assert not valid
    assert np.isfinite(r).all() and np.isfinite(U).all()  # the depth clamped at 1e-9, as np.fmax


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.integers(4, 12), st.integers(0, 3))
def test_measurement_gram_and_gradient_are_the_dense_products(seed, F, count, nuisance_blocks):
    rng = np.random.default_rng(seed)
    index, w0, *_ = _window(rng, F, count)
    nm = 3 * nuisance_blocks
    n = 3 * count + 1 + nm  # a turn rate's column between the controls and the nuisances
    nuis_cols = np.arange(3 * count + 1, n, dtype=np.int64)
    U = rng.normal(0.0, 1e3, (2, 3 + nm, F))
    r = rng.normal(0.0, 1.0, 2 * F + 7)
    Hf = rng.normal(size=(n, n))
    H_fixed = Hf @ Hf.T
    H, H_ref = np.full((n, n), np.nan), np.full((n, n), np.nan)
    kernels.measurement_gram(U, index, w0, nuis_cols, H_fixed, H)
    kernels.measurement_gram_reference(U, index, w0, nuis_cols, H_fixed, H_ref)
    _close(H, H_ref)
    np.testing.assert_array_equal(H, H.T)
    g, g_ref = np.full(n, np.nan), np.full(n, np.nan)
    kernels.measurement_gradient(U, r, index, w0, nuis_cols, g)
    kernels.measurement_gradient_reference(U, r, index, w0, nuis_cols, g_ref)
    _close(g, g_ref)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(5, 14), st.floats(-0.5, 0.5))
def test_the_turn_priors_kernels_are_the_dense_products(seed, count, om):
    rng = np.random.default_rng(seed)
    G = 3 * (count - 3)
    # banded like the bases: row g touches the 4 controls of its interval
    Bq1, Bq2 = np.zeros((G, count)), np.zeros((G, count))
    for g in range(G):
        Bq1[g, g // 3 : g // 3 + 4] = rng.normal(size=4)
        Bq2[g, g // 3 : g // 3 + 4] = rng.normal(size=4)
    sq_h, sq_v = rng.uniform(0.1, 10.0, G), rng.uniform(0.1, 10.0, G)
    nc = 3 * count
    # the prior rows' Jacobian on the controls: sq Bq2 per axis, om sq_h Bq1 east -> north, minus north -> east
    Jp = np.zeros((3 * G, nc))
    for ax, sq in ((0, sq_h), (1, sq_h), (2, sq_v)):
        Jp[ax::3, ax::3] = sq[:, None] * Bq2
    Jp[0::3, 1::3] += om * sq_h[:, None] * Bq1
    Jp[1::3, 0::3] -= om * sq_h[:, None] * Bq1
    x = rng.normal(size=3 * G)
    out = np.ones(nc)
    kernels.add_turn_prior_transpose(Bq1, Bq2, sq_h, sq_v, x, om, out)
    _close(out, 1.0 + Jp.T @ x)
    P_acc, P_turn = np.zeros_like(Jp), np.zeros_like(Jp)
    for ax, sq in ((0, sq_h), (1, sq_h), (2, sq_v)):
        P_acc[ax::3, ax::3] = sq[:, None] * Bq2
    P_turn[0::3, 1::3] = sq_h[:, None] * Bq1
    P_turn[1::3, 0::3] = -sq_h[:, None] * Bq1
    A, B, C = P_acc.T @ P_acc, P_acc.T @ P_turn + P_turn.T @ P_acc, P_turn.T @ P_turn
    j_om = rng.normal(size=3 * G)
    J = np.hstack([Jp, j_om[:, None]])
    H = np.zeros((nc + 1, nc + 1))
    kernels.add_turn_prior_gram(H, A, B, C, om, Bq1, Bq2, sq_h, sq_v, j_om, nc)
    _close(H, J.T @ J)

    c = rng.normal(0.0, 100.0, (count, 3))
    rp, j_omega = np.full(3 * G, np.nan), np.zeros(3 * G)
    kernels.turn_prior_rows(Bq1, Bq2, sq_h, sq_v, c, om, rp, j_omega, True)
    _close(rp, P_acc @ c.reshape(-1) + om * (P_turn @ c.reshape(-1)))
    v = Bq1 @ c
    _close(j_omega, np.stack([sq_h * v[:, 1], -sq_h * v[:, 0], np.zeros(G)], axis=1).reshape(-1))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 30), st.booleans())
def test_the_column_scaling_is_numpys_bit_for_bit(seed, n, zero_column):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n + 3, n)) * np.exp(rng.uniform(-10.0, 10.0, n))
    if zero_column:
        A[:, rng.integers(n)] = 0.0
    H, g = A.T @ A, rng.normal(size=n)
    d_ref = np.sqrt(H.diagonal())
    d_ref[d_ref == 0] = 1.0
    H_ref, g_ref = H / np.multiply.outer(d_ref, d_ref), g / d_ref
    d = kernels.scale_normal_equations(H, g)
    np.testing.assert_array_equal(d, d_ref)
    np.testing.assert_array_equal(H, H_ref)
    np.testing.assert_array_equal(g, g_ref)


@pytest.fixture(scope="module")
def bench_window():
    """P1 under RTK errors (the bench's window: F = 300, attitude bias and position nuisances)."""
    sc = load_scenario(reference_scenario_paths()["P1"])
    noise = load_noise_cases()["RTK"]
    _, obs = synthesize_scenario(sc, noise, 0)
    return obs, estimator_noise_model(noise), sc.camera.intrinsics


def test_the_estimator_compiles_the_kernels_at_construction_for_the_types_a_selection_passes(bench_window):
    obs, noise, intrinsics = bench_window
    est = MapEstimator(noise=noise)
    dispatchers = [
        kernels.linearise_measurements,
        kernels.measurement_gram,
        kernels.measurement_gradient,
        kernels.add_turn_prior_gram,
        kernels.add_turn_prior_transpose,
        kernels.turn_prior_rows,
        kernels.scale_normal_equations,
    ]
    compiled = [list(d.signatures) for d in dispatchers]
    assert all(len(s) == 1 for s in compiled)
    sel = est.solve(obs)
    assert np.isfinite(sel.p_ned_m).all()
    # the sliding window's own calls too: its provisional first choice, the spread selections, the re-solves
    sw = SlidingWindowEstimator(SlidingConfig(), noise=noise)
    estimates = [
        sw.add(obs.t_s[i], obs.uv_px[i], intrinsics, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i]) for i in range(len(obs))
    ]
    assert sum(e is not None for e in estimates) > len(obs) // 2
    # no kernel compiled again: every call (every family and nuisance layout) matched warm()'s types
    assert [list(d.signatures) for d in dispatchers] == compiled


def test_a_selection_with_the_kernels_is_the_numpy_formulations(bench_window, monkeypatch):
    obs, noise, _ = bench_window
    ours = MapEstimator(noise=noise).solve(obs)
    monkeypatch.setattr(window_problem, "linearise_measurements", kernels.linearise_measurements_reference)
    monkeypatch.setattr(window_problem, "measurement_gram", kernels.measurement_gram_reference)
    monkeypatch.setattr(window_problem, "measurement_gradient", kernels.measurement_gradient_reference)
    ref = MapEstimator(noise=noise).solve(obs)
    assert ours.prior == ref.prior and ours.observable == ref.observable
    _close(ours.theta, ref.theta, rtol=1e-9)
    # the covariance comes from the Cholesky factor of the normal equations, which squares the condition number
    # (~1e10 scaled here): rounding-level differences of J^T J move it by ~1e-5 of itself
    _close(ours.cov_p_ned_m2, ref.cov_p_ned_m2, rtol=1e-3)
    assert ours.log_evidence == pytest.approx(ref.log_evidence, abs=1e-5)


@pytest.mark.parametrize("module", ["onboard.estimation.window_problem", "onboard.imaging.objects"])
def test_without_numba_the_import_fails_naming_it(module):
    code = f"import sys; sys.modules['numba'] = None\nimport {module}"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "compiled kernels need numba" in done.stderr and "pip install ." in done.stderr
