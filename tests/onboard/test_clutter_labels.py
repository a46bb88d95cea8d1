"""The point detector's labelling of a few thresholded pixels among themselves (onboard.imaging.clutter) against
OpenCV's labelling of the whole mask: the same components, numbered the same, so the candidates (and their order
among equal scores) do not depend on which of the two ran."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.imaging.clutter import ClutterParams, label_points, point_candidates


def _opencv_labels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    n, labels = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_32S)
    pts = cv2.findNonZero(mask).reshape(-1, 2)
    jj, ii = pts[:, 0].astype(np.intp), pts[:, 1].astype(np.intp)
    return jj, ii, labels[ii, jj], n


@settings(max_examples=200, deadline=None)
@given(
    st.integers(2, 40),
    st.integers(2, 40),
    st.floats(0.02, 0.6),
    st.integers(0, 2**31 - 1),
)
def test_label_points_numbers_components_as_opencv_does(h, w, density, seed):
    mask = (np.random.default_rng(seed).random((h, w)) < density).astype(np.uint8)
    if not mask.any():
        return
    jj, ii, ref, n = _opencv_labels(mask)
    labels, n_mine = label_points(jj, ii)
    assert n_mine == n
    np.testing.assert_array_equal(labels, ref)


def test_point_candidates_are_the_same_with_either_labelling(monkeypatch):
    """A frame with a few warm points, two of them touching (one component) and equal scores (the order
    among them is the labels'): the candidates from the sparse labelling equal OpenCV's, in order."""
    import onboard.imaging.clutter as clutter

    contrast = np.zeros((64, 80), np.float32)
    for (i, j), c in {(5, 70): 3.0, (5, 10): 3.0, (6, 11): 2.0, (40, 40): 3.0, (41, 20): 5.0}.items():
        contrast[i, j] = c
    threshold = np.ones_like(contrast)
    params = ClutterParams()
    sparse = point_candidates(contrast, threshold, params)
    monkeypatch.setattr(clutter, "SPARSE_LABEL_MAX_PX", 0)  # every mask through cv2.connectedComponents
    dense = point_candidates(contrast, threshold, params)
    assert sparse == dense
    assert [(c.bbox, c.area_px) for c in sparse] == [
        ((20, 41, 1, 1), 1),
        ((10, 5, 2, 2), 2),
        ((70, 5, 1, 1), 1),
        ((40, 40, 1, 1), 1),
    ]


@settings(max_examples=200, deadline=None)
@given(
    st.integers(3, 30),
    st.integers(3, 30),
    st.floats(0.01, 0.3),
    st.integers(0, 2**31 - 1),
    st.integers(1, 6),
    st.integers(1, 8),
)
def test_few_pixels_in_plain_python_give_numpys_candidates(h, w, density, seed, max_area, max_candidates):
    """Up to ``FEW_PX`` thresholded pixels go through plain Python: the same candidates, bit for bit and in
    order, as the array path (random masks, contrasts on a few levels so that scores tie, areas and
    counts over the limits)."""
    import onboard.imaging.clutter as clutter

    rng = np.random.default_rng(seed)
    mask = rng.random((h, w)) < density
    if not 0 < mask.sum() <= clutter.FEW_PX:
        return
    threshold = rng.choice(np.float32([0.7, 1.0, 1.3]), (h, w))
    contrast = np.where(mask, threshold * rng.choice(np.float32([1.0, 1.5, 2.25]), (h, w)), 0.0).astype(np.float32)
    params = ClutterParams(max_area_px=max_area, max_candidates=max_candidates)
    few = clutter.point_candidates(contrast, threshold, params)
    saved = clutter.FEW_PX
    clutter.FEW_PX = 0
    try:
        ref = clutter.point_candidates(contrast, threshold, params)
    finally:
        clutter.FEW_PX = saved
    assert few == ref
    assert [type(x) for c in few for x in (c.u_px, c.peak, c.score, c.area_px)] == [float, float, float, int] * len(few)
