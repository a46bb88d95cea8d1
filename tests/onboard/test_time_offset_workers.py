"""The estimator workers make their window again from rows (``rebuild``): what the frame pipeline calls when the
camera clock's compensation moves (onboard.pipeline.frame_pipeline, step 7), instead of restarting the window.

Driven with synthetic observations of a reference scenario, as tests/onboard/test_worker_restart.py; waits bounded.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from onboard.app.config import OnboardConfig
from onboard.app.estimator_worker import ProcessEstimator, ThreadedEstimator
from onboard.app.locked_counter import LockedCounter
from onboard.pipeline.frame_pipeline import make_estimator

RESULT_WAIT_S = 30.0  # upper bound of one wait for the worker's own estimate (spawn + one model selection)
ROWS = 240  # 8 s at 30 Hz: a window that can be solved
HONEST_SIGMAS = 4.0  # the rebuilt window's estimate is within this many reported sigma (sqrt trace P) of the truth


pytestmark = pytest.mark.usefixtures("one_blas_thread")


@pytest.fixture(scope="module")
def scene(p3_px03_flight):
    K, truth, obs = p3_px03_flight
    rows = [(obs.t_s[i], obs.uv_px[i], K, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i]) for i in range(ROWS + 1)]
    return rows, truth.p_target_ned_m[ROWS]


@pytest.mark.integration
@pytest.mark.parametrize("kind", ["thread", "process"])
def test_a_worker_rebuilt_from_rows_answers_the_next_frame_over_the_whole_window(scene, kind):
    rows, p_true = scene
    counter = LockedCounter(logger=logging.getLogger("onboard.rejects"))
    if kind == "thread":
        worker = ThreadedEstimator(make_estimator(OnboardConfig()), counter, result_wait_s=RESULT_WAIT_S)
    else:
        worker = ProcessEstimator(OnboardConfig(), counter, result_wait_s=RESULT_WAIT_S)
    reference = make_estimator(OnboardConfig())
    try:
        worker.add(*rows[0])  # a window under way, made again by the rebuild (the epoch moves on)
        assert worker.rebuild(rows[:ROWS]) is None  # the estimate comes with the next frame
        reference.rebuild(rows[:ROWS])
        late = worker.late_results
        est = worker.add(*rows[ROWS])
        ref = reference.add(*rows[ROWS])
        assert worker.late_results == late and est is not None  # the worker's own answer, not a propagation
        assert est.t_s == rows[ROWS][0] and est.window_frames == ref.window_frames  # the whole window
        # (not the reference's numbers to the bit: the process worker's parent passes only the rows its window
        # keeps, so its one selection runs on the newest kept row, the reference's on the newest row given)
        err_m = float(np.linalg.norm(est.p_ned_m - p_true))
        assert err_m <= HONEST_SIGMAS * float(np.sqrt(np.trace(est.cov_p_ned_m2)))
        assert counter["estimator_error"] == 0 and counter["estimator_input"] == 0
    finally:
        worker.close()
