"""The objects chain carries its tracks as lines of sight: on a camera with lens distortion a turn of the camera
moves a track's pixel through the lens model, not the pinhole's (a wide lens: several pixels near the edge for a
degree of turn, against a 4 px association gate)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics, quat_from_rotvec, rotmat_from_quat
from onboard.imaging.objects_model import los_from_pixel, pixel_from_los, pixels_from_los

WIDE = PinholeIntrinsics(300.0, 300.0, 320.0, 256.0, 640, 512, distortion=(-0.3, 0.05, 0.0, 0.0, 0.0))
ATOL_PX = 1e-6  # the undistortion's iterations converge far below this
ATOL_RAD = 1e-9

finite = dict(allow_nan=False, allow_infinity=False)


@given(
    st.floats(40.0, 600.0, **finite),
    st.floats(40.0, 470.0, **finite),
    st.lists(st.floats(-0.035, 0.035, **finite), min_size=3, max_size=3),
)
@settings(max_examples=100, deadline=None)
def test_a_turned_camera_sees_the_line_of_sight_where_its_lens_puts_it(u, v, turn_rad):
    R0 = rotmat_from_quat(quat_from_rotvec([0.1, -0.2, 0.3]))
    R1 = R0 @ rotmat_from_quat(quat_from_rotvec(turn_rad))
    los = los_from_pixel(WIDE, u, v, R0)
    assert abs(np.linalg.norm(los) - 1.0) < ATOL_RAD
    np.testing.assert_allclose(pixel_from_los(WIDE, los, R0), (u, v), atol=ATOL_PX)  # the round trip
    truth = WIDE.project(R1.T @ los)  # the lens model's own projection of that direction
    np.testing.assert_allclose(pixel_from_los(WIDE, los, R1), truth, atol=ATOL_PX)
    np.testing.assert_allclose(pixels_from_los(WIDE, np.array([los, los]), R1)[1], truth, atol=ATOL_PX)


def test_the_pinhole_would_miss_the_association_gate_near_a_wide_lens_edge():
    R0 = np.eye(3)
    R1 = rotmat_from_quat(quat_from_rotvec([0.0, math.radians(2.0), 0.0]))
    los = los_from_pixel(WIDE, 600.0, 470.0, R0)
    lens = np.asarray(pixel_from_los(WIDE, los, R1))
    # what the chain predicted while it took every camera for a pinhole: through the pinhole both ways
    K = WIDE
    ray = R0 @ np.array([(600.0 - K.cx_px) / K.fx_px, (470.0 - K.cy_px) / K.fy_px, 1.0])
    c = R1.T @ ray
    pinhole = np.array([K.fx_px * c[0] / c[2] + K.cx_px, K.fy_px * c[1] / c[2] + K.cy_px])
    assert np.linalg.norm(lens - pinhole) > 4.0
    assert pixel_from_los(WIDE, -los, R0) is None  # behind the camera
    assert pixels_from_los(WIDE, np.array([-los]), R0) == [None]
