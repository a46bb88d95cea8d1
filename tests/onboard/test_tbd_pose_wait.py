"""The objects chain's wait for the telemetry that brackets its frame (``imaging.pose_wait_ms``).

In the loop the frame often arrives before the attitude and gimbal samples after it; the chain then got
an extrapolated rotation (or none, and kept the last one), and track-before-detect's integration and the
tracks' motion fit carried that error (docs/perception.md, "C4 and C5 in the loop").  These tests pin the two
hooks: :meth:`SharedPoseBuffer.wait_for` with ``bracket=True`` waits for the bracketing sample where the
plain wait would extrapolate, and :class:`FramePipeline` calls ``chain_pose_wait`` before it looks up the
chain's rotation, so the chain gets the sample that arrived during the wait; the objects chain asks for that
rotation only once it has detected the frame, so the wait overlaps the detection.
"""

from __future__ import annotations

import threading

import numpy as np

from onboard.app.config import OnboardConfig, build_config
from onboard.app.shared_pose import SharedPoseBuffer
from onboard.core.frames import GeodeticOrigin, quat_from_rotvec, quat_multiply, rotmat_from_quat
from onboard.core.irframe import IrFrame
from onboard.core.pose import PoseBuffer
from onboard.imaging import TrackState, TrackUpdate
from onboard.pipeline.frame_pipeline import FramePipeline

US = 1_000_000
ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)
ATOL_RAD = 1e-6  # float rounding of a SLERP between two samples
JOIN_TIMEOUT_S = 10.0  # a waiter that has not returned by then is a failure, not a slow machine
W_FRD_RPS = np.array([0.0, 0.0, 0.5])  # a steady yaw rate: extrapolation is possible, so the plain wait never waits


def q_at(t_us: int) -> np.ndarray:
    return quat_from_rotvec(W_FRD_RPS * t_us / US)


def filled(until_us: int, first_us: int = 0) -> PoseBuffer:
    """Attitude (with body rates) and position at 50 Hz from ``first_us`` up to ``until_us``."""
    buf = PoseBuffer(origin=ORIGIN)
    for t in range(first_us, until_us + 1, 20_000):
        buf.add_attitude(t, q_at(t), W_FRD_RPS)
        buf.add_position_ned(t, [0.0, 0.0, -50.0], [0.0, 0.0, 0.0])
    return buf


class _Signal:
    """A clock for ``wait_for`` that sets ``event`` once the waiter is inside its loop (second call), while
    it still holds the buffer's lock: a sample added after ``event`` is therefore added while it waits."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.calls = 0

    def __call__(self) -> float:
        import time

        self.calls += 1
        if self.calls >= 2:
            self.event.set()
        return time.monotonic()


def test_plain_wait_extrapolates_but_bracket_wait_waits_for_the_sample_after():
    t_frame = 110_000  # 10 ms past the newest sample (100 ms): extrapolable with the body rates
    shared = SharedPoseBuffer(filled(100_000))
    assert shared.wait_for(t_frame, 0.0) is False  # extrapolation is possible: the plain wait returns at once
    assert shared.pose_at(t_frame).mode == "extrapolated"
    assert shared.wait_for(t_frame, 0.0, bracket=True) is False  # no time to wait: not bracketed

    clock = _Signal()
    result: list[bool] = []
    waiter = threading.Thread(target=lambda: result.append(shared.wait_for(t_frame, 60.0, clock, bracket=True)))
    waiter.start()
    assert clock.event.wait(JOIN_TIMEOUT_S)
    shared.add_attitude(120_000, q_at(120_000), W_FRD_RPS)  # the attitude after the frame; position stays behind
    shared.add_position_ned(120_000, [0.0, 0.0, -50.0], [0.0, 0.0, 0.0])
    waiter.join(JOIN_TIMEOUT_S)
    assert not waiter.is_alive() and result == [True]
    pose = shared.pose_at(t_frame)
    assert pose.mode != "extrapolated" and pose.att_extrapolated_us == 0


def test_bracket_wait_waits_for_the_attitude_only_not_the_slower_position():
    """The chain's rotation is made of the attitude (and a gimbal's): the wait ends with the attitude sample after
    the frame, while the position (25 Hz against 50) is still behind and extrapolated."""
    t_frame = 110_000
    shared = SharedPoseBuffer(filled(100_000))
    clock = _Signal()
    result: list[bool] = []
    waiter = threading.Thread(target=lambda: result.append(shared.wait_for(t_frame, 60.0, clock, bracket=True)))
    waiter.start()
    assert clock.event.wait(JOIN_TIMEOUT_S)
    shared.add_attitude(120_000, q_at(120_000), W_FRD_RPS)
    waiter.join(JOIN_TIMEOUT_S)  # the 60 s wait for the position would be a failure
    assert not waiter.is_alive() and result == [True]
    pose = shared.pose_at(t_frame)
    assert pose.att_extrapolated_us == 0 and pose.mode == "extrapolated"  # the position's extrapolation


def test_bracket_wait_waits_on_for_a_position_the_look_up_cannot_extrapolate():
    """The attitude after the frame is in, but the position has no velocity to extrapolate with: without a
    position there is no rotation (the pose's), so the wait goes on until the position after the frame."""
    buf = PoseBuffer(origin=ORIGIN)
    for t in range(0, 100_001, 20_000):
        buf.add_attitude(t, q_at(t), W_FRD_RPS)
        buf.add_position_ned(t, [0.0, 0.0, -50.0])  # no velocity
    shared = SharedPoseBuffer(buf)
    t_frame = 110_000
    shared.add_attitude(120_000, q_at(120_000), W_FRD_RPS)
    assert shared.pose_at(t_frame) is None  # the position cannot be extrapolated
    clock = _Signal()
    result: list[bool] = []
    waiter = threading.Thread(target=lambda: result.append(shared.wait_for(t_frame, 60.0, clock, bracket=True)))
    waiter.start()
    assert clock.event.wait(JOIN_TIMEOUT_S)
    assert waiter.is_alive()
    shared.add_position_ned(120_000, [0.0, 0.0, -50.0])
    waiter.join(JOIN_TIMEOUT_S)
    assert not waiter.is_alive() and result == [True] and shared.pose_at(t_frame) is not None


def test_bracket_wait_does_not_wait_before_the_first_sample():
    shared = SharedPoseBuffer(filled(100_000, first_us=40_000))
    clock = _Signal()
    assert shared.wait_for(20_000, 60.0, clock, bracket=True) is False  # a valid time no sample can bracket
    assert clock.calls <= 2


def test_bracket_wait_does_not_wait_for_what_cannot_come():
    shared = SharedPoseBuffer(filled(100_000))
    # before the buffer's first sample: no later sample can bracket it, so it returns at once even with time left
    clock = _Signal()
    assert shared.wait_for(-50_000, 60.0, clock, bracket=True) is False
    assert clock.calls <= 2


class _PoseChain:
    """A stand-in for the objects chain: records the rotation it is given, reports searching."""

    uses_pose = True

    def __init__(self) -> None:
        self.rotations: list = []

    def update(self, pixels, R_ned_from_cam=None, time_boot_us=None):
        self.rotations.append(R_ned_from_cam() if callable(R_ned_from_cam) else R_ned_from_cam)
        return TrackUpdate(TrackState.SEARCHING, None, None, None, None, False, None, None, len(self.rotations))


def test_pipeline_waits_before_the_chain_looks_its_rotation_up():
    cfg = build_config({"imaging": {"chain": "objects"}, "estimator": {"enabled": False}})
    assert isinstance(cfg, OnboardConfig) and cfg.imaging.pose_wait_ms > 0
    buf = filled(100_000)
    chain = _PoseChain()
    t_frame = 130_000  # 30 ms past the newest sample: the newest samples alone would be extrapolated
    extrapolated = buf.pose_at(t_frame)
    assert extrapolated is not None and extrapolated.mode == "extrapolated"
    # the attitude after the frame is off the constant-rate path (the gimbal or the airframe moved otherwise)
    q_after = quat_multiply(quat_from_rotvec([0.0, 0.01, 0.0]), q_at(140_000))
    waited: list[int] = []

    def arrive(t_us: int) -> None:  # the telemetry after the frame comes in while the pipeline waits
        waited.append(t_us)
        buf.add_attitude(140_000, q_after, W_FRD_RPS)
        buf.add_position_ned(140_000, [0.0, 0.0, -50.0], [0.0, 0.0, 0.0])

    pipe = FramePipeline(cfg, buf, chain, None, ORIGIN, chain_pose_wait=arrive)
    K = cfg.camera.intrinsics
    pipe.process(IrFrame(0, t_frame, np.zeros((K.height_px, K.width_px), np.uint8)))
    assert waited == [t_frame]
    R = chain.rotations[0]
    pose = buf.pose_at(t_frame)
    assert pose is not None and pose.mode != "extrapolated"
    assert np.allclose(R, rotmat_from_quat(pose.q_ned_from_cam), atol=ATOL_RAD)
    # what the chain got without the wait: 0.0075 rad (~6 px at 765 px) away
    assert not np.allclose(R, rotmat_from_quat(extrapolated.q_ned_from_cam), atol=1e-3)


def test_the_objects_chain_detects_the_frame_before_the_wait():
    # the detection needs no pose: a frame sent the instant it is captured is detected while the attitude
    # sample after its capture is still on its way, not after it came
    from onboard.pipeline.frame_pipeline import make_tracker

    cfg = build_config({"imaging": {"chain": "objects"}, "estimator": {"enabled": False}})
    K = cfg.camera.intrinsics
    chain = make_tracker(cfg)
    buf = filled(100_000)
    t_frame = 110_000
    pixels = np.full((K.height_px, K.width_px), 20, np.uint8)
    detected_at_wait: list[bool] = []

    def arrive(t_us: int) -> None:
        detected_at_wait.append(chain.objects.detector.clean is not None)
        buf.add_attitude(120_000, q_at(120_000), W_FRD_RPS)
        buf.add_position_ned(120_000, [0.0, 0.0, -50.0], [0.0, 0.0, 0.0])

    pipe = FramePipeline(cfg, buf, chain, None, ORIGIN, chain_pose_wait=arrive)
    pipe.process(IrFrame(0, t_frame, pixels))
    assert detected_at_wait == [True]
    # the rotation the chain kept is the bracketed one, looked up after the wait
    pose = buf.pose_at(t_frame)
    assert pose is not None and pose.mode != "extrapolated"
    assert np.allclose(chain._R, rotmat_from_quat(pose.q_ned_from_cam), atol=ATOL_RAD)


def test_a_click_frame_is_tracked_with_its_own_rotation_and_time():
    """The frame an operator's click was decided on updated the chain with no rotation and no capture time: its
    tracks were predicted with the last frame's rotation (an operator clicks while the gimbal slews) and the
    chain lost count of the time since; and a refused click's frame was measured twice, the second time as a
    frozen frame (the tracks predicted a period that did not pass)."""
    from onboard.core.selection import TrackRequest
    from onboard.pipeline.frame_pipeline import make_tracker

    cfg = build_config({"imaging": {"chain": "objects"}, "estimator": {"enabled": False}})
    K = cfg.camera.intrinsics
    chain = make_tracker(cfg)
    buf = filled(200_000)
    pipe = FramePipeline(cfg, buf, chain, None, ORIGIN)
    rng = np.random.default_rng(0)

    def frame_pixels():
        return rng.integers(18, 23, (K.height_px, K.width_px), dtype=np.uint8)

    pipe.process(IrFrame(0, 100_000, frame_pixels()))
    for kind in ("point", "rectangle"):
        results: list = []
        request = (
            TrackRequest(1, "point", u_px=320.0, v_px=256.0, radius_px=20.0)
            if kind == "point"
            else TrackRequest(2, "rectangle", rect_px=(300.0, 240.0, 340.0, 270.0))
        )
        t_us = 133_333 if kind == "point" else 166_667
        pipe.request_selection(request, results.append)
        pipe.process(IrFrame(1 if kind == "point" else 2, t_us, frame_pixels()))
        assert len(results) == 1 and not results[0].accepted  # nothing confirmed there: refused, frame tracked
        pose = buf.pose_at(t_us)
        assert pose is not None and np.allclose(chain._R, rotmat_from_quat(pose.q_ned_from_cam), atol=ATOL_RAD)
        assert chain.objects._last_time_us == t_us and chain.objects.frozen_frames == 0
