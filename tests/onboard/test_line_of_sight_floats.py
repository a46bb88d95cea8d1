"""The line of sight's floats-only computation (onboard/core/track.py) against the matrix form it
replaced (first-order propagation through J = R M dxy and C = s_px^2 J J^T + s_att^2 (I - l l^T)),
with and without lens distortion."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics, quat_normalize, rotmat_from_quat
from onboard.core.track import SIGMA_AZ_CAP_DEG, line_of_sight_ned


def _reference(uv_px, intrinsics, q_ned_from_cam, pixel_sigma_px, attitude_sigma_rad) -> tuple:
    """The matrix form, as it was: (line of sight, azimuth, elevation, their sigmas), degrees."""
    uv = np.asarray(uv_px, dtype=float).reshape(2)
    R = rotmat_from_quat(np.asarray(q_ned_from_cam, dtype=float))
    xy = np.asarray(intrinsics.normalized_from_pixel(uv), dtype=float)
    if intrinsics.has_distortion:
        step = 0.5  # px, central differences of the undistortion
        dxy = np.stack(
            [
                (
                    np.asarray(intrinsics.normalized_from_pixel(uv + d))
                    - np.asarray(intrinsics.normalized_from_pixel(uv - d))
                )
                / (2 * step)
                for d in (np.array([step, 0.0]), np.array([0.0, step]))
            ],
            axis=1,
        )
    else:
        dxy = np.diag([1.0 / intrinsics.fx_px, 1.0 / intrinsics.fy_px])
    b = np.array([xy[0], xy[1], 1.0])
    nb = float(np.linalg.norm(b))
    b_unit = b / nb
    los = R @ b_unit
    J = R @ ((np.eye(3) - np.outer(b_unit, b_unit)) / nb)[:, :2] @ dxy  # dl/d(u, v), 3 x 2
    C = pixel_sigma_px**2 * (J @ J.T) + attitude_sigma_rad**2 * (np.eye(3) - np.outer(los, los))
    n, e, d = (float(c) for c in los)
    h = math.hypot(n, e)
    az = math.degrees(math.atan2(e, n)) if h > 0 else 0.0
    el = math.degrees(math.atan2(-d, h))
    g_el = np.array([d * n / h, d * e / h, -h]) if h > 0 else np.array([0.0, 0.0, -1.0])
    s_el = math.degrees(math.sqrt(max(float(g_el @ C @ g_el), 0.0)))
    if h > 1e-9:
        g_az = np.array([-e, n, 0.0]) / h**2
        s_az = min(math.degrees(math.sqrt(max(float(g_az @ C @ g_az), 0.0))), SIGMA_AZ_CAP_DEG)
    else:
        s_az = SIGMA_AZ_CAP_DEG
    return tuple(float(c) for c in los), az, el, s_az, s_el


K_PLAIN = PinholeIntrinsics.vue_pro_640()
K_DISTORTED = PinholeIntrinsics(520.0, 515.0, 322.0, 255.0, 640, 512, (-0.2, 0.05, 0.001, -0.001, 0.0))
unit = st.floats(-1.0, 1.0)


@settings(max_examples=400, deadline=None)
@given(
    st.floats(0.0, 639.0),
    st.floats(0.0, 511.0),
    st.tuples(unit, unit, unit, unit).filter(lambda q: sum(c * c for c in q) > 1e-3),
    st.floats(0.0, 3.0),
    st.floats(0.0, 0.05),
    st.booleans(),
)
def test_floats_only_line_of_sight_equals_the_matrix_form(u, v, q, s_px, s_att, distorted):
    K = K_DISTORTED if distorted else K_PLAIN
    qn = quat_normalize(np.array(q))
    got = line_of_sight_ned((u, v), K, qn, (1.0, 2.0, -3.0), s_px, s_att)
    los, az, el, s_az, s_el = _reference((u, v), K, qn, s_px, s_att)
    np.testing.assert_allclose(got.u_ned, los, rtol=0, atol=1e-12)
    assert math.isclose(got.azimuth_deg, az, abs_tol=1e-9) or abs(abs(got.azimuth_deg - az) - 360.0) < 1e-9
    assert math.isclose(got.elevation_deg, el, abs_tol=1e-9)
    assert math.isclose(got.sigma_elevation_deg, s_el, rel_tol=1e-7, abs_tol=1e-9)
    assert math.isclose(got.sigma_azimuth_deg, s_az, rel_tol=1e-7, abs_tol=1e-9)
    assert got.p_cam_ned_m == (1.0, 2.0, -3.0)


def test_looking_straight_down_caps_the_azimuth_sigma():
    # camera z (optical axis) along NED down: R_ned_from_cam with columns x->east, y->south... any roll
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    from onboard.core.frames import quat_from_rotmat

    got = line_of_sight_ned((K_PLAIN.cx_px, K_PLAIN.cy_px), K_PLAIN, quat_from_rotmat(R), (0, 0, 0), 0.3, 0.002)
    assert got.elevation_deg == -90.0 and got.sigma_azimuth_deg == SIGMA_AZ_CAP_DEG
    assert np.allclose(rotmat_from_quat(quat_from_rotmat(R)), R)


def test_a_non_finite_pixel_is_refused():
    import pytest

    with pytest.raises(InputError, match="pixel must be finite"):
        line_of_sight_ned((math.nan, 1.0), K_PLAIN, (1.0, 0, 0, 0), (0, 0, 0), 0.3, 0.002)


def test_due_south_is_plus_180_degrees_not_minus():
    """The documented azimuth range is (-180, 180]: a line of sight due south whose east component rounds to a
    tiny negative number (atan2 then gives -pi, -180 after rounding) is +180."""
    from onboard.core.frames import Q_MOUNT_FROM_CAM, quat_from_euler, quat_multiply

    q = quat_multiply(quat_from_euler(0.0, 0.0, -math.pi), Q_MOUNT_FROM_CAM)  # a level camera looking south
    got = line_of_sight_ned((K_PLAIN.cx_px, K_PLAIN.cy_px), K_PLAIN, q, (0, 0, 0), 0.3, 0.002)
    assert got.u_ned[0] < -0.999 and got.u_ned[1] <= 0.0 and got.azimuth_deg == 180.0
