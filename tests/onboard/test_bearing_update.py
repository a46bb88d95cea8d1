"""TrackEstimate.with_bearing: the correction of a propagated estimate by a frame's own line of sight."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics
from onboard.estimation.map_estimator import NoiseModel
from onboard.estimation.sliding import TrackEstimate, bearing_sigma_rad, line_of_sight_unit_ned


def _estimate(p, cov) -> TrackEstimate:
    return TrackEstimate(
        t_s=1.0,
        p_ned_m=np.asarray(p, float),
        v_ned_mps=np.zeros(3),
        cov_p_ned_m2=np.asarray(cov, float),
        cov_v_ned_m2ps2=np.eye(3),
        observable=True,
        range_m=float(np.linalg.norm(p)),
        range_sigma_ratio=0.01,
        window_frames=100,
        model="cv",
    )


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


vec = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 0.2)


@settings(max_examples=200, deadline=None)
@given(
    u=vec,
    rng=st.floats(50.0, 2000.0),
    off=st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-3, 3)),
    sig=st.floats(0.2, 5.0),
    sigma_mrad=st.floats(0.05, 2.0),
)
def test_the_update_moves_the_position_towards_the_ray_and_never_grows_the_covariance(u, rng, off, sig, sigma_mrad):
    u = _unit(u)
    c = np.array([10.0, -5.0, -80.0])
    p0 = c + rng * u + np.asarray(off)
    P0 = np.eye(3) * sig**2
    est = _estimate(p0, P0)
    out = est.with_bearing(c, u, sigma_mrad * 1e-3, gate_chi2=math.inf)
    assert out is not None

    def cross(p):
        d = p - c
        return np.linalg.norm(d - (d @ u) * u)

    assert cross(out.p_ned_m) <= cross(p0) + 1e-9
    # the correction is across the ray only: the along-ray coordinate is kept (isotropic prior)
    assert abs((out.p_ned_m - c) @ u - (p0 - c) @ u) < 1e-6 * rng
    # P0 - P+ is positive semi-definite, and P+ is symmetric
    assert np.linalg.eigvalsh(P0 - out.cov_p_ned_m2).min() > -1e-9 * sig**2
    np.testing.assert_allclose(out.cov_p_ned_m2, out.cov_p_ned_m2.T, atol=1e-12 * sig**2)
    assert math.isclose(out.range_m, float(np.linalg.norm(out.p_ned_m - c)), rel_tol=1e-12)


def test_a_position_on_the_ray_is_kept_and_its_cross_range_sigma_drops_to_the_bearing_accuracy():
    c = np.zeros(3)
    u = _unit([1.0, 0.0, 0.0])
    est = _estimate([200.0, 0.0, 0.0], np.diag([4.0, 4.0, 4.0]))
    out = est.with_bearing(c, u, 1e-3)
    np.testing.assert_allclose(out.p_ned_m, [200.0, 0.0, 0.0], atol=1e-12)
    # prior 2 m, measurement 0.2 m (200 m x 1 mrad) across: posterior 1/sqrt(1/4 + 1/0.04) m
    expect = 1.0 / math.sqrt(1 / 4.0 + 1 / 0.04)
    np.testing.assert_allclose(np.sqrt(np.diag(out.cov_p_ned_m2)), [2.0, expect, expect], rtol=1e-9)


def test_a_bearing_outside_the_gate_is_not_fused():
    c = np.zeros(3)
    est = _estimate([200.0, 0.0, 0.0], np.eye(3) * 0.01)  # 0.1 m sigma
    assert est.with_bearing(c, _unit([200.0, 5.0, 0.0]), 1e-4) is None  # 5 m across, sigma ~0.1 m
    assert est.with_bearing(c, _unit([200.0, 0.05, 0.0]), 1e-4) is not None


def test_the_line_of_sight_and_its_sigma_follow_the_camera_model():
    K = PinholeIntrinsics(fx_px=500.0, fy_px=500.0, cx_px=320.0, cy_px=256.0, width_px=640, height_px=512)
    # camera looking north with x east, y down (frames: camera z forward): q of R = [[0,0,1],[1,0,0],[0,1,0]]
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    w = math.sqrt(1 + np.trace(R)) / 2
    q = np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])
    np.testing.assert_allclose(line_of_sight_unit_ned([320.0, 256.0], K, q), [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(line_of_sight_unit_ned([820.0, 256.0], K, q), _unit([1.0, 1.0, 0.0]), atol=1e-12)
    noise = NoiseModel(pixel_sigma_px=0.5, attitude_white_sigma_rad=3e-4, attitude_bias_sigma_rad=4e-4)
    assert math.isclose(bearing_sigma_rad(noise, K), math.sqrt(1e-6 + 9e-8 + 1.6e-7), rel_tol=1e-12)


def test_non_square_pixels_give_the_line_of_sight_per_axis_and_the_sigma_of_the_mean_focal_length():
    """fx 800, fy 790, principal point off the centre: each axis its own focal length; one pixel of noise is
    1 / sqrt(fx fy) rad (the geometric mean: the sigma of a round pixel of the same area)."""
    K = PinholeIntrinsics(fx_px=800.0, fy_px=790.0, cx_px=161.5, cy_px=128.0, width_px=320, height_px=256)
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # camera looking north, x east, y down
    w = math.sqrt(1 + np.trace(R)) / 2
    q = np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])
    # (cx + 0.1 fx, cy + 0.05 fy): 0.1 east and 0.05 down per metre north
    u = line_of_sight_unit_ned([161.5 + 80.0, 128.0 + 39.5], K, q)
    np.testing.assert_allclose(u, _unit([1.0, 0.1, 0.05]), atol=1e-12)
    noise = NoiseModel(pixel_sigma_px=0.5)
    assert math.isclose(bearing_sigma_rad(noise, K), 0.5 / math.sqrt(800.0 * 790.0), rel_tol=1e-12)


def _unobservable(p, cam, sigma_cross_m: float, sigma_range_m: float) -> TrackEstimate:
    """An unobservable estimate at ``p`` seen from ``cam``: ``sigma_range_m`` along the line of sight (the range
    floor), ``sigma_cross_m`` across it."""
    p, cam = np.asarray(p, float), np.asarray(cam, float)
    u = _unit(p - cam)
    P = sigma_cross_m**2 * (np.eye(3) - np.outer(u, u)) + sigma_range_m**2 * np.outer(u, u)
    est = _estimate(p, P)
    rng = float(np.linalg.norm(p - cam))
    return dataclasses.replace(est, observable=False, range_m=rng, range_sigma_ratio=sigma_range_m / rng)


def _camera_looking_at(cam, target):
    """The frame's quaternion of a camera at ``cam`` whose optical axis (camera z) points at ``target``."""
    from onboard.core.frames import quat_from_rotmat

    z = _unit(np.asarray(target, float) - np.asarray(cam, float))
    x = _unit(np.cross([0.0, 0.0, 1.0], z))  # NED down x forward: the image's right
    R = np.column_stack([x, np.cross(z, x), z])
    return quat_from_rotmat(R)


def test_a_worker_carried_unobservable_estimate_keeps_the_range_floor_after_a_bearing_update():
    from onboard.app.estimator_worker import _propagate
    from onboard.core.counters import RejectCounter
    from onboard.estimation.map_estimator import MapConfig
    from onboard.estimation.sliding import range_floored

    cfg = MapConfig()
    target, cam0, cam1 = np.array([120.0, 0.0, 0.0]), np.zeros(3), np.array([0.0, 20.0, 0.0])
    est = _unobservable(target, cam0, 1.0, 150.0)  # the floor: max(0.5 x 120, 150) m along the first ray
    K = PinholeIntrinsics(fx_px=500.0, fy_px=500.0, cx_px=320.0, cy_px=256.0, width_px=640, height_px=512)
    noise = NoiseModel(pixel_sigma_px=0.3)
    u1 = line_of_sight_unit_ned([320.0, 256.0], K, _camera_looking_at(cam1, target))
    # the bearing from the moved camera, fused across a floor laid along the first ray, shrinks the range sigma as
    # if the range had been measured twice
    fused = est.propagated(1.0, cam1).with_bearing(cam1, u1, bearing_sigma_rad(noise, K))
    assert fused is not None and fused.range_sigma_ratio * fused.range_m < 0.8 * cfg.unobservable_range_sigma_min_m
    floored = range_floored(fused, cam1, cfg)
    sig_r = math.sqrt(u1 @ floored.cov_p_ned_m2 @ u1)
    assert sig_r >= cfg.unobservable_range_sigma_min_m * 0.999
    assert floored.range_sigma_ratio * floored.range_m >= cfg.unobservable_range_sigma_min_m * 0.999
    # what a busy worker publishes for the frame: the same, floored
    obs = ([320.0, 256.0], K, cam1, _camera_looking_at(cam1, target))
    out = _propagate(dataclasses.replace(est, t_s=0.9), 1.0, cam1, 1.0, RejectCounter(), obs, noise, cfg)
    assert out is not None and out.range_sigma_ratio * out.range_m >= cfg.unobservable_range_sigma_min_m * 0.999
    observable = dataclasses.replace(fused, observable=True)
    assert range_floored(observable, cam1, cfg) is observable  # an observable estimate is left as it is
