"""The frame pipeline's camera-clock handling: the offset estimator sees the pose at the frame's stamp, the 3-D and
the line of sight the pose at the stamp minus the compensation, and a compensation that moves restarts the window."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from onboard.app.config import OnboardConfig
from onboard.core.track import track_from_json, track_to_json
from onboard.estimation.time_offset import TimeOffsetEstimate
from tests.fakes import idle_status
from tests.onboard.test_pipeline import Rig

POS_TOL_M = 1e-9  # the same interpolation twice


class StubOffset:
    """An offset estimator whose compensation the test sets; records what it is fed."""

    def __init__(self) -> None:
        self.compensated_ms = 0.0
        self.fed: list[tuple] = []
        self.resets = 0
        self.estimate = TimeOffsetEstimate(None, None, "unknown", 0.0, 0, 0, 0, None)

    def add(self, t_s, bearing_cam, q_ned_from_cam, p_cam_ned_m, v_cam_ned_mps, range_m=None, track_id=None):
        self.fed.append((t_s, np.array(p_cam_ned_m), range_m, track_id))
        return self.estimate

    def reset(self) -> None:
        self.resets += 1


class LookupLog:
    """A pose source that logs the times looked up."""

    def __init__(self, source) -> None:
        self.source, self.times = source, []

    def pose_at(self, t_us, *args, **kwargs):
        self.times.append(t_us)
        return self.source.pose_at(t_us, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.source, name)


def _rig(compensated_ms: float) -> tuple[Rig, StubOffset, LookupLog]:
    rig = Rig()
    stub = StubOffset()
    stub.compensated_ms = compensated_ms
    rig.pipe.time_offset = stub
    log = LookupLog(rig.pose)
    rig.pipe.pose_source = log
    return rig, stub, log


def test_compensated_frames_get_the_pose_at_stamp_minus_offset_and_the_estimator_the_stamps():
    rig, stub, log = _rig(40.0)
    tracks = [rig.step(k) for k in range(15)]
    k = 14
    t_us = rig.scene.t_us(k)
    assert log.times[-2:] == [t_us, t_us - 40_000]  # the stamp's, then the compensated one last (what a recorder keeps)
    assert [name for name, _ in rig.est.calls].count("add") == 15
    # the offset estimator got the stamp's pose, with the estimator's range once there was an estimate
    t_s, p_fed, range_m, track_id = stub.fed[-1]
    assert t_s == pytest.approx(t_us / 1e6)
    np.testing.assert_allclose(p_fed, rig.pose.pose_at(t_us).p_cam_ned_m, atol=POS_TOL_M)
    assert range_m is not None and range_m > 0 and track_id == tracks[-1].track_id
    assert stub.fed[0][2] is None  # before the estimator's first estimate: no range
    # the line of sight starts at the compensated camera position
    los = tracks[-1].los
    assert los is not None
    np.testing.assert_allclose(los.p_cam_ned_m, rig.pose.pose_at(t_us - 40_000).p_cam_ned_m, atol=POS_TOL_M)
    assert not np.allclose(los.p_cam_ned_m, rig.pose.pose_at(t_us).p_cam_ned_m, atol=0.05)
    # and the track says so, for a consumer that times it (the fleet fusion): its line of sight is of t_us - 40 ms
    assert tracks[-1].compensated_us == 40_000 and track_from_json(track_to_json(tracks[-1])).compensated_us == 40_000
    assert _rig(0.0)[0].step(0).compensated_us == 0


def test_a_camera_stamping_later_than_the_telemetry_reaches_still_gets_the_compensated_pose():
    # 80 ms late, telemetry fed to 25 ms past the capture (stamp minus 80 ms) when the frame is processed: the
    # capture is bracketed, the stamp 55 ms past the newest sample has no pose (this rig's attitude has no rates to
    # extrapolate with; the daemon's, beyond pose.max_extrapolation_ms, 50 ms, none either). The live daemon is
    # there once it compensates: its image chain waits for the capture's telemetry, not the stamp's
    rig, stub, log = _rig(80.0)
    tracks = [rig.step(k, lead_us=-55_000) for k in range(15)]
    t_us = rig.scene.t_us(14)
    assert log.times[-2:] == [t_us, t_us - 80_000]
    assert rig.pose.pose_at(t_us) is None and rig.pose.pose_at(t_us - 80_000) is not None
    los = tracks[-1].los
    assert los is not None and tracks[-1].compensated_us == 80_000
    np.testing.assert_allclose(los.p_cam_ned_m, rig.pose.pose_at(t_us - 80_000).p_cam_ned_m, atol=POS_TOL_M)
    assert [name for name, _ in rig.est.calls].count("add") == 15
    assert stub.fed == []  # the offset estimator gets no stamp pose: nothing to compare the bearing with


def test_a_compensation_that_moves_restarts_the_estimator_a_small_drift_does_not():
    rig, stub, _ = _rig(0.0)
    rig.run(12)
    stub.compensated_ms = (
        6.0  # within COMPENSATION_RESTART_MS: this estimator has no rebuild, and a restart loses its window
    )
    rig.run(3, start=12)
    assert not any(name == "reset" for name, _ in rig.est.calls)
    stub.compensated_ms = 45.0
    rig.run(3, start=15)
    assert sum(name == "reset" for name, _ in rig.est.calls) == 1  # this estimator has no rebuild: a restart
    assert rig.pipe.estimator_resets == 1 and rig.pipe.window_restamps == 0


def test_the_offset_estimator_is_on_by_default_and_off_by_config_and_in_the_status():
    rig = Rig()
    assert rig.pipe.time_offset is not None and rig.pipe.time_offset_estimate.state == "unknown"
    off = dataclasses.replace(
        OnboardConfig(), time_offset=dataclasses.replace(OnboardConfig().time_offset, enabled=False)
    )
    assert Rig(config=off).pipe.time_offset_estimate is None
    status = idle_status(
        camera_time_offset={**TimeOffsetEstimate(48.2, 3.1, "confident", 48.2, 4, 320, 0, 6.5).as_dict()}
    )
    assert status["camera_time_offset"]["state"] == "confident"
    assert (
        status["camera_time_offset"]["estimate_ms"] == 48.2 and status["camera_time_offset"]["compensated_ms"] == 48.2
    )
