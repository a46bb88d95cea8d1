"""The track-before-detect search's texture map (``TrackBeforeDetect._texture_map``) on flat frames: finite
local rms, and cloud flagged, where a box filter's rounding left a slightly negative mean square (a flat
MJPG clip printed ``RuntimeWarning: invalid value encountered in sqrt`` and searched with no map at all)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.clutter import noise_window_cells
from onboard.imaging.tbd import STATS_FACTOR, TbdParams, TrackBeforeDetect

H_PX, W_PX = 128, 160
K = PinholeIntrinsics(300.0, 300.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
R_MOUNT = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # cam z = north, x = east, y = down
STRIP = slice(14, 26)  # the textured columns of the coarse grid (of 40); the window reaches 8 cells either side


def _tbd() -> TrackBeforeDetect:
    return TrackBeforeDetect(K, TbdParams(search_px=0))


def test_a_flat_frame_has_no_texture_and_no_warning():
    tbd = _tbd()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a NaN rms warns from np.sqrt
        for _ in range(3):
            assert tbd.update(np.full((H_PX, W_PX), 15000, np.uint16), R_MOUNT) == []
    tex = tbd._texture
    assert tex is not None and tex.shape == (H_PX // STATS_FACTOR, W_PX // STATS_FACTOR)
    assert not tex.any()  # nothing above a quiet floor of zero


def _strip_frame() -> np.ndarray:
    """A suppressed frame flat (exactly 0) but for a vertical strip of texture whose local rms spans many
    orders of magnitude (a cloud's bright and faint cells), in blocks of one coarse cell."""
    rng = np.random.default_rng(1)
    cells = np.zeros((H_PX // STATS_FACTOR, W_PX // STATS_FACTOR))
    cells[:, STRIP] = 300.0 * rng.uniform(0.0, 1.0, (cells.shape[0], STRIP.stop - STRIP.start)) ** 4
    return np.kron(cells, np.ones((STATS_FACTOR, STATS_FACTOR))).astype(np.float32)


def test_a_flat_frame_beside_texture_keeps_a_finite_floor_and_flags_the_texture():
    tbd = _tbd()
    frame = _strip_frame()
    # the case itself: the box filter's running sums leave a negative residue right of the strip, where
    # the window holds nothing but zeros
    k = noise_window_cells(tbd.params.noise_window_px, tbd.params.decimation * STATS_FACTOR)
    sq = cv2.resize(
        cv2.multiply(frame, frame), (W_PX // STATS_FACTOR, H_PX // STATS_FACTOR), interpolation=cv2.INTER_AREA
    )
    assert (cv2.blur(sq, (k, k), borderType=cv2.BORDER_REFLECT) < 0).any(), "no negative residue: case not covered"

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tex = tbd._texture_map(frame)
    assert tex.shape == sq.shape
    # the strip is cloud against a quiet floor of zero (a NaN floor had left the whole map False) ...
    assert tex[:, STRIP].all()
    # ... and the flat cells left of it, out of the window's reach, are sky (right of it the running sums
    # leave a rounding residue of either sign: a residue above zero counts as texture there, harmless on a
    # flat area, where there is no peak to skip)
    assert not tex[:, : STRIP.start - k // 2 - 1].any()
