"""The CFAR threshold's cap where an integer frame's ground quantises to two adjacent grey levels
(onboard.imaging.clutter.two_level_cap): the premise (noise on two levels makes no point contrast over
one level), where the cap applies and where not, and a faint target found under it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.clutter import (
    ClutterParams,
    cfar_threshold,
    local_noise_coarse,
    point_candidates,
    point_contrast,
    two_level_cap,
)
from onboard.imaging.objects_detection import NOISE_FACTOR, ObjectDetector
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
    rng = np.random.default_rng(11)
    u, v = 64.3, 47.6
    ground = LEVEL + 0.5 + rng.normal(0.0, SENSOR_NOISE_GREY, (H_PX, W_PX))
    _target(ground, u, v, TARGET_GREY, TARGET_SIGMA_PX)
    img = np.rint(ground).clip(0, 255).astype(np.uint8)
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
    "kwargs", [{"two_level_cap_lsb": 0.5}, {"two_level_cap_lsb": -1.0}, {"two_level_fraction": 0.0}]
)
def test_clutter_params_refuse_a_cap_under_the_floor(kwargs):
    with pytest.raises(ValueError):
        ClutterParams(**kwargs)


def test_detector_finds_the_faint_target_on_a_mono8_frame_only_with_the_cap():
    rng = np.random.default_rng(13)
    u, v = 40.4, 50.2
    ground = LEVEL + 0.5 + rng.normal(0.0, SENSOR_NOISE_GREY, (H_PX, W_PX))
    _target(ground, u, v, TARGET_GREY, TARGET_SIGMA_PX)
    img = np.rint(ground).clip(0, 255).astype(np.uint8)
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
