"""The model selection as an anytime computation (MapEstimator.selection) and the sliding window that
spreads it over frames (SlidingConfig.selection_work_per_frame): same answers, bounded pieces."""

from __future__ import annotations

import numpy as np
import pytest

from groundsim.evaluation.synth import estimator_noise_model, synthesize_scenario
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
from onboard.estimation.map_estimator import FACTOR_WORK, MapConfig, MapEstimator
from onboard.estimation.sliding import PROVISIONAL_MODEL, SlidingConfig, SlidingWindowEstimator
from onboard.estimation.window_problem import drain

#: one Levenberg-Marquardt iteration evaluates the residuals at most this often (12 steps, Gauss-Newton then
#: damped, and the start's own evaluation in the first; none when the Gauss-Newton step promises too little
#: to try: WindowProblem.solve_steps)
MAX_EVALUATIONS_PER_ITERATION = 13


@pytest.fixture(scope="module")
def window():
    """P2 under RTK navigation errors (CA wins there), every other frame of its 10 s: 150 rows."""
    sc = load_scenario(reference_scenario_paths()["P2"])
    nc = load_noise_cases()["RTK"]
    truth, obs = synthesize_scenario(sc, nc, 1, t_s=sc.frame_times_s()[::2])
    return sc, nc, obs


def _estimator(nc) -> MapEstimator:
    return MapEstimator(MapConfig(knot_spacing_s=1.0), estimator_noise_model(nc))


def test_selection_run_in_pieces_gives_the_batch_solve_bit_for_bit(window):
    _, nc, obs = window
    whole = _estimator(nc).solve(obs)
    steps = _estimator(nc).selection(obs)
    works = []
    while True:
        try:
            works.append(next(steps))
        except StopIteration as done:
            pieces = done.value
            break
    assert pieces.model == whole.model and pieces.prior == whole.prior
    assert pieces.observable == whole.observable
    np.testing.assert_array_equal(pieces.theta, whole.theta)
    np.testing.assert_array_equal(pieces.cov_p_ned_m2, whole.cov_p_ned_m2)
    assert pieces.log_evidence == whole.log_evidence
    assert pieces.grid_log_evidence == whole.grid_log_evidence
    # many small pieces, each at most one iteration's evaluations (or a kept solution's factorisation)
    assert len(works) > 50
    assert all(0 <= w <= max(MAX_EVALUATIONS_PER_ITERATION, FACTOR_WORK) for w in works)
    assert sum(works) > len(works)  # and they measure work: most iterations evaluate, some more than once


def test_drain_returns_the_generators_value():
    def steps():
        yield 3
        yield 4
        return "done"

    assert drain(steps()) == "done"


def _feed(sw: SlidingWindowEstimator, sc, obs, frames):
    out = None
    for i in frames:
        out = sw.add(obs.t_s[i], obs.uv_px[i], sc.camera.intrinsics, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i])
    return out


def test_a_spread_selection_chooses_what_the_whole_one_chooses_on_its_window(window):
    sc, nc, obs = window
    noise = estimator_noise_model(nc)
    sw = SlidingWindowEstimator(SlidingConfig(selection_work_per_frame=10), noise=noise)
    i = 0
    est = None
    while est is None:  # the track's provisional first choice runs at once, in the frame that calls it
        assert sw._pending is None
        est = _feed(sw, sc, obs, [i])
        i += 1
    first_at = i - 1
    assert sw.stats["provisional"] == 1 and sw.stats["selections"] == 0
    family, (q,) = PROVISIONAL_MODEL
    assert sw._model == family and sw._prior == sw.map.config.motion_prior(family, q)
    assert est.t_s == obs.t_s[first_at] and not est.observable  # published at once, never confident
    # the full selection on the same rows follows, spread over the next frames, each with its own estimate
    assert sw._pending is not None and not sw._pending.provisional and sw._pending.t_s == obs.t_s[first_at]
    frozen, t_sel = sw._pending.obs, sw._pending.t_s
    spread_over = 0
    while sw.stats["selections"] == 0:
        est = _feed(sw, sc, obs, [i])
        assert est is not None and est.t_s == obs.t_s[i]
        i += 1
        spread_over += 1
    assert spread_over > 2  # it did take several frames
    whole = sw.map.solve(frozen, grid=sw._grid)
    assert (sw._model, sw._prior) == (whole.model, whole.prior)
    assert sw._window_observable == whole.observable
    assert sw._last_select_t == t_sel
    # and at once (budget 0): the full selection first, on the same rows in the same frame, the same choice
    at_once = SlidingWindowEstimator(SlidingConfig(selection_work_per_frame=0), noise=noise)
    _feed(at_once, sc, obs, range(first_at + 1))
    assert at_once.stats["selections"] == 1 and at_once.stats["provisional"] == 0 and at_once._pending is None
    assert (at_once._model, at_once._prior, at_once._last_select_t) == (sw._model, sw._prior, t_sel)


def test_frames_during_a_selection_keep_their_estimates_and_a_snapshot_drops_it(window):
    sc, nc, obs = window
    noise = estimator_noise_model(nc)
    cfg = SlidingConfig(selection_work_per_frame=5, warmup_reselect_period_s=0.5)
    sw = SlidingWindowEstimator(cfg, noise=noise)
    i = 0
    while sw.stats["selections"] == 0:  # the provisional first choice, then the first full selection
        _feed(sw, sc, obs, [i])
        i += 1
    while sw._pending is None:  # the next one starts ...
        assert _feed(sw, sc, obs, [i]) is not None
        i += 1
    est = _feed(sw, sc, obs, [i])  # ... and runs while every frame still gets a fresh estimate
    i += 1
    assert sw._pending is not None and est is not None and est.t_s == obs.t_s[i - 1]
    restored = SlidingWindowEstimator(cfg, noise=noise)
    restored.restore(sw.snapshot())
    assert restored._pending is None and restored.stats == sw.stats
    # the restored estimator starts the selection again (still due) and ends it, as the original does
    n = sw.stats["selections"]
    for k in range(i, len(obs)):
        a, b = _feed(sw, sc, obs, [k]), _feed(restored, sc, obs, [k])
        assert a is not None and b is not None
        if sw.stats["selections"] > n and restored.stats["selections"] > n:
            break
    assert sw.stats["selections"] > n and restored.stats["selections"] > n
    assert restored._prior == sw._prior


def test_rebuild_ends_its_selection_on_the_newest_row(window):
    sc, nc, obs = window
    sw = SlidingWindowEstimator(SlidingConfig(selection_work_per_frame=1), noise=estimator_noise_model(nc))
    rows = [
        (obs.t_s[i], obs.uv_px[i], sc.camera.intrinsics, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i])
        for i in range(len(obs))
    ]
    est = sw.rebuild(rows)
    assert est is not None and est.t_s == obs.t_s[-1]
    assert sw.stats["selections"] == 1 and sw._pending is None
    assert sw.config.selection_work_per_frame == 1


def test_selection_work_per_frame_must_not_be_negative():
    from onboard.core.errors import ConfigError

    with pytest.raises(ConfigError, match="selection_work_per_frame: expected an integer >= 0"):
        SlidingConfig(selection_work_per_frame=-1)
