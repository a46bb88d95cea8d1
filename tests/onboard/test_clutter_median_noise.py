"""The CFAR threshold's noise from the noise window's median (onboard.imaging.clutter.median_window_noise): uniform
noise gives the window mean's figure, a bright edge in a few of the window's cells moves the median little and
the mean much, the figure scales with the noise, and a bird beside a cloud's edge is a candidate with it and not
with the mean alone, while the edge itself stays out."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.clutter import MEAN_ABS_TO_SIGMA, ClutterParams, median_window_noise, window_noise
from onboard.imaging.objects_detection import ObjectDetector
from onboard.imaging.objects_model import ObjectParams

WINDOW_CELLS = 7  # the detector's: a 31 px window on a 4 px grid
SKY_DEV_GREY, EDGE_DEV_GREY = 0.4, 20.0  # mean absolute deviation per cell
REL_TOL = 1e-5  # float32 area means, a median and bilinear weights of equal values
H_PX, W_PX = 96, 128
SKY_GREY, CLOUD_GREY = 74.0, 116.0  # C3 seed 0 over 30 s, frame 340: clear sky, a cloud's body
SKY_SIGMA_GREY = 0.3  # a clear sky in mono8: mostly quantisation
CLOUD_TEXTURE_GREY = 4.0  # the cloud body's fine structure, which lifts the cells' deviations there
EDGE_ROW_PX, EDGE_WIDTH_PX = 60.0, 0.8  # the cloud's edge: a logistic ramp from sky to cloud
BIRD_GREY = (
    4.5  # over the sky: under the ~5.7 grey threshold the window's mean gives beside the edge, over the median's ~2.9
)
BIRD_GAP_PX = 8.0  # from the edge's middle (4-8 px in C3)
TOL_PX = 1.5


def test_uniform_cells_give_the_window_mean():
    cells = np.full((32, 40), SKY_DEV_GREY, np.float32)
    np.testing.assert_allclose(
        median_window_noise(cells, WINDOW_CELLS), window_noise(cells, WINDOW_CELLS), rtol=REL_TOL
    )


def test_an_edge_in_two_of_seven_rows_moves_the_median_little():
    cells = np.full((40, 40), SKY_DEV_GREY, np.float32)
    cells[20:22] = EDGE_DEV_GREY
    med = median_window_noise(cells, WINDOW_CELLS)
    mean = window_noise(cells, WINDOW_CELLS)
    rows = slice(18, 20)  # 1-2 cells above the edge: its two rows inside the 7-cell window
    sky = SKY_DEV_GREY * MEAN_ABS_TO_SIGMA
    assert np.all(mean[rows] > 10 * sky)
    assert np.all(med[rows] < 1.5 * sky)
    # far from it, both the sky's
    np.testing.assert_allclose(med[:8], sky, rtol=REL_TOL)


@settings(max_examples=60, deadline=None)
@given(
    cells=arrays(np.float32, (24, 30), elements=st.floats(0.0625, 32.0, width=32)),
    scale=st.floats(0.01, 100.0),
)
def test_scales_with_the_noise_and_stays_within_its_neighbourhood(cells, scale):
    got = median_window_noise(cells, WINDOW_CELLS)
    scaled = median_window_noise(cells * np.float32(scale), WINDOW_CELLS)
    np.testing.assert_allclose(scaled, got * np.float32(scale), rtol=1e-4)
    # an area mean, a median and bilinear weights never leave the range of the cells they read: the window and the
    # coarse grid's reach beyond it (a coarse cell of 1.4 cells, the interpolation's neighbour)
    pad = WINDOW_CELLS // 2 + 3
    padded = np.pad(cells, pad, mode="edge")
    for i, j in ((0, 0), (12, 15), (23, 29), (5, 20)):
        around = padded[i : i + 2 * pad + 1, j : j + 2 * pad + 1] * MEAN_ABS_TO_SIGMA
        assert around.min() * (1 - 1e-5) <= got[i, j] <= around.max() * (1 + 1e-5)


def _sky_with_cloud_edge_and_bird(seed: int, u: float, v: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    cloud = 1.0 / (1.0 + np.exp(-(yy + 0.5 - EDGE_ROW_PX) / EDGE_WIDTH_PX))
    img = SKY_GREY + cloud * (CLOUD_GREY - SKY_GREY + rng.normal(0.0, CLOUD_TEXTURE_GREY, cloud.shape))
    img += rng.normal(0.0, SKY_SIGMA_GREY, img.shape)
    # a 2 x 2 px bird, its light spread a little by the optics (not a one-pixel outlier the defect map repairs)
    img += BIRD_GREY * np.exp(-(((xx + 0.5 - u) / 1.2) ** 4 + ((yy + 0.5 - v) / 1.2) ** 4))
    return np.rint(img).clip(0, 255).astype(np.uint8)


def _detector(floor: float) -> ObjectDetector:
    K = PinholeIntrinsics(200.0, 200.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
    return ObjectDetector(K, ObjectParams(), ClutterParams(destripe=False, quiet_block_px=0, median_noise_floor=floor))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bird_beside_a_cloud_edge_is_found_with_the_median_only(seed):
    u, v = 64.0, EDGE_ROW_PX - BIRD_GAP_PX
    img = _sky_with_cloud_edge_and_bird(seed, u, v)
    near = {}
    for floor in (1.0, ClutterParams().median_noise_floor):
        cands = _detector(floor).detect(img, 0)
        near[floor] = [c for c in cands if math.hypot(c.u_px - u, c.v_px - v) < TOL_PX]
        # nothing on the sky, the cloud or along its edge
        assert len(cands) == len(near[floor])
    assert near[1.0] == []
    assert len(near[ClutterParams().median_noise_floor]) == 1


@pytest.mark.parametrize("floor", [0.0, -0.5, 1.5, math.nan])
def test_floor_out_of_range_is_refused(floor):
    with pytest.raises(ValueError, match="median_noise_floor"):
        ClutterParams(median_noise_floor=floor)


@pytest.mark.parametrize("window_cells", [3, 5])
def test_a_small_window_is_the_exact_median(window_cells):
    from scipy import ndimage

    rng = np.random.default_rng(window_cells)
    cells = rng.gamma(2.0, 0.3, (20, 26)).astype(np.float32)
    want = ndimage.median_filter(cells, size=window_cells, mode="nearest") * MEAN_ABS_TO_SIGMA
    np.testing.assert_allclose(median_window_noise(cells, window_cells), want, rtol=REL_TOL)


@pytest.mark.parametrize("seed", [0, 1])
def test_lowered_searches_keep_the_mean_threshold(seed):
    """Track-aided detection and the difference search lower a threshold by a track's prior: theirs stays the
    window mean's (the median's, lowered again, let a held track slide onto field edges in the loop), while the
    whole-frame threshold is at most it and lower beside the edge."""
    img = _sky_with_cloud_edge_and_bird(seed, 64.0, EDGE_ROW_PX - BIRD_GAP_PX)
    mean_only = _detector(1.0)
    mean_only.detect(img, 0)
    det = _detector(ClutterParams().median_noise_floor)
    det.detect(img, 0)
    assert mean_only.lowered_base is mean_only.threshold
    np.testing.assert_array_equal(det.lowered_base, mean_only.threshold)
    assert np.all(det.threshold <= det.lowered_base)
    beside = slice(int(EDGE_ROW_PX - BIRD_GAP_PX) - 2, int(EDGE_ROW_PX - BIRD_GAP_PX) + 3)
    assert np.all(det.threshold[beside] < 0.75 * det.lowered_base[beside])


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 3),
    y0=st.integers(0, H_PX - 1),
    x0=st.integers(0, W_PX - 1),
    dy=st.integers(1, 60),
    dx=st.integers(1, 60),
    floor=st.sampled_from([ClutterParams().median_noise_floor, 1.0]),
)
def test_a_block_of_the_lowered_threshold_is_the_frames(seed, y0, x0, dy, dx, floor):
    """The searches read the lowered threshold block by block: each block is the frame's, edges and corners too."""
    det = _detector(floor)
    det.detect(_sky_with_cloud_edge_and_bird(seed, 64.0, EDGE_ROW_PX - BIRD_GAP_PX), 0)
    y1, x1 = min(y0 + dy, H_PX), min(x0 + dx, W_PX)
    block = det.lowered_base_block(y0, y1, x0, x1)  # before the whole frame's is made
    assert block is not None
    np.testing.assert_array_equal(block, det.lowered_base[y0:y1, x0:x1])
    np.testing.assert_array_equal(det.lowered_base_block(y0, y1, x0, x1), block)  # and after
