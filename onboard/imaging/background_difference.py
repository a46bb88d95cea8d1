"""The background difference: a moving point target against textured surroundings, from two frames with
the camera's own rotation taken out.

While the gimbal slews over terrain or cloud, one frame's texture is the previous frame's moved by the
camera's rotation (:func:`rotation_shift_px`, a point at infinity's image motion); what does not move with
it is an object of its own.  :func:`background_difference` subtracts the previous frame shifted by that
motion about a point, :func:`difference_peak` finds the object's peak in it, :func:`surround_residuals`
tells an object carried with its surroundings (a fragment of terrain) from one moving across them, and
:func:`two_level_difference_cap` bounds the difference's threshold where the ground quantises to two grey
levels (as :func:`onboard.imaging.clutter.two_level_cap` does for one frame).  Pixel conventions as
:mod:`onboard.imaging.clutter`'s.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from onboard.imaging import kernels
from onboard.imaging.clutter import MEAN_ABS_TO_SIGMA, PointCandidate

__all__ = [
    "rotation_shift_px",
    "surround_residuals",
    "background_difference",
    "difference_centre",
    "difference_peak",
    "two_level_difference_cap",
    "keys_weights",
    "cubic_square",
]

SURROUND_STEP_PX = 0.5  # surround_residuals' grid of displacements


def rotation_shift_px(K, u_px: float, v_px: float, R_then: np.ndarray, R_now: np.ndarray) -> tuple[float, float] | None:
    """Where a point at infinity seen at ``(u_px, v_px)`` on an earlier frame (camera attitude ``R_then``,
    ned_from_cam) is on this one (``R_now``), minus ``(u_px, v_px)``: the image motion the camera's own
    rotation alone makes there (pinhole ``K``; px).  None when the point is now behind the camera."""
    ray = np.array([(u_px - K.cx_px) / K.fx_px, (v_px - K.cy_px) / K.fy_px, 1.0])
    c = R_now.T @ (R_then @ ray)
    if c[2] <= 1e-6:
        return None
    return K.fx_px * c[0] / c[2] + K.cx_px - u_px, K.fy_px * c[1] / c[2] + K.cy_px - v_px


def surround_residuals(
    current: np.ndarray,
    previous: np.ndarray,
    uv_px: tuple[float, float],
    displacement_px: tuple[float, float],
    half_px: int = 16,
    blank_px: int = 4,
    own_px: float = 1.0,
    alt_px: float = 3.0,
    min_pixels: int = 200,
) -> tuple[float, float]:
    """How well an object's displacement explains the motion of its surroundings: ``(own, alt)``, the
    mean absolute difference between ``current``'s ``2 half_px + 1`` square about ``uv_px`` (its
    ``2 blank_px + 1`` core, the object itself, left out) and ``previous``'s square moved by
    ``displacement_px`` (the best within ``own_px`` of it: ``own``) or by any displacement within half a
    pixel of the eight ``alt_px`` away from it (the best: ``alt``); displacements on a half-pixel grid
    (the diagonal ones 2.83 px away at 3 px), bilinear sub-pixel squares, grey.

    Surroundings carried with the object (a terrain or cloud feature: it is part of them) give ``own``
    well under ``alt``; an object moving across textured surroundings gives ``own`` no better than
    ``alt``; featureless surroundings (a clear sky) give both alike.  Both are searched: an object's
    measured displacement is off by up to a pixel (a fragment's centroid on a quantised frame moves in
    half-pixel steps), and a minimum over many bilinear squares of noise is lower than over few (the
    half-pixel ones average the noise), so a search on one side only biases the comparison.  Only
    pixels inside both frames count (``alt_px + 1`` px of margin in ``previous``); nan when fewer than
    ``min_pixels`` remain."""
    u1, v1 = uv_px
    du, dv = displacement_px
    side = 2 * half_px + 1
    c = cv2.getRectSubPix(current, (side, side), (u1 - 0.5, v1 - 0.5), patchType=cv2.CV_32F)
    ring = np.ones((side, side), bool)
    ring[half_px - blank_px : half_px + blank_px + 1, half_px - blank_px : half_px + blank_px + 1] = False
    # getRectSubPix repeats the edge's pixels outside the frame: those must not count, now or then (one
    # mask for every displacement tried: alt_px + 1 px of margin about the track's own; as much inside
    # the current frame, whose outermost rows a blur at the border smooths: on C2 the fragment leaving
    # through the bottom edge no longer matched its surroundings there)
    h, w = current.shape
    m = alt_px + 1.0
    off = np.arange(side) - half_px
    ring &= ((v1 + off >= m) & (v1 + off < h - m))[:, None] & ((u1 + off >= m) & (u1 + off < w - m))[None, :]
    ring &= ((v1 - dv + off >= m) & (v1 - dv + off < h - m))[:, None]
    ring &= ((u1 - du + off >= m) & (u1 - du + off < w - m))[None, :]
    n = int(ring.sum())
    if n < min_pixels:
        return math.nan, math.nan
    # displacements (du, dv) + (i, j) / 2: own's within own_px, alt's about the eight points alt_px away
    r_own = own_px / SURROUND_STEP_PX
    a, d = round(alt_px / SURROUND_STEP_PX), round(alt_px / math.sqrt(2) / SURROUND_STEP_PX)
    own_ij = [
        (i, j)
        for i in range(-int(r_own), int(r_own) + 1)
        for j in range(-int(r_own), int(r_own) + 1)
        if i * i + j * j <= r_own * r_own
    ]
    alt_ij = [
        (ci + x, cj + y)
        for ci, cj in ((a, 0), (-a, 0), (0, a), (0, -a), (d, d), (d, -d), (-d, d), (-d, -d))
        for x in (-1, 0, 1)
        for y in (-1, 0, 1)
    ]
    # the square moved by (du + i / 2, dv + j / 2) is previous's centred at (u1 - du - i / 2, v1 - dv - j / 2):
    # one larger bilinear square per half-pixel phase, whole-pixel slices of it
    reach = max(abs(k) for ij in own_ij + alt_ij for k in ij) // 2 + 1
    big = {
        (pi, pj): cv2.getRectSubPix(
            previous,
            (side + 2 * reach, side + 2 * reach),
            (u1 - du - pi * SURROUND_STEP_PX - 0.5, v1 - dv - pj * SURROUND_STEP_PX - 0.5),
            patchType=cv2.CV_32F,
        )
        for pi in (0, 1)
        for pj in (0, 1)
    }
    weight = ring.astype(np.float32) / np.float32(n)

    def best(ij: list[tuple[int, int]]) -> float:
        squares = np.stack(
            [
                big[i % 2, j % 2][reach - j // 2 : reach - j // 2 + side, reach - i // 2 : reach - i // 2 + side]
                for i, j in ij
            ]
        )
        return float(np.min((np.abs(squares - c) * weight).sum(axis=(1, 2))))

    return best(own_ij), best(alt_ij)


def keys_weights(t: float, a: float = -0.5) -> np.ndarray:
    """Keys' cubic convolution weights of the samples at -1, 0, 1, 2 for a point at fraction ``t`` of [0, 1)
    (``a = -0.5``: the third-order accurate kernel)."""
    x = np.array([1.0 + t, t, 1.0 - t, 2.0 - t])
    near = (a + 2.0) * x**3 - (a + 3.0) * x**2 + 1.0
    far = a * x**3 - 5.0 * a * x**2 + 8.0 * a * x - 4.0 * a
    return np.where(x <= 1.0, near, far).astype(np.float32)


def cubic_square(img: np.ndarray, side: int, cu_px: float, cv_px: float) -> np.ndarray:
    """``img``'s ``side`` x ``side`` square centred at ``(cu_px, cv_px)`` (pixel (i, j) spans [j, j + 1) x
    [i, i + 1)), resampled by Keys' cubic convolution with exact weights (cv2.remap's are quantised to 1/32 px),
    float32; edge pixels repeated outside the frame, as ``cv2.getRectSubPix`` does.  Why not bilinear: the
    optics blur a roof's edge over about a pixel, less than the pixel pitch can carry, and bilinear
    interpolation of such an edge at a sub-pixel shift is off by up to ~6 % of its step (cubic ~3 %): on C2's roofs,
    80 grey steps, that is more than the target's 2-grey signal (bench/imaging_bound.py)."""
    h = side // 2
    x0, y0 = cu_px - 0.5 - h, cv_px - 0.5 - h  # the first sample, in pixel-index coordinates
    ix, iy = math.floor(x0), math.floor(y0)
    n = side + 3
    big = cv2.getRectSubPix(img, (n, n), (ix - 1 + (n - 1) / 2, iy - 1 + (n - 1) / 2), patchType=cv2.CV_32F)
    # held within the four pixels about each sample, as a bilinear value is: the kernel's negative lobes
    # overshoot a step, and on ground quantised to two grey levels a value off {L, L + 1} would be read as
    # signal (two_level_difference_cap's premise)
    return kernels.cubic_patch(big, keys_weights(x0 - ix), keys_weights(y0 - iy))


def _parabola_vertex(a: float, b: float, c: float) -> float:
    """Offset in (-0.5, 0.5) of the minimum of the parabola through (-1, a), (0, b), (1, c)."""
    d = a - 2.0 * b + c
    return 0.0 if d <= 0 else float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))


def difference_centre(uv_px: tuple[float, float]) -> tuple[float, float]:
    """The centre of the pixel holding ``uv_px`` (frames.py convention): where a
    :func:`background_difference` square about ``uv_px`` is centred."""
    return math.floor(uv_px[0]) + 0.5, math.floor(uv_px[1]) + 0.5


def background_difference(
    current: np.ndarray,
    previous: np.ndarray,
    uv_px: tuple[float, float],
    displacement_px: tuple[float, float],
    half_px: int = 16,
    search_px: int = 6,
    blank_px: int = 4,
    refine_steps: int = 3,
) -> tuple[np.ndarray, tuple[float, float]]:
    """``current``'s ``2 half_px + 1`` square of whole pixels about the pixel holding ``uv_px`` (centred at
    :func:`difference_centre`) minus ``previous``'s registered onto it: the background's own
    displacement is searched within ``search_px`` of ``displacement_px`` (the least squared difference
    over the square with its ``2 blank_px + 1`` core left out, the object's own place; whole pixels, then
    a parabola through the neighbours), refined by up to ``refine_steps`` Gauss-Newton steps on the same
    pixels (Lucas-Kanade), and ``previous``'s square so moved is resampled by :func:`cubic_square`.  Returns (the
    difference, float32, grey; the displacement found, px).

    What stays put on the ground (or moves with it) cancels, texture and field edges included; an
    object that moved against it stands out at its current place even where its point contrast is
    negative (on a field edge, a warmer field beside it).  Why whole pixels and the refinement: a
    current square taken at the prediction's fraction of a pixel is itself interpolated, which spreads
    a 2 x 2 px target's peak over its neighbours, and the parabola's displacement is off by up to a
    tenth of a pixel, which leaves a sharp edge's gradient times that error in the difference (C2's
    roofs: at the target's truth its difference reached 5 of the square's sigmas on 48 % of seed 1's
    frames this way against 61 % with both changes, and more often on every seed measured)."""
    u, v = difference_centre(uv_px)
    side = 2 * half_px + 1
    cur = cv2.getRectSubPix(current, (side, side), (u - 0.5, v - 0.5), patchType=cv2.CV_32F)
    big = side + 2 * search_px
    region = cv2.getRectSubPix(
        previous, (big, big), (u - displacement_px[0] - 0.5, v - displacement_px[1] - 0.5), patchType=cv2.CV_32F
    )
    mask = np.full((side, side), 255, np.uint8)
    mask[half_px - blank_px : half_px + blank_px + 1, half_px - blank_px : half_px + blank_px + 1] = 0
    r = cv2.matchTemplate(region, cur, cv2.TM_SQDIFF, mask=mask)
    _, _, (x, y), _ = cv2.minMaxLoc(r)
    fx = _parabola_vertex(r[y, x - 1], r[y, x], r[y, x + 1]) if 0 < x < r.shape[1] - 1 else 0.0
    fy = _parabola_vertex(r[y - 1, x], r[y, x], r[y + 1, x]) if 0 < y < r.shape[0] - 1 else 0.0
    # region's (search_px, search_px) offset is previous's square moved by displacement_px exactly
    du = displacement_px[0] + search_px - (x + fx)
    dv = displacement_px[1] + search_px - (y + fy)
    old = cubic_square(previous, side, u - du, v - dv)
    keep = mask.astype(bool)
    du0, dv0 = du, dv
    for _ in range(refine_steps):
        # old(x - d - delta) ~ old(x - d) - grad . delta: the least squares delta over the surroundings
        gy, gx = np.gradient(old)
        ex, ey, res = gx[keep], gy[keep], (cur - old)[keep]
        a, b, c = float(ex @ ex), float(ex @ ey), float(ey @ ey)
        det = a * c - b * b
        if not det > 1e-6 * (a + c) ** 2:  # no gradient to register on (a featureless sky), or one direction only
            break
        gu, gv = float(ex @ res), float(ey @ res)
        step_u, step_v = -(c * gu - b * gv) / det, -(a * gv - b * gu) / det
        if abs(du + step_u - du0) > 0.5 or abs(dv + step_v - dv0) > 0.5:
            break  # beyond the parabola's own half-pixel: not a refinement
        du, dv = du + step_u, dv + step_v
        old = cubic_square(previous, side, u - du, v - dv)
        if abs(step_u) < 1e-3 and abs(step_v) < 1e-3:
            break
    return cur - old, (float(du), float(dv))


def two_level_difference_cap(
    current: np.ndarray,
    previous: np.ndarray,
    uv_px: tuple[float, float],
    displacement_px: tuple[float, float],
    cap_lsb: float,
    half_px: int = 8,
    min_fraction: float = 0.9,
    level: float | None = None,
) -> float:
    """The most a :func:`background_difference` square's 2 x 2 means can owe to noise where both frames'
    squares lie on two adjacent grey levels: ``cap_lsb`` levels (+inf elsewhere, for float frames or
    ``cap_lsb`` 0).  ``level``: the grey of one level (:func:`grey_level`), also for frames of whole levels
    kept as float (the detector keeps a 16-bit frame as float32; a square off whole levels is never capped);
    None: an integer frame's one count, and no cap for a float frame.  Pixels on {L, L+1} differ by at most
    one level, and so do their bilinear interpolations, :func:`cubic_square`'s (held within the four pixels about each sample) and 2 x 2 means; its own-sigma threshold there reads the toggling as noise (C2 seed 1,
    flat ground, frames 50-100: sigma 0.3-0.57 grey, 5 sigmas over the target's 1.7-2.1 grey).  Judged
    on the ``2 half_px + 1`` squares (whole pixels) about ``uv_px`` in ``current`` and about ``uv_px``
    minus ``displacement_px`` (:func:`background_difference`'s) in ``previous``, the gate's
    neighbourhood: each is two-level when at least ``min_fraction`` of its pixels lie on its two most
    common adjacent levels, so that the target's own few pixels, now and where it was, do not lift the
    cap (the 33 px square about C2 seed 1's target held a warm patch, 8 % of it, 10 px away).  Not within
    ``half_px`` of either frame's edge (C3 seed 1: a track leaving through the left edge, measured there
    once more with the cap)."""
    integer = np.issubdtype(current.dtype, np.integer) and np.issubdtype(previous.dtype, np.integer)
    if cap_lsb <= 0 or (level is None and not integer):
        return math.inf
    for img, (u, v) in ((current, uv_px), (previous, (uv_px[0] - displacement_px[0], uv_px[1] - displacement_px[1]))):
        i, j = int(math.floor(v)), int(math.floor(u))
        if not (half_px <= i < img.shape[0] - half_px and half_px <= j < img.shape[1] - half_px):
            return math.inf  # the difference there reads replicated edge pixels: no easier threshold
        sq = img[i - half_px : i + half_px + 1, j - half_px : j + half_px + 1]
        if integer and level in (None, 1.0):
            steps = (sq.ravel() - int(sq.min())).astype(np.intp)
        else:  # float32 holds a 16-bit frame's grey exactly, and the quotient of whole levels is whole
            above = (sq.ravel() - sq.min()) / np.float64(level)
            steps = above.astype(np.intp)
            if not np.array_equal(steps, above):
                return math.inf  # not on whole levels
        counts = np.bincount(steps)
        pairs = counts[:-1] + counts[1:] if counts.size > 1 else counts
        if int(pairs.max()) < min_fraction * sq.size:
            return math.inf
    return cap_lsb * (1.0 if level is None else level)


def difference_peak(
    diff: np.ndarray,
    uv_px: tuple[float, float],
    gate_px: float,
    k_sigma: float,
    floor: float,
    cap: float = math.inf,
    near_px: float = 0.0,
    near_k_sigma: float = math.inf,
) -> PointCandidate | None:
    """The strongest 2 x 2 mean of a :func:`background_difference` square (taken about ``uv_px``) within
    ``gate_px`` of ``uv_px``, if it reaches ``min(max(k_sigma * sigma, floor), cap)``, sigma the
    square's noise (1.2533 x the mean absolute 2 x 2 mean more than 4.5 px from the centre), as a
    candidate at the centroid of the positive 2 x 2 means about it (``score``: peak over that
    threshold); failing that, the strongest within ``near_px`` if it reaches ``near_k_sigma`` sigmas (the
    same floor and cap); else None.  A target on a field edge beside a warmer field has a negative point
    contrast but stands out here (C2: ~40 frames, 1.2-3.8 grey against a noise of ~0.23 grey).
    ``cap``: :func:`two_level_difference_cap`'s."""
    d2 = cv2.blur(diff, (2, 2))  # d2[i, j]: the mean of diff[i - 1 : i + 1, j - 1 : j + 1]
    h = diff.shape[0] // 2
    cu, cv_ = difference_centre(uv_px)
    off = np.arange(diff.shape[0]) - h - 0.5  # d2's centres relative to the square's centre
    dist = np.hypot(off[:, None] + (cv_ - uv_px[1]), off[None, :] + (cu - uv_px[0]))  # ... and to uv_px
    sigma = MEAN_ABS_TO_SIGMA * float(np.mean(np.abs(d2[dist > 4.5])))
    inside = np.where(dist <= gate_px, d2, -np.inf)
    i, j = np.unravel_index(int(np.argmax(inside)), inside.shape)
    peak = float(inside[i, j])
    thr = min(max(k_sigma * sigma, floor), cap)
    weak = False
    if not peak >= thr and near_px > 0.0:
        weak = True
        near = np.where(dist <= near_px, d2, -np.inf)
        i, j = np.unravel_index(int(np.argmax(near)), near.shape)
        peak = float(near[i, j])
        thr = min(max(near_k_sigma * sigma, floor), cap)
    if not peak >= thr or not 1 <= i < 2 * h or not 1 <= j < 2 * h:
        return None
    w = np.maximum(d2[i - 1 : i + 2, j - 1 : j + 2], 0.0)
    u = cu + off[j] + float((w.sum(axis=0) @ np.array([-1.0, 0.0, 1.0])) / w.sum())
    v = cv_ + off[i] + float((w.sum(axis=1) @ np.array([-1.0, 0.0, 1.0])) / w.sum())
    return PointCandidate(u, v, (int(u) - 1, int(v) - 1, 2, 2), 4, peak, peak / thr, weak)
