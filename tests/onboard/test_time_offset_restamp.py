"""The poses at the frames' stamps kept to make the 3-D window again at a new clock compensation
(onboard.pipeline.restamp), and the pipeline doing so through the estimator's ``rebuild`` instead of a restart."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import quat_from_rotvec, rotvec_from_quat
from onboard.pipeline.frame_pipeline import COMPENSATION_REBUILD_MS
from onboard.pipeline.restamp import StampPoseHistory
from tests.onboard.test_pipeline import Rig
from tests.onboard.test_pipeline_time_offset import LookupLog, StubOffset

ANGLE_TOL_RAD = 1e-9  # slerp about one fixed axis is exact
POS_TOL_M = 1e-9
FRAME_US = 33_333
INTERP_POS_TOL_M = 0.01  # the rig's camera moves ~5 m/s: 1 cm across 33 ms is a chord's error, not a wrong time
INTERP_ANGLE_TOL_RAD = 2e-4


def _history(rate_radps: float, axis, v_ned_mps, n: int = 30, t0_us: int = 1_000_000) -> StampPoseHistory:
    """A camera turning at a constant rate about a fixed axis while moving at constant velocity, one pose per frame."""
    h = StampPoseHistory(span_s=10.0)
    for k in range(n):
        t_s = k * FRAME_US / 1e6
        h.append(
            t0_us + k * FRAME_US, quat_from_rotvec(rate_radps * t_s * np.asarray(axis)), np.asarray(v_ned_mps) * t_s
        )
    return h


@settings(max_examples=40, deadline=None)
@given(
    rate=st.floats(-1.0, 1.0),
    axis=st.sampled_from([(1.0, 0.0, 0.0), (0.0, 0.6, 0.8), (0.0, 0.0, 1.0)]),
    frac=st.floats(0.0, 28.0),
)
def test_interpolates_a_constant_turn_and_a_constant_velocity_exactly(rate, axis, frac):
    v = np.array([4.0, -3.0, 0.5])
    h = _history(rate, axis, v)
    t_us = 1_000_000 + int(round(frac * FRAME_US))
    q, p, ok = h.poses_at([t_us])
    assert ok[0]
    t_s = (t_us - 1_000_000) / 1e6
    # the rotation from the interpolated attitude to the true one at that time: nothing
    err = rotvec_from_quat(quat_from_rotvec(-rate * t_s * np.asarray(axis))) + rotvec_from_quat(q[0])
    assert np.linalg.norm(err) < 1e-6
    np.testing.assert_allclose(p[0], v * t_s, atol=1e-6)


def test_samples_are_returned_as_stored_and_outside_or_across_a_gap_there_is_no_pose():
    h = _history(0.3, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), n=5)
    q, p, ok = h.poses_at([1_000_000 + 2 * FRAME_US])
    assert ok[0]
    np.testing.assert_allclose(p[0], [2 * FRAME_US / 1e6, 0.0, 0.0], atol=POS_TOL_M)
    _, _, ok = h.poses_at([999_999, 1_000_000 + 4 * FRAME_US + 1])
    assert not ok.any()  # before the first, after the last: never extrapolated
    h.append(1_000_000 + 4 * FRAME_US + 300_000, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # 0.3 s later
    q, p, ok = h.poses_at([1_000_000 + 4 * FRAME_US + 100_000])
    assert not ok[0] and np.all(np.isnan(q[0])) and np.all(np.isnan(p[0]))


def test_keeps_its_span_and_a_time_going_back_starts_it_over():
    h = StampPoseHistory(span_s=1.0)
    for k in range(100):
        h.append(k * FRAME_US, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert len(h) == 31  # 1 s at 30 Hz, both ends
    h.append(5 * FRAME_US, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert len(h) == 1


class RebuildingFake:
    """The rig's fake estimator with a ``rebuild`` that records the rows it is handed."""

    def __init__(self, fake) -> None:
        self.fake = fake
        self.rebuilt: list[list[tuple]] = []

    def rebuild(self, rows):
        self.rebuilt.append(list(rows))
        self.fake.calls.append(("rebuild", rows[-1][0]))
        return None

    def __getattr__(self, name):
        return getattr(self.fake, name)


def test_a_compensation_that_moves_makes_the_window_again_at_the_new_stamps_without_a_restart():
    rig = Rig()
    stub = StubOffset()
    rig.pipe.time_offset = stub
    rig.pipe.pose_source = LookupLog(rig.pose)
    rig.pipe.estimator = est = RebuildingFake(rig.est)
    rig.run(20)
    stub.compensated_ms = 45.0
    rig.run(2, start=20)
    assert rig.pipe.estimator_resets == 0 and not any(name == "reset" for name, _ in rig.est.calls)
    assert len(est.rebuilt) == 1 and rig.pipe.window_restamps == 1
    rows = est.rebuilt[0]
    # the 20 frames added before the move, less those whose stamp minus 45 ms is before the first stamp (2 frames)
    assert [round(r[0] * 1e6) for r in rows] == [rig.scene.t_us(k) for k in range(2, 20)]
    for t_s, uv, _, p, q in rows:
        t_us = round(t_s * 1e6)
        truth = rig.pose.pose_at(t_us - 45_000)
        np.testing.assert_allclose(p, truth.p_cam_ned_m, atol=INTERP_POS_TOL_M)
        angle = 2.0 * math.acos(min(1.0, abs(float(np.dot(q, truth.q_ned_from_cam)))))
        assert angle < INTERP_ANGLE_TOL_RAD
        assert np.all(np.isfinite(uv))
    # a later frame after the move adds as usual
    rig.run(1, start=22)
    assert len(est.rebuilt) == 1 and rig.est.calls[-1][0] == "add"
    # a small move makes it again too (a window mixing rows of two compensations disagrees with itself); still no
    # restart, and a move under COMPENSATION_REBUILD_MS does nothing
    stub.compensated_ms = 50.0
    rig.run(1, start=23)
    assert len(est.rebuilt) == 2 and rig.pipe.window_restamps == 2 and rig.pipe.estimator_resets == 0
    stub.compensated_ms = 50.0 + COMPENSATION_REBUILD_MS / 2
    rig.run(1, start=24)
    assert len(est.rebuilt) == 2 and rig.est.calls[-1][0] == "add"
