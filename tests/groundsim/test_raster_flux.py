"""The target's radiance integral when it is unresolved (groundsim.world.render: the renderer's target raster).

A target a pixel or two across is an unresolved spot: what a tracker sees of it is its radiance integral
(the silhouette's area times its contrast, in px^2 x radiance) spread by the pixel and the optics.  That
integral must not depend on where the target lies within a pixel, and times the squared range it must not
depend on the range.  The reference here is an independent numpy silhouette: parallel rays along the view
on a fine grid turned away from the parts' edges, the nearest part per ray, its area converted to pixels by
the pinhole's solid angle (``A fx fy R / z^3``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundsim.world.render import IrRenderer, IrSettings, SceneBackground, TargetPart
from groundsim.world.render.planck import band_radiance
from groundsim.world.render.splat_kernels import visible_fractions
from onboard.core.frames import CameraMount, PinholeIntrinsics, camera_pose_ned, quat_from_euler, rotmat_from_quat

INTR = PinholeIntrinsics.vue_pro_640()
CAMERA_P_NED_M = np.array([10.0, 5.0, -80.0])
SPREAD_RTOL = 0.02  # each sub-pixel position's integral against their mean
FLUX_RTOL = 0.025  # the integral against the silhouette's (the visible fractions' sampling: <= 1.6 %)
CENTROID_TOL_PX = 0.05  # the drawn energy's centroid against the silhouette's
SILHOUETTE_GRID = 500  # rays per side of the reference silhouette's grid (1 mm cells on the quad-rotor)
SIDE_VIEW = (0.0, 6.0, 90.0)  # roll, pitch, yaw (deg): arms edge-on, lined up with the pixel rows
OBLIQUE = (17.0, -24.0, 131.0)


def R_cam(pitch_deg: float = 10.0, yaw_deg: float = 0.0) -> np.ndarray:
    """R_ned_from_cam of a level camera pitched up ``pitch_deg`` (the target in front of the sky)."""
    q_body = quat_from_euler(0.0, math.radians(pitch_deg), math.radians(yaw_deg))
    return rotmat_from_quat(camera_pose_ned(np.zeros(3), q_body, CameraMount())[1])


def R_body(rpy_deg) -> np.ndarray:
    return rotmat_from_quat(quat_from_euler(*(math.radians(a) for a in rpy_deg)))


def target_at(R_nc, u_px, v_px, range_m) -> np.ndarray:
    b = INTR.bearing_cam_from_pixel(np.array([u_px, v_px]))
    return CAMERA_P_NED_M + R_nc @ b * range_m


@pytest.fixture(scope="module")
def renderer():
    return IrRenderer(INTR, IrSettings(netd_k=0.0, encoding="mono16"), seed=0)


@pytest.fixture(scope="module")
def renderer_clear():
    return IrRenderer(INTR, IrSettings(netd_k=0.0, encoding="mono16", extinction_per_km=0.0), seed=0)


def drawn(renderer, R_nc, p_t, R_nt) -> tuple[float, float, float, int, float]:
    """``(integral, u, v, supersample, background)``: the target's radiance integral (W m^-2 sr^-1 px^2), the
    centroid of its drawn energy, how it was drawn (1: the splat) and the background radiance under it."""
    base = renderer.base_radiance(CAMERA_P_NED_M, R_nc)
    bg = SceneBackground(base, base, np.full(base.shape, 1e7, np.float32), np.zeros_like(base))
    _, (rows, cols, delta, ss) = renderer.render_radiance(CAMERA_P_NED_M, R_nc, p_t, R_nt, bg)
    d = delta.astype(np.float64)
    ii, jj = np.mgrid[rows, cols]
    total = float(d.sum())
    u, v = renderer.intrinsics.project(R_nc.T @ (p_t - CAMERA_P_NED_M))
    L_bg = float(base[int(v), int(u)])
    return total, float((d * (jj + 0.5)).sum() / total), float((d * (ii + 0.5)).sum() / total), ss, L_bg


def silhouette(parts, view_b: np.ndarray, n: int = SILHOUETTE_GRID) -> tuple[np.ndarray, np.ndarray]:
    """Per part, the area (m^2) of its silhouette in front of the other parts seen along ``view_b`` (body
    frame, camera to object), and its centroid in the body frame (on the plane through the origin across
    the view).  Parallel rays on an ``n`` x ``n`` grid whose rows run along no body axis (so no part's edge
    lines up with them), the nearest part per ray (slab test, scaled-sphere quadratic)."""
    d = view_b / np.linalg.norm(view_b)
    e1 = np.cross(d, np.array([0.31, 0.52, 0.79]))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    c = np.array([p.center_frd_m for p in parts])
    h = np.array([p.half_extent_m for p in parts])
    r = float(np.max(np.linalg.norm(np.abs(c) + h, axis=1)))
    g = (np.arange(n) + 0.5) / n * 2.0 * r - r
    o = (g[:, None, None] * e1 + g[None, :, None] * e2).reshape(-1, 3)  # ray origins, the plane through 0
    best = np.full(o.shape[0], np.inf)
    who = np.full(o.shape[0], -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, p in enumerate(parts):
            q = o - c[k]
            if p.shape == "box":
                t1, t2 = (-h[k] - q) / d, (h[k] - q) / d
                t_in, t_out = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
                t = np.where(t_in <= t_out, t_in, np.inf)
            else:
                qs, ds = q / h[k], d / h[k]
                a, b = ds @ ds, qs @ ds
                disc = b * b - a * ((qs * qs).sum(axis=1) - 1.0)
                t = np.where(disc >= 0.0, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)
            nearer = t < best
            best[nearer], who[nearer] = t[nearer], k
    cell = (2.0 * r / n) ** 2
    area = np.array([np.count_nonzero(who == k) * cell for k in range(len(parts))])
    centroid = np.array([o[who == k].mean(axis=0) if area[k] else c[k] for k in range(len(parts))])
    return area, centroid


def expected(renderer, R_nc, p_t, R_nt, L_bg: float) -> tuple[float, float, float]:
    """The silhouette's radiance integral (W m^-2 sr^-1 px^2) and contrast-weighted centroid (u, v)."""
    s = renderer.settings
    p_c = R_nc.T @ (p_t - CAMERA_P_NED_M)
    range_m = float(np.linalg.norm(p_c))
    area, centroid_b = silhouette(s.target_parts, R_nt.T @ (p_t - CAMERA_P_NED_M))
    tau = math.exp(-s.extinction_per_km * range_m / 1e3)
    L_air = float(band_radiance(s.air_temperature_k, s.band_um))
    L_env = renderer.environment_radiance
    contrast = np.array(
        [
            tau * (p.emissivity * float(band_radiance(p.temperature_k, s.band_um)) + (1 - p.emissivity) * L_env)
            + (1 - tau) * L_air
            - L_bg
            for p in s.target_parts
        ]
    )
    px2_per_m2 = INTR.fx_px * INTR.fy_px * range_m / p_c[2] ** 3  # solid angle per m^2 over a pixel's
    w = area * contrast
    uv = INTR.project((R_nc.T @ (p_t + centroid_b @ R_nt.T - CAMERA_P_NED_M).T).T)
    return float(w.sum() * px2_per_m2), float(w @ uv[:, 0] / w.sum()), float(w @ uv[:, 1] / w.sum())


SHIFTS = [((0.37 * k) % 1.0 - 0.5, k / 16.0 - 0.5) for k in range(16)]


@pytest.mark.parametrize("rpy_deg", [SIDE_VIEW, OBLIQUE], ids=["side", "oblique"])
@pytest.mark.parametrize("range_m", [400.0, 800.0])
def test_far_targets_integral_does_not_move_with_its_sub_pixel_position(renderer, range_m, rpy_deg):
    """The default quad-rotor (16 mm arms) at 400 and 800 m, moved over a pixel in 1/16 px steps: its radiance
    integral stays within 2 % of its mean, the mean within 2.5 % of the silhouette's."""
    R_nc, R_nt = R_cam(), R_body(rpy_deg)
    totals = []
    for du, dv in SHIFTS:
        p_t = target_at(R_nc, 320.0 + du, 250.0 + dv, range_m)
        total, _, _, ss, L_bg = drawn(renderer, R_nc, p_t, R_nt)
        totals.append(total)
    totals = np.array(totals)
    mean = float(totals.mean())
    assert np.all(np.abs(totals / mean - 1.0) <= SPREAD_RTOL), (totals.min(), totals.max())
    p_t = target_at(R_nc, 320.0, 250.0, range_m)
    want, _, _ = expected(renderer, R_nc, p_t, R_nt, drawn(renderer, R_nc, p_t, R_nt)[4])
    assert mean == pytest.approx(want, rel=FLUX_RTOL)


@pytest.mark.parametrize("rpy_deg", [SIDE_VIEW, OBLIQUE], ids=["side", "oblique"])
def test_unresolved_targets_integral_times_range_squared_is_constant(renderer_clear, rpy_deg):
    """Without extinction the integral of an unresolved target falls as 1 / R^2: R^2 x integral within 2 %
    from 250 m (1.5 px across) to 1200 m, at the same place on the image and the same view of the target."""
    R_nc, R_nt = R_cam(), R_body(rpy_deg)
    scaled = []
    for range_m in (250.0, 330.0, 400.0, 570.0, 800.0, 1200.0):
        p_t = target_at(R_nc, 320.3, 250.6, range_m)
        total, _, _, ss, _ = drawn(renderer_clear, R_nc, p_t, R_nt)
        scaled.append(total * range_m**2)
    scaled = np.array(scaled)
    assert scaled.max() / scaled.min() - 1.0 <= SPREAD_RTOL, scaled


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    range_m=st.floats(250.0, 1000.0),
    u=st.floats(60.0, 580.0),
    v=st.floats(60.0, 450.0),
    roll=st.floats(-60.0, 60.0),
    pitch=st.floats(-60.0, 60.0),
    yaw=st.floats(-180.0, 180.0),
)
def test_unresolved_targets_integral_and_centroid_are_the_silhouettes(renderer, range_m, u, v, roll, pitch, yaw):
    """Anywhere on the image (above the horizon), any attitude, 250-1000 m: the drawn integral within 2.5 % of
    the silhouette's and the drawn energy's centroid within 0.05 px of the silhouette's."""
    R_nc, R_nt = R_cam(pitch_deg=25.0), R_body((roll, pitch, yaw))
    p_t = target_at(R_nc, u, v, range_m)
    total, cu, cv, ss, L_bg = drawn(renderer, R_nc, p_t, R_nt)
    want, wu, wv = expected(renderer, R_nc, p_t, R_nt, L_bg)
    assert total == pytest.approx(want, rel=FLUX_RTOL)
    assert math.hypot(cu - wu, cv - wv) <= CENTROID_TOL_PX


@pytest.mark.parametrize("range_m, splat", [(100.0, False), (170.0, False), (195.0, True), (800.0, True)])
def test_resolved_target_keeps_the_ray_cast(renderer, range_m, splat):
    """The target is ray cast (16 x 16 sub-samples a pixel) while its bounding sphere spans more than 2 px
    (the default quad-rotor nearer than ~190 m), and drawn as the splat beyond."""
    R_nc = R_cam()
    ss = drawn(renderer, R_nc, target_at(R_nc, 320.4, 250.2, range_m), R_body(OBLIQUE))[3]
    assert ss == (1 if splat else renderer.settings.supersample)


def test_visible_fractions_of_a_plate_in_front_of_a_larger_one():
    """Along +z (body down), a 0.1 m plate above (-z) a 0.3 m plate hides (0.1 / 0.3)^2 of it: the sampled
    fraction is within 1 % of 8 / 9; a part clear of every other is exactly 1; the order of the parts does not
    matter."""
    front = TargetPart("front", "box", (0.0, 0.0, -0.1), (0.05, 0.05, 0.01), 300.0, 1.0)
    back = TargetPart("back", "box", (0.0, 0.0, 0.0), (0.15, 0.15, 0.01), 300.0, 1.0)
    aside = TargetPart("aside", "ellipsoid", (0.4, 0.0, 0.0), (0.05, 0.05, 0.05), 300.0, 1.0)
    for parts, i_back in (((front, back, aside), 1), ((aside, back, front), 1)):
        centre = np.array([p.center_frd_m for p in parts])
        half = np.array([p.half_extent_m for p in parts])
        is_box = np.array([p.shape == "box" for p in parts])
        f = visible_fractions(np.array([0.0, 0.0, 1.0]), centre, half, is_box, 2048)
        assert f[i_back] == pytest.approx(8.0 / 9.0, rel=0.01)
        assert all(f[k] == 1.0 for k in range(3) if k != i_back)
