"""Frame conventions (onboard/core/frames.py): round trips, sign conventions and property tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from onboard.core import frames as fr

ATOL_M = 1e-6  # 1 um: geodesy round trips
ATOL_DEG = 1e-9  # ~0.1 mm of latitude
ATOL_ROT = 1e-12  # rotation matrices and quaternions, dimensionless
ATOL_PX = 1e-9  # pixels
ATOL_OPENCV_PX = 1e-9  # OpenCV's projectPoints: the same model in double, its own order of operations

ORIGIN = fr.GeodeticOrigin(32.0, 118.8, 0.0)

finite = dict(allow_nan=False, allow_infinity=False)
quats = st.lists(st.floats(-1, 1, **finite), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)


def unit(q):
    q = np.asarray(q, float)
    return q / np.linalg.norm(q)


# ------------------------------------------------------------------------------------ geodesy


@given(st.floats(-3000, 3000, **finite), st.floats(-3000, 3000, **finite), st.floats(-500, 500, **finite))
@settings(max_examples=200, deadline=None)
def test_ned_geodetic_round_trip(n, e, d):
    lat, lon, alt = fr.geodetic_from_ned([n, e, d], ORIGIN)
    back = fr.ned_from_geodetic(lat, lon, alt, ORIGIN)
    assert np.allclose(back, [n, e, d], atol=ATOL_M)


@given(st.floats(-89.5, 89.5, **finite), st.floats(-179.9, 179.9, **finite), st.floats(-89.5, 89.5, **finite))
@settings(max_examples=200, deadline=None)
def test_the_local_levels_axes_are_the_geodesys_own(lat, lon, lat0):
    """q_ned_from_level(lat, lon, origin) turns the local level's axes into the origin's NED as the geodesy does:
    its down is the direction from a point 100 m up to the point beneath it, its north the direction to a point a
    hair north, both measured with ned_from_geodetic (no rotation matrix shared with the function)."""
    origin = fr.GeodeticOrigin(lat0, 118.8, 50.0)
    q = fr.q_ned_from_level(lat, lon, origin)
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=ATOL_ROT)
    assert np.allclose(fr.q_ned_from_level1(lat, lon, origin), q, atol=ATOL_ROT)
    up, down = fr.ned_from_geodetic(lat, lon, 100.0, origin), fr.ned_from_geodetic(lat, lon, 0.0, origin)
    d = (down - up) / np.linalg.norm(down - up)
    north = fr.ned_from_geodetic(lat + 1e-5, lon, 0.0, origin) - down
    north -= d * (north @ d)  # the meridian's step, made horizontal
    assert np.allclose(fr.quat_rotate(q, [0.0, 0.0, 1.0]), d, atol=1e-9)
    assert np.allclose(fr.quat_rotate(q, [1.0, 0.0, 0.0]), north / np.linalg.norm(north), atol=1e-6)


def test_the_local_level_is_the_origins_ned_at_the_origin_and_tilts_0_009_deg_a_km():
    assert np.allclose(fr.q_ned_from_level(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN), [1, 0, 0, 0], atol=ATOL_ROT)
    north_5km = fr.geodetic_from_ned([5000.0, 0.0, 0.0], ORIGIN)
    q = fr.q_ned_from_level(float(north_5km[0]), float(north_5km[1]), ORIGIN)
    tilt_deg = math.degrees(2.0 * math.acos(min(1.0, abs(q[0]))))
    assert tilt_deg == pytest.approx(0.0452, abs=0.0005)  # 5 km over the meridian's radius of curvature there
    # a level vehicle 5 km north: its down leans back towards the origin (north component < 0)
    assert fr.quat_rotate(q, [0.0, 0.0, 1.0])[0] == pytest.approx(-math.radians(tilt_deg), rel=1e-3)


@given(st.floats(-89.9, 89.9, **finite), st.floats(-179.9, 179.9, **finite), st.floats(-400, 9000, **finite))
@settings(max_examples=200, deadline=None)
def test_ecef_geodetic_round_trip(lat, lon, alt):
    la, lo, al = fr.geodetic_from_ecef(fr.ecef_from_geodetic(lat, lon, alt))
    assert la == pytest.approx(lat, abs=ATOL_DEG)
    assert lo == pytest.approx(lon, abs=ATOL_DEG)
    assert al == pytest.approx(alt, abs=ATOL_M * 1e3)


def test_ned_signs_north_east_down():
    # 0.001 deg of latitude north is ~110.9 m at 32 N; of longitude east ~94.5 m; 10 m up is d = -10
    p = fr.ned_from_geodetic(32.001, 118.8, 0.0, ORIGIN)
    assert p[0] == pytest.approx(110.9, abs=0.1) and abs(p[1]) < 1e-6
    p = fr.ned_from_geodetic(32.0, 118.801, 0.0, ORIGIN)
    assert p[1] == pytest.approx(94.5, abs=0.1) and abs(p[0]) < 1e-3
    p = fr.ned_from_geodetic(32.0, 118.8, 10.0, ORIGIN)
    assert p[2] == pytest.approx(-10.0, abs=ATOL_M)


def test_origin_validation_names_the_field():
    with pytest.raises(fr.FrameError, match="lat_deg"):
        fr.GeodeticOrigin(91.0, 0.0)
    with pytest.raises(fr.FrameError, match="alt_m"):
        fr.GeodeticOrigin(0.0, 0.0, math.nan)


# ------------------------------------------------------------------------------------ quaternions


@given(quats)
@settings(max_examples=200, deadline=None)
def test_rotmat_matches_scipy_with_w_first(q):
    q = unit(q)
    ours = fr.rotmat_from_quat(q)
    ref = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy is scalar-last
    assert np.allclose(ours, ref, atol=1e-12)
    assert np.allclose(ours @ ours.T, np.eye(3), atol=1e-12)


@given(quats, quats)
@settings(max_examples=200, deadline=None)
def test_hamilton_product_composes_like_matrices(a, b):
    a, b = unit(a), unit(b)
    assert np.allclose(
        fr.rotmat_from_quat(fr.quat_multiply(a, b)), fr.rotmat_from_quat(a) @ fr.rotmat_from_quat(b), atol=1e-12
    )
    assert np.allclose(fr.rotmat_from_quat(fr.quat_conjugate(a)), fr.rotmat_from_quat(a).T, atol=1e-12)


@given(quats)
@settings(max_examples=200, deadline=None)
def test_quat_from_rotmat_round_trip(q):
    q = fr.quat_normalize(q)
    back = fr.quat_from_rotmat(fr.rotmat_from_quat(q))
    # q and -q are one rotation; with w ~ 0 the w >= 0 convention cannot pick a side
    assert np.allclose(back, q, atol=1e-9) or np.allclose(back, -q, atol=1e-9)


@given(st.floats(-3.1, 3.1, **finite), st.floats(-1.5, 1.5, **finite), st.floats(-3.1, 3.1, **finite))
@settings(max_examples=200, deadline=None)
def test_euler_round_trip_zyx(roll, pitch, yaw):
    r, p, y = fr.euler_from_quat(fr.quat_from_euler(roll, pitch, yaw))
    assert (r, p, y) == pytest.approx((roll, pitch, yaw), abs=1e-9)


def test_euler_sign_conventions_body_frd_to_ned():
    # yaw +90 deg: the nose (body x) points east
    assert np.allclose(fr.quat_rotate(fr.quat_from_euler(0, 0, math.pi / 2), [1, 0, 0]), [0, 1, 0], atol=ATOL_ROT)
    # pitch +30 deg: nose up, so body x gets a negative down component
    v = fr.quat_rotate(fr.quat_from_euler(0, math.radians(30), 0), [1, 0, 0])
    assert v[2] == pytest.approx(-0.5, abs=1e-12)
    # roll +30 deg: right wing down, so body y gets a positive down component
    v = fr.quat_rotate(fr.quat_from_euler(math.radians(30), 0, 0), [0, 1, 0])
    assert v[2] == pytest.approx(0.5, abs=1e-12)


@given(st.lists(st.floats(-3.0, 3.0, **finite), min_size=3, max_size=3))
@settings(max_examples=200, deadline=None)
def test_rotvec_exp_log_round_trip(phi):
    phi = np.asarray(phi)
    if np.linalg.norm(phi) >= math.pi:
        phi = phi / np.linalg.norm(phi) * 3.0
    assert np.allclose(fr.rotvec_from_quat(fr.quat_from_rotvec(phi)), phi, atol=1e-9)
    assert np.allclose(fr.rotmat_from_rotvec(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)


def test_slerp_end_points_midpoint_and_shortest_arc():
    q0 = fr.quat_from_euler(0, 0, 0.0)
    q1 = fr.quat_from_euler(0, 0, 1.0)
    assert np.allclose(fr.quat_slerp(q0, q1, 0.0), q0, atol=ATOL_ROT)
    assert np.allclose(fr.quat_slerp(q0, q1, 1.0), q1, atol=ATOL_ROT)
    assert fr.euler_from_quat(fr.quat_slerp(q0, q1, 0.5))[2] == pytest.approx(0.5, abs=1e-12)
    # -q1 is the same rotation: the interpolation must not go the long way round
    assert fr.euler_from_quat(fr.quat_slerp(q0, -q1, 0.5))[2] == pytest.approx(0.5, abs=1e-12)


@pytest.mark.parametrize("q", [[math.nan, 0, 0, 1], [0, 0, 0, 0], [1.0, 0.1, 0, 0], 1.0, np.float64(0.5), None])
def test_check_unit_quat_rejects_nan_zero_non_unit_and_a_lone_number(q):
    """A lone number (a 0-d array) is refused as the others are, not an IndexError from its missing last axis."""
    with pytest.raises(fr.FrameError, match="attitude"):
        fr.check_unit_quat(q, "attitude")


# ------------------------------------------------------------------------------------ camera and mount


def test_identity_mount_camera_axes_in_body():
    R = fr.rotmat_from_quat(fr.CameraMount().q_body_from_cam())
    assert np.allclose(R @ [0, 0, 1], [1, 0, 0], atol=ATOL_ROT)  # optical axis = body forward
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0], atol=ATOL_ROT)  # image right = body right
    assert np.allclose(R @ [0, 1, 0], [0, 0, 1], atol=ATOL_ROT)  # image down = body down


def test_mount_pitched_down_looks_down_and_lever_arm_rotates_with_the_body():
    mount = fr.CameraMount.from_euler_deg((0.2, 0.0, 0.1), pitch_deg=-30.0)
    q_nb = fr.quat_from_euler(0.0, 0.0, math.pi / 2)  # heading east
    p_cam, q_nc = fr.camera_pose_ned([10.0, 20.0, -50.0], q_nb, mount)
    assert np.allclose(p_cam, [10.0, 20.2, -49.9], atol=ATOL_M)  # 0.2 m forward = east, 0.1 m down
    axis = fr.quat_rotate(q_nc, [0, 0, 1])
    assert np.allclose(axis, [0, math.cos(math.radians(30)), 0.5], atol=1e-12)  # east and 30 deg down


def test_gimbal_composes_after_the_mount():
    mount = fr.CameraMount(gimballed=True)
    q_gimbal = fr.quat_from_euler(0, 0, math.pi / 2)  # gimbal panned right by 90 deg
    _, q_nc = fr.camera_pose_ned([0, 0, 0], [1, 0, 0, 0], mount, q_gimbal)
    assert np.allclose(fr.quat_rotate(q_nc, [0, 0, 1]), [0, 1, 0], atol=ATOL_ROT)


def test_vue_pro_640_intrinsics():
    K = fr.PinholeIntrinsics.vue_pro_640()
    assert K.fx_px == pytest.approx(764.70588, abs=1e-4) and K.fy_px == K.fx_px
    assert (K.cx_px, K.cy_px, K.width_px, K.height_px) == (320.0, 256.0, 640, 512)
    assert math.degrees(2 * math.atan(320 / K.fx_px)) == pytest.approx(45.4, abs=0.05)
    assert math.degrees(2 * math.atan(256 / K.fx_px)) == pytest.approx(37.0, abs=0.05)


@given(st.floats(-300, 300, **finite), st.floats(-250, 250, **finite))
@settings(max_examples=200, deadline=None)
def test_project_and_bearing_round_trip_with_distortion(du, dv):
    K = fr.PinholeIntrinsics(764.7, 760.0, 321.0, 255.0, 640, 512, (-0.12, 0.03, 0.001, -0.0005, 0.0))
    uv = np.array([K.cx_px + du, K.cy_px + dv])
    b = K.bearing_cam_from_pixel(uv)
    assert np.linalg.norm(b) == pytest.approx(1.0, abs=1e-12)
    assert np.allclose(K.project(b * 37.0), uv, atol=1e-6)


@given(
    fx=st.floats(250.0, 2000.0, **finite),
    k1=st.floats(-0.6, 0.6, **finite),
    k2=st.floats(-0.4, 0.4, **finite),
    p=st.tuples(st.floats(-0.02, 0.02, **finite), st.floats(-0.02, 0.02, **finite)),
    k3=st.floats(-0.2, 0.2, **finite),
    uv=st.tuples(st.floats(0.0, 640.0, **finite), st.floats(0.0, 512.0, **finite)),
)
@settings(max_examples=300, deadline=None)
def test_every_pixel_of_a_lens_the_check_passes_undistorts(fx, k1, k2, p, k3, uv):
    """Wide and narrow lenses, barrel and pincushion: where the check finds no fault, any pixel of the image
    goes to a bearing that projects back onto it; where it finds one, some pixel really is off."""
    K = fr.PinholeIntrinsics(fx, fx, 320.0, 256.0, 640, 512, (k1, k2, p[0], p[1], k3))
    failure = K.undistortion_failure()
    if failure is None:
        b = K.bearing_cam_from_pixel(np.array(uv))
        assert np.allclose(K.project(b * 37.0), uv, atol=1e-6)
    else:
        pixels = [np.array([float(v) for v in part.split(")")[0].split(", ")]) for part in failure.split("pixel (")[1:]]
        with np.errstate(over="ignore", invalid="ignore"):
            if "does not undistort" in failure:
                back = K.project(K.bearing_cam_from_pixel(pixels[0]))
                assert not np.allclose(back, pixels[0], atol=fr.UNDISTORT_TOLERANCE_PX / 2), failure
            else:  # a fold: along the ray, sampled 16 times as finely, an ideal point goes back towards the centre
                centre = np.array([K.cx_px, K.cy_px])
                ray = centre + np.linspace(0.0, 1.0, 16 * fr.RAY_STEPS + 1)[1:, None] * (pixels[0] - centre)
                r = np.hypot(*K.normalized_from_pixel(ray).T)
                assert "folds" in failure and not np.all(np.diff(r) > 0.0), failure


def test_a_lens_that_fails_only_beside_a_corner_is_refused():
    """Found by the property above: strong barrel with a tangential term, where the undistortion finds the wrong
    ideal point for a few pixels along the border next to the (0, 0) corner (pixel (0, 1) came back 19 px away),
    while every pixel on the rays through the corners and edge midpoints held."""
    K = fr.PinholeIntrinsics(795.5, 795.5, 320.0, 256.0, 640, 512, (-0.544921875, 0.0, 0.01953125, 0.0, 0.0625))
    failure = K.undistortion_failure()
    assert failure is not None and "does not undistort" in failure
    pixel = np.array([float(v) for v in failure.split("pixel (")[1].split(")")[0].split(", ")])
    assert np.hypot(*(K.project(K.bearing_cam_from_pixel(pixel)) - pixel)) > 1.0


def test_a_wide_thermal_lens_undistorts_to_its_corners():
    """fx 300 px on 640 x 512 (94 deg across) with a strong barrel: twenty of OpenCV's fixed-point steps leave the
    corner 6 px off; Newton's put the corner pixel's bearing back onto it."""
    K = fr.PinholeIntrinsics(300.0, 300.0, 320.0, 256.0, 640, 512, (-0.3, 0.05, 0.0, 0.0, 0.0))
    assert K.undistortion_failure() is None
    xy_d = np.array([-320.0, -256.0]) / 300.0
    xy = xy_d.copy()
    for _ in range(20):
        xy = xy + (xy_d - K.distort_normalized(xy))
    assert 300.0 * np.hypot(*(K.distort_normalized(xy) - xy_d)) > 1.0
    for uv in ([0.0, 0.0], [640.0, 512.0], [0.0, 256.0]):
        assert np.allclose(K.project(K.bearing_cam_from_pixel(np.array(uv))), uv, atol=1e-9)


# fx != fy, the principal point off the centre: a swapped focal length or centre shows
NON_SQUARE = fr.PinholeIntrinsics(800.0, 790.0, 161.5, 128.0, 320, 256)


@given(st.floats(-0.3, 0.3, **finite), st.floats(-0.3, 0.3, **finite))
@settings(max_examples=100, deadline=None)
def test_a_non_square_pixels_bearing_is_its_normalised_coordinates(x, y):
    """Pixel (cx + fx x, cy + fy y) looks along (x, y, 1): both the array path and the float path."""
    K = NON_SQUARE
    uv = (K.cx_px + K.fx_px * x, K.cy_px + K.fy_px * y)
    expected = np.array([x, y, 1.0]) / math.sqrt(x * x + y * y + 1.0)
    np.testing.assert_allclose(K.bearing_cam_from_pixel(uv), expected, atol=ATOL_ROT)
    np.testing.assert_allclose(np.array(K.bearing_cam_from_uv(*uv)), expected, atol=ATOL_ROT)
    np.testing.assert_allclose(K.normalized_from_pixel(uv), [x, y], atol=ATOL_ROT)
    np.testing.assert_allclose(K.project(expected * 25.0), uv, atol=ATOL_PX)


@given(
    st.floats(-0.2, 0.2, **finite),
    st.floats(-0.16, 0.16, **finite),
    st.floats(1.0, 1e4, **finite),
)
@settings(max_examples=100, deadline=None)
def test_projection_with_every_distortion_term_matches_opencv(x, y, z_m):
    """``project`` against ``cv2.projectPoints`` (an independent implementation of the same Brown-Conrady model),
    k1, k2, p1, p2, k3 all non-zero and fx != fy.  Pixel conventions: ours puts a pixel's centre at +0.5 (the
    top-left pixel's centre is (0.5, 0.5)), OpenCV's on integers (0, 0); the same camera in OpenCV has
    cx - 0.5, cy - 0.5 and gives u - 0.5, v - 0.5."""
    import cv2

    dist = (-0.21, 0.06, 0.0021, -0.0032, -0.011)
    K = fr.PinholeIntrinsics(800.0, 790.0, 161.5, 128.0, 320, 256, dist)
    p = np.array([x * z_m, y * z_m, z_m])
    K_cv = np.array([[K.fx_px, 0.0, K.cx_px - 0.5], [0.0, K.fy_px, K.cy_px - 0.5], [0.0, 0.0, 1.0]])
    uv_cv, _ = cv2.projectPoints(p.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K_cv, np.array(dist))
    np.testing.assert_allclose(K.project(p) - 0.5, uv_cv.reshape(2), atol=ATOL_OPENCV_PX)


def test_project_signs_and_behind_camera():
    K = fr.PinholeIntrinsics.vue_pro_640()
    u, v = K.project([1.0, 2.0, 100.0])
    assert u > K.cx_px and v > K.cy_px  # right and down of the centre
    assert u == pytest.approx(320 + K.fx_px * 0.01, abs=ATOL_PX)
    assert np.all(np.isnan(K.project([0.0, 0.0, -5.0])))


def test_intrinsics_validation_names_the_field():
    with pytest.raises(fr.FrameError, match="fx_px"):
        fr.PinholeIntrinsics(math.inf, 1.0, 0.0, 0.0, 10, 10)
    with pytest.raises(fr.FrameError, match="distortion"):
        fr.PinholeIntrinsics(1.0, 1.0, 0.0, 0.0, 10, 10, (0.0, 0.0))
