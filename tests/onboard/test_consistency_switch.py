"""A target that changes motion model: the innovation CUSUM and the agreement of consecutive selections."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.estimation.consistency import ManoeuvreDetector, SelectionHistory, unsteady_evidence_nats

FRAME_S = 1.0 / 15.0


def _run(det: ManoeuvreDetector, x: np.ndarray) -> list[int]:
    """The frames at which ``det`` fired (reset after each firing, as the estimator's next selection does)."""
    fired = []
    for k, xk in enumerate(x):
        if det.add(float(xk), k * FRAME_S):
            fired.append(k)
            det.reset()
    return fired


def test_cusum_is_quiet_on_white_innovations():
    # a followed target: 0.5 r^T r of two standard normal residuals, exponential with mean 1; 20000 frames
    # (22 minutes of incremental updates at 15 Hz) fire it a few times at most
    rng = np.random.default_rng(5)
    x = 0.5 * np.sum(rng.standard_normal((20000, 2)) ** 2, axis=1)
    assert len(_run(ManoeuvreDetector(), x)) <= 3


@settings(max_examples=30, deadline=None)
@given(change=st.integers(20, 200), level=st.floats(6.0, 50.0), seed=st.integers(0, 1000))
def test_cusum_fires_within_three_frames_of_a_change_and_dates_it(change, level, seed):
    # innovations of 6-50 per axis once the target left the selected model (what a racetrack turn gave)
    rng = np.random.default_rng(seed)
    x = 0.5 * np.sum(rng.standard_normal((change + 20, 2)) ** 2, axis=1)
    x[change:] = level
    det = ManoeuvreDetector()
    fired = next(k for k in range(x.size) if det.add(float(x[k]), k * FRAME_S))
    assert change <= fired <= change + 2 or fired < change  # a white-noise excursion may fire first: rare
    if fired >= change:
        # the onset is the start of the excursion that fired: the change, or the start of a short noise
        # excursion just before it (the statistic drifts down by 1 a frame under white innovations)
        assert change - 15 <= round(det.onset_t_s / FRAME_S) <= change


def test_one_outlier_does_not_fire_it_but_two_in_a_row_do():
    det = ManoeuvreDetector()
    assert not det.add(1e6, 0.0) and det.statistic == pytest.approx(6.0)  # a wrong detection: clipped to 8
    for k in range(1, 10):  # then white innovations: the statistic decays to 0
        assert not det.add(0.5, k * FRAME_S)
    assert det.statistic == 0.0
    assert not det.add(1e6, 1.0)
    assert det.add(float("nan"), 1.0 + FRAME_S)  # a second one (non-finite counts as the clip): 12 > 10
    assert det.onset_t_s == pytest.approx(1.0) and det.fired == 1


def _window(t, range_m, sigma_m):
    """A window solution: the target due north of a camera at the origin, at ``range_m``, range sigma ``sigma_m``."""
    t = np.asarray(t, float)
    p = np.zeros((t.size, 3))
    p[:, 0] = range_m
    P = np.tile(np.diag([sigma_m**2, 0.01, 0.01]), (t.size, 1, 1))
    return t, p, P, np.zeros((t.size, 3))


def test_selections_agreeing_on_range_pass_and_a_jump_beyond_their_sigmas_does_not():
    rows = np.arange(0.0, 40.0, FRAME_S)
    hist = SelectionHistory(nsigma=3.0)
    a = rows[(rows >= 0) & (rows < 20)]
    b = rows[(rows >= 5) & (rows < 25)]
    assert hist.check(*_window(a, 230.0, 5.0), observable=True)  # nothing to compare: passes, kept
    assert hist.check(*_window(b, 235.0, 5.0), observable=True)  # 5 m apart, sigma sqrt(50): agrees
    assert hist.last_max_nsigma == pytest.approx(5.0 / np.sqrt(50.0), rel=1e-6)
    c = rows[(rows >= 10) & (rows < 30)]
    # the racetrack's wrong-range selection: 30 % short at a 2 % range sigma
    assert not hist.check(*_window(c, 160.0, 3.0), observable=True)
    assert hist.conflicts == 1
    # it was kept: the next one at the true range disagrees with it on their common frames, and is demoted too
    d = rows[(rows >= 15) & (rows < 35)]
    assert not hist.check(*_window(d, 231.0, 5.0), observable=True)
    # once the window has slid past the kept ones' frames there is nothing left to disagree with
    e = rows[(rows >= 36) & (rows < 40)]
    assert hist.check(*_window(e, 231.0, 5.0), observable=True) and np.isnan(hist.last_max_nsigma)


def test_agreeing_with_a_disputed_selection_is_no_confirmation():
    # the right selection, then a wrong-range one over a window that held a change (they conflict), then one
    # over the change's second motion model alone in the wrong one's basin: the right one's frames have left
    # the window, so it agrees with the wrong one alone, whose frames are disputed (all of them: which of the
    # two is wrong is unknown, and the wrong one is wrong over its whole window)
    rows = np.arange(0.0, 60.0, FRAME_S)
    hist = SelectionHistory(nsigma=3.0)
    assert hist.check(*_window(rows[rows < 20], 230.0, 5.0), observable=True)
    assert not hist.check(*_window(rows[(rows >= 10) & (rows < 30)], 160.0, 3.0), observable=True)
    assert hist.conflicts == 1
    c = rows[(rows >= 21) & (rows < 41)]
    assert not hist.check(*_window(c, 161.0, 3.0), observable=True)
    assert hist.last_max_nsigma < 1.0 and hist.conflicts == 1 and hist.disputed == 1
    # once the window has slid past the disputed frames, agreeing with the last one is agreeing again: the one
    # demoted only for sharing disputed frames did not make its own frames disputed
    d = rows[(rows >= 30) & (rows < 50)]
    assert hist.check(*_window(d, 161.0, 3.0), observable=True) and hist.disputed == 1


def test_unobservable_selections_are_compared_but_not_kept():
    rows = np.arange(0.0, 30.0, FRAME_S)
    hist = SelectionHistory()
    a = rows[rows < 20]
    assert hist.check(*_window(a, 160.0, 100.0), observable=False)
    b = rows[(rows >= 5) & (rows < 25)]
    assert hist.check(*_window(b, 230.0, 5.0), observable=True)  # the unobservable one left nothing behind


def test_only_common_frames_are_compared():
    hist = SelectionHistory()
    t = np.arange(0.0, 20.0, 0.5)
    assert hist.check(*_window(t, 230.0, 5.0), observable=True)
    # another window whose rows are other frames (shifted by a quarter frame): nothing in common
    assert hist.check(*_window(t[4:] + 0.25, 100.0, 1.0), observable=True) and np.isnan(hist.last_max_nsigma)


def test_unsteady_evidence_is_the_best_models_lead_over_the_best_stiffest_one():
    # a single leg: the stiff CV is the best model
    leg = {"cv": [(1e-1, -30.0), (1e-2, -8.0), (1e-6, 0.0)], "ct": [(1e-1, -25.0), (1e-6, -5.0)]}
    assert unsteady_evidence_nats(leg) == 0.0
    # a leg and a turn: only a loose intensity bends through them; the best steady model is CT's stiffest
    both = {"cv": [(1e-2, 0.0), (1e-3, -20.0), (1e-6, -300.0)], "ct": [(1e-2, -3.0), (1e-6, -27.5)]}
    assert unsteady_evidence_nats(both) == pytest.approx(27.5)
    # the order of the intensities does not matter; a family without a solution is left out
    assert unsteady_evidence_nats({"cv": [(1e-6, -300.0), (1e-2, 0.0)], "ca": []}) == pytest.approx(300.0)
    assert unsteady_evidence_nats(None) == 0.0 and unsteady_evidence_nats({}) == 0.0


def test_invalid_settings_are_refused():
    with pytest.raises(ValueError, match=r"^ManoeuvreDetector: invalid reference 1\.0, "):
        ManoeuvreDetector(reference=1.0)
    with pytest.raises(ValueError, match=r"^SelectionHistory: invalid nsigma 0\.0 "):
        SelectionHistory(nsigma=0.0)


def _racetrack_flight(seed: int, duration_s: float, config) -> tuple[dict, list[tuple[float, bool]]]:
    """bench.honesty's switching flight ``seed`` (RTK) through the sliding window under ``config``: the estimator's
    counters and the (time, observable) of every position beyond 3 sigma."""
    from bench.honesty import FRAME_RATE_HZ, family_motions
    from groundsim.evaluation.synth import estimator_noise_model, synthesize
    from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
    from onboard.estimation.sliding import SlidingWindowEstimator

    nc = load_noise_cases()["RTK"]
    intr = load_scenario(reference_scenario_paths()["P1"]).camera.intrinsics
    obs_m, tgt_m = family_motions("switching", seed)
    t = np.arange(0.0, duration_s, 1.0 / FRAME_RATE_HZ)
    truth, obs = synthesize(obs_m, tgt_m, t, intr, nc, np.random.default_rng([seed, 7]))
    sw = SlidingWindowEstimator(config, noise=estimator_noise_model(nc))
    beyond = []
    for i in range(t.size):
        est = sw.add(t[i], obs.uv_px[i], intr, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i])
        if est is not None:
            err_m = float(np.linalg.norm(est.p_ned_m - truth.p_target_ned_m[i]))
            if err_m > 3.0 * np.sqrt(np.trace(est.cov_p_ned_m2)):
                beyond.append((float(t[i]), est.observable))
    return sw.stats, beyond


GUARDS_OFF = {"manoeuvre_cusum_threshold": 0.0, "selection_consistency_nsigma": 0.0, "innovation_gate_chi2": 0.0}


def test_a_racetrack_turn_after_a_leg_is_not_published_confidently_at_the_wrong_range():
    """The sliding window on bench.honesty's racetrack: the target leaves a 25 s leg for a half-turn at 33.5 s;
    the stiff constant-velocity model selected over the leg put it 1-7 % of range off at a 0.4 % range sigma
    within 2 s (positions beyond 3 sigma) until innovations are caught: they no longer are."""
    from onboard.estimation.sliding import SlidingConfig

    stats_off, beyond_off = _racetrack_flight(1, 38.0, SlidingConfig(**GUARDS_OFF))
    stats_on, beyond_on = _racetrack_flight(1, 38.0, SlidingConfig())
    assert len(beyond_off) > 20 and all(obs for _, obs in beyond_off)  # confident and wrong, after the change
    assert min(ts for ts, _ in beyond_off) > 33.5
    assert stats_off["manoeuvres"] == 0
    assert stats_on["manoeuvres"] >= 1 and beyond_on == []


def test_a_change_in_a_young_window_is_not_published_confidently_at_the_wrong_range():
    """Racetrack seed 4: a 4 s leg, then the turn, both in the track's first window.  Every model explains the
    windows that hold both at 0.6-0.7 of the range with a 3-5 % range sigma; the CUSUM fires 2-3 s after the
    change, when no model had yet been held for long.  The selections over both motions find no steady model
    near the best one: no verdict from them, and the young firing's onset is a change."""
    from onboard.estimation.sliding import SlidingConfig

    _, beyond_off = _racetrack_flight(4, 30.0, SlidingConfig(**GUARDS_OFF))
    stats_on, beyond_on = _racetrack_flight(4, 30.0, SlidingConfig())
    assert len(beyond_off) > 50 and all(obs for _, obs in beyond_off)  # confident and wrong, from 13.6 s on
    assert stats_on["manoeuvres"] >= 1 and beyond_on == []
