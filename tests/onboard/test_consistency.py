"""The consistency monitor: an estimate whose prediction misses the new bearing is demoted, for a while."""

from __future__ import annotations

import math

import numpy as np

from onboard.estimation.consistency import ConsistencyMonitor
from onboard.estimation.sliding import TrackEstimate

CAM = np.zeros(3)


def _est(t_s, p, v, sigma_m=0.5, observable=True):
    P = sigma_m**2 * np.eye(3)
    return TrackEstimate(
        t_s, np.asarray(p, float), np.asarray(v, float), P, 1e-4 * np.eye(3), observable, 200.0, 0.01, 100, "cv"
    )


def _los(p):
    p = np.asarray(p, float)
    return p / np.linalg.norm(p)


def _demote(e):
    return e  # the estimator's range floor is not this test's business: the verdict is


def test_a_target_leaving_its_prediction_is_demoted_and_held():
    mon = ConsistencyMonitor(bearing_sigma_rad=1e-3, horizon_s=2.0, hold_s=3.0)
    v = np.array([0.0, 5.0, 0.0])
    out = []
    for k in range(60):  # 15 Hz for 4 s; from 2 s on, the target is 10 m east of where it was going
        t = k / 15.0
        p_true = np.array([200.0, 5.0 * t + (10.0 if t >= 2.0 else 0.0), -50.0])
        # the published estimate follows the bearing (the window fits it) but keeps its stale velocity
        out.append(mon.check(_est(t, p_true, v), CAM, _los(p_true), _demote))
    verdicts = [e.observable for e in out]
    assert all(verdicts[:30])  # consistent while the target goes where predicted
    assert not any(verdicts[30:])  # then missed by 10 m against a 0.2 m bearing sigma: demoted and held
    assert mon.last_nis > 13.8 or mon.demoted == 30


def test_consistent_flight_is_rarely_demoted_and_nis_is_chi_square_sized():
    rng = np.random.default_rng(3)
    mon = ConsistencyMonitor(bearing_sigma_rad=1e-3, horizon_s=2.0, hold_s=0.0)
    v = np.array([1.0, 5.0, 0.0])
    nis = []
    for k in range(300):
        t = k / 15.0
        p_true = np.array([200.0, 0.0, -50.0]) + v * t
        los = _los(p_true) + 1e-3 * rng.standard_normal(3)
        mon.check(_est(t, p_true, v, sigma_m=0.05), CAM, los / np.linalg.norm(los), _demote)
        if math.isfinite(mon.last_nis):
            nis.append(mon.last_nis)
    # the bearing noise's 3-D draw projects to ~2 dof: mean NIS ~2 (0.05 m over 200 m adds little)
    assert 1.2 < np.mean(nis) < 3.0
    # false alarms at the chi-square(2) 1e-3 threshold: a few of 270 checks at most
    assert mon.demoted <= 3


def test_unobservable_estimates_pass_through_untouched():
    mon = ConsistencyMonitor(bearing_sigma_rad=1e-3)
    calls = []
    e0 = _est(0.0, [200.0, 0.0, 0.0], [0.0, 0.0, 0.0], observable=False)
    e1 = _est(3.0, [200.0, 50.0, 0.0], [0.0, 0.0, 0.0], observable=False)
    mon.check(e0, CAM, _los(e0.p_ned_m), calls.append)
    assert mon.check(e1, CAM, _los(e1.p_ned_m), calls.append) is e1
    assert calls == []


def test_a_model_change_demotes_for_model_hold_s():
    mon = ConsistencyMonitor(bearing_sigma_rad=1e-3, model_hold_s=2.0)
    v = np.array([0.0, 5.0, 0.0])
    verdicts = []
    for k in range(60):
        t = k / 15.0
        p = np.array([200.0, 5.0 * t, -50.0])
        e = _est(t, p, v)
        if t >= 1.0:  # the selection moved to another model at 1 s (consistent bearings all along)
            e = TrackEstimate(**{**e.__dict__, "model": "ct"})
        verdicts.append(mon.check(e, CAM, _los(p), _demote).observable)
    assert all(verdicts[:15]) and not any(verdicts[15:46]) and all(verdicts[46:])
