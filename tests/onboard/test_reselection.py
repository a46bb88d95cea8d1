"""When the sliding window re-selects its motion model (onboard/estimation/sliding.py, module
docstring): the period backs off while full-window selections confirm each other, and the data
calls a selection early when the model stops explaining the bearings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from groundsim.evaluation.synth import estimator_noise_model, synthesize
from groundsim.world.motion import Circular
from groundsim.world.scenario import load_noise_cases
from onboard.core.errors import ConfigError
from onboard.core.frames import PinholeIntrinsics
from onboard.estimation.sliding import SlidingConfig, SlidingWindowEstimator

RATE_HZ = 30.0


def _fly(uv_offset=None, seconds: float = 60.0, config: SlidingConfig | None = None):
    """A minute of steady geometry under RTK navigation errors: the observer circles (40 m, 8 m/s, 70 m
    up), the target flies a wide circle 150-300 m away (6 m/s, 85 m up; the coordinated-turn model's
    case).  Returns the estimator, the selection times (each selection's window's newest frame; it ends a few
    frames later, spread over them) and the last estimate with its truth.
    ``uv_offset(t_s)`` adds pixels to the measured centre (a target leaving the model)."""
    t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    nc = load_noise_cases()["RTK"]
    observer = Circular((0.0, 0.0, -70.0), 40.0, 0.0, 8.0 / 40.0)
    target = Circular((220.0, 0.0, -85.0), 70.0, 0.0, 6.0 / 70.0)
    K = PinholeIntrinsics.vue_pro_640()
    truth, obs = synthesize(observer, target, t, K, nc, np.random.default_rng(1))
    sw = SlidingWindowEstimator(config, noise=estimator_noise_model(nc))
    selections, last = [], None
    for i in range(t.size):
        uv = obs.uv_px[i] + (uv_offset(t[i]) if uv_offset else 0.0)
        n0 = sw.stats["selections"]
        est = sw.add(t[i], uv, K, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i])
        if sw.stats["selections"] != n0:  # a selection ended: the newest frame of the window it was made on
            selections.append(sw._last_select_t)
        if est is not None:
            last = (est, truth.p_target_ned_m[i], truth.range_m[i])
    return sw, np.array(selections), last


@pytest.fixture(scope="module")
def quiet_flight():
    """``_fly()`` without an offset, shared: both tests read it, and a minute of estimation costs seconds."""
    return _fly()


def test_confirmed_full_window_selections_back_off_to_the_cap_and_the_estimate_stays_honest(quiet_flight):
    sw, sel, (est, p_true, rng) = quiet_flight
    cfg = sw.config
    gaps = np.diff(sel[sel >= cfg.window_s])
    assert gaps.size >= 2
    assert gaps.max() >= 2 * cfg.reselect_period_s - 0.1  # backed off at least once
    assert gaps.max() <= cfg.reselect_max_period_s + 0.1  # never beyond the cap
    # a fixed 5 s period would have selected ~8 times over the 40 s of full window
    assert np.count_nonzero(sel > cfg.window_s) < 40.0 / cfg.reselect_period_s - 2
    err = float(np.linalg.norm(est.p_ned_m - p_true))
    assert err < 3 * math.sqrt(np.trace(est.cov_p_ned_m2))
    assert err / rng < 0.03 and est.observable


def test_a_target_that_leaves_the_model_calls_a_selection_before_the_backed_off_period(quiet_flight):
    _, quiet, _ = quiet_flight
    cfg = SlidingConfig()
    # the quiet flight's longest full-window gap, and a manoeuvre that starts inside it
    starts, gaps = quiet[:-1], np.diff(quiet)
    k = int(np.argmax(np.where(starts >= cfg.window_s, gaps, 0.0)))
    t_turn = starts[k] + 1.0
    assert gaps[k] >= 2 * cfg.reselect_period_s - 0.1

    def sideways(t_s: float) -> np.ndarray:  # 1.5 px/s^2 across the image from t_turn on
        dt = max(t_s - t_turn, 0.0)
        return np.array([0.75 * dt * dt, 0.0])

    _, sel, _ = _fly(sideways)
    after = sel[sel > t_turn]
    assert after.size and after[0] <= max(starts[k] + cfg.reselect_period_s, t_turn + 3.0) + 0.1
    assert after[0] < quiet[k + 1] - 0.5  # earlier than the quiet flight's backed-off selection


@pytest.mark.parametrize(
    "field, value",
    [
        ("reselect_max_period_s", 4.0),  # below reselect_period_s
        ("reselect_innovation_trigger", 0.0),
        ("reselect_innovation_frames", 0),
    ],
)
def test_bad_reselection_settings_are_refused_naming_the_field(field, value):
    with pytest.raises(ConfigError, match=f"SlidingConfig>: {field}: expected"):
        SlidingConfig(**{field: value})


def test_a_window_longer_than_its_rows_hold_counts_as_full_and_backs_off():
    # 150 rows at every other frame of 30 Hz hold 10 s of a 60 s window: full once they are all taken,
    # else its re-selection period would stay at reselect_period_s for ever
    cfg = SlidingConfig(window_s=60.0, max_frames=150)
    sw, sel, _ = _fly(seconds=40.0, config=cfg)
    assert len(sw._t) == cfg.max_frames
    gaps = np.diff(sel[sel >= 12.0])
    assert gaps.size >= 1
    assert gaps.max() >= 2 * cfg.reselect_period_s - 0.1
