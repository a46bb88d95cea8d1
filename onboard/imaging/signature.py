"""A held target's occlusion signature: what it adds to the background difference wherever it is, warm or cold
against what it hides.

The background difference (:mod:`onboard.imaging.background_difference`) takes this frame minus an earlier one
registered on the target's surroundings.  Where the target now hides background of grey ``B(x)``, it adds
``A g(x) (T - B(x))``: ``g`` the image of a point (the optics' Gaussian over the pixel box, :func:`point_footprint`),
``A`` the target's apparent area (px^2), ``T`` its grey.  The chain's own test, a 2 x 2 mean over its sigmas,
sees a warm point; over a roof edge the target hides the hot roof on one side and cooler ground on the other,
its change is of both signs within two pixels and the mean cancels it.  A matched filter that signs each pixel
by ``T - B(x)`` adds both halves: with ``A`` and ``T`` known it is the most powerful test there is for that
difference.  :class:`Signature` learns ``A`` and ``T`` from the frames a track is measured on (linear least
squares in ``A T`` and ``A``; it needs backgrounds of different grey among them, which a target crossing
fields gives), :func:`signature_peak` searches a held track's gate with it.

Measured at the truth on C2 (``python -m bench.imaging --scene C2 --seed 1 5 --bound``): A 0.27-0.29 px^2 at
169-174 grey on both seeds, warm frames and cold alike; on the frames where the target is colder than the roof
it crosses the matched filter's z has a median of 4.8-4.9.  Pixel conventions as :mod:`onboard.imaging.clutter`'s;
squares as :func:`onboard.imaging.background_difference.background_difference` returns them.
"""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np
from scipy.special import erf

from onboard.imaging.clutter import PointCandidate

__all__ = ["PSF_SIGMA_PX", "point_footprint", "square_sigma", "Signature", "signature_peak"]

PSF_SIGMA_PX = 0.6  # the optics' blur the footprint assumes (groundsim's ir.blur_sigma_px, which C1-C5 keep)
WINDOW_PX = 3  # the signal's (2 WINDOW_PX + 1)^2 window about a position
AWAY_PX = 4.5  # a square's pixels this far from its centre make its noise
MIN_FRAMES = 20  # frames learned before the signature is used
# the fit's standard error on T (grey) beyond which it is not used: the test needs the signs and rough sizes of
# T - B over roofs and ground some 80 grey apart, not T to the grey (C2 seed 1, its first ~30 frames learned over
# fields 17 grey apart: A 0.19-0.23 px^2 at 180-190 grey, +-9-12 grey, beside the truth's 0.28 at 171)
MAX_GREY_SE = 15.0
MAX_FRAMES = 120  # frames kept (the last ~16 s at 30 Hz, one in four): a target's aspect, and so A, drifts
OUTLIER_CHI2 = 4.0  # a frame the first fit explains this many times worse than the median is left out


def point_footprint(du_px: float, dv_px: float, r: int = WINDOW_PX, sigma_px: float = PSF_SIGMA_PX) -> np.ndarray:
    """The image of a point of unit flux at ``(du_px, dv_px)`` from the centre of the middle pixel of a
    ``(2 r + 1)^2`` grid of whole pixels: the Gaussian optics (``sigma_px``) integrated over each pixel's
    box (sums to 1 for a point well inside the grid)."""
    k = np.arange(-r, r + 1, dtype=float)
    s = sigma_px * math.sqrt(2.0)
    ax = 0.5 * (erf((k + 0.5 - du_px) / s) - erf((k - 0.5 - du_px) / s))
    ay = 0.5 * (erf((k + 0.5 - dv_px) / s) - erf((k - 0.5 - dv_px) / s))
    return np.outer(ay, ax)


def _away(side: int) -> np.ndarray:
    """A ``side`` x ``side`` square's pixels more than ``AWAY_PX`` from its centre."""
    off = np.arange(side) - side // 2
    return np.hypot(off[:, None], off[None, :]) > AWAY_PX


def square_sigma(diff: np.ndarray) -> float:
    """The difference square's noise (grey): 1.4826 x the median absolute value of its pixels more than
    ``AWAY_PX`` from its centre (robust to the target's own earlier place, a few pixels off)."""
    return 1.4826 * float(np.median(np.abs(diff[_away(diff.shape[0])])))


def _window(centre_ij: tuple[int, int], side: int) -> tuple[slice, slice] | None:
    i0, j0 = centre_ij
    r = WINDOW_PX
    if not (r <= i0 < side - r and r <= j0 < side - r):
        return None
    return slice(i0 - r, i0 + r + 1), slice(j0 - r, j0 + r + 1)


def _at(uv_sq: tuple[float, float]) -> tuple[tuple[int, int], np.ndarray]:
    """The pixel holding a position given in square coordinates (pixel (i, j)'s centre at (j, i)) and the
    point's footprint about it."""
    j0, i0 = math.floor(uv_sq[0] + 0.5), math.floor(uv_sq[1] + 0.5)
    return (i0, j0), point_footprint(uv_sq[0] - j0, uv_sq[1] - i0)


class Signature:
    """``A`` and ``T`` of one track, from the squares of the last ``MAX_FRAMES`` frames it was measured on."""

    __slots__ = ("_rows", "frames", "_fitted")

    def __init__(self) -> None:
        # per frame: (A^T W A (2 x 2), A^T W d (2), d^T W d, pixels); ~0.1 KB each
        self._rows: deque = deque(maxlen=MAX_FRAMES)
        self.frames = 0  # frames added, all told
        self._fitted: tuple[int, tuple[float, float] | None] = (-1, None)  # (frames when fitted, the fit)

    def add(self, diff: np.ndarray, old: np.ndarray, uv_sq: tuple[float, float], sigma: float) -> None:
        """One frame: ``diff`` and ``old`` (the registered earlier square) about the track, ``uv_sq`` its
        measured place in the square's coordinates, ``sigma`` the square's noise.  Weighted by ``1 / sigma^2``."""
        ij, f = _at(uv_sq)
        win = _window(ij, diff.shape[0])
        if win is None or not sigma > 0.0:
            return
        g, fb, d = f.ravel(), (f * old[win]).ravel(), diff[win].astype(float).ravel()
        w = 1.0 / (sigma * sigma)
        # d = (A T) g - A (g B): columns g and -g B
        ata = w * np.array([[g @ g, -(g @ fb)], [-(g @ fb), fb @ fb]])
        atb = w * np.array([g @ d, -(fb @ d)])
        self._rows.append((ata, atb, w * float(d @ d), d.size))
        self.frames += 1

    def fit(self) -> tuple[float, float] | None:
        """``(A px^2, T grey)``, or None: too few frames, no area, or a ``T`` uncertain by more than ``MAX_GREY_SE``
        (backgrounds too alike to tell ``A`` from ``T`` among them); the last fit that was not, when there was one.
        Least squares over the frames kept, then again without the frames the first fit explains worst (reduced chi-square over ``OUTLIER_CHI2`` times the median: a
        centre measured off the target, a neighbour in the window), the covariance scaled by the median.  Fitted
        again only after a frame was added."""
        if self._fitted[0] != self.frames:
            # a frame that makes the fit uncertain (a high-leverage square at a roof's edge, registered worse) does
            # not throw away the signature learned before it
            self._fitted = (self.frames, self._fit() or self._fitted[1])
        return self._fitted[1]

    def _fit(self) -> tuple[float, float] | None:
        rows = list(self._rows)
        if len(rows) < MIN_FRAMES:
            return None
        x = _solve(rows)
        if x is None:
            return None
        chi2 = np.array([max(r[2] - 2.0 * float(x @ r[1]) + float(x @ r[0] @ x), 0.0) / r[3] for r in rows])
        typical = max(float(np.median(chi2)), 1.0)
        kept = [r for r, c in zip(rows, chi2) if c <= OUTLIER_CHI2 * typical]
        if len(kept) < MIN_FRAMES:
            return None
        x = _solve(kept)
        if x is None:
            return None
        p, a = float(x[0]), float(x[1])
        if not a > 0.0:
            return None
        # var(T) by the delta method on T = p / a; the weights are 1 / sigma^2, scaled by the typical frame's
        # reduced chi-square where the model explains the squares worse than their noise
        cov = np.linalg.inv(sum(r[0] for r in kept)) * typical
        jac = np.array([1.0 / a, -p / (a * a)])
        if not float(jac @ cov @ jac) <= MAX_GREY_SE**2:
            return None
        return a, p / a


def _solve(rows) -> np.ndarray | None:
    ata = sum(r[0] for r in rows)
    if not float(np.linalg.det(ata)) > 1e-12 * float(np.trace(ata)) ** 2:
        return None
    return np.linalg.solve(ata, sum(r[1] for r in rows))


def _filter_map(diff: np.ndarray, old: np.ndarray, grey: float) -> np.ndarray:
    """The matched filter's output ``d' . s' / |s'|`` (grey) for a target centred on each whole pixel of the
    square, ``s = g (T - B)`` (:func:`point_footprint` at a pixel's centre), ``'`` the window's part that the
    background's own gradients do not explain: a registration off by a hundredth of a pixel leaves ``-grad B . delta``
    along every sharp edge, a residual of one sign across the edge that a filter signed by ``T - B`` (opposite
    signs across it) would partly take for the target; its two directions are projected out of both the
    difference and the signal in each window (least squares, unweighted), so only what they cannot make counts."""
    f = point_footprint(0.0, 0.0).astype(np.float32)
    box = np.ones_like(f)
    d, b = diff.astype(np.float32), old.astype(np.float32)
    gy, gx = (np.asarray(g, dtype=np.float32) for g in np.gradient(b))

    def corr(img: np.ndarray, k: np.ndarray) -> np.ndarray:
        return cv2.filter2D(img, cv2.CV_32F, k, borderType=cv2.BORDER_REPLICATE).astype(np.float64)

    tb: np.ndarray = np.float32(grey) - b  # T - B
    ds = corr(d * tb, f)  # d . s
    ss = corr(tb * tb, f * f)  # s . s
    # G = [gx, gy] over the window: G'G, G'd, G's
    gxx, gxy, gyy = corr(gx * gx, box), corr(gx * gy, box), corr(gy * gy, box)
    gxd, gyd = corr(gx * d, box), corr(gy * d, box)
    gxs, gys = corr(gx * tb, f), corr(gy * tb, f)
    det = gxx * gyy - gxy * gxy
    ok = det > 1e-6 * (gxx + gyy) ** 2 + 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    # (G'd)' (G'G)^-1 (G's) and (G's)' (G'G)^-1 (G's), with the 2 x 2 inverse written out; a window without two
    # independent gradient directions (a flat field, a straight edge's one) projects out what it has
    ds_p = np.where(ok, ds - inv * (gxd * (gyy * gxs - gxy * gys) + gyd * (gxx * gys - gxy * gxs)), ds)
    ss_p = np.where(ok, ss - inv * (gxs * (gyy * gxs - gxy * gys) + gys * (gxx * gys - gxy * gxs)), ss)
    # one direction only (a straight edge along a pixel axis): project along the larger
    one = ~ok & (gxx + gyy > 1e-12)
    if one.any():
        along_x = gxx >= gyy
        gg = np.maximum(np.where(along_x, gxx, gyy), 1e-12)
        gd, gs = np.where(along_x, gxd, gyd), np.where(along_x, gxs, gys)
        ds_p = np.where(one, ds - gd * gs / gg, ds_p)
        ss_p = np.where(one, ss - gs * gs / gg, ss_p)
    return ds_p / np.sqrt(np.maximum(ss_p, 1e-12))


def _vertex(a: float, b: float, c: float) -> float:
    """Offset in [-0.5, 0.5] of the maximum of the parabola through (-1, a), (0, b), (1, c)."""
    d = a - 2.0 * b + c
    return 0.0 if not d < 0.0 else float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))


def signature_peak(
    diff: np.ndarray,
    old: np.ndarray,
    uv_sq: tuple[float, float],
    gate_px: float,
    signature: tuple[float, float],
    z_min: float,
    origin_px: tuple[float, float],
) -> tuple[PointCandidate, float] | None:
    """The best whole pixel within ``gate_px`` of ``uv_sq`` (square coordinates) by the matched filter of
    :func:`_filter_map` (``s = A g (T - B)``, ``signature`` = (A, T); ``A`` only scales it), in robust spreads
    (1.4826 x the median absolute deviation) of the same filter over the square's pixels more than ``AWAY_PX``
    from its centre, from their median: a CFAR on the filter's own output, whatever the noise and the edges'
    residuals there.  If that ``z`` reaches ``z_min``: a weak candidate at the vertex of the parabolas through
    ``z`` at the pixel and its neighbours along each axis (image pixels: square coordinates plus ``origin_px``, the image position of the square's
    pixel (0, 0) centre), and its ``z``; else None."""
    _, grey = signature
    zmap = _filter_map(diff, old, grey)
    side = diff.shape[0]
    inner = np.zeros((side, side), bool)
    inner[WINDOW_PX:-WINDOW_PX, WINDOW_PX:-WINDOW_PX] = True
    vals = zmap[inner & _away(side)]
    med = float(np.median(vals))
    spread = 1.4826 * float(np.median(np.abs(vals - med)))
    if not spread > 0.0:
        return None
    z = (zmap - med) / spread
    jj, ii = np.meshgrid(np.arange(side), np.arange(side))
    gate = inner & (np.hypot(jj - uv_sq[0], ii - uv_sq[1]) <= gate_px)
    if not gate.any():
        return None
    zg = np.where(gate, z, -np.inf)
    i, j = np.unravel_index(int(np.argmax(zg)), zg.shape)
    best = float(zg[i, j])
    if not best >= z_min:
        return None
    # the vertex of the parabola through the peak and its two neighbours, along each axis
    pu = j + _vertex(float(z[i, j - 1]), best, float(z[i, j + 1]))
    pv = i + _vertex(float(z[i - 1, j]), best, float(z[i + 1, j]))
    u, v = pu + origin_px[0], pv + origin_px[1]
    return PointCandidate(u, v, (int(u) - 1, int(v) - 1, 2, 2), 4, best * spread, best / z_min, True), best
