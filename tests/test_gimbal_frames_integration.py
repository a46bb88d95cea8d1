"""The simulated vehicle's #285 in either frame, through the daemon's autopilot link, gives the camera the same pose.

``groundsim run``'s ArduPilot vehicle sends its gimbal in the vehicle frame, as ArduPilot does (yaw relative to the
nose, ROLL_LOCK | PITCH_LOCK | YAW_IN_VEHICLE_FRAME | YAW_LOCK, delta_yaw NaN); the generic one in the earth frame.
The daemon must turn the first into the second with the vehicle's own attitude stream: the simulator's P1 flight is
sent by :class:`~groundsim.io.mavlink_vehicle.MavlinkVehicle` over UDP on 127.0.0.1 to a
:class:`~onboard.io.mavlink_link.MavlinkLink` tick by tick (lockstep: each tick's datagrams read before the next is
sent), once per frame, and the camera's attitude and line of sight at each frame time are compared, and with the
simulator's truth.  Everything is in this process: the sockets are closed at the end, no process is started.
"""

from __future__ import annotations

import math
import select
import time

import numpy as np
import pytest

from groundsim.evaluation.eval import onboard_config_for
from groundsim.io.mavlink_vehicle import MavlinkVehicle
from groundsim.io.ports import free_udp_port
from groundsim.world.scenario import load_scenario, scenarios_dir
from groundsim.world.sim import SimCore
from onboard.core.counters import RejectCounter
from onboard.core.frames import quat_conjugate, quat_multiply, quat_rotate
from onboard.core.pose import PoseBuffer
from onboard.io.mavlink_link import MavlinkConfig, MavlinkLink
from tests.fakes import FakeClock

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

WAIT_S = 3.0  # upper bound on the wait for one tick's datagrams on the loopback
FLIGHT_S = 3.0
#: between the two frames: the vehicle frame's gimbal samples (10 Hz) are interpolated relative to the nose and
#: turned by the 50 Hz attitude's yaw, the earth frame's interpolated in the earth frame; over P1's gentle turns the
#: two part by little more than the wire's float32 quaternions (~1e-7 rad); a #285 read in the wrong frame (ArduPilot's
#: YAW_LOCK taken for the legacy earth-frame flag) would be off by the vehicle's yaw
SAME_RAD = 1e-5  # 10 urad
#: to the truth: the wire's float32, and the interpolation between samples
TRUTH_RAD = 5e-4  # 0.5 mrad


def _camera_attitudes(frame: str, sc, cfg) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """``({frame index: q_ned_from_cam}, {frame index: the truth's})``: what the daemon's pose buffer gives at each
    frame's capture time, with the vehicle's #285 in ``frame``, and the simulator's truth."""
    core = SimCore(sc, 0, FLIGHT_S, render=False, nav_noise="exact")
    assert core.gimballed
    truth: dict[int, tuple[int, np.ndarray]] = {}
    port = free_udp_port()
    clock = FakeClock()
    counter = RejectCounter(clock=clock)
    pose = PoseBuffer(cfg.camera.camera_mount(), cfg.pose, cfg.pose.geodetic_origin(), counter=counter)
    link = MavlinkLink(
        MavlinkConfig(connection=f"udpin:127.0.0.1:{port}", autopilot_sysid=1),
        pose,
        counter,
        gimballed=True,
        clock=clock,
    )
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", gimballed=True, gimbal_yaw_frame=frame)
    out: dict[int, np.ndarray] = {}
    try:
        for i in range(core.tick_count):
            k, r = divmod(i, core.ticks_per_frame)
            if r == 0:  # the simulator keeps the latest chunks only: each frame's truth as it is flown
                t = core.frame(k).truth
                q = np.array([t.q_ned_from_cam_w, t.q_ned_from_cam_x, t.q_ned_from_cam_y, t.q_ned_from_cam_z])
                truth[k] = (t.time_boot_us, q)
            vehicle.update_state(**core.vehicle_state(i))
            before = link.messages_rx
            sent = vehicle.poll(core.time_boot_us(i))
            deadline = time.monotonic() + WAIT_S
            while link.messages_rx < before + sent and time.monotonic() < deadline:
                select.select([link.fileno()], [], [], 0.05)
                link.poll()
            assert link.messages_rx >= before + sent, f"tick {i}: {sent} sent, {link.messages_rx - before} read"
        assert link.gimbal_device_id == 1 and counter["second_gimbal"] == 0
        for k, (t_us, _) in truth.items():
            got = pose.pose_at(t_us, extrapolate=False)
            if got is not None:
                out[k] = np.asarray(got.q_ned_from_cam, dtype=float)
    finally:
        vehicle.close()
        link.close()
    return out, {k: q for k, (_, q) in truth.items()}


def _angle_rad(q_a, q_b) -> float:
    d = quat_multiply(quat_conjugate(np.asarray(q_a)), np.asarray(q_b))
    return 2.0 * math.atan2(float(np.linalg.norm(d[1:])), abs(float(d[0])))


def test_vehicle_frame_gimbal_gives_the_camera_the_earth_frame_attitude():
    sc = load_scenario(scenarios_dir() / "P1.yaml")
    cfg = onboard_config_for(sc)
    earth, truth = _camera_attitudes("earth", sc, cfg)
    vehicle, _ = _camera_attitudes("vehicle", sc, cfg)
    # the frames after the gimbal stream's first bracket: all of them, both ways
    assert len(earth) >= len(truth) - 5 and set(vehicle) == set(earth)
    z_cam = np.array([0.0, 0.0, 1.0])  # the optical axis (OpenCV camera: z forward)
    worst_same = worst_truth = 0.0
    for k, q_e in earth.items():
        q_v = vehicle[k]
        worst_same = max(worst_same, _angle_rad(q_e, q_v))
        los_e, los_v = quat_rotate(q_e, z_cam), quat_rotate(q_v, z_cam)
        assert float(np.dot(los_e, los_v)) == pytest.approx(1.0, abs=SAME_RAD**2)
        worst_truth = max(worst_truth, _angle_rad(truth[k], q_v))
    assert worst_same < SAME_RAD, f"earth and vehicle frames part by {worst_same:.2e} rad"
    assert worst_truth < TRUTH_RAD, f"the vehicle frame is {worst_truth:.2e} rad off the truth"
