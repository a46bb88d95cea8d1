"""The known-signal bound of bench.imaging --bound: its resampling, and its fit on a scene whose target's grey and
size are known (the footprint it shares with the chain: tests/onboard/test_signature.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import erf

from bench.imaging_bound import (
    PSF_SIGMA_PX,
    cubic_square,
    keys_weights,
    known_signal_bound,
    point_footprint,
)
from bench.imaging_scenes import SceneRun
from onboard.core.frames import PinholeIntrinsics


@given(st.floats(0.0, 0.999))
def test_keys_weights_reproduce_a_quadratic(t):
    w = keys_weights(t)
    x = np.array([-1.0, 0.0, 1.0, 2.0])
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-5)
    assert float(w @ x) == pytest.approx(t, abs=1e-5)
    assert float(w @ x**2) == pytest.approx(t * t, abs=1e-4)


@given(st.floats(20.0, 40.0), st.floats(20.0, 40.0))
@settings(max_examples=40, deadline=None)
def test_cubic_square_samples_where_get_rect_sub_pix_does(cu, cv_):
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float32)
    img = (3.0 * xx + 0.05 * (yy - 30.0) ** 2).astype(np.float32)  # a quadratic: cubic convolution is exact on it
    got = cubic_square(img, 9, cu, cv_)
    xs = cu - 0.5 + np.arange(-4, 5)  # pixel (i, j)'s centre is index (j, i): the square's samples
    ys = cv_ - 0.5 + np.arange(-4, 5)
    want = 3.0 * xs[None, :] + 0.05 * (ys[:, None] - 30.0) ** 2
    np.testing.assert_allclose(got, want, atol=2e-3)
    whole = cubic_square(img, 9, math.floor(cu) + 0.5, math.floor(cv_) + 0.5)
    linear = cv2.getRectSubPix(img, (9, 9), (math.floor(cu), math.floor(cv_)), patchType=cv2.CV_32F)
    np.testing.assert_allclose(whole, linear, atol=1e-3)


def _blurred_edges(h: int, w: int) -> np.ndarray:
    """A background of vertical stripes 0 / 80 grey, each edge blurred as the renderer's optics and pixel box."""
    x = np.arange(w) + 0.5
    s = PSF_SIGMA_PX * math.sqrt(2.0)
    row = np.zeros(w)
    for e0 in range(10, w, 14):  # stripe [e0, e0 + 7) at 80 grey
        for e, sign in ((e0, 1.0), (e0 + 7, -1.0)):
            # the step's pixel-box integral: the mean of the blurred step over each pixel
            xs = x[:, None] + np.linspace(-0.5, 0.5, 41)[None, :]
            row += sign * 80.0 * (0.5 * (1.0 + erf((xs - e) / s))).mean(axis=1)
    return np.tile(100.0 + row, (h, 1))


def _synthetic_run(area_px2: float, grey: float, noise: float, seed: int = 0) -> SceneRun:
    """A still camera over stripes; a target of ``area_px2`` at ``grey`` crossing them at 0.7 px a frame,
    hiding the background (linear occlusion through the point footprint), Gaussian noise ``noise`` grey."""
    rng = np.random.default_rng(seed)
    h, w, n = 64, 160, 150
    bg = _blurred_edges(h, w)
    frames, labels = [], []
    for k in range(n):
        u, v = 20.3 + 0.7 * k, 31.6 + 0.05 * k
        img = bg.copy()
        i0, j0 = int(math.floor(v)), int(math.floor(u))
        f = point_footprint(u - (j0 + 0.5), v - (i0 + 0.5))
        win = (slice(i0 - 3, i0 + 4), slice(j0 - 3, j0 + 4))
        img[win] += area_px2 * f * (grey - bg[win])
        frames.append((img + rng.normal(0.0, noise, img.shape)).astype(np.float32))
        warm = grey > bg[i0, j0]
        labels.append([(0, "target", u, v, "visible", 10.0, warm)])
    K = PinholeIntrinsics(fx_px=500.0, fy_px=500.0, cx_px=w / 2, cy_px=h / 2, width_px=w, height_px=h)
    return SceneRun("synthetic", frames, labels, np.tile(np.eye(3), (n, 1, 1)), K, 30.0)


def test_the_fit_recovers_the_targets_grey_and_area_and_z_its_snr():
    run = _synthetic_run(area_px2=0.5, grey=140.0, noise=0.3)
    b = known_signal_bound(run)
    fit = b["fit"]
    assert fit.area_px2 == pytest.approx(0.5, rel=0.05)
    assert fit.grey == pytest.approx(140.0, abs=3.0)
    assert b["counted"] == 150 - 30  # the first second is not counted
    # over the stripe (180 grey) the target is colder than what it hides, over the ground warmer
    assert b["warm"]["n"] > 0 and b["cold"]["n"] > 0
    for cls in ("warm", "cold"):
        # the matched filter's z at the truth has the mean of |s| / sigma: medians within a unit of each other
        assert abs(b[cls]["z_median"] - b[cls]["snr_median"]) < 1.0
        assert b[cls]["snr_median"] > 5.0
    assert b["pd_bound"][3.0] > 95.0


def test_a_target_that_adds_nothing_is_not_found():
    # grey 0 and area 0: no signal; the fit finds no area and no frame passes z > 3 beyond the noise's share
    run = _synthetic_run(area_px2=0.0, grey=140.0, noise=0.3)
    b = known_signal_bound(run)
    assert abs(b["fit"].area_px2) < 0.05
