"""The objects chain's constant-velocity fits under a noisy camera attitude (onboard.imaging.objects_model):
the projection's variance under a white attitude error, and the fit's allowance for it."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics, quat_from_rotvec, rotmat_from_quat
from onboard.imaging.objects_association import COAST_FIT_MIN, fitted_coast
from onboard.imaging.objects_model import attitude_jitter_px2, fit_constant_velocity, los_from_pixel

K = PinholeIntrinsics(764.7, 764.7, 320.0, 256.0, 640, 512)
SIGMA_RAD = math.radians(0.05)  # RTK's white attitude error, 1 sigma per axis
MC_DRAWS = 20000
MC_REL_TOL = 0.05  # the Monte Carlo variance of 20 000 draws is within ~2 % (1 sigma)
FIT_LIMIT_PX = 0.5  # ObjectParams.max_fit_rms_px


def _projected(R: np.ndarray, los: np.ndarray) -> tuple[float, float]:
    c = R.T @ los
    return K.fx_px * c[0] / c[2] + K.cx_px, K.fy_px * c[1] / c[2] + K.cy_px


def _rotmats(rotvecs: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors (n, 3), all at once (Rodrigues' formula)."""
    theta = np.linalg.norm(rotvecs, axis=1)
    k = rotvecs / theta[:, None]
    kx = np.zeros((len(k), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx -= kx.transpose(0, 2, 1)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * kx + (1.0 - c) * kx @ kx


@settings(max_examples=15, deadline=None)
@given(st.floats(0.0, 640.0), st.floats(0.0, 512.0))
def test_the_jitter_variance_is_the_projections_under_random_attitude_errors(u, v):
    """Lines of sight made at (u, v) with the camera rotated by a white error about its own axes, projected
    back through the exact attitude: their variance is attitude_jitter_px2's (the pinhole's Jacobian).  The
    draws are rotated all at once; the first ones through the project's own functions, which they must equal
    (20 000 draws one by one took ~1 s an example)."""
    rng = np.random.default_rng(int(u * 1000 + v))
    R = np.eye(3)
    d = rng.normal(0.0, SIGMA_RAD, (MC_DRAWS, 3))
    los = _rotmats(d) @ los_from_pixel(K, u, v, R)  # the camera's own axes: R @ R_err, with R the identity
    for i in range(20):
        one = los_from_pixel(K, u, v, R @ rotmat_from_quat(quat_from_rotvec(d[i])))
        assert np.allclose(los[i], one, rtol=0.0, atol=1e-12)
        assert np.allclose(_projected(R, los[i]), _projected(R, one), rtol=0.0, atol=1e-9)
    pu = K.fx_px * los[:, 0] / los[:, 2] + K.cx_px  # _projected, R the identity
    pv = K.fy_px * los[:, 1] / los[:, 2] + K.cy_px
    var = float(pu.var() + pv.var())
    assert math.isclose(var, attitude_jitter_px2(K, u, v, SIGMA_RAD), rel_tol=MC_REL_TOL)


def test_the_jitter_grows_off_axis():
    centre = attitude_jitter_px2(K, K.cx_px, K.cy_px, SIGMA_RAD)
    assert math.isclose(centre, 2 * (SIGMA_RAD * K.fx_px) ** 2)  # 0.67 px per axis at RTK's 0.05 deg
    assert attitude_jitter_px2(K, 620.0, 500.0, SIGMA_RAD) > 1.3 * centre


def _history(rng: np.random.Generator, n: int, jump_px: float, sigma_rad: float) -> tuple[list, np.ndarray]:
    """A point moving 0.4 px a frame in bearing space while the camera swings about its y axis (0.01 rad, so its
    pixels do not fit a line), measured with 0.1 px centroid noise, each line of sight made with that frame's
    reported attitude (in error by ``sigma_rad`` per axis); every 4th position ``jump_px`` off in v.  Returns
    the history and the last frame's true attitude."""
    hist, R_k = [], np.eye(3)
    for k in range(n):
        R_k = rotmat_from_quat(quat_from_rotvec(np.array([0.0, 0.01 * math.sin(k / 2.0), 0.0])))
        los_true = los_from_pixel(K, 200.0 + 0.4 * k, 300.0 + (jump_px if k % 4 == 2 else 0.0), np.eye(3))
        u, v = _projected(R_k, los_true)
        u, v = u + rng.normal(0.0, 0.1), v + rng.normal(0.0, 0.1)
        R_rep = R_k @ rotmat_from_quat(quat_from_rotvec(rng.normal(0.0, sigma_rad, 3)))
        hist.append((k, los_from_pixel(K, u, v, R_rep), u, v))
    return hist, R_k


def _rms(hist_R: tuple[list, np.ndarray], sigma_rad: float) -> float:
    hist, R = hist_R
    return float(fit_constant_velocity(K, [hist], R, sigma_rad)[1][0])


def test_the_fit_allows_for_the_attitude_error_and_not_for_more():
    """15 positions of a constant-velocity point seen by a swinging camera under RTK's attitude error: without
    the allowance the fit exceeds 0.5 px on most draws, with it on few (its ~2-sigma quantile); a point
    jumping 3 px every 4th frame fails with it, and with an exact attitude its fit is well inside.  (Under
    this attitude error the projected positions cannot tell a 2 px jump every 4th frame from the noise: it
    fails on ~60 % of draws.)"""
    rng = np.random.default_rng(3)
    draws = 200
    plain = np.array([_rms(_history(rng, 15, 0.0, SIGMA_RAD), 0.0) for _ in range(draws)])
    allowed = np.array([_rms(_history(rng, 15, 0.0, SIGMA_RAD), SIGMA_RAD) for _ in range(draws)])
    jumpy = np.array([_rms(_history(rng, 15, 3.0, SIGMA_RAD), SIGMA_RAD) for _ in range(50)])
    exact = np.array([_rms(_history(rng, 15, 0.0, 0.0), 0.0) for _ in range(50)])
    assert np.mean(plain > FIT_LIMIT_PX) > 0.8
    assert np.mean(allowed > FIT_LIMIT_PX) < 0.05
    assert np.mean(jumpy > FIT_LIMIT_PX) > 0.95
    assert np.all(exact < 0.5 * FIT_LIMIT_PX)


def test_the_daemon_gives_the_chain_its_configured_attitude_noise():
    """The objects chain allows for the attitude error the estimator is configured with (0.05 deg by default,
    RTK's), not a constant of its own."""
    from onboard.app.config import build_config
    from onboard.pipeline.frame_pipeline import make_tracker

    default = make_tracker(build_config({"imaging": {"chain": "objects"}}))
    assert math.isclose(default.objects.params.attitude_white_sigma_rad, math.radians(0.05))
    other = make_tracker(
        build_config({"imaging": {"chain": "objects"}, "estimator": {"attitude_white_sigma_deg": 0.2}})
    )
    assert math.isclose(other.objects.params.attitude_white_sigma_rad, math.radians(0.2))
    assert other.objects.params.primary_max_off_axis_rad == default.objects.params.primary_max_off_axis_rad


def _shift_inputs(preds, cands, held, gate_px=4.0):
    from onboard.imaging.objects_association import common_shift

    puv, cuv = np.array(preds, float), np.array(cands, float)
    d = np.hypot(puv[:, 0:1] - cuv[None, :, 0], puv[:, 1:2] - cuv[None, :, 1])
    return common_shift(puv, cuv, d, np.full(len(puv), gate_px), held)


def test_the_frames_common_offset_is_the_median_over_unambiguous_held_tracks():
    """Three held tracks each measured (1.2, -0.8) px off its prediction (one 0.3 px more): the median; a track
    not held, or one whose candidate another gate shares, does not count; fewer than two: none (a lone
    track's own innovation is not the frame's); over COMMON_SHIFT_MAX_PX: none."""
    preds = [(100.0, 100.0), (200.0, 150.0), (300.0, 80.0)]
    off = [(1.2, -0.8), (1.5, -0.8), (1.2, -0.5)]
    cands = [(p[0] + o[0], p[1] + o[1]) for p, o in zip(preds, off)]
    np.testing.assert_allclose(_shift_inputs(preds, cands, [True, True, True]), (1.2, -0.8))
    assert _shift_inputs(preds, cands, [True, False, False]) is None
    # two predictions 2 px apart share both candidates: neither is unambiguous, the third alone is too few
    crowded = [(100.0, 100.0), (102.0, 100.0), (300.0, 80.0)]
    assert _shift_inputs(crowded, [(101.0, 100.0), (103.0, 100.0), (301.2, 79.2)], [True, True, True]) is None
    far = [(p[0] + 3.5, p[1]) for p in preds]
    assert _shift_inputs(preds, far, [True, True, True], gate_px=5.0) is None


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3),
    st.lists(st.floats(-2e-3, 2e-3), min_size=3, max_size=3),
    st.integers(COAST_FIT_MIN, 15),
    st.integers(1, 40),
)
def test_a_coasting_track_follows_the_line_fitted_to_its_positions(a, b, n, ahead):
    """Lines of sight on a straight line (frames 100, 101, ...; one skipped): the coast starts where the line is on
    the asked frame, with its rate; with fewer than COAST_FIT_MIN positions there is no fit (the filter's rate)."""
    base, rate = np.array([0.1, 0.0, 1.0]) + np.array(a), np.array(b)
    frames = [100 + i + (i > 2) for i in range(n)]  # a missed frame inside
    history = [(f, base + rate * f, 0.0, 0.0) for f in frames]
    k = frames[-1] + ahead
    los, fitted_rate = fitted_coast(history, k)
    expected = base + rate * k
    np.testing.assert_allclose(los, expected / np.linalg.norm(expected), atol=1e-9)
    np.testing.assert_allclose(fitted_rate, rate, atol=1e-10)
    assert fitted_coast(history[: COAST_FIT_MIN - 1], k) is None


def test_the_fitted_coast_drifts_less_than_the_filters_rate_under_the_attitude_error():
    """An object moving 0.5 px a frame, measured through a camera attitude with RTK's white error (0.05 deg, 0.67 px
    per axis) for 15 frames, then coasting 30: over 200 draws the line fitted to the 15 positions lands a median
    ~1.7 px from it (the slope's own error, ~0.04 px a frame, times 37 frames), the alpha-beta filter's last rate
    (ObjectParams alpha, beta) ~4.4 px."""
    rng = np.random.default_rng(5)
    alpha, beta, ahead = 0.6, 0.15, 30
    err_fit, err_filter = [], []
    for _ in range(200):
        history, los, rate = [], None, np.zeros(3)
        for f in range(15):
            R = rotmat_from_quat(quat_from_rotvec(rng.normal(0.0, SIGMA_RAD, 3)))
            zm = R @ los_from_pixel(K, 300.0 + 0.5 * f, 250.0, np.eye(3))  # measured through an attitude off by R
            history.append((f, zm, 0.0, 0.0))
            if los is None:
                los = zm
            else:
                pred = los + rate
                los, rate = pred + alpha * (zm - pred), rate + beta * (zm - pred)
        k = 14 + ahead
        truth = los_from_pixel(K, 300.0 + 0.5 * k, 250.0, np.eye(3))
        coast, _ = fitted_coast(history, k)
        filt = los + ahead * rate
        err_fit.append(float(np.linalg.norm(coast - truth)) * K.fx_px)
        err_filter.append(float(np.linalg.norm(filt / np.linalg.norm(filt) - truth)) * K.fx_px)
    assert float(np.median(err_fit)) <= 2.0, np.median(err_fit)
    assert float(np.median(err_filter)) >= 2.0 * float(np.median(err_fit)), (np.median(err_filter), np.median(err_fit))
