"""The simulator's world is the origin's NED; its autopilot reports attitude, velocity and an earth-frame gimbal in
the local level where the observer is (onboard.core.frames, "Local level"); the daemon's pose buffer turns them back.
Five kilometres out, where the two frames are 0.045 deg apart, the round trip must give the truth's camera."""

from __future__ import annotations

import math

import numpy as np

from groundsim.world.scenario import read_spec_yaml, reference_scenario_paths, scenario_from_dict
from groundsim.world.sim import SimCore
from onboard.core.frames import quat_conjugate, quat_multiply, rotvec_from_quat
from onboard.core.pose import GimbalReference, PoseBuffer

ATOL_RAD = 1e-9  # the round trip's rounding, far below the 7.9e-4 rad between the two frames there
ATOL_MPS = 1e-9
NORTH_M = 5000.0


def _far_north_p1() -> SimCore:
    d = read_spec_yaml(reference_scenario_paths()["P1"])
    for who in ("observer", "target"):
        p = d[who]["motion"]["p0_ned_m"]
        d[who]["motion"]["p0_ned_m"] = [p[0] + NORTH_M, p[1], p[2]]
    return SimCore(scenario_from_dict(d), 0, 0.5, render=False)


def _angle_rad(q0, q1) -> float:
    return float(np.linalg.norm(rotvec_from_quat(quat_multiply(quat_conjugate(np.asarray(q0)), np.asarray(q1)))))


def test_the_telemetry_turned_back_by_the_pose_buffer_is_the_truths_camera_five_km_out():
    core = _far_north_p1()
    sc = core.scenario
    buf = PoseBuffer(mount=sc.camera.mount, origin=sc.origin)
    tilts = []
    for i in range(0, 60, 4):  # each tick's pose looked up at its own samples' time (no interpolation)
        st = core.vehicle_state(i)
        t = st["time_boot_us"]
        assert buf.add_attitude(t, st["q_ned_from_body"], st["body_rates_radps"])
        assert buf.add_position(t, st["lat_deg"], st["lon_deg"], st["alt_amsl_m"], st["v_ned_mps"])
        assert buf.add_gimbal_status(t, st["q_gimbal"], GimbalReference.EARTH)
        c = core.flight.chunk_of(i)
        j = i - c.i0
        pose = buf.pose_at(t)
        assert _angle_rad(pose.q_ned_from_cam, c.cam_q_ned_from_cam[j]) < ATOL_RAD
        np.testing.assert_allclose(pose.body.v_ned_mps, c.obs_v_ned_mps[j], atol=ATOL_MPS)
        # what went over the wire is not the world's: the local level is turned by the distance to the origin
        tilts.append(_angle_rad(st["q_ned_from_body"], c.obs_q_ned_from_body[j]))
    assert min(tilts) > math.radians(0.044)
