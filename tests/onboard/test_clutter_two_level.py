"""The thresholds' caps where an integer frame's ground quantises to two adjacent grey levels
(onboard.imaging.clutter.two_level_cap for the CFAR threshold, two_level_difference_cap for the
background difference's): the premise (noise on two levels makes no point contrast, and no difference,
over one level), where the caps apply and where not, and a faint target found under them."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.background_difference import background_difference, difference_peak, two_level_difference_cap
from onboard.imaging.clutter import (
    ClutterParams,
    cfar_threshold,
    local_noise_coarse,
    point_candidates,
    point_contrast,
    two_level_cap,
)
from onboard.imaging.objects_detection import (
    DIFFERENCE_GATE_PX,
    DIFFERENCE_SIGMA,
    DIFFERENCE_TWO_LEVEL_CAP,
    NOISE_FACTOR,
    ObjectDetector,
)
from onboard.imaging.objects_model import ObjectParams

H_PX, W_PX = 96, 128
LEVEL = 115  # the boundary the ground's radiance sits at: pixels read 115 or 116
SENSOR_NOISE_GREY = 0.13  # C2 seed 2's sensor noise in mono8 grey
CONTRAST_TOL_GREY = 1e-4  # float32 box means of whole grey levels
# C2 seed 2's target in mono8: 2-3 grey over its ring, a point contrast of 1.25 grey (its median there)
TARGET_GREY, TARGET_SIGMA_PX = 2.5, 1.0
TARGET_TOL_PX = 1.0  # a quantised 2 x 2-ish blob's candidate centre


def _two_level_ground(rng: np.random.Generator, mean_grey: float = LEVEL + 0.5) -> np.ndarray:
    """Flat ground whose radiance sits at a level boundary, sensor noise well under a level, quantised."""
    return np.rint(mean_grey + rng.normal(0.0, SENSOR_NOISE_GREY, (H_PX, W_PX))).clip(0, 255)


def _target(img: np.ndarray, u: float, v: float, amp: float, sigma_px: float = 0.7) -> None:
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]].astype(np.float64)
    img += amp * np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * sigma_px**2))


def _two_level_frame_with_target(seed: int, u: float, v: float) -> np.ndarray:
    """:func:`_two_level_ground` with a faint target at (u, v) added before quantisation (uint8)."""
    ground = LEVEL + 0.5 + np.random.default_rng(seed).normal(0.0, SENSOR_NOISE_GREY, (H_PX, W_PX))
    _target(ground, u, v, TARGET_GREY, TARGET_SIGMA_PX)
    return np.rint(ground).clip(0, 255).astype(np.uint8)


def _thresholds(img: np.ndarray, p: ClutterParams) -> tuple[np.ndarray, np.ndarray]:
    """The uncapped and capped CFAR thresholds on the noise grid, ``img`` an integer frame."""
    noise = local_noise_coarse(img.astype(np.float32), p.noise_window_px, NOISE_FACTOR, full=False)
    cap = two_level_cap(img, p.noise_window_px, NOISE_FACTOR, p.two_level_cap_lsb, p.two_level_fraction)
    return (
        cfar_threshold(noise, p.threshold_sigma, p.min_threshold_lsb),
        cfar_threshold(noise, p.threshold_sigma, p.min_threshold_lsb, cap),
    )


@settings(max_examples=40, deadline=None)
@given(st.floats(0.02, 0.98), st.integers(0, 2**31 - 1), st.integers(0, 254))
def test_two_level_noise_makes_no_point_contrast_over_one_level(q, seed, low):
    # the cap's premise: pixels on levels {L, L+1} in any proportion and arrangement
    rng = np.random.default_rng(seed)
    img = (low + (rng.random((40, 40)) < q)).astype(np.float32)
    assert float(point_contrast(img, ClutterParams()).max()) <= 1.0 + CONTRAST_TOL_GREY


def test_cap_lowers_the_threshold_on_two_level_ground_to_one_level():
    rng = np.random.default_rng(7)
    img = _two_level_ground(rng).astype(np.uint8)
    assert set(np.unique(img)) == {LEVEL, LEVEL + 1}  # the premise of the scene: toggling between two levels
    p = ClutterParams()
    plain, capped = _thresholds(img, p)
    # the mean absolute deviation reads the toggling as ~0.45 grey of noise: a threshold over 2 grey
    assert float(np.median(plain)) > 2.0
    assert np.all(capped == np.float32(p.two_level_cap_lsb))
    # and no noise pixel reaches it
    c = point_contrast(img.astype(np.float32), p)
    assert point_candidates(c, np.full(c.shape, p.two_level_cap_lsb, np.float32), p) == []


def test_a_faint_target_on_two_level_ground_is_found_under_the_cap_and_nothing_else():
    u, v = 64.3, 47.6
    img = _two_level_frame_with_target(11, u, v)
    p = ClutterParams()
    c = point_contrast(img.astype(np.float32), p)
    plain, capped = _thresholds(img, p)
    i, j = int(v) // NOISE_FACTOR, int(u) // NOISE_FACTOR
    assert capped[i, j] == np.float32(p.two_level_cap_lsb)  # the target's own cells do not lift the cap
    full = (W_PX, H_PX)
    before = point_candidates(c, cv2.resize(plain, full, interpolation=cv2.INTER_LINEAR), p)
    after = point_candidates(c, cv2.resize(capped, full, interpolation=cv2.INTER_LINEAR), p)
    assert before == []
    assert len(after) == 1
    assert math.hypot(after[0].u_px - u, after[0].v_px - v) < TARGET_TOL_PX


@settings(max_examples=30, deadline=None)
@given(st.integers(29, 70), st.integers(29, 70), st.integers(0, 2**31 - 1), st.sampled_from([np.uint8, np.uint16]))
def test_two_level_cap_matches_its_definition_cell_by_cell(h, w, seed, dtype):
    # the cells' extremes by plain reshaping against the function's faster path, on frame sizes that
    # are not multiples of the cell, patches of two and of three levels
    rng = np.random.default_rng(seed)
    levels = rng.integers(1, 4, (h // 8 + 1, w // 8 + 1)).repeat(8, 0).repeat(8, 1)[:h, :w]
    img = (100 + rng.integers(0, 1_000_000, (h, w)) % levels).astype(dtype)
    f, k = NOISE_FACTOR, max(31 // NOISE_FACTOR, 1) | 1
    hc, wc = h // f, w // f
    cells = img[: hc * f, : wc * f].astype(np.int64).reshape(hc, f, wc, f)
    hi, lo = cells.max(axis=(1, 3)), cells.min(axis=(1, 3))
    padded = np.pad(lo, k // 2, mode="edge")
    lowest = np.array([[padded[i : i + k, j : j + k].min() for j in range(wc)] for i in range(hc)])
    two = np.pad((hi - lowest <= 1).astype(np.float64), k // 2, mode="edge")
    share = np.array([[two[i : i + k, j : j + k].mean() for j in range(wc)] for i in range(hc)])
    expected = np.where(share >= 0.9 - 1e-6, 1.0, np.inf)
    cap = two_level_cap(img, 31, NOISE_FACTOR, 1.0, 0.9)
    assert cap is not None and cap.shape == (hc, wc)
    assert np.array_equal(cap, expected)


@pytest.mark.parametrize(
    "what, make",
    [
        # a sensor noise spanning several levels: a real CFAR noise, no cap
        ("three levels", lambda rng: np.rint(LEVEL + rng.normal(0.0, 0.8, (H_PX, W_PX)))),
        # texture: fields a few levels apart
        (
            "texture",
            lambda rng: np.rint(LEVEL + 3.0 * (rng.random((H_PX // 8, W_PX // 8)) > 0.5)).repeat(8, 0).repeat(8, 1),
        ),
    ],
)
def test_no_cap_where_the_ground_spans_more_than_two_levels(what, make):
    img = make(np.random.default_rng(5)).astype(np.uint8)
    p = ClutterParams()
    cap = two_level_cap(img, p.noise_window_px, NOISE_FACTOR, p.two_level_cap_lsb, p.two_level_fraction)
    assert cap is not None
    assert np.isinf(cap).mean() > 0.9, what


def test_no_cap_for_a_float_frame_or_when_switched_off():
    img = _two_level_ground(np.random.default_rng(3))
    p = ClutterParams()
    assert two_level_cap(img.astype(np.float32), p.noise_window_px, NOISE_FACTOR, 1.0, 0.9) is None
    assert two_level_cap(img.astype(np.uint8), p.noise_window_px, NOISE_FACTOR, 0.0, 0.9) is None
    mono16 = two_level_cap(img.astype(np.uint16), p.noise_window_px, NOISE_FACTOR, 1.0, 0.9)
    assert mono16 is not None and np.all(mono16 == np.float32(1.0))  # an integer frame of any depth


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (
            {"two_level_cap_lsb": 0.5},
            r"^ClutterParams\.two_level_cap_lsb must be 0 \(no cap\) or >= min_threshold_lsb \(0\.8\), got 0\.5$",
        ),
        ({"two_level_cap_lsb": -1.0}, r"^ClutterParams\.two_level_cap_lsb must be 0 \(no cap\) or >= .*, got -1\.0$"),
        ({"two_level_fraction": 0.0}, r"^ClutterParams\.two_level_fraction must be in \(0, 1\], got 0\.0$"),
    ],
    ids=["cap_0.5", "cap_negative", "fraction_0"],
)
def test_clutter_params_refuse_a_cap_under_the_floor(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ClutterParams(**kwargs)


def test_detector_finds_the_faint_target_on_a_mono8_frame_only_with_the_cap():
    u, v = 40.4, 50.2
    img = _two_level_frame_with_target(13, u, v)
    K = PinholeIntrinsics(200.0, 200.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
    found = {}
    for cap_lsb in (0.0, 1.0):
        # no destriping: on a small frame two-level throughout, the column offsets measured are the
        # toggling itself (+-0.4 grey from 24 sampled rows; <= 0.13 grey on C2's rendered frames)
        det = ObjectDetector(K, ObjectParams(), ClutterParams(destripe=False, two_level_cap_lsb=cap_lsb))
        found[cap_lsb] = det.detect(img, 0)
    assert found[0.0] == []
    assert len(found[1.0]) == 1
    assert math.hypot(found[1.0][0].u_px - u, found[1.0][0].v_px - v) < TARGET_TOL_PX


DIFFERENCE_CAP_LSB = DIFFERENCE_TWO_LEVEL_CAP * ClutterParams().two_level_cap_lsb


def _ground_pair(
    seed: int, shift_px: tuple[int, int], mover: tuple[float, float] | None, amp_grey: float = TARGET_GREY
) -> tuple[np.ndarray, np.ndarray]:
    """Two frames of two-level ground 8 frames apart, the ground moved by ``shift_px`` (whole pixels: its
    quantisation toggles afresh anyway), the target at ``mover`` (current frame) and 4 px left of it
    before (it moves against the ground), as uint8."""
    rng = np.random.default_rng(seed)
    frames = []
    for k, offset in ((0, (-4.0, 0.0)), (1, (0.0, 0.0))):
        g = LEVEL + 0.5 + rng.normal(0.0, SENSOR_NOISE_GREY, (H_PX, W_PX))
        if mover is not None:
            _target(
                g,
                mover[0] + offset[0] - shift_px[0] * (1 - k),
                mover[1] + offset[1] - shift_px[1] * (1 - k),
                amp_grey,
                TARGET_SIGMA_PX,
            )
        frames.append(np.rint(g).clip(0, 255).astype(np.uint8))
    return frames[0], frames[1]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(0.05, 0.95))
@example(9993, 0.5, 0.0, 0.90625)  # a toggle cluster over the floor: found with the cap and without it
def test_two_level_frames_make_no_difference_peak_over_the_cap(seed, du, dv, q):
    # any two frames on levels {L, L+1}: whatever the registration found, no value of the difference
    # reaches the cap, so the cap adds no detection of noise: whatever it lets through, the threshold without
    # it (its own sigmas, or the floor) lets through too.  (Where the toggles are rare, q near 0 or 1, the
    # sigma is tiny and the 0.8 floor is what holds: a 2 x 2 cluster of toggles can pass it, cap or none,
    # e.g. seed 9993, du 0.5, dv 0, q 0.90625.)
    rng = np.random.default_rng(seed)
    prev = (LEVEL + (rng.random((H_PX, W_PX)) < q)).astype(np.uint8)
    cur = (LEVEL + (rng.random((H_PX, W_PX)) < q)).astype(np.uint8)
    uv = (64.0, 48.0)
    diff, moved = background_difference(cur, prev, uv, (du, dv))
    cap = two_level_difference_cap(cur, prev, uv, moved, DIFFERENCE_CAP_LSB)
    assert cap == DIFFERENCE_CAP_LSB
    assert float(np.abs(diff).max()) <= 1.0 + CONTRAST_TOL_GREY < cap
    if difference_peak(diff, uv, DIFFERENCE_GATE_PX, DIFFERENCE_SIGMA, 0.8, cap) is not None:
        assert difference_peak(diff, uv, DIFFERENCE_GATE_PX, DIFFERENCE_SIGMA, 0.8) is not None


def test_the_difference_finds_a_faint_mover_on_two_level_ground_only_with_the_cap():
    uv = (64.3, 47.6)
    # 2 grey: its 2 x 2 peak 1.58 grey on whole pixels, 5 own sigmas of the toggling 1.62
    prev, cur = _ground_pair(22, (3, 2), uv, amp_grey=2.0)
    diff, moved = background_difference(cur, prev, uv, (3.0, 2.0))
    cap = two_level_difference_cap(cur, prev, uv, moved, DIFFERENCE_CAP_LSB)
    assert cap == DIFFERENCE_CAP_LSB  # its own pixels, now and 4 px away before, do not lift it
    assert difference_peak(diff, uv, DIFFERENCE_GATE_PX, DIFFERENCE_SIGMA, 0.8) is None  # 5 own sigmas: too high
    found = difference_peak(diff, uv, DIFFERENCE_GATE_PX, DIFFERENCE_SIGMA, 0.8, cap)
    assert found is not None
    assert math.hypot(found.u_px - uv[0], found.v_px - uv[1]) < TARGET_TOL_PX


def test_no_difference_cap_on_texture_float_frames_or_switched_off():
    rng = np.random.default_rng(9)
    textured = np.rint(LEVEL + rng.normal(0.0, 0.8, (H_PX, W_PX))).astype(np.uint8)
    uv = (64.0, 48.0)
    assert two_level_difference_cap(textured, textured, uv, (0.0, 0.0), DIFFERENCE_CAP_LSB) == math.inf
    prev, cur = _ground_pair(3, (0, 0), None)
    assert two_level_difference_cap(cur, prev, uv, (0.0, 0.0), DIFFERENCE_CAP_LSB) == DIFFERENCE_CAP_LSB
    as_float = cur.astype(np.float32), prev.astype(np.float32)
    assert two_level_difference_cap(*as_float, uv, (0.0, 0.0), DIFFERENCE_CAP_LSB) == math.inf
    assert two_level_difference_cap(cur, prev, uv, (0.0, 0.0), 0.0) == math.inf
    # about the frame's edge, or where the ground was beyond it: the squares are not whole
    assert two_level_difference_cap(cur, prev, (3.0, 48.0), (0.0, 0.0), DIFFERENCE_CAP_LSB) == math.inf
    assert two_level_difference_cap(cur, prev, uv, (0.0, 45.0), DIFFERENCE_CAP_LSB) == math.inf


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_difference_takes_four_sigmas_only_near_a_held_prediction(seed):
    """A 2 x 2 peak of 4.5 of the square's own sigmas: under the 5-sigma threshold; taken with the 4-sigma one
    within ``near_px`` of the prediction (0.7 px away), not 2.5 px away, where only 5 sigmas count."""
    from onboard.imaging.clutter import MEAN_ABS_TO_SIGMA

    uv = (64.5, 48.5)
    for col, found_near in ((16, True), (18, False)):
        rng = np.random.default_rng(seed)
        diff = rng.normal(0.0, 1.0, (33, 33)).astype(np.float32)
        d2 = cv2.blur(diff, (2, 2))
        off = np.arange(33) - 16 - 0.5
        far = np.hypot(off[:, None], off[None, :]) > 4.5
        sigma = MEAN_ABS_TO_SIGMA * float(np.mean(np.abs(d2[far])))
        diff[16:18, col : col + 2] = 4.5 * sigma
        assert difference_peak(diff, uv, 3.0, 5.0, 0.0) is None
        got = difference_peak(diff, uv, 3.0, 5.0, 0.0, math.inf, 1.5, 4.0)
        if found_near:
            assert got is not None
            assert math.hypot(got.u_px - 65.0, got.v_px - 49.0) < 0.5  # the centroid of the 2 x 2 means about it
            assert got.weak  # the tracker takes it for a position, not a velocity
        else:
            assert got is None
        # over 5 sigmas it is an ordinary detection, near or not
        diff[16:18, col : col + 2] = 6.0 * sigma
        strong = difference_peak(diff, uv, 3.0, 5.0, 0.0, math.inf, 1.5, 4.0)
        assert strong is not None and not strong.weak
