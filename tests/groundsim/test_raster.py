"""The IR rasteriser (groundsim.world.render.raster): geometry and sign conventions, sub-pixel centroid
accuracy, radiometry of sky/ground/target, sensor noise, determinism and input validation.

Centroid tests: ``truth_pixel`` (the projection of the target body centre) against an intensity-
weighted, background-subtracted centroid over the blob.  The background is the same renderer's
frame without the target (identical pixels when NETD is off).  Geometric accuracy is tested with
noise off: 40 mK is 0.16 grey in mono8, below the quantisation step, and its effect on a centroid
is a zero-mean random error, not a property of the rasteriser.  One test keeps noise on in mono8
and thresholds the difference at 2 grey levels (the quantisation flicker of a noisy background).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundsim.world.render import IrRenderer, IrSettings, PartRaster, TargetPart, truth_pixel
from groundsim.world.render.planck import band_radiance, grey_float_from_radiance, noise_sigma_grey
from groundsim.world.render.raster import BOX_FRACTION
from onboard.core.errors import InputError
from onboard.core.frames import CameraMount, PinholeIntrinsics, camera_pose_ned, quat_from_euler, rotmat_from_quat

CENTROID_TOL_PX = 0.25  # the requirement, default (asymmetric) target
SYMMETRIC_CENTROID_TOL_PX = 0.08  # a point-symmetric target: anti-aliasing within the ray budget (measured <= 0.05)
TRUTH_ATOL_PX = 1e-9
SKY_GROUND_ATOL_GREY16 = 2.0  # table look-up + smoothing + rounding, of 65535
HORIZON_ATOL_PX = 0.25
FLUX_RTOL = 0.01  # integrated target signal vs the analytic silhouette area x contrast
NOISE_RTOL = 0.05  # sample std over ~30k pixels
COARSE_BG_ATOL_GREY8 = 0.05  # coarse-grid background vs per-pixel look-up
WINDOW_PX = 12  # half size of the centroid window around the truth pixel
CAMERA_P_NED_M = np.array([10.0, 5.0, -80.0])

INTR = PinholeIntrinsics.vue_pro_640()
SYMMETRIC_PARTS = (
    TargetPart("disc", "ellipsoid", (0.0, 0.0, 0.0), (0.2, 0.2, 0.05), 310.0, 0.9),
    TargetPart("bar", "box", (0.0, 0.0, 0.0), (0.2, 0.02, 0.02), 320.0, 0.9),
)


def R_cam(roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0) -> np.ndarray:
    """R_ned_from_cam of a camera looking along the body x axis of a vehicle at these Euler angles."""
    q_body = quat_from_euler(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
    _, q_cam = camera_pose_ned(np.zeros(3), q_body, CameraMount())
    return rotmat_from_quat(q_cam)


def target_at(intr, p_cam, R, u_px, v_px, range_m) -> np.ndarray:
    """The NED point at ``range_m`` along the ray of pixel (u, v)."""
    b = intr.bearing_cam_from_pixel(np.array([u_px, v_px]))
    return p_cam + R @ b * range_m


def blob_centroid(img, bg, uv, threshold=None) -> tuple[float, float, float]:
    """Intensity-weighted centroid of (img - bg) in a window around uv; returns (u, v, peak)."""
    u, v = uv
    i0, j0 = int(v) - WINDOW_PX, int(u) - WINDOW_PX
    d = img[i0 : i0 + 2 * WINDOW_PX + 1, j0 : j0 + 2 * WINDOW_PX + 1].astype(float) - bg[
        i0 : i0 + 2 * WINDOW_PX + 1, j0 : j0 + 2 * WINDOW_PX + 1
    ].astype(float)
    w = d if threshold is None else np.where(d >= threshold, d, 0.0)
    ii, jj = np.mgrid[i0 : i0 + d.shape[0], j0 : j0 + d.shape[1]]
    s = w.sum()
    assert s > 0, "target not rendered"
    return float((w * (jj + 0.5)).sum() / s), float((w * (ii + 0.5)).sum() / s), float(d.max())


@pytest.fixture(scope="module")
def r16_default():
    return IrRenderer(INTR, IrSettings(netd_k=0.0, encoding="mono16"), seed=3)


@pytest.fixture(scope="module")
def r16_symmetric():
    return IrRenderer(INTR, IrSettings(netd_k=0.0, encoding="mono16", target_parts=SYMMETRIC_PARTS), seed=3)


@pytest.fixture(scope="module")
def r8_noisy():
    return IrRenderer(INTR, IrSettings(), seed=3)


# ---------------------------------------------------------------------------- truth pixel, signs


def test_truth_pixel_sign_conventions():
    R = R_cam()  # level, looking north
    p = np.zeros(3)
    assert truth_pixel(INTR, p, R, [100.0, 0.0, 0.0]) == pytest.approx((320.0, 256.0), abs=TRUTH_ATOL_PX)
    u, v = truth_pixel(INTR, p, R, [100.0, 10.0, 0.0])  # east = right
    assert u == pytest.approx(320.0 + INTR.fx_px * 0.1, abs=TRUTH_ATOL_PX) and v == pytest.approx(256.0)
    u, v = truth_pixel(INTR, p, R, [100.0, 0.0, -10.0])  # up = smaller v
    assert v == pytest.approx(256.0 - INTR.fy_px * 0.1, abs=TRUTH_ATOL_PX) and u == pytest.approx(320.0)
    assert all(math.isnan(c) for c in truth_pixel(INTR, p, R, [-100.0, 0.0, 0.0]))


def test_target_is_drawn_where_truth_pixel_says(r16_default):
    R = R_cam(pitch_deg=5.0)
    p_t = CAMERA_P_NED_M + np.array([100.0, 30.0, -20.0])  # ahead, right, up
    uv = truth_pixel(INTR, CAMERA_P_NED_M, R, p_t)
    assert uv[0] > 320 and uv[1] < 256
    img = r16_default.render(CAMERA_P_NED_M, R, p_t, np.eye(3))
    box = r16_default.last_target_box_px
    bg = r16_default.render(CAMERA_P_NED_M, R, None, None)
    assert r16_default.last_target_box_px is None
    diff = img.astype(float) - bg
    i, j = np.unravel_index(np.argmax(diff), diff.shape)
    assert abs(j + 0.5 - uv[0]) <= 1.5 and abs(i + 0.5 - uv[1]) <= 1.5
    assert diff[i, j] > 1000  # a hot target on a cold sky is bright
    nonzero = np.argwhere(diff != 0)
    assert np.all(np.abs(nonzero[:, 1] + 0.5 - uv[0]) < 10) and np.all(np.abs(nonzero[:, 0] + 0.5 - uv[1]) < 10)

    # the truth's box (x0, y0, x1, y1; ends exclusive): the pixels holding BOX_FRACTION of the peak, read off
    # the integer frames (a pixel within 0.2 % of the threshold, 1.5 grey, may fall either side of it after rounding)
    def extent(fraction):
        ii, jj = np.nonzero(diff >= fraction * diff.max())
        return jj.min(), ii.min(), jj.max() + 1, ii.max() + 1

    inner, outer = extent(1.002 * BOX_FRACTION), extent(0.998 * BOX_FRACTION)
    assert box is not None and outer[0] <= box[0] <= inner[0] and outer[1] <= box[1] <= inner[1]
    assert inner[2] <= box[2] <= outer[2] and inner[3] <= box[3] <= outer[3], (box, inner, outer)


# ---------------------------------------------------------------------------- centroid accuracy

offsets = st.floats(-0.5, 0.5)


def _centroid_error(renderer, cam_pitch_deg, du, dv, range_m, rpy, threshold=None) -> tuple[float, float]:
    """(px, peak): how far the rendered target's centroid is from its truth pixel, the target ``range_m`` away at
    (320 + du, 256 + dv) in a camera pitched ``cam_pitch_deg`` (yaw 17 deg), its body at roll, pitch, yaw ``rpy``."""
    R = R_cam(pitch_deg=cam_pitch_deg, yaw_deg=17.0)
    p_t = target_at(INTR, CAMERA_P_NED_M, R, 320.0 + du, 256.0 + dv, range_m)
    img = renderer.render(CAMERA_P_NED_M, R, p_t, rotmat_from_quat(quat_from_euler(*rpy)))
    bg = renderer.render(CAMERA_P_NED_M, R, None, None)
    uv = truth_pixel(INTR, CAMERA_P_NED_M, R, p_t)
    cu, cv, peak = blob_centroid(img, bg, uv, threshold=threshold)
    return math.hypot(cu - uv[0], cv - uv[1]), peak


angles = st.floats(-0.4, 0.4)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(du=offsets, dv=offsets, range_m=st.floats(50.0, 300.0), roll=angles, pitch=angles, yaw=st.floats(-3.1, 3.1))
@pytest.mark.parametrize("cam_pitch_deg", [10.0, -20.0])  # target on sky, target on ground
def test_centroid_symmetric_target(r16_symmetric, cam_pitch_deg, du, dv, range_m, roll, pitch, yaw):
    err_px, _ = _centroid_error(r16_symmetric, cam_pitch_deg, du, dv, range_m, (roll, pitch, yaw))
    assert err_px < SYMMETRIC_CENTROID_TOL_PX


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(du=offsets, dv=offsets, roll=angles, pitch=angles, yaw=st.floats(-3.1, 3.1))
@pytest.mark.parametrize("range_m", [50.0, 100.0, 200.0, 300.0])
@pytest.mark.parametrize("cam_pitch_deg", [10.0, -20.0])
def test_centroid_default_target(r16_default, cam_pitch_deg, range_m, du, dv, roll, pitch, yaw):
    """The default quad-rotor (battery and motors above the centre, hotter motors): its radiance
    centroid is within 0.2 px of the body centre at 50 m, closer beyond."""
    err_px, _ = _centroid_error(r16_default, cam_pitch_deg, du, dv, range_m, (roll, pitch, yaw))
    assert err_px < CENTROID_TOL_PX


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(du=offsets, dv=offsets, roll=angles, pitch=angles, yaw=st.floats(-3.1, 3.1))
@pytest.mark.parametrize("range_m", [50.0, 100.0, 150.0])
def test_centroid_mono8_with_noise(r8_noisy, range_m, du, dv, roll, pitch, yaw):
    """mono8, NETD on.  Beyond ~150 m the default target peaks at < 10 grey levels over the sky and
    8-bit quantisation, not the rasteriser, limits the centroid (the mono16 test covers 300 m)."""
    err_px, peak = _centroid_error(r8_noisy, 10.0, du, dv, range_m, (roll, pitch, yaw), threshold=2.0)
    assert peak >= 4  # visible: measured >= 7 grey levels out to 150 m
    assert err_px < CENTROID_TOL_PX


def test_centroid_with_lens_distortion():
    intr = replace(INTR, distortion=(-0.12, 0.03, 0.0005, -0.0003, 0.0))
    r = IrRenderer(intr, IrSettings(netd_k=0.0, encoding="mono16", target_parts=SYMMETRIC_PARTS), seed=0)
    R = R_cam(pitch_deg=8.0)
    for u, v in ((520.3, 420.7), (80.6, 60.2), (330.1, 250.9)):
        p_t = target_at(intr, CAMERA_P_NED_M, R, u, v, 120.0)
        uv = truth_pixel(intr, CAMERA_P_NED_M, R, p_t)
        assert uv == pytest.approx((u, v), abs=1e-6)  # bearing_cam_from_pixel and project agree
        cu, cv, _ = blob_centroid(
            r.render(CAMERA_P_NED_M, R, p_t, np.eye(3)), r.render(CAMERA_P_NED_M, R, None, None), uv
        )
        assert math.hypot(cu - u, cv - v) < SYMMETRIC_CENTROID_TOL_PX


# ---------------------------------------------------------------------------- radiometry


def _grey16(settings, L):
    return float(grey_float_from_radiance(L, settings))


def test_sky_grey_value_at_known_elevation(r16_default):
    s = r16_default.settings
    img = r16_default.render(CAMERA_P_NED_M, R_cam(pitch_deg=30.0), None, None)
    # the centre pixel (319.5..320.5) looks 30 deg up, +-0.04 deg: sin(el) = 0.5
    T_sky = s.sky_horizon_k + (s.sky_zenith_k - s.sky_horizon_k) * 0.5
    expected = _grey16(s, band_radiance(T_sky, s.band_um))
    assert float(img[255:257, 319:321].mean()) == pytest.approx(expected, abs=SKY_GROUND_ATOL_GREY16 + 0.5 * 0.9)


def test_ground_grey_value_through_the_atmosphere():
    s = IrSettings(netd_k=0.0, encoding="mono16", extinction_per_km=2.0)  # a hazy day: tau matters
    r = IrRenderer(INTR, s)
    height_m = 100.0
    img = r.render([0.0, 0.0, -height_m], R_cam(pitch_deg=-30.0), None, None, altitude_ground_d_m=0.0)
    range_km = height_m / math.sin(math.radians(30.0)) / 1000.0
    tau = math.exp(-s.extinction_per_km * range_km)
    L_sky_mirror = band_radiance(s.sky_horizon_k + (s.sky_zenith_k - s.sky_horizon_k) * 0.5, s.band_um)
    L = tau * (
        s.ground_emissivity * band_radiance(s.ground_temperature_k, s.band_um)
        + (1 - s.ground_emissivity) * L_sky_mirror
    ) + (1 - tau) * band_radiance(s.air_temperature_k, s.band_um)
    # the 2 x 2 centre pixels straddle 30 deg by +-0.04 deg: the ground changes by < 1 level there
    assert float(img[255:257, 319:321].mean()) == pytest.approx(_grey16(s, L), abs=SKY_GROUND_ATOL_GREY16 + 1.0)
    # and the ground level shifts the scene: a camera 10x higher sees more air, nearer L(T_air)
    img_hi = r.render([0.0, 0.0, -10 * height_m], R_cam(pitch_deg=-30.0), None, None)
    L_air = _grey16(s, band_radiance(s.air_temperature_k, s.band_um))
    assert abs(float(img_hi[256, 320]) - L_air) < abs(float(img[256, 320]) - L_air)


@pytest.fixture(scope="module")
def r16_flat():
    """Uniform 260 K sky over 300 K ground in vacuum: a pure (smoothed) step at the horizon."""
    s = IrSettings(
        netd_k=0.0,
        encoding="mono16",
        sky_zenith_k=260.0,
        sky_horizon_k=260.0,
        ground_temperature_k=300.0,
        extinction_per_km=0.0,
    )
    return IrRenderer(INTR, s)


def _horizon_crossing(col: np.ndarray, k: int, half: int) -> float:
    """Where the column's sky-to-ground step crosses the mid level of rows k - half and k + half: linearly
    interpolated between the pixel centres of rows k - half + 1 .. k + half - 1."""
    mid = 0.5 * (col[k - half] + col[k + half])
    rows = np.arange(k - half + 1, k + half)
    vals = col[k - half + 1 : k + half]
    n = int(np.flatnonzero(np.diff(np.sign(vals - mid)))[0])
    return rows[n] + 0.5 + (mid - vals[n]) / (vals[n + 1] - vals[n])


@pytest.mark.parametrize("pitch_deg", [-10.0, 0.0, 3.3, 12.0])
def test_horizon_row_follows_camera_pitch(r16_flat, pitch_deg):
    img = r16_flat.render(CAMERA_P_NED_M, R_cam(pitch_deg=pitch_deg), None, None).astype(float)
    v_expected = INTR.cy_px + INTR.fy_px * math.tan(math.radians(pitch_deg))  # pitch up: horizon lower
    col = img[:, 100]
    k = int(v_expected)
    assert _horizon_crossing(col, k, 6) == pytest.approx(v_expected, abs=HORIZON_ATOL_PX)
    assert col[k + 6] > col[k - 6] + 10000  # warm ground below the cold sky


def test_horizon_tilts_with_roll(r16_flat):
    # roll right (right wing down): the right of the image looks lower, the horizon there is higher
    img = r16_flat.render(CAMERA_P_NED_M, R_cam(roll_deg=10.0), None, None).astype(float)
    u = np.array([120.5, 520.5])
    v_expected = INTR.cy_px - (u - INTR.cx_px) * math.tan(math.radians(10.0))
    for j, ve in zip(u.astype(int), v_expected):
        v_cross = _horizon_crossing(img[:, j], int(ve), 8)
        assert v_cross == pytest.approx(ve, abs=2 * HORIZON_ATOL_PX)  # the pixel box of a slanted edge
    assert v_expected[1] < v_expected[0]


def test_background_does_not_depend_on_yaw():
    s = IrSettings(encoding="mono16")
    a = IrRenderer(INTR, s, seed=5).render(CAMERA_P_NED_M, R_cam(4.0, 7.0, 0.0), None, None)
    b = IrRenderer(INTR, s, seed=5).render(CAMERA_P_NED_M, R_cam(4.0, 7.0, 123.0), None, None)
    np.testing.assert_array_equal(a, b)


def test_coarse_background_matches_per_pixel_lookup():
    r = IrRenderer(INTR, IrSettings(), seed=0)
    rng = np.random.default_rng(11)
    worst = 0.0
    for k in range(30):
        height_m = float(rng.choice([0.5, 5.0, 100.0, 3000.0]))
        spread = 1.5 if k % 2 else 0.3
        R = R_cam(*np.degrees(rng.uniform(-spread, spread, 2)), float(rng.uniform(-180, 180)))
        r.render([0.0, 0.0, -height_m], R, None, None)  # builds the table for this height
        worst = max(worst, float(np.max(np.abs(r._background_coarse(R[2]) - r._background_exact(R[2])))))
    assert worst < COARSE_BG_ATOL_GREY8


@pytest.mark.parametrize("range_m", [60.0, 240.0])
def test_target_flux_and_atmospheric_transmission(range_m):
    """Sum of (target - background) over the image = silhouette area (px^2) x (target - sky) grey.
    A black sphere in front of the sky, seen through the atmosphere (tau = exp(-k r))."""
    rho_m = 0.3
    s = IrSettings(
        netd_k=0.0,
        encoding="mono16",
        extinction_per_km=1.0,
        target_parts=(TargetPart("ball", "ellipsoid", (0.0, 0.0, 0.0), (rho_m,) * 3, 318.0, 1.0),),
    )
    r = IrRenderer(INTR, s)
    R = R_cam(pitch_deg=30.0)
    p_t = CAMERA_P_NED_M + R[:, 2] * range_m  # on the optical axis: sin(elevation) = 0.5
    img = r.render(CAMERA_P_NED_M, R, p_t, np.eye(3)).astype(float)
    bg = r.render(CAMERA_P_NED_M, R, None, None).astype(float)
    flux = float((img - bg).sum())
    tan_half = rho_m / math.sqrt(range_m**2 - rho_m**2)  # tangent cone of the sphere
    area_px2 = math.pi * (INTR.fx_px * tan_half) * (INTR.fy_px * tan_half)
    tau = math.exp(-s.extinction_per_km * range_m / 1000.0)
    L_t = tau * band_radiance(318.0, s.band_um) + (1 - tau) * band_radiance(s.air_temperature_k, s.band_um)
    L_bg = band_radiance(s.sky_horizon_k + (s.sky_zenith_k - s.sky_horizon_k) * 0.5, s.band_um)
    expected = area_px2 * (_grey16(s, L_t) - _grey16(s, L_bg))
    assert flux == pytest.approx(expected, rel=FLUX_RTOL)


# ---------------------------------------------------------------------------- sensor noise, determinism


def test_noise_level_and_independence_between_frames():
    s = IrSettings(encoding="mono16", sky_zenith_k=270.0, sky_horizon_k=270.0)  # uniform, inside the grey range
    r = IrRenderer(INTR, s, seed=9)
    R = R_cam(pitch_deg=40.0)
    f1 = r.render(CAMERA_P_NED_M, R, None, None).astype(float)[200:312, 200:440]
    f2 = r.render(CAMERA_P_NED_M, R, None, None).astype(float)[200:312, 200:440]
    sigma = noise_sigma_grey(s)
    assert 30.0 < sigma < 50.0
    assert float(np.std(f1 - f2)) / math.sqrt(2) == pytest.approx(sigma, rel=NOISE_RTOL)
    assert abs(float(np.corrcoef((f1 - f1.mean()).ravel(), (f2 - f2.mean()).ravel())[0, 1])) < 0.03
    clean = (
        IrRenderer(INTR, replace(s, netd_k=0.0)).render(CAMERA_P_NED_M, R, None, None).astype(float)[200:312, 200:440]
    )
    assert abs(float((f1 - clean).mean())) < 1.0  # zero-mean


def test_same_seed_same_frames_and_other_seed_other_noise():
    def sequence(seed):
        r = IrRenderer(INTR, IrSettings(), seed=seed)
        out = []
        for k in range(3):
            R = R_cam(pitch_deg=5.0 + k)
            p_t = target_at(INTR, CAMERA_P_NED_M, R, 300.0 + 10 * k, 240.0, 90.0)
            out.append(r.render(CAMERA_P_NED_M, R, p_t, np.eye(3)))
        return out

    a, b, c = sequence(1), sequence(1), sequence(2)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert any(np.any(x != z) for x, z in zip(a, c))
    assert np.any(a[0] != a[1])


def test_no_noise_frames_repeat_exactly():
    r = IrRenderer(INTR, IrSettings(netd_k=0.0), seed=0)
    R = R_cam(pitch_deg=2.0)
    p_t = target_at(INTR, CAMERA_P_NED_M, R, 200.0, 200.0, 80.0)
    np.testing.assert_array_equal(
        r.render(CAMERA_P_NED_M, R, p_t, np.eye(3)), r.render(CAMERA_P_NED_M, R, p_t, np.eye(3))
    )


GREY_STRIP_PX = 64  # one row of pixels, one temperature each


@functools.cache
def _strip_renderer(encoding: str) -> IrRenderer:
    """A noiseless renderer one row of GREY_STRIP_PX pixels high (the grey map alone: no noise to reorder it)."""
    intr = PinholeIntrinsics(400.0, 400.0, GREY_STRIP_PX / 2, 0.5, GREY_STRIP_PX, 1)
    return IrRenderer(intr, IrSettings(netd_k=0.0, encoding=encoding))


@settings(max_examples=60, deadline=None)
@given(
    encoding=st.sampled_from(("mono8", "mono16")),
    temps_k=st.lists(st.floats(150.0, 450.0), min_size=GREY_STRIP_PX, max_size=GREY_STRIP_PX),
)
def test_fixed_span_grey_map_is_monotonic_and_saturates_within_the_encoding(encoding, temps_k):
    # the camera without a sensor section (C2's): a fixed linear span t_min_k .. t_max_k in radiance onto
    # 0 .. full scale, no AGC.  Warmer is never darker, and a scene outside the span saturates at 0 or
    # full scale instead of wrapping round (a uint cast of an out-of-range float would wrap).
    r = _strip_renderer(encoding)
    s = r.settings
    full_scale = 255 if encoding == "mono8" else 65535
    T_k = np.sort(np.asarray(temps_k))
    L = band_radiance(T_k, s.band_um).astype(np.float32)[None, :]
    grey = r.quantise(L)[0].astype(np.int64)
    assert r.quantise(L).dtype == (np.uint8 if encoding == "mono8" else np.uint16)
    assert np.all(np.diff(grey) >= 0)
    assert grey.min() >= 0 and grey.max() <= full_scale
    want = np.clip(np.rint(grey_float_from_radiance(L[0], s)), 0, full_scale)
    assert np.all(np.abs(grey - want) <= 1)  # float32 arithmetic vs float64 at a rounding tie
    assert np.all(grey[T_k <= s.t_min_k - 1.0] == 0)
    assert np.all(grey[T_k >= s.t_max_k + 1.0] == full_scale)


@pytest.mark.parametrize("encoding, dtype", [("mono8", np.uint8), ("mono16", np.uint16)])
def test_output_type_and_shape(encoding, dtype):
    intr = PinholeIntrinsics(400.0, 410.0, 150.3, 110.8, 322, 241)  # odd size, off-centre
    r = IrRenderer(intr, IrSettings(encoding=encoding))
    R = R_cam(pitch_deg=1.0)
    p_t = target_at(intr, CAMERA_P_NED_M, R, 300.0, 230.0, 40.0)  # near the bottom-right corner
    img = r.render(CAMERA_P_NED_M, R, p_t, np.eye(3))
    assert img.dtype == dtype and img.shape == (241, 322)
    bg = r.render(CAMERA_P_NED_M, R, None, None)
    assert np.any(img[220:, 280:] != bg[220:, 280:])
    v_h = intr.cy_px + intr.fy_px * math.tan(math.radians(1.0))
    assert float(img[int(v_h) + 8, 20]) > float(img[int(v_h) - 8, 20])  # horizon there


def test_timing_report_and_background_reuse():
    r = IrRenderer(INTR, IrSettings(), seed=0)
    R = R_cam(pitch_deg=3.0)
    p_t = target_at(INTR, CAMERA_P_NED_M, R, 320.0, 200.0, 100.0)
    r.render(CAMERA_P_NED_M, R, p_t, np.eye(3))
    t = r.last_timing
    assert not t.background_reused and t.table_rebuilt and t.target_roi_px > 0 and t.supersample == 16
    r.render(CAMERA_P_NED_M + [5.0, 0.0, 0.0], R_cam(pitch_deg=3.0, yaw_deg=40.0), p_t, np.eye(3))
    assert r.last_timing.background_reused and not r.last_timing.table_rebuilt
    r.render(CAMERA_P_NED_M + [0.0, 0.0, -50.0], R, p_t, np.eye(3))
    assert r.last_timing.table_rebuilt and not r.last_timing.background_reused
    assert r.last_timing.total_ms >= r.last_timing.background_ms


@pytest.mark.parametrize("tilt_over_tol, reused", [(0.5, True), (2.0, False)])
def test_background_is_reused_only_within_its_tilt_tolerance(tilt_over_tol, reused):
    """A pitch change moves the third row of R_ned_from_cam by about the angle: the background is reused within
    ``background_reuse_tol_rad`` of the one it was made for, and made afresh beyond it (as a new renderer's)."""
    s = IrSettings(netd_k=0.0, encoding="mono16")
    r = IrRenderer(INTR, s, seed=0)
    r.render(CAMERA_P_NED_M, R_cam(pitch_deg=3.0), None, None)
    R = R_cam(pitch_deg=3.0 + math.degrees(tilt_over_tol * s.background_reuse_tol_rad))
    img = r.render(CAMERA_P_NED_M, R, None, None)
    assert r.last_timing.background_reused == reused and not r.last_timing.table_rebuilt
    if not reused:
        np.testing.assert_array_equal(img, IrRenderer(INTR, s, seed=0).render(CAMERA_P_NED_M, R, None, None))


# ---------------------------------------------------------------------------- edge cases, validation


def test_target_out_of_view_leaves_background(r16_default):
    R = R_cam()
    bg = r16_default.render(CAMERA_P_NED_M, R, None, None)
    for p_t in (CAMERA_P_NED_M + [-50.0, 0.0, 0.0], CAMERA_P_NED_M + [50.0, 200.0, 0.0]):  # behind, far right
        np.testing.assert_array_equal(r16_default.render(CAMERA_P_NED_M, R, p_t, np.eye(3)), bg)
        assert r16_default.last_timing.target_roi_px == 0


def test_target_cut_by_the_image_edge(r16_default):
    R = R_cam(pitch_deg=4.0)
    p_t = target_at(INTR, CAMERA_P_NED_M, R, -1.0, 100.0, 30.0)  # centre just left of the image
    img = r16_default.render(CAMERA_P_NED_M, R, p_t, np.eye(3))
    bg = r16_default.render(CAMERA_P_NED_M, R, None, None)
    changed = np.argwhere(img != bg)
    assert changed.size and changed[:, 1].min() == 0 and changed[:, 1].max() < 12


@pytest.mark.timeout(20)
@pytest.mark.parametrize("range_m", [0.0, 0.1, 1.0])
def test_camera_inside_or_very_near_the_target(range_m):
    r = IrRenderer(INTR, IrSettings(), seed=0)
    R = R_cam(pitch_deg=2.0)
    t0 = time.perf_counter()
    img = r.render(CAMERA_P_NED_M, R, CAMERA_P_NED_M + R[:, 2] * range_m, np.eye(3))
    assert time.perf_counter() - t0 < 10.0
    assert img.shape == (512, 640)
    assert r.last_timing.supersample >= 1
    if range_m >= 1.0:
        assert r.last_timing.supersample < 16  # the ray budget caps a target hundreds of px wide
        assert float(img[256, 320]) > 150  # the 305 K body fills the centre


def test_camera_below_ground_is_rendered_at_ground_level():
    r = IrRenderer(INTR, IrSettings(netd_k=0.0), seed=0)
    a = r.render([0.0, 0.0, 2.0], R_cam(pitch_deg=-20.0), None, None, altitude_ground_d_m=0.0)
    b = IrRenderer(INTR, IrSettings(netd_k=0.0), seed=0).render([0.0, 0.0, 0.0], R_cam(pitch_deg=-20.0), None, None)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(p_cam_ned_m=[0.0, np.nan, 0.0]), "p_cam_ned_m"),
        (dict(p_cam_ned_m=[0.0, 0.0]), "p_cam_ned_m"),
        (dict(R_ned_from_cam=np.eye(3) * 1.01), "R_ned_from_cam"),
        (dict(R_ned_from_cam=np.diag([1.0, 1.0, -1.0])), "R_ned_from_cam"),
        (dict(R_ned_from_cam=np.eye(2)), r"R_ned_from_cam: expected a finite 3x3 rotation matrix, got shape \(2, 2\)"),
        # not finite: said so (it had said "got shape (3, 3)")
        (
            dict(R_ned_from_cam=np.full((3, 3), np.nan)),
            r"R_ned_from_cam: expected a finite 3x3 rotation matrix, got 9 of 9 entries not finite",
        ),
        (dict(p_target_ned_m=[1.0, 2.0, "x"]), "p_target_ned_m"),
        (dict(R_ned_from_target_body=None), "R_ned_from_target_body"),
        (dict(R_ned_from_target_body=np.ones((3, 3))), "R_ned_from_target_body"),
        (dict(altitude_ground_d_m=float("inf")), "altitude_ground_d_m"),
        (dict(altitude_ground_d_m="low"), "altitude_ground_d_m"),
    ],
)
def test_bad_inputs_name_the_field(r16_default, kwargs, field):
    args = dict(
        p_cam_ned_m=CAMERA_P_NED_M,
        R_ned_from_cam=R_cam(),
        p_target_ned_m=CAMERA_P_NED_M + [50.0, 0.0, 0.0],
        R_ned_from_target_body=np.eye(3),
        altitude_ground_d_m=0.0,
    )
    args.update(kwargs)
    with pytest.raises(InputError, match=field):
        r16_default.render(**args)


def test_bad_constructor_arguments():
    with pytest.raises(InputError, match="intrinsics"):
        IrRenderer("vue", IrSettings())
    with pytest.raises(InputError, match="settings"):
        IrRenderer(INTR, {"netd_k": 0.04})
    with pytest.raises(InputError, match="seed"):
        IrRenderer(INTR, IrSettings(), seed=1.5)


BIRD_PARTS = (
    TargetPart("body", "ellipsoid", (0.0, 0.0, 0.0), (0.12, 0.035, 0.035), 300.0, 0.95),
    TargetPart("wings", "box", (0.01, 0.0, -0.01), (0.05, 0.3, 0.006), 296.0, 0.95),
)
DISC_PART = (TargetPart("disc", "ellipsoid", (0.0, 0.0, 0.0), (0.3, 0.3, 0.1), 300.0, 0.95),)


def _spot(raster, bg, p_t, R_t, R_c) -> tuple[float, float, float]:
    """Sum and intensity centroid (u, v) of a PartRaster's delta over a flat background."""
    rows, cols, delta, _ = raster.delta(bg, CAMERA_P_NED_M, R_c, p_t, R_t)
    ii, jj = np.mgrid[rows, cols]
    total = float(delta.sum())
    return total, float((delta * (jj + 0.5)).sum() / total), float((delta * (ii + 0.5)).sum() / total)


@pytest.mark.parametrize("parts", [DISC_PART, BIRD_PARTS])
@pytest.mark.parametrize("yaw_deg, pitch_deg", [(0.0, 0.0), (35.0, 20.0), (80.0, -50.0)])
@pytest.mark.parametrize("du, dv", [(0.0, 0.0), (0.3, -0.2), (0.5, 0.45)])
def test_small_object_splat_matches_the_ray_cast(parts, yaw_deg, pitch_deg, du, dv):
    """An object a few pixels across drawn as a splat keeps a fine ray cast's radiance integral within 2 %
    (the bird's body over its wings: the visible fractions along the view) and its intensity centroid.  The
    cast samples 256 x 256 rays a pixel (1 mm at 200 m): the 16 x 16 default is several % off on the bird's
    12 mm wings alone."""
    settings = IrSettings(netd_k=0.0, encoding="mono16", supersample=16)
    env = 0.5 * float(band_radiance(280.0, settings.band_um))
    fine = replace(settings, supersample=256, max_target_rays=10**6)
    cast = PartRaster(INTR, fine, parts, env, 0.0, 1.0)
    splat = PartRaster(INTR, settings, parts, env, 0.0, 1.0, splat_max_px=6)
    R_c = R_cam()
    p_t = target_at(INTR, CAMERA_P_NED_M, R_c, 320.0 + du, 256.0 + dv, 200.0)
    R_t = rotmat_from_quat(quat_from_euler(0.2, math.radians(pitch_deg), math.radians(yaw_deg)))
    bg = np.full((INTR.height_px, INTR.width_px), float(band_radiance(250.0, settings.band_um)), np.float32)
    assert splat.delta(bg, CAMERA_P_NED_M, R_c, p_t, R_t)[3] == 1  # drawn by the splat
    f_cast, u_cast, v_cast = _spot(cast, bg, p_t, R_t, R_c)
    f_splat, u_splat, v_splat = _spot(splat, bg, p_t, R_t, R_c)
    assert f_splat == pytest.approx(f_cast, rel=0.02)
    assert abs(u_splat - u_cast) < 0.1 and abs(v_splat - v_cast) < 0.1


def test_splat_is_left_to_the_ray_cast_for_a_near_object():
    settings = IrSettings(netd_k=0.0, encoding="mono16")
    splat = PartRaster(INTR, settings, BIRD_PARTS, 0.0, 0.0, 1.0, splat_max_px=6)
    R_c = R_cam()
    p_t = target_at(INTR, CAMERA_P_NED_M, R_c, 320.0, 256.0, 20.0)
    bg = np.zeros((INTR.height_px, INTR.width_px), np.float32)
    assert splat.delta(bg, CAMERA_P_NED_M, R_c, p_t, np.eye(3))[3] > 1


_NO_SPLAT_COMPILE_IN_FLIGHT = r"""
import numpy as np
from groundsim.world.render import splat_kernels as sk
from groundsim.world.scenario import load_scenario, reference_scenario_paths
from groundsim.world.sim import SimCore

dispatchers = (sk.splat_moments, sk.splat_spot, sk.visible_fractions)
core = SimCore(load_scenario(reference_scenario_paths()["P1"]), 0, 1.0, render=True)
core.frame(0)  # the renderer built: its target's raster warms the splat
before = [len(d.signatures) for d in dispatchers]
r = core.renderer()
R = np.eye(3)  # looking down NED: the target 3 km below, a fraction of a pixel across: the splat draws it
r.render(np.zeros(3), R, np.array([0.0, 0.0, 3000.0]), R, altitude_ground_d_m=5000.0)
scene_core = SimCore(load_scenario(reference_scenario_paths()["C3"]), 0, 1.0, render=True)
for k in range(0, 30, 3):  # a scene's objects (birds, a second aircraft) drawn on its float32 image
    scene_core.frame(k)
print([len(d.signatures) - b for d, b in zip(dispatchers, before)])
"""


def test_the_splat_is_compiled_before_the_flight_not_when_the_target_first_shrinks():
    """Compiled at first use, a new install's simulator stalled 4 s in real time 18.6 s into P1, when the target
    first became a few pixels across; a process of its own (another test's render would have compiled them)."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", _NO_SPLAT_COMPILE_IN_FLIGHT], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[0, 0, 0]", out.stdout
