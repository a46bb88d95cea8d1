"""The long-flight honesty benchmark's motions and tables (its flights are measured, not tested)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.honesty import (
    FAMILIES,
    family_motions,
    recall_table,
    run_flight,
    summary_table,
    switch_table,
    time_table,
)
from groundsim.evaluation.synth import Racetrack, Weave


@settings(max_examples=20, deadline=None)
@given(
    straight=st.floats(20.0, 300.0),
    radius=st.floats(10.0, 100.0),
    speed=st.floats(2.0, 20.0),
    t0=st.floats(0.0, 500.0),
)
def test_racetrack_is_continuous_at_constant_speed(straight, radius, speed, t0):
    rt = Racetrack((200.0, 10.0, -80.0), straight, radius, speed)
    dt = 1e-3
    t = t0 + np.arange(0.0, 2 * (straight / speed + np.pi * radius / speed) + 1.0, 0.05)
    s = rt.state(t)
    np.testing.assert_allclose(np.linalg.norm(s.v_ned_mps, axis=1), speed, rtol=1e-9)
    # the velocity is the position's derivative everywhere, corners included (no jumps)
    num = (rt.state(t + dt).p_ned_m - rt.state(t - dt).p_ned_m) / (2 * dt)
    np.testing.assert_allclose(num, s.v_ned_mps, atol=speed * 1e-2)
    # it stays on its track: within radius + straight / 2 of the centre, at its height
    d = s.p_ned_m - np.array([200.0, 10.0, -80.0])
    assert np.all(np.abs(d[:, 1]) <= radius + 1e-9)
    assert np.all(np.abs(d[:, 0]) <= straight / 2 + radius + 1e-9)
    np.testing.assert_allclose(d[:, 2], 0.0)
    # straight legs have no acceleration, turns the centripetal v^2 / r
    a = np.linalg.norm(s.a_ned_mps2, axis=1)
    assert np.all(np.isclose(a, 0.0) | np.isclose(a, speed**2 / radius))
    assert np.any(np.isclose(a, 0.0)) and np.any(np.isclose(a, speed**2 / radius))


def test_weave_oscillates_across_its_track():
    w = Weave((0.0, 0.0, -70.0), (5.0, 0.0, 0.0), (0.0, 2.0, 0.0), 30.0, 20.0)
    s = w.state(np.array([0.0, 5.0, 10.0, 15.0]))
    np.testing.assert_allclose(s.p_ned_m[:, 0], [0.0, 25.0, 50.0, 75.0])
    np.testing.assert_allclose(s.p_ned_m[:, 1], [0.0, 30.0, 0.0, -30.0], atol=1e-9)
    np.testing.assert_allclose(s.v_ned_mps[1], [5.0, 0.0, 0.0], atol=1e-9)


def test_families_keep_the_target_in_front_between_50_and_400_m():
    t = np.arange(0.0, 300.0, 1.0)
    for fam in FAMILIES:
        obs, tgt = family_motions(fam, 3)
        r = np.linalg.norm(tgt.state(t).p_ned_m - obs.state(t).p_ned_m, axis=1)
        assert 50.0 < r.min() and r.max() < 400.0, (fam, r.min(), r.max())


def _run(family, rows, duration_s=60.0, manoeuvres=0):
    stats = {"manoeuvres": manoeuvres, "inconsistent_selections": 1, "unsteady_selections": 2}
    return {"family": family, "seed": 0, "duration_s": duration_s, "cpu_s": 1.0, "stats": stats, "rows": rows}


def test_tables_count_what_is_beyond_3_sigma_and_the_end_verdict():
    # (t, err, sqrt trace P, observable, range, model, range sigma ratio)
    rows_a = [(float(t), 1.0, 1.0, True, 200.0, "cv:1e-06", 0.02) for t in range(60)]
    rows_a[40] = (40.0, 5.0, 1.0, True, 200.0, "ct:1e-06", 0.02)  # beyond 3 sigma, right after a change
    rows_b = [(float(t), 10.0, 100.0, False, 200.0, "cv:1e-06", 0.08) for t in range(60)]
    runs = [_run("weaving", rows_a, manoeuvres=3), _run("weaving", rows_b)]
    tt = time_table(runs, 30.0)
    assert "| weaving | 1 | 2 | 30-60 | 60 | 1.67 % | 50 % | 0.50 % |" in tt
    assert "| weaving | 1 | 2 | all | 120 | 0.83 % | 50 % | 0.50 % |" in tt
    # per family and flight length: 1 of 120 beyond, 1 of 60 in the worst bin (30-60 s) and of 60 in run a;
    # 3 manoeuvres, 2 inconsistent and 4 unsteady selections in 2 minutes of flight
    summary = summary_table(runs, 30.0)
    assert "| weaving | 1 | 2 | 120 | 0.83 % | 1.67 % | 1.67 % | 50 % | 0.50 % | 1.5 | 1.0 | 2.0 |" in summary
    # another flight length is another row
    longer = summary_table(runs + [_run("weaving", rows_b, duration_s=120.0)], 30.0)
    assert "| weaving | 2 | 1 | 60 | 0.00 % | 0.00 % | 0.00 % | 0 % | - | 0.0 | 0.5 | 1.0 |" in longer
    st_ = switch_table(runs)
    # two changes (cv -> ct at 40 s, back at 41 s) in 2 minutes of flight; 40-46 s are near a change
    assert "| weaving | 1.0 | 7 | 14.29 % | 0.00 % |" in st_
    rec = recall_table(runs)
    # run a: 0.5 % at the end and observable; run b: 5 % and not: one good run, recalled
    assert "err/range <= 2 % at the end: 1; of them called observable: 1 (recall 100.00 %)" in rec
    assert "honest (<= 1 % beyond 3 sigma over the flight) 0/1" in rec


def test_the_estimators_own_monitor_publishes_what_the_benchs_monitor_measured():
    """``estimator.sliding.consistency_check`` runs the monitor bench.honesty --monitor measures, on the same
    estimates: a racetrack target's flight gives the same rows either way, some of them demoted."""
    own = run_flight("switching", 3, 36.0, monitor=True, in_estimator=True)["rows"]
    bench = run_flight("switching", 3, 36.0, monitor=True)["rows"]
    plain = run_flight("switching", 3, 36.0)["rows"]
    assert own == bench
    assert sum(r[3] for r in own) < sum(r[3] for r in plain)  # fewer called observable: some demoted
