"""The objects chain (onboard.imaging.objects) on 8-bit frames and on the same frames widened to 16 bits (x 257,
full scale, or shifted by 8 bits): the same tracks, since its floors and caps are in the frame's own grey levels
(onboard.imaging.clutter.grey_level)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.background_difference import two_level_difference_cap
from onboard.imaging.clutter import GREY16_PER_GREY8, grey_level
from onboard.imaging.objects import ObjectTracker

W_PX, H_PX = 256, 192
K = PinholeIntrinsics(300.0, 300.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
N_FRAMES = 30
SKY_GREY, SKY_NOISE_GREY = 100.0, 0.3  # a flat sky: most pixels on one level, a few a level off
# ground on a level boundary, its pixels toggling between two levels (the threshold's cap there)
GROUND_GREY, GROUND_NOISE_GREY = 100.5, 0.15
# (start u, v px; velocity px/frame; amplitude grey): points moving apart; the last, over the right half, under
# the threshold toggling pixels make but over the cap when that half is ground
POINTS = (
    ((60.0, 60.0), (0.5, 0.2), 12.0),
    ((60.0, 140.0), (0.3, -0.5), 4.0),
    ((180.0, 60.0), (-0.3, 0.4), 6.0),
    ((190.0, 130.0), (-0.4, 0.3), 4.0),
)
# x 257: the float32 arithmetic (the column offsets' running means, the box means) rounds apart from the 8-bit
# frame's x 257 by an ulp of the grey; a power of two scales every rounding exactly
ATOL_PX = 1e-4
SCORE_RTOL = 1e-4


def _frames(ground: bool) -> list[np.ndarray]:
    """Sky; with ``ground``, ground on two levels in the right half."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    out = []
    for k in range(N_FRAMES):
        img = SKY_GREY + rng.normal(0.0, SKY_NOISE_GREY, (H_PX, W_PX))
        if ground:
            img[:, W_PX // 2 :] = GROUND_GREY + rng.normal(0.0, GROUND_NOISE_GREY, (H_PX, W_PX - W_PX // 2))
        for (u0, v0), (du, dv), amp in POINTS:
            u, v = u0 + du * k, v0 + dv * k
            img += amp * np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * 0.7**2))
        out.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return out


def _tracks(frames: list[np.ndarray]) -> list[list[tuple[int, str, float, float, float]]]:
    tr = ObjectTracker(K)
    return [[(o.object_id, o.state, o.u_px, o.v_px, o.score) for o in tr.update(f, np.eye(3)).objects] for f in frames]


def test_frames_widened_to_16_bits_keep_the_8_bit_frames_tracks():
    """A flat sky of one grey level with a few pixels a level off, four points moving over it: the 16-bit frames x
    257 give the tracks of the 8-bit ones, id for id, frame by frame (a floor in counts took the sky's lone
    pixels a level up for points, and their tentative tracks took ids)."""
    frames = _frames(ground=False)
    mono8 = _tracks(frames)
    mono16 = _tracks([f.astype(np.uint16) * np.uint16(GREY16_PER_GREY8) for f in frames])
    assert sum(o[1] == "confirmed" for o in mono8[-1]) == len(POINTS)
    for k, (a, b) in enumerate(zip(mono8, mono16)):
        assert [(o[0], o[1]) for o in a] == [(o[0], o[1]) for o in b], k
        np.testing.assert_allclose([o[2:4] for o in b], [o[2:4] for o in a], rtol=0, atol=ATOL_PX, err_msg=str(k))
        np.testing.assert_allclose([o[4] for o in b], [o[4] for o in a], rtol=SCORE_RTOL, err_msg=str(k))


def test_frames_shifted_to_16_bits_keep_the_8_bit_frames_tracks():
    """Sky and two-level ground, a point over the ground under its toggling pixels' threshold but over the cap: the
    frames shifted by 8 bits (x 256) give the 8-bit frames' tracks, id for id and state for state (the two-level
    rule on adjacent counts never capped the 16-bit ground).  Not bit for bit: the background's motion over the
    window (its float32 phase correlation) rounds apart by ~1e-7 px, and a difference square resampled there moves
    a tentative track's centre by ~1e-6 px.  x 257 rounds apart more, and a contrast of exactly one level, the
    cap, may fall either side of it."""
    frames = _frames(ground=True)
    mono8 = _tracks(frames)
    mono16 = _tracks([f.astype(np.uint16) << 8 for f in frames])
    assert sum(o[1] == "confirmed" for o in mono8[-1]) == len(POINTS)
    for k, (a, b) in enumerate(zip(mono8, mono16)):
        assert [(o[0], o[1]) for o in a] == [(o[0], o[1]) for o in b], k
        np.testing.assert_allclose([o[2:4] for o in b], [o[2:4] for o in a], rtol=0, atol=ATOL_PX, err_msg=str(k))
        np.testing.assert_allclose([o[4] for o in b], [o[4] for o in a], rtol=SCORE_RTOL, err_msg=str(k))


@pytest.mark.parametrize(
    "scale, offset, level",
    [
        (GREY16_PER_GREY8, 0, GREY16_PER_GREY8),  # an 8-bit frame widened to full scale
        (256, 128, 256),  # shifted by 8 bits, a half level up
        (16, 0, 16),  # 12-bit counts left-aligned
        (514, 0, GREY16_PER_GREY8),  # coarser than 8 bits: never more than an 8-bit level
    ],
)
def test_grey_level_of_a_widened_16_bit_frame(scale, offset, level):
    frame = np.random.default_rng(3).integers(0, 120, (H_PX, W_PX))
    assert grey_level((frame * int(scale) + offset).astype(np.uint16)) == level


def test_grey_level_is_one_for_8_bit_native_16_bit_and_flat_frames():
    rng = np.random.default_rng(4)
    assert grey_level((rng.integers(0, 120, (H_PX, W_PX)) * 2).astype(np.uint8)) == 1.0  # 8-bit: always one grey
    native = (rng.integers(0, 120, (H_PX, W_PX)) * 257).astype(np.uint16)
    native[H_PX // 2 + 1, W_PX // 2 + 1] += 1  # one count off the sampled rows and columns
    assert grey_level(native) == 1.0
    assert grey_level(np.full((H_PX, W_PX), 1000, np.uint16)) == 1.0


def test_the_difference_cap_reads_a_widened_frame_kept_as_float_in_its_levels():
    """The background difference's frames: an 8-bit frame as it is, a 16-bit one as float32 (its sub-pixel reads);
    the x 257 frames on two levels are capped as the 8-bit ones, in their grey."""
    rng = np.random.default_rng(11)
    cur, prev = (np.rint(GROUND_GREY + rng.normal(0.0, GROUND_NOISE_GREY, (H_PX, W_PX))).astype(np.uint8) for _ in "ab")
    uv, cap_levels = (W_PX / 2, H_PX / 2), 1.25
    assert two_level_difference_cap(cur, prev, uv, (0.0, 0.0), cap_levels) == cap_levels
    wide = [f.astype(np.float32) * np.float32(GREY16_PER_GREY8) for f in (cur, prev)]
    widened = two_level_difference_cap(*wide, uv, (0.0, 0.0), cap_levels, level=GREY16_PER_GREY8)
    assert widened == cap_levels * GREY16_PER_GREY8
    assert two_level_difference_cap(*wide, uv, (0.0, 0.0), cap_levels) == math.inf  # a float frame of unknown levels
    wide[0][H_PX // 2, W_PX // 2] += 1.0  # one pixel off whole levels
    assert two_level_difference_cap(*wide, uv, (0.0, 0.0), cap_levels, level=GREY16_PER_GREY8) == math.inf


def test_two_cameras_of_different_encodings_alternating_log_the_offset_step_once_an_interval(caplog):
    """mono8 and mono16 frames of one size alternating (two cameras on the key): every frame is an offset step and
    restarts the defect map, as before (counted in offset_steps), but it was logged at every frame: logged once,
    then once per reject-log interval with the count since."""
    frames = _frames(ground=False)
    tr = ObjectTracker(K)
    with caplog.at_level(logging.INFO, logger="onboard.imaging.objects"):
        for i, f in enumerate(frames):
            tr.update(f.astype(np.uint16) * 257 if i % 2 else f, np.eye(3))
    steps = [r.getMessage() for r in caplog.records if "offset step" in r.getMessage()]
    assert tr.offset_steps == N_FRAMES - 1
    assert len(steps) == 1 and steps[0].startswith("imaging_offset_step: frame 1: offset step")
