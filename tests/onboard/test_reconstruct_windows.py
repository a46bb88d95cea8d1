"""``onboard.reconstruct`` on files longer than one MAP problem: the window plan (properties), a long observable
flight solved in windows against its truth and against one problem over the whole file, rows apart from the
others refused naming their times, the summary's and the report line's windows."""

from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.evaluation.synth import synthesize
from groundsim.world.motion import Circular
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
from onboard.app.reconstruct import ReconstructOptions, reconstruct
from onboard.estimation.crb import bayesian_crb, bayesian_crb_in_windows, online_verdict_bound_ratios
from onboard.estimation.map_estimator import MapEstimator
from onboard.estimation.sliding import SlidingConfig, SlidingWindowEstimator
from onboard.estimation.windows import (
    DEFAULT_WINDOW_S,
    WindowingError,
    plan_windows,
    solvable_rows,
    solve_in_windows,
    stitch,
)
from tests.onboard.test_reconstruct_cli import obs_csv_text, read_out, run_main_io

MIN_ROWS = 10


@st.composite
def row_times(draw):
    """Strictly increasing times: rows at one rate (30 Hz to one every 5 s, regular or each step longer by up to a
    factor of two) cut by up to three gaps of 5 s to minutes, with a window between 1 and 90 s.

    One rate a case, not each step drawn as dense, sparse or a gap: those left most cases a stretch of fewer than
    ``MIN_ROWS`` rows between two gaps, refused before any window was planned."""
    n = draw(st.integers(0, 400))
    step_s = draw(st.one_of(st.floats(0.01, 0.2), st.floats(0.2, 5.0)))
    # the jitter from a seed: hypothesis drawing up to 400 floats a case made the properties several times slower
    spread = draw(st.floats(0.0, 1.0))
    steps = step_s * np.random.default_rng(draw(st.integers(0, 2**32 - 1))).uniform(1.0, 1.0 + spread, n)
    for at, gap_s in draw(st.lists(st.tuples(st.integers(0, 399), st.floats(5.0, 400.0)), max_size=3)):
        if at < n:
            steps[at] = gap_s
    t0 = draw(st.floats(-1e4, 1e4))
    return t0 + np.concatenate([[0.0], np.cumsum(steps)]), draw(st.floats(1.0, 90.0))


@settings(max_examples=300, deadline=None)
@given(row_times())
def test_window_plan_takes_every_row_once_from_a_window_holding_it(case):
    t, window_s = case
    try:
        windows = plan_windows(t, window_s, MIN_ROWS)
    except WindowingError as e:
        assert "t_s" in str(e) and f"at least {MIN_ROWS}" in str(e)
        return
    taken = np.concatenate([np.arange(w.take_first, w.take_stop) for w in windows])
    assert np.array_equal(taken, np.arange(t.size))  # each row once, in order
    for w in windows:
        assert w.first <= w.take_first < w.take_stop <= w.stop
        if len(windows) > 1:
            assert w.stop - w.first >= MIN_ROWS
            assert t[w.stop - 1] - t[w.first] <= window_s * (1 + 1e-12)  # no problem longer than asked
            assert np.all(np.diff(t[w.first : w.stop]) <= window_s / 2)  # nor across a gap of over half a window
    if t[-1] - t[0] <= window_s:
        assert len(windows) == 1 and (windows[0].first, windows[0].stop) == (0, t.size)


@settings(max_examples=200, deadline=None)
@given(row_times())
def test_window_plan_takes_rows_away_from_their_windows_ends(case):
    """A window holds exactly the rows within its interval, and a row is taken from a window whose interval
    reaches at least a quarter window beyond it on both sides, unless the rows end there (the file's ends, a gap
    of over half a window)."""
    t, window_s = case
    try:
        windows = plan_windows(t, window_s, MIN_ROWS)
    except WindowingError:
        return
    if len(windows) == 1:
        return
    quarter = window_s / 4 * (1 - 1e-9)
    for w in windows:
        inside = np.flatnonzero((t >= w.t_start_s) & (t <= w.t_end_s))
        assert (inside[0], inside[-1] + 1) == (w.first, w.stop)
        taken = t[w.take_first : w.take_stop]
        stretch_starts_here = w.first == 0 or t[w.first] - t[w.first - 1] > window_s / 2
        stretch_ends_here = w.stop == t.size or t[w.stop] - t[w.stop - 1] > window_s / 2
        if not stretch_starts_here:
            assert np.all(taken - w.t_start_s >= quarter)
        if not stretch_ends_here:
            assert np.all(w.t_end_s - taken >= quarter)


def test_window_plan_default_and_zero():
    t = np.arange(0.0, 200.0, 0.1)
    assert len(plan_windows(t, 0.0, MIN_ROWS)) == 1  # 0: one problem whatever the span
    windows = plan_windows(t, DEFAULT_WINDOW_S, MIN_ROWS)
    # 200 s: windows starting at 0, 30, 60, 90, 120 and the last ending at the last row
    assert [round(t[w.first], 6) for w in windows] == [0.0, 30.0, 60.0, 90.0, 120.0, 139.9]


def test_the_last_window_holds_the_last_row_where_its_start_plus_the_window_rounds_below_it():
    """(30.3 - 5.4) + 5.4 is 30.299999999999997 in floats: the last window ended an ulp before the row it takes, and
    stitching its solution back failed (an array of 30 rows into 31)."""
    t = np.round(np.arange(304) * 0.1, 6)
    windows = plan_windows(t, 5.4, MIN_ROWS)
    last = windows[-1]
    assert (last.stop, last.take_stop, last.t_end_s) == (t.size, t.size, 30.3)
    np.testing.assert_array_equal(stitch(windows, [t[w.first : w.stop] for w in windows], t.size), t)


def test_rows_apart_are_refused_naming_their_times():
    t = np.concatenate([[-1440.0], np.arange(0.0, 1.2, 0.1)])
    with pytest.raises(
        WindowingError,
        match=r"1 row\(s\) at t_s -1440\.000\.\.-1440\.000 s lie over 30 s \(half a 60 s window\) from the other rows",
    ):
        plan_windows(t, DEFAULT_WINDOW_S, MIN_ROWS)
    # a sparse stretch: rows 20 s apart leave 3-4 in each 60 s window
    with pytest.raises(
        WindowingError, match=r"one of the 60 s windows a long span is solved in; each needs at least 10 rows"
    ):
        plan_windows(np.arange(0.0, 300.0, 20.0), DEFAULT_WINDOW_S, MIN_ROWS)


# --------------------------------------------------------------------------- a long observable flight


@pytest.fixture(scope="module")
def long_circling_flight():
    """H1's camera circling (40 m at 8 m/s), a target circling 160 m away (30 m at 6 deg/s), 0.3 px, 10 Hz over
    95 s: observable everywhere, so each window's solution can be held to the truth."""
    sc = load_scenario(reference_scenario_paths()["H1"])
    target = Circular((160.0, 0.0, -85.0), 30.0, 0.0, math.radians(6.0))
    t = np.arange(0.0, 95.0, 0.1)
    truth, obs = synthesize(
        sc.observer_motion(), target, t, sc.camera.intrinsics, load_noise_cases()["px0.3"], np.random.default_rng(3)
    )
    return truth.p_target_ned_m, obs


@pytest.fixture(scope="module")
def long_solutions(long_circling_flight):
    _, obs = long_circling_flight
    calls = []
    windowed = reconstruct(obs, ReconstructOptions(window_s=40.0), lambda *a: calls.append(a))
    whole = reconstruct(obs, ReconstructOptions(window_s=0.0))
    return windowed, whole, calls


def test_long_flight_in_windows_is_as_good_as_one_problem(long_circling_flight, long_solutions):
    truth, obs = long_circling_flight
    windowed, whole, calls = long_solutions
    assert windowed.summary["windows"] == 4 and whole.summary["windows"] == 1
    assert [c[:2] for c in calls] == [(1, 4), (2, 4), (3, 4), (4, 4)]
    assert calls[0][2] == 0.0 and calls[-1][3] == pytest.approx(obs.t_s[-1])
    for rec in (windowed, whole):
        assert rec.summary["observable"] is True
        err = np.linalg.norm(rec.p_ned_m - truth, axis=1)
        assert np.median(err) < 0.5  # metres, at 160 m
        z = np.abs(rec.p_ned_m - truth) / rec.sigma_ned_m
        assert np.mean(np.any(z > 3, axis=1)) < 0.01
    gap = np.linalg.norm(windowed.p_ned_m - whole.p_ned_m, axis=1)
    assert np.median(gap) < 0.2


def test_windowed_summary_names_each_window(long_circling_flight, long_solutions):
    _, obs = long_circling_flight
    s = long_solutions[0].summary
    results = s["window_results"]
    assert len(results) == 4 and s["window_s"] == 40.0
    assert sum(w["rows_taken"] for w in results) == len(obs)
    assert all(w["t_last_s"] - w["t_first_s"] <= 40.0 for w in results)
    assert s["observable_rows_fraction"] == 1.0 and all(w["observable"] for w in results)
    assert s["range_sigma_ratio"] == max(w["range_sigma_ratio"] for w in results)
    assert s["iterations"] == sum(w["iterations"] for w in results)
    assert s["model"] in (None, "cv", "ca", "ct")
    json.dumps(s, allow_nan=False)


def test_cli_windows_in_summary_and_report_line(long_circling_flight, tmp_path):
    _, obs = long_circling_flight
    part = obs.select(slice(0, 450))  # 45 s: windows of 30 s from 0 and from 14.9 s
    src = tmp_path / "obs.csv"
    src.write_text(obs_csv_text(part))
    out, summ = tmp_path / "out.csv", tmp_path / "s.json"
    rc, stdout, err = run_main_io(src, "-o", out, "--summary-json", summ, "--window-s", "30")
    assert rc == 0, err
    assert stdout.strip().endswith(", 2 windows of at most 30 s (observable: 100 % of rows)")
    assert err == ""  # not a terminal: no progress line
    summary = json.loads(summ.read_text())
    assert summary["windows"] == 2 and len(summary["window_results"]) == 2
    assert read_out(out).shape == (450, 7)
    rc, stdout, _ = run_main_io(src, "-o", out, "--window-s", "0")
    # one problem: no windows in the line
    assert rc == 0 and re.search(r"range sigma median [0-9.]+ % of range, max [0-9.]+ %$", stdout.strip())


def test_cli_rows_apart_exit_2_with_one_line(long_circling_flight, tmp_path):
    _, obs = long_circling_flight
    lines = obs_csv_text(obs.select(slice(0, 12))).splitlines()
    cells = lines[1].split(",")
    cells[0] = "-1440"
    lines[1] = ",".join(cells)
    src = tmp_path / "obs.csv"
    src.write_text("\n".join(lines) + "\n")
    rc, _, err = run_main_io(src, "-o", tmp_path / "out.csv")
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith(f"error: {src}: cannot reconstruct: 1 row(s) at t_s -1440.000..")
    assert not (tmp_path / "out.csv").exists()


@pytest.mark.parametrize("value", ["-1", "nan", "inf", "x"])
def test_cli_refuses_a_bad_window(tmp_path, value):
    rc, _, err = run_main_io(tmp_path / "obs.csv", "-o", tmp_path / "out.csv", "--window-s", value)
    assert rc == 2 and "--window-s" in err and err.count("\n") == 1


def test_windowed_bound_is_each_windows_own_and_close_to_the_whole(long_circling_flight, long_solutions):
    """The bound of a windowed solution takes each row's from its window: at least the whole problem's (a window
    sees less of the flight), within a few times it here, and the windowed estimate's errors are of its size."""
    truth, obs = long_circling_flight
    est = MapEstimator()
    windowed = solve_in_windows(est.solve, obs, 40.0, est.config.min_frames)
    whole = solve_in_windows(est.solve, obs, 0.0, est.config.min_frames)
    assert len(windowed.windows) == 4 and len(whole.windows) == 1
    b_windows = bayesian_crb_in_windows(est, windowed, obs, truth)
    b_whole = bayesian_crb_in_windows(est, whole, obs, truth)
    # one window: bayesian_crb itself, with that window's prior
    direct = bayesian_crb(est, obs, truth, whole.results[0].prior, whole.results[0].turn_rate_radps)
    assert b_whole.rms_m() == direct.rms_m()
    P_w, P_1 = b_windows.point_covariances(), b_whole.point_covariances()
    assert P_w.shape == P_1.shape == (len(obs), 3, 3)
    tr_w, tr_1 = np.einsum("fii->f", P_w), np.einsum("fii->f", P_1)
    assert np.median(tr_w / tr_1) >= 0.999
    assert b_whole.rms_m() <= b_windows.rms_m() < 3 * b_whole.rms_m()
    # each row's bound is its own window's: the first window's rows as that window alone bounds them
    w0, r0 = windowed.windows[0], windowed.results[0]
    alone = bayesian_crb(
        est, obs.select(slice(w0.first, w0.stop)), truth[w0.first : w0.stop], r0.prior, r0.turn_rate_radps
    )
    take = slice(w0.take_first, w0.take_stop)
    np.testing.assert_array_equal(P_w[take], alone.point_covariances()[take.start - w0.first : take.stop - w0.first])
    err = np.linalg.norm(windowed.p_ned_m - truth, axis=1)
    assert 0.2 < np.sqrt(np.mean(err**2)) / b_windows.rms_m() < 5


def _verdict_ratio(bound, p_true, p_cam, edge_factor):
    los = p_true - p_cam
    r = np.linalg.norm(los, axis=1)
    u = los / r[:, None]
    ratio = np.sqrt(np.einsum("fi,fij,fj->f", u, bound.point_covariances(), u)) / r
    return max(float(np.median(ratio)), float(ratio[-1]) / edge_factor)


def test_online_bound_is_the_verdicts_figure_on_the_windows_own_rows_up_to_each_time(long_circling_flight):
    truth, obs = long_circling_flight
    est = MapEstimator()
    whole = solve_in_windows(est.solve, obs, 0.0, est.config.min_frames)
    res = whole.results[0]
    online = MapEstimator(SlidingWindowEstimator.default_map_config(SlidingConfig()))
    # 20 s up to 50.05 s, rows 0.25 s apart at least: of the 10 Hz rows every third, the newest at or before then
    sliding = SlidingConfig(min_spacing_s=0.25, min_frames=30, min_span_s=1.5, edge_sigma_factor=2.0)
    t_eval = np.array([2.5, 4.0, 50.05])
    ratios = online_verdict_bound_ratios(online, whole, obs, truth, t_eval, sliding)
    kept = np.arange(0, len(obs), 3)
    rows = kept[(obs.t_s[kept] <= 50.05) & (obs.t_s[kept] >= 49.8 - 20.0)]
    assert obs.t_s[rows[-1]] == pytest.approx(49.8) and obs.t_s[rows[0]] == pytest.approx(30.0)
    bound = bayesian_crb(online, obs.select(rows), truth[rows], res.prior, res.turn_rate_radps)
    expected = _verdict_ratio(bound, truth[rows], obs.p_cam_ned_m[rows], 2.0)
    assert ratios[2] == pytest.approx(expected, rel=1e-12)
    assert math.isnan(ratios[0])  # 2.5 s: 9 rows kept, fewer than the window's 30: it publishes nothing yet
    # 4.0 s: 14 rows; with min_frames 10 the window answers, from those rows
    ratios = online_verdict_bound_ratios(
        online, whole, obs, truth, t_eval[:2], dataclasses.replace(sliding, min_frames=10)
    )
    rows = kept[obs.t_s[kept] <= 4.0]
    bound = bayesian_crb(online, obs.select(rows), truth[rows], res.prior, res.turn_rate_radps)
    assert math.isnan(ratios[0]) and ratios[1] == pytest.approx(
        _verdict_ratio(bound, truth[rows], obs.p_cam_ned_m[rows], 2.0), rel=1e-12
    )
    assert ratios[1] > expected  # 4 s of bearings pin the range less than 20 s


@pytest.mark.parametrize("window_s", [math.nan, -1.0, math.inf])
def test_window_plan_refuses_a_window_that_is_no_length(window_s):
    with pytest.raises(ValueError, match="window_s must be a finite number >= 0"):
        plan_windows(np.arange(0.0, 100.0, 0.1), window_s, MIN_ROWS)


def test_window_plan_of_hours_of_rows_costs_the_rows_not_rows_times_windows():
    """Two hours of 30 Hz rows: 239 windows planned from the rows' times alone (a rows x windows distance matrix
    was 1.7 GB here); a window too short for its rows refused as such."""
    t = np.arange(0.0, 7200.0, 1 / 30)
    windows = plan_windows(t, DEFAULT_WINDOW_S, MIN_ROWS)
    assert len(windows) == 239 and windows[-1].take_stop == t.size
    with pytest.raises(WindowingError, match=r"4 row\(s\) at t_s 0\.000\.\.0\.100 s, one of the 0\.1 s windows"):
        plan_windows(t, 0.1, MIN_ROWS)


def test_verbose_summary_keeps_each_windows_attitude_bias(long_circling_flight, tmp_path):
    _, obs = long_circling_flight
    src = tmp_path / "obs.csv"
    src.write_text(obs_csv_text(obs.select(slice(0, 450))))
    summ = tmp_path / "s.json"
    args = [src, "-o", tmp_path / "o.csv", "--summary-json", summ, "--attitude-bias-deg", "0.1"]
    rc, _, err = run_main_io(*args, "--window-s", "30")
    assert rc == 0, err
    s = json.loads(summ.read_text())
    assert "attitude_bias_ned_deg" not in s
    assert all(len(w["attitude_bias_ned_deg"]) == 3 for w in s["window_results"])
    rc, _, err = run_main_io(*args, "--window-s", "0")
    assert rc == 0 and len(json.loads(summ.read_text())["attitude_bias_ned_deg"]) == 3


def test_solvable_rows_drops_only_the_stretches_plan_windows_would_refuse():
    t = np.concatenate([np.arange(0.0, 40.0, 0.1), [75.0, 75.1], np.arange(110.0, 150.0, 0.1)])
    keep = solvable_rows(t, DEFAULT_WINDOW_S, MIN_ROWS)
    assert keep.sum() == t.size - 2 and not keep[400] and not keep[401]
    with pytest.raises(WindowingError):
        plan_windows(t, DEFAULT_WINDOW_S, MIN_ROWS)
    assert len(plan_windows(t[keep], DEFAULT_WINDOW_S, MIN_ROWS)) == 2  # the two stretches, each one problem
    short = np.array([0.0, 50.0])  # a span within one window: one problem, nothing dropped
    assert solvable_rows(short, DEFAULT_WINDOW_S, MIN_ROWS).all()
