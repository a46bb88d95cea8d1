"""The CFAR threshold's noise from the noise window's quietest block (onboard.imaging.clutter
.quietest_block_noise): a roof or a warmer field in part of the window leaves the threshold at the
ground's own noise, uniform texture gives the window's mean, a target beside a roof is found while the
tracker acquires, near the optical axis, and nowhere else or later is the threshold changed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.clutter import MEAN_ABS_TO_SIGMA, ClutterParams, quietest_block_noise
from onboard.imaging.objects_detection import ObjectDetector
from onboard.imaging.objects_model import ObjectParams

WINDOW_CELLS, BLOCK_CELLS = 7, 3  # the detector's: a 31 px window and a 12 px block on a 4 px grid
GROUND_DEV_GREY, ROOF_DEV_GREY = 0.4, 6.0  # mean absolute deviation per cell
REL_TOL = 1e-6  # float32 box means of a few cells
H_PX, W_PX = 96, 128
GROUND_SIGMA_GREY = 0.5  # textured ground under the target
GROUND_GREY = 120.0
ROOF_GREY = 80.0  # above the ground (C2 seed 1: roofs 205 grey over ground at ~124)
TARGET_GREY = 10.0  # its peak over the ground: a point contrast over the ground's threshold (~2.5), under the roof-lifted one (~16)
TARGET_SIGMA_PX = 1.0  # blurred by the optics: not an isolated one-pixel outlier the defect map repairs
TARGET_TOL_PX = 1.0


def test_uniform_cells_give_the_window_mean():
    cells = np.full((20, 24), GROUND_DEV_GREY, np.float32)
    got = quietest_block_noise(cells, WINDOW_CELLS, BLOCK_CELLS)
    np.testing.assert_allclose(got, GROUND_DEV_GREY * MEAN_ABS_TO_SIGMA, rtol=REL_TOL)


def test_a_roof_in_part_of_the_window_is_left_out():
    cells = np.full((20, 24), GROUND_DEV_GREY, np.float32)
    cells[:, 12:] = ROOF_DEV_GREY  # a roof edge between cell columns 11 and 12
    got = quietest_block_noise(cells, WINDOW_CELLS, BLOCK_CELLS)
    # a block centred up to 2 cells from the window's centre: up to one cell into the roof (column 12), a
    # block of ground only still lies within the window
    np.testing.assert_allclose(got[:, :13], GROUND_DEV_GREY * MEAN_ABS_TO_SIGMA, rtol=REL_TOL)
    # from three cells in, every block within the window is roof only
    np.testing.assert_allclose(got[:, 15:], ROOF_DEV_GREY * MEAN_ABS_TO_SIGMA, rtol=REL_TOL)
    # the window's mean beside the edge, for contrast: 3 of its 7 columns roof
    mean_beside = (4 * GROUND_DEV_GREY + 3 * ROOF_DEV_GREY) / 7 * MEAN_ABS_TO_SIGMA
    assert got[10, 10] < mean_beside / 5


def test_one_cell_block_is_the_window_minimum():
    rng = np.random.default_rng(3)
    cells = rng.uniform(0.2, 3.0, (16, 16)).astype(np.float32)
    got = quietest_block_noise(cells, WINDOW_CELLS, 1)
    i, j = 8, 8
    want = cells[i - 3 : i + 4, j - 3 : j + 4].min() * MEAN_ABS_TO_SIGMA
    assert got[i, j] == pytest.approx(want, rel=REL_TOL)


def _frame_with_roof_and_target(seed: int, u: float, v: float) -> np.ndarray:
    """Textured ground, a flat roof (C2's read one grey level throughout) filling the frame's right part 6 px
    from the target, and the target."""
    rng = np.random.default_rng(seed)
    img = GROUND_GREY + rng.normal(0.0, GROUND_SIGMA_GREY, (H_PX, W_PX))
    img[:, int(u) + 6 :] = GROUND_GREY + ROOF_GREY
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    img += TARGET_GREY * np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * TARGET_SIGMA_PX**2))
    return np.rint(img).clip(0, 255).astype(np.uint8)


def _detector(block_px: int) -> ObjectDetector:
    K = PinholeIntrinsics(200.0, 200.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
    return ObjectDetector(K, ObjectParams(), ClutterParams(destripe=False, quiet_block_px=block_px))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_target_beside_a_roof_is_found_with_the_quiet_block_only(seed):
    u, v = 60.3, 48.6
    img = _frame_with_roof_and_target(seed, u, v)
    near = {}
    for block_px in (0, 12):
        det = _detector(block_px)
        cands = det.detect(img, 0)
        near[block_px] = [c for c in cands if math.hypot(c.u_px - u, c.v_px - v) < TARGET_TOL_PX]
        # nothing on the ground or along the roof's edge
        assert len(cands) == len(near[block_px])
    assert near[0] == []
    assert len(near[12]) == 1


@pytest.mark.parametrize("acquiring", [True, False])
def test_only_while_acquiring_and_only_near_the_axis(acquiring):
    """With a primary (``acquiring`` False) the threshold is the window mean's everywhere; while
    acquiring, lower only within primary_max_off_axis_rad of the principal point (here 30 px)."""
    u, v = 60.3, 48.6
    img = _frame_with_roof_and_target(0, u, v)
    thr = {}
    for block_px in (0, 12):
        det = _detector(block_px)
        det.acquiring = acquiring
        det.detect(img, 0)
        thr[block_px] = det.threshold.copy()
    half_px = 200.0 * math.tan(ObjectParams().primary_max_off_axis_rad)  # the fixture's focal length
    near = (slice(int(H_PX / 2 - half_px) + 4, int(H_PX / 2 + half_px) - 4), slice(int(u) - 4, int(u) + 4))
    if acquiring:
        assert np.all(thr[12][near] < thr[0][near] / 2)  # the roof 2-10 px away lifts the mean's only
    else:
        np.testing.assert_array_equal(thr[12], thr[0])
    # beyond the square and the bilinear reach of its last cell, the mean's
    far_cols = slice(int(W_PX / 2 + half_px) + 8, W_PX)
    np.testing.assert_array_equal(thr[12][:, far_cols], thr[0][:, far_cols])
    far_rows = slice(int(H_PX / 2 + half_px) + 8, H_PX)
    np.testing.assert_array_equal(thr[12][far_rows], thr[0][far_rows])


def test_the_tracker_lowers_the_threshold_for_its_first_acquisition_only():
    """The tracker tells its detector it is acquiring until a primary is first chosen, and not again once
    that primary is lost (re-acquiring with the lowered threshold picked terrain in the closed loop)."""
    from onboard.imaging.objects import ObjectTracker

    K = PinholeIntrinsics(200.0, 200.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
    tr = ObjectTracker(K)
    img = _frame_with_roof_and_target(0, 60.3, 48.6)
    tr.detect(img)
    assert tr.detector.acquiring
    tr.primary_changes = 1  # a primary was chosen once ...
    tr.clear_primary()  # ... and is gone (clear_primary counts nothing without one)
    tr.detect(img)
    assert not tr.detector.acquiring
