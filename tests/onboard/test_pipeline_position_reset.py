"""A GNSS step the pose buffer accepts (``position_reset``) breaks the camera's position track: the frame pipeline
starts its 3-D estimate again, before the first frame past the break reaches it, and no window (nor time-offset
block) holds camera positions from both sides."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from onboard.core.pose_types import PoseAt
from tests.onboard.test_pipeline import FakeEstimator, Rig

STEP_NED_M = np.array([50.0, 0.0, 0.0])  # a GNSS jump: 50 m north, persisting
ON_NEW_TRACK_M = 25.0  # a camera position this far from the truth is on the stepped track (noise-free scene: ~0)
N_BEFORE, N_AFTER = 45, 45  # 1.5 s of frames on each side of the step


class SteppedTelemetry:
    """The rig's telemetry writer, with every position from ``t_step_us`` on shifted by ``STEP_NED_M``."""

    def __init__(self, buffer, t_step_us: int) -> None:
        self.buffer, self.t_step_us = buffer, t_step_us

    def add_attitude(self, *args):
        return self.buffer.add_attitude(*args)

    def add_position_ned(self, t_us, p_ned_m, v_ned_mps=None):
        shift = STEP_NED_M if t_us >= self.t_step_us else 0.0
        return self.buffer.add_position_ned(t_us, np.asarray(p_ned_m) + shift, v_ned_mps)


class WindowEstimator(FakeEstimator):
    """The fake, keeping its window's camera positions (what a restart must empty)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.window: list[tuple[float, np.ndarray]] = []
        self.mixed = False  # a window ever held camera positions from both sides of the step

    def add(self, t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        self.window.append((t_s, np.array(p_cam_ned_m)))
        sides = {self.scene_side(t, p) for t, p in self.window}
        self.mixed |= len(sides) > 1
        return super().add(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)

    def reset(self):
        self.window.clear()
        super().reset()

    def scene_side(self, t_s: float, p_cam) -> bool:
        """True: ``p_cam`` is on the stepped track."""
        return on_new_track(self.scene, t_s * 1e6, p_cam)


def on_new_track(scene, t_us: float, p_cam) -> bool:
    true_m = scene.camera((t_us - scene.boot_us0) / 1e6)[0]
    return bool(np.linalg.norm(np.asarray(p_cam) - true_m) > ON_NEW_TRACK_M)


def stepped_rig() -> tuple[Rig, WindowEstimator]:
    rig = Rig(ready_after=5)
    est = WindowEstimator(rig.scene, ready_after=5)
    rig.est = rig.pipe.estimator = est
    rig.pose = SteppedTelemetry(rig.pose, rig.scene.t_us(N_BEFORE))  # type: ignore[assignment]
    return rig, est


def test_a_gnss_step_restarts_the_estimator_once_and_no_window_mixes_the_two_tracks():
    rig, est = stepped_rig()
    before = rig.run(N_BEFORE)
    assert rig.pipe.estimator_resets == 0 and before[-1].window_frames == N_BEFORE
    after = rig.run(N_AFTER, start=N_BEFORE)

    assert rig.counter["position_reset"] == 1 and rig.counter["estimator_pose_reset"] == 1
    assert rig.pipe.estimator_resets == 1 and [c[0] for c in est.calls].count("reset") == 1
    # the tracks say when their estimate started again: one step from 0 to 1, never back
    epochs = [t.estimate_epoch for t in before + after]
    assert epochs[0] == 0 and epochs[-1] == 1 and epochs == sorted(epochs)
    assert not est.mixed
    # the estimate after the step is made of rows of the new track only, fewer than the frames since the start
    assert est.window and all(est.scene_side(t, p) for t, p in est.window)
    assert after[-1].window_frames == len(est.window) < N_AFTER
    assert all(t.has_position for t in after[-5:])
    # the window had grown through the jumps the buffer refused first (dead-reckoned on the old track), then dropped
    assert after[-1].window_frames < N_BEFORE < max(t.window_frames for t in after)


def test_the_time_offset_block_ends_at_the_step_and_keeps_its_compensation():
    rig, _ = stepped_rig()
    offset = rig.pipe.time_offset
    assert offset is not None  # on by default
    resets: list[int] = []
    real_reset = offset.reset

    def counted_reset() -> None:
        resets.append(1)
        real_reset()

    offset.reset = counted_reset  # type: ignore[method-assign]
    rig.run(N_BEFORE)
    assert offset._frames  # a block is being filled with the old track
    rig.run(N_AFTER, start=N_BEFORE)
    t0_us = rig.scene.t_us(N_BEFORE)
    rows = offset._frames
    assert rows and not resets  # the clock did not change: blocks and compensation stay
    assert all(on_new_track(rig.scene, t_s * 1e6, row[7:10]) for t_s, row in zip(offset._t, rows, strict=True))
    assert offset._t[0] * 1e6 > t0_us


class RelabelledPoses:
    """The rig's pose buffer, its poses carrying the (epoch, discontinuities) the test sets."""

    def __init__(self, source) -> None:
        self.source, self.key = source, (0, 0)

    def pose_at(self, time_boot_us: int) -> PoseAt | None:
        pose = self.source.pose_at(time_boot_us)
        return None if pose is None else dataclasses.replace(pose, epoch=self.key[0], discontinuities=self.key[1])

    def __getattr__(self, name):
        return getattr(self.source, name)


@pytest.mark.parametrize(
    ("key", "position_reset"),
    [
        ((0, 1), True),  # a position reset
        ((1, 1), False),  # a reboot: a break of the clock, counted by the pose buffer and the admission
        ((1, 0), False),  # a reboot in poses that do not carry the count (a recording's)
    ],
)
def test_each_break_restarts_the_estimate_once_under_its_own_name(key, position_reset):
    rig = Rig(ready_after=5)
    poses = RelabelledPoses(rig.pose)
    rig.pipe.pose_source = poses
    rig.run(10)
    poses.key = key
    rig.run(10, start=10)
    assert rig.pipe.estimator_resets == 1 and [c[0] for c in rig.est.calls].count("reset") == 1
    assert rig.counter["estimator_pose_reset"] == (1 if position_reset else 0)
    assert rig.pipe.last_track is not None and rig.pipe.last_track.window_frames == 10
