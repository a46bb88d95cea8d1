"""Error metrics and covariance consistency (onboard.estimation.metrics): hand-computed values,
statistics on sampled errors, and every rejected input."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from onboard.core.errors import InputError
from onboard.estimation.metrics import ErrorReport, evaluate, nees_interval_95, score_frames

EXACT_TOL = 1e-12
INTERVAL_TOL = 1e-9  # gammaincinv vs scipy.stats.chi2.ppf
AXIS_FRACTION_SAMPLES = 50000
# |observed - 0.0027| per axis: ~5 sigma of the binomial, sqrt(0.0027 * 0.9973 / 50000) = 2.3e-4; below 0.0027, so a
# fraction of 0 (or of the one-sided 0.00135) fails
AXIS_FRACTION_TOL = 0.0012

TRUTH = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 10.0]])
EST = np.array([[3.0, 4.0, 1.0], [0.0, 2.0, 10.0]])
CAM = np.array([[3.0, 0.0, 0.0], [0.0, 0.0, 5.0]])


def test_hand_computed_values():
    r = evaluate(TRUTH, EST, CAM)
    # errors 1 and 2 m; |X| = 5 and 10; ranges 4 and 5
    assert r.frames == 2
    assert r.paper_relative_error == pytest.approx((1 / 5 + 2 / 10) / 2, abs=EXACT_TOL)
    assert r.range_normalised_error == pytest.approx((1 / 4 + 2 / 5) / 2, abs=EXACT_TOL)
    assert r.rmse_m == pytest.approx(math.sqrt((1 + 4) / 2), abs=EXACT_TOL)
    assert r.rmse_ned_m == pytest.approx((0.0, math.sqrt(2.0), math.sqrt(0.5)), abs=EXACT_TOL)
    assert (r.mean_error_m, r.max_error_m) == pytest.approx((1.5, 2.0), abs=EXACT_TOL)
    np.testing.assert_allclose(r.error_norm_m, [1.0, 2.0], atol=EXACT_TOL)
    assert r.mean_nees is None and r.nees is None and r.outside_3sigma_trace_fraction is None


def test_origin_moves_only_the_paper_metric():
    a = evaluate(TRUTH, EST, CAM)
    b = evaluate(TRUTH, EST, CAM, origin_ned_m=(3.0, 4.0, -5.0))
    # |X - O| = 5 and sqrt(9 + 16 + 225)
    assert b.paper_relative_error == pytest.approx((1 / 5 + 2 / math.sqrt(250)) / 2, abs=EXACT_TOL)
    assert b.paper_relative_error != pytest.approx(a.paper_relative_error)
    assert (b.range_normalised_error, b.rmse_m) == (a.range_normalised_error, a.rmse_m)


def test_nees_and_three_sigma_fractions_by_hand():
    cov = np.stack([np.diag([1.0, 1.0, 0.01]), np.diag([4.0, 0.25, 1.0])])
    r = evaluate(TRUTH, EST, CAM, cov=cov)
    # e0 = (0, 0, 1): NEES 100; e1 = (0, 2, 0): NEES 16
    np.testing.assert_allclose(r.nees, [100.0, 16.0], rtol=1e-12)
    assert r.mean_nees == pytest.approx(58.0)
    # trace bounds: 3 sqrt(2.01) = 4.25 > 1; 3 sqrt(5.25) = 6.87 > 2 -> none outside
    assert r.outside_3sigma_trace_fraction == 0.0
    # per axis: e0_d = 1 > 3 * 0.1; e1_e = 2 > 3 * 0.5
    assert r.outside_3sigma_axis_fraction == pytest.approx((0.0, 0.5, 0.5))
    assert r.nees_interval_95 == nees_interval_95(2)
    assert r.nees_consistent is False


@pytest.mark.parametrize("frames", [1, 2, 10, 300, 5000])
def test_nees_interval_matches_chi2(frames):
    lo, hi = nees_interval_95(frames)
    assert lo == pytest.approx(chi2.ppf(0.025, 3 * frames) / frames, rel=INTERVAL_TOL)
    assert hi == pytest.approx(chi2.ppf(0.975, 3 * frames) / frames, rel=INTERVAL_TOL)
    assert lo < 3.0 < hi


def _random_spd(rng, n):
    A = rng.standard_normal((n, 3, 3))
    return np.einsum("nij,nkj->nik", A, A) + 0.05 * np.eye(3)


def test_honest_covariance_passes_and_overconfident_fails():
    rng = np.random.default_rng(7)
    n = AXIS_FRACTION_SAMPLES
    P = _random_spd(rng, n)
    L = np.linalg.cholesky(P)
    e = np.einsum("nij,nj->ni", L, rng.standard_normal((n, 3)))
    truth = rng.uniform(-100, 100, (n, 3)) + np.array([0.0, 0.0, -200.0])
    cam = truth + rng.uniform(50, 100, (n, 3))
    r = evaluate(truth, truth + e, cam, cov=P)
    assert r.nees_consistent, (r.mean_nees, r.nees_interval_95)
    assert r.outside_3sigma_trace_fraction < 1e-3
    for f in r.outside_3sigma_axis_fraction:
        assert abs(f - 0.0027) < AXIS_FRACTION_TOL
    over = evaluate(truth, truth + e, cam, cov=P / 10.0)
    assert over.nees_consistent is False and over.mean_nees == pytest.approx(10 * r.mean_nees, rel=1e-9)
    assert min(over.outside_3sigma_axis_fraction) > 0.1
    under = evaluate(truth, truth + e, cam, cov=P * 10.0)  # under-confident: as inconsistent
    assert under.mean_nees == pytest.approx(r.mean_nees / 10, rel=1e-9)
    assert under.mean_nees < under.nees_interval_95[0] and under.nees_consistent is False


def test_three_sigma_fractions_count_negative_errors_and_take_the_square_root_of_the_trace():
    """Errors below the estimate count as much as above it; the trace bound is 3 sqrt(trace P), a length."""
    truth = np.array([[100.0, 0.0, -50.0], [0.0, 100.0, -50.0]])
    cam = np.zeros((2, 3))
    cov = np.stack([np.eye(3), np.eye(3)])
    e = np.array([[-4.0, 0.0, 0.0], [0.0, -0.5, -3.5]])  # 1 sigma per axis: -4 and -3.5 beyond 3 sigma
    r = evaluate(truth, truth + e, cam, cov=cov)
    assert r.outside_3sigma_axis_fraction == pytest.approx((0.5, 0.0, 0.5), abs=EXACT_TOL)
    # trace 4, so 3 sigma (trace) = 6 m: |e| = 7 m lies beyond it, 5.9 m inside (3 * trace = 12 m would hold both)
    cov = np.stack([np.eye(3) * 4.0 / 3.0] * 2)
    e = np.array([[0.0, 7.0, 0.0], [0.0, 0.0, -5.9]])
    r = evaluate(truth, truth + e, cam, cov=cov)
    assert r.outside_3sigma_trace_fraction == pytest.approx(0.5, abs=EXACT_TOL)
    assert evaluate(truth[:1], truth[:1] + e[:1], cam[:1], cov=cov[:1]).outside_3sigma_trace_fraction == 1.0


@settings(max_examples=50, deadline=None)
@given(n=st.integers(1, 20), seed=st.integers(0, 2**31), shift=st.tuples(*[st.floats(-1e3, 1e3)] * 3))
def test_translation_invariance_of_errors(n, seed, shift):
    """Moving truth, estimate, camera and origin together changes nothing."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-200, 200, (n, 3)) + 500.0
    est = truth + rng.standard_normal((n, 3))
    cam = truth + rng.uniform(20, 50, (n, 3))
    P = _random_spd(rng, n)
    a = evaluate(truth, est, cam, cov=P)
    s = np.array(shift)
    b = evaluate(truth + s, est + s, cam + s, cov=P, origin_ned_m=s)
    for k in ("paper_relative_error", "range_normalised_error", "rmse_m", "mean_nees"):
        assert getattr(b, k) == pytest.approx(getattr(a, k), rel=1e-6, abs=1e-9)


def test_summary_is_strict_json_and_inputs_not_mutated():
    cov = np.stack([np.eye(3), 2 * np.eye(3)])
    t0, e0, c0, p0 = TRUTH.copy(), EST.copy(), CAM.copy(), cov.copy()
    r = evaluate(TRUTH, EST, CAM, cov=cov)
    d = json.loads(json.dumps(r.summary(), allow_nan=False))
    assert d["frames"] == 2 and "nees" not in d and "error_norm_m" not in d
    assert d["mean_nees"] == pytest.approx(r.mean_nees)
    assert len(d["outside_3sigma_axis_fraction"]) == 3
    for a, b in ((TRUTH, t0), (EST, e0), (CAM, c0), (cov, p0)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.rmse_m = 0.0  # frozen


BAD_COV = np.stack([np.eye(3), np.eye(3)])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(truth_p_ned_m=TRUTH[:, :2]), r"truth_p_ned_m must have shape \(N, 3\)"),
        (dict(truth_p_ned_m=np.zeros((0, 3))), "N >= 1"),
        (dict(est_p_ned_m=EST[:1]), "est_p_ned_m has 1 rows"),
        (dict(cam_p_ned_m=np.vstack([CAM, CAM])), "cam_p_ned_m has 4 rows"),
        (dict(est_p_ned_m=np.array([[0, 0, 0], [np.nan, 0, 0]])), "est_p_ned_m row 1 is not finite"),
        (dict(truth_p_ned_m="abc"), "truth_p_ned_m must be numbers"),
        (dict(origin_ned_m=(0.0, 0.0)), "origin_ned_m"),
        (dict(truth_p_ned_m=np.array([[0.0, 0, 0], [0, 0, 10]])), "truth row 0 is at the origin"),
        (dict(cam_p_ned_m=np.array([[3.0, 0, 0], [0, 0, 10]])), "truth row 1 coincides with the camera"),
        (dict(cov=np.eye(3)), r"cov must have shape \(2, 3, 3\)"),
        (dict(cov=np.stack([np.eye(3), np.diag([1.0, 0.0, 1.0])])), r"cov\[1\] is not positive definite"),
        (dict(cov=np.stack([-np.eye(3), np.eye(3)])), r"cov\[0\] is not positive definite"),
        (
            dict(cov=np.stack([np.eye(3), np.array([[1, 0.5, 0], [0, 1, 0], [0, 0, 1.0]])])),
            r"cov\[1\] is not symmetric",
        ),
        (dict(cov=np.stack([np.eye(3), np.full((3, 3), np.nan)])), r"cov\[1\] is not finite"),
    ],
)
def test_rejected_inputs_name_the_field(kwargs, match):
    args = dict(truth_p_ned_m=TRUTH, est_p_ned_m=EST, cam_p_ned_m=CAM)
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        evaluate(**args)


def test_report_validates_frames_and_interval_args():
    with pytest.raises(InputError, match="frames"):
        ErrorReport(
            frames=0,
            paper_relative_error=0,
            range_normalised_error=0,
            rmse_m=0,
            rmse_ned_m=(0, 0, 0),
            mean_error_m=0,
            max_error_m=0,
            error_norm_m=np.zeros(0),
        )
    with pytest.raises(InputError, match="frames and dof"):
        nees_interval_95(0)


# ---------------------------------------------------------------------------------------- score_frames


def test_score_frames_scores_the_selected_rows_in_per_cent():
    """The one scoring path of eval, the demo and the harnesses: the selected rows only, per cent figures."""
    truth, est, cam = (np.vstack([a, [[1e3, 1e3, 1e3]]]) for a in (TRUTH, EST, CAM))
    est[2] += 500.0  # a wild third row that the selection leaves out
    d = score_frames(truth, est, cam, None, [True, True, False])
    assert d["frames"] == 2
    assert d["err_range_pct"] == pytest.approx(100 * (1 / 4 + 2 / 5) / 2, abs=EXACT_TOL)
    assert d["err_paper_pct"] == pytest.approx(100 * (1 / 5 + 2 / 10) / 2, abs=EXACT_TOL)
    assert d["rmse_m"] == pytest.approx(math.sqrt(2.5), abs=EXACT_TOL) and d["mean_nees"] is None
    assert "note" not in d and json.loads(json.dumps(d)) == d
    assert score_frames(truth, est, cam, None, np.zeros(3, bool)) is None


def test_score_frames_reports_a_refused_covariance_and_keeps_the_errors():
    cov = np.stack([np.eye(3), np.diag([1.0, -1.0, 1.0])])  # the second is not positive definite
    d = score_frames(TRUTH, EST, CAM, cov, [True, True])
    assert "cov[1] is not positive definite" in d["note"] and d["mean_nees"] is None
    assert d["err_range_pct"] == pytest.approx(100 * (1 / 4 + 2 / 5) / 2, abs=EXACT_TOL)
    ok = score_frames(TRUTH, EST, CAM, cov, [True, False])  # the refused row not selected: scored with covariance
    assert "note" not in ok and ok["mean_nees"] == pytest.approx(1.0, abs=EXACT_TOL)  # e = (0, 0, 1), P = I
    with pytest.raises(InputError, match="est_p_ned_m row 0 is not finite"):  # bad points are never hidden
        score_frames(TRUTH, np.full((2, 3), np.nan), CAM, cov, [True, True])


def test_nees_per_point_is_e_p_inverse_e_and_a_singular_row_gets_the_caller_s_value():
    from onboard.estimation.metrics import nees_per_point

    e = np.array([[1.0, 2.0, 0.0], [3.0, 0.0, 0.0]])
    P = np.array([np.diag([1.0, 4.0, 9.0]), np.diag([9.0, 1.0, 0.0])])  # the second cannot be inverted
    out = nees_per_point(e, P, singular=np.inf)
    assert out[0] == pytest.approx(1.0 + 1.0) and out[1] == np.inf
    assert np.isnan(nees_per_point(e, P)[1])
    np.testing.assert_allclose(nees_per_point(e[:1], P[:1]), [2.0])  # a stack that inverts: at once
