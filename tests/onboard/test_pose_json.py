"""onboard.io.pose_json: a recorded pose reads back bit for bit, and a malformed one is refused naming the field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from onboard.core.errors import InputError
from onboard.io.pose_json import pose_from_json, pose_to_json
from tests.onboard.test_record import _pose


def test_pose_json_round_trip_is_bit_exact():
    p = _pose(123_456_789, 3)
    q = pose_from_json(json.loads(json.dumps(pose_to_json(p))))
    for name in ("p_cam_ned_m", "q_ned_from_cam"):
        assert np.array_equal(getattr(p, name), getattr(q, name))
    assert np.array_equal(p.body.q_ned_from_body, q.body.q_ned_from_body)
    assert np.array_equal(p.body.v_ned_mps, q.body.v_ned_mps, equal_nan=True)
    assert (q.origin, q.epoch, q.att_span_us, q.sigma_extrapolation_rad) == (p.origin, 0, 20000, 1e-5)


def test_pose_from_json_names_the_missing_field():
    obj = pose_to_json(_pose(1000))
    del obj["q_ned_from_cam"]
    with pytest.raises(Exception, match="frame 7.*q_ned_from_cam"):
        pose_from_json(obj, "frame 7")


@pytest.mark.parametrize(
    "field, value, said",
    [
        ("q_ned_from_cam", [0.0, 0.0, 0.0, 0.0], "q_ned_from_cam: quaternion norm"),
        ("q_ned_from_cam", [1.7, 0.0, 0.0, 0.0], "q_ned_from_cam: quaternion norm"),
        ("q_ned_from_cam", [1.0, None, 0.0, 0.0], "q_ned_from_cam: quaternion must be 4 finite numbers"),
        ("q_mount_from_gimbal", [0.5, 0.0, 0.0, 0.0], "q_mount_from_gimbal: quaternion norm"),
        ("p_cam_ned_m", [1.0, None, 2.0], "p_cam_ned_m must be 3 finite numbers"),
    ],
)
def test_a_recorded_pose_with_a_bad_camera_quaternion_or_position_is_refused_naming_it(field, value, said):
    """A zero camera quaternion had replayed as a line of sight straight down with the pose valid, a scaled one as
    frames without a line of sight, nothing refused."""
    obj = pose_to_json(_pose(1000))
    obj[field] = value
    with pytest.raises(InputError, match=f"frame 7: {said}"):
        pose_from_json(obj, "frame 7")
