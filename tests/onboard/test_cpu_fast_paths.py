"""The per-frame paths made cheaper for the daemon's CPU give what they gave before, bit for bit: the camera clock
estimator's lines of sight made once per block instead of once per frame, the pipeline's pixel bearing in floats."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from onboard.app.config import OnboardConfig, build_config
from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics, quat_normalize, rotmat_from_quat
from onboard.estimation.time_offset import TimeOffsetEstimator, _unit_ned
from onboard.pipeline.frame_pipeline import FramePipeline

UNIT = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(
    arrays(np.float64, st.tuples(st.integers(1, 40), st.just(3)), elements=UNIT),
    arrays(np.float64, (40, 4), elements=UNIT),
)
def test_a_blocks_lines_of_sight_are_the_per_frame_ones(bearings, quats):
    """``R(q) b / |b|`` for the whole block at once equals what the estimator made frame by frame before."""
    b = bearings + np.array([0.0, 0.0, 1.5])  # |b| > 0: a bearing in front of the camera
    q = quat_normalize(quats[: len(b)] + np.array([2.0, 0.0, 0.0, 0.0]))  # w >= 1: never a zero quaternion
    per_frame = np.array([rotmat_from_quat(q[k]) @ (b[k] / np.linalg.norm(b[k])) for k in range(len(b))])
    np.testing.assert_array_equal(_unit_ned(b, q), per_frame)


@pytest.mark.parametrize(
    "args, message",
    [
        (([0.0, 1.0], [1.0, 0, 0, 0], [0.0, 0, 0], [0.0, 0, 0]), "bearing_cam has 2 values, expected 3"),
        # sizes that add up, wrongly split
        (
            ([0.0, 0, 1], [1.0, 0, 0], [0.0, 0, 0, 0], [0.0, 0, 0]),
            "q_ned_from_cam has 3 values, expected 4; p_cam_ned_m has 4 values, expected 3",
        ),
        (([0.0, 0, 1], [1.0, 0, 0, 0], [0.0, 0, 0], [0.0, 0]), "v_cam_ned_mps has 2 values, expected 3"),
    ],
)
def test_a_frame_of_the_wrong_shape_is_refused_and_not_kept(args, message):
    est = TimeOffsetEstimator()
    with pytest.raises(InputError) as e:
        est.add(1.0, *args, 100.0)
    assert str(e.value) == f"TimeOffsetEstimator.add: {message}"
    est.add(2.0, [0.0, 0, 1], [1.0, 0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], 100.0)
    est.close_block()  # one frame: nothing to pool, and no leftover of the refused one
    assert est.estimate.blocks == 0 and est.estimate.frames == 0


BEARING_ATOL = 1e-15  # a unit vector's components, a few ulp
# fx != fy and an off-centre principal point: a focal length or centre taken for the other axis shows
NON_SQUARE_INTRINSICS = {"fx_px": 800, "fy_px": 790, "cx_px": 161.5, "cy_px": 128, "width_px": 320, "height_px": 256}
CAMERAS = {"default": {}, "non-square": {"camera": {"intrinsics": NON_SQUARE_INTRINSICS}}}


@functools.cache
def _pipeline_intrinsics(camera: str) -> PinholeIntrinsics:
    return FramePipeline(build_config(CAMERAS[camera]), None, tracker=None).intrinsics


@pytest.mark.parametrize("camera", list(CAMERAS))
@settings(max_examples=300, deadline=None)
@given(st.floats(-2000.0, 2000.0, allow_nan=False), st.floats(-2000.0, 2000.0, allow_nan=False))
def test_the_pipelines_pixel_bearing_is_the_cameras(camera, u_px, v_px):
    K = _pipeline_intrinsics(camera)
    expected = K.bearing_cam_from_pixel((u_px, v_px))
    got = K.bearing_cam_from_uv(u_px, v_px)
    assert isinstance(got, tuple)
    np.testing.assert_array_equal(np.array(got), expected)


def test_the_non_square_pipeline_camera_is_the_configured_one():
    K = _pipeline_intrinsics("non-square")
    assert (K.fx_px, K.fy_px, K.cx_px, K.cy_px, K.width_px, K.height_px) == (800.0, 790.0, 161.5, 128.0, 320, 256)
    # pixel (cx + 0.1 fx, cy - 0.2 fy) looks along (0.1, -0.2, 1)
    b = K.bearing_cam_from_uv(161.5 + 80.0, 128.0 - 158.0)
    np.testing.assert_allclose(np.array(b), np.array([0.1, -0.2, 1.0]) / np.sqrt(1.05), rtol=0, atol=BEARING_ATOL)


def test_a_camera_with_distortion_keeps_the_cameras_own_bearing():
    K = PinholeIntrinsics(500.0, 500.0, 320.0, 256.0, 640, 512, distortion=(-0.2, 0.05, 0.0, 0.0, 0.0))
    np.testing.assert_array_equal(K.bearing_cam_from_uv(600.0, 30.0), K.bearing_cam_from_pixel((600.0, 30.0)))
    assert K.bearing_cam_from_uv(600.0, 30.0)[0] != pytest.approx(
        FramePipeline(OnboardConfig(), None, tracker=None).intrinsics.bearing_cam_from_uv(600.0, 30.0)[0], abs=1e-6
    )
