"""Detection of warm blobs with a sub-pixel, background-subtracted, intensity-weighted centroid.

Blobs (hysteresis on the pre-processed residual, see :mod:`onboard.imaging.preprocess`): every
pixel with ``r >= Th_high`` seeds, strongest first, an 8-connected component of ``r >= Th_low``
found in a window of ``max_blob_side_px`` around the seed (a component reaching the window's
edge is too large: horizon, cloud edge, ground).  Components are kept when their area, side and
aspect ratio are within :class:`ImagingParams`' limits.

Centre (on the raw frame, not the filtered or thresholded one, so neither the mean filter nor
the threshold's truncation biases it), in two stages over ``w = g - b``, the raw grey minus a
plane ``b`` through the means of a ring ``background_ring_px`` wide around the blob's box grown
by ``centroid_margin_px``:

1. plain intensity-weighted centroid over that box: ``u = sum w * (j + 0.5) / sum w`` (and v),
   plus the blob's rms radius ``sigma_obj``.  Its error grows with the box: a background error
   ``db`` pulls it towards the box centre by ``db * |box| * offset / flux``, and noise adds
   ``sigma_noise * sqrt(|box|) * rms_radius / flux`` (Auer & van Altena 1978, AJ 83, 531).
2. Gaussian-windowed centroid started there (:func:`_windowed_centroid`, SExtractor's
   XWIN_IMAGE): the window follows the estimate, so for a blob symmetric about its centre the
   fixed point is that centre whatever the constant background error, and far, noise-only pixels
   get little weight.  Measured on synthetic 640 x 512 frames (Gaussian blobs sigma 0.7-5 px,
   amplitude 30-80 grey, NETD 1 grey): 0.01-0.04 px rms, against 0.05-0.25 px for stage 1 alone.

Weights are not clipped at 0 (clipping noise at 0 biases the centre towards the window).
Pixel convention of onboard.core.frames: the centre of pixel (i, j) is (u, v) = (j + 0.5, i + 0.5).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.core.errors import InputError
from onboard.imaging.preprocess import (
    SUPPORTED_DTYPES,
    ImagingParams,
    Preprocessed,
    Region,
    check_frame,
    preprocess_frame,
    ring_plane,
)

__all__ = ["Detection", "Blob", "find_blobs", "measure_blob", "detect_targets"]

log = logging.getLogger(__name__)

MAX_SEEDS_VISITED = 64  # seeds examined per region at most (bounds the cost on a cluttered frame)
_sum, _max = np.add.reduce, np.maximum.reduce  # ndarray.sum / .max without the Python-level wrapper
_DTYPE_MAX = {t: float(np.iinfo(t).max) for t in SUPPORTED_DTYPES}  # np.iinfo is slow to build per call


@dataclass(frozen=True)
class Blob:
    """A thresholded component: ``bbox`` (x, y, w, h) whole pixels in the full frame, ``area_px``
    pixels >= Th_low, ``peak_residual`` its largest mean-filtered residual (input grey units)."""

    bbox: tuple[int, int, int, int]
    area_px: int
    peak_residual: float


@dataclass(frozen=True)
class Detection:
    """One warm blob.

    ``u_px, v_px``: sub-pixel intensity-weighted centroid (frames.py pixel convention);
    ``area_px``: pixels at or above Th_low in the mean-filtered residual;
    ``contrast``: largest raw grey minus local background in the centroid window (input units);
    ``flux``: sum of raw grey minus background over the window (input units x pixels);
    ``bbox``: (x, y, w, h) of the thresholded component, whole pixels;
    ``peak``: largest raw grey value in the window; ``snr``: contrast / the region's noise sigma
    (inf when the noise estimate is 0); ``touches_border``: the centroid window was cut by the
    image border, so the centroid may be biased; ``saturated``: the peak is the dtype's maximum.
    """

    u_px: float
    v_px: float
    area_px: int
    contrast: float
    flux: float
    bbox: tuple[int, int, int, int]
    peak: float
    snr: float
    touches_border: bool = False
    saturated: bool = False

    def __post_init__(self) -> None:
        for name in ("u_px", "v_px", "contrast", "flux", "peak"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"Detection.{name} must be finite, got {getattr(self, name)!r}")
        if self.area_px < 1:
            raise InputError(f"Detection.area_px must be >= 1, got {self.area_px}")
        if len(self.bbox) != 4 or self.bbox[2] < 1 or self.bbox[3] < 1:
            raise InputError(f"Detection.bbox must be (x, y, w, h) with w, h >= 1, got {self.bbox!r}")
        if self.flux <= 0:
            raise InputError(f"Detection.flux must be > 0, got {self.flux}")


def find_blobs(pre: Preprocessed, params: ImagingParams) -> list[Blob]:
    """Accepted hysteresis components of ``pre``, strongest seed first, at most ``max_candidates``."""
    r = pre.residual
    rh, rw = r.shape
    fh, fw = pre.frame_shape
    high = np.float32(pre.threshold_high)
    flat = r.ravel()  # a view when r is C-contiguous (preprocess_frame's residual is)
    seeds = np.flatnonzero(r >= high)
    if seeds.size == 0:
        return []
    if seeds.size > MAX_SEEDS_VISITED * 16:
        vals = flat[seeds]
        keep = np.argpartition(-vals, MAX_SEEDS_VISITED * 16 - 1)[: MAX_SEEDS_VISITED * 16]
        seeds = seeds[keep]
    seeds = seeds[np.argsort(-flat[seeds], kind="stable")]
    low = np.float32(pre.threshold_low)
    half = params.max_blob_side_px
    blobs: list[Blob] = []
    visited = 0
    window: tuple[int, int, int, int] | None = None  # the first seed sets it, and labels with it
    labels: np.ndarray = np.empty((0, 0), dtype=np.int32)
    covered: np.ndarray | None = None
    while seeds.size and visited < MAX_SEEDS_VISITED and len(blobs) < params.max_candidates:
        si, sj = divmod(int(seeds[0]), rw)
        visited += 1
        wy0, wy1 = max(si - half, 0), min(si + half + 1, rh)
        wx0, wx1 = max(sj - half, 0), min(sj + half + 1, rw)
        if window != (wy0, wy1, wx0, wx1):  # a region smaller than the window gives every seed the same one
            window = (wy0, wy1, wx0, wx1)
            mask = (r[wy0:wy1, wx0:wx1] >= low).view(np.uint8)
            _, labels = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_32S)
        lab = labels[si - wy0, sj - wx0]
        comp = labels == lab
        # drop every seed this component holds (the seeds of earlier components are gone already)
        if wy1 - wy0 == rh and wx1 - wx0 == rw:  # the window is the whole region: seeds index comp
            held = comp.ravel()[seeds]
        else:
            if covered is None:
                covered = np.zeros(r.shape, dtype=bool)
            covered[wy0:wy1, wx0:wx1] |= comp
            held = covered.ravel()[seeds]
        seeds = seeds[~held]
        comp_u8 = comp.view(np.uint8)
        cj0, ci0, bw, bh = cv2.boundingRect(comp_u8)  # of the component's pixels: exact whole pixels
        area = cv2.countNonZero(comp_u8)
        ci1, cj1 = ci0 + bh, cj0 + bw
        # a component reaching its window's edge is too large, or is cut by the region of
        # interest (then the full-frame search will see it whole); the frame's own edge is fine
        ay0, ax0 = pre.region.y0_px + wy0, pre.region.x0_px + wx0
        ay1, ax1 = pre.region.y0_px + wy1, pre.region.x0_px + wx1
        cut = (
            (ci0 == 0 and ay0 > 0)
            or (ci1 == wy1 - wy0 and ay1 < fh)
            or (cj0 == 0 and ax0 > 0)
            or (cj1 == wx1 - wx0 and ax1 < fw)
        )
        if cut or max(bw, bh) > params.max_blob_side_px:
            continue
        if not params.min_area_px <= area <= params.max_area_px:
            continue
        if max(bw, bh) > params.max_aspect_ratio * min(bw, bh):
            continue
        x0 = pre.region.x0_px + wx0 + cj0
        y0 = pre.region.y0_px + wy0 + ci0
        blobs.append(Blob((x0, y0, bw, bh), area, float(r[si, sj])))
    return blobs


def measure_blob(image: np.ndarray, blob: Blob, params: ImagingParams, noise_sigma: float) -> Detection | None:
    """Sub-pixel centre of ``blob`` on the raw ``image`` (see the module docstring); None when the
    background-subtracted flux in the window is not positive."""
    h, w = image.shape
    bx, by, bw, bh = blob.bbox
    m, ring = params.centroid_margin_px, params.background_ring_px
    wx0, wy0 = bx - m, by - m
    wx1, wy1 = bx + bw + m, by + bh + m
    touches = wx0 < 0 or wy0 < 0 or wx1 > w or wy1 > h
    wx0, wy0, wx1, wy1 = max(wx0, 0), max(wy0, 0), min(wx1, w), min(wy1, h)
    ox0, oy0 = max(wx0 - ring, 0), max(wy0 - ring, 0)
    ox1, oy1 = min(wx1 + ring, w), min(wy1 + ring, h)
    patch = image[oy0:oy1, ox0:ox1].astype(np.float64)
    ix0, iy0, ix1, iy1 = wx0 - ox0, wy0 - oy0, wx1 - ox0, wy1 - oy0
    level, gx, gy = ring_plane(patch, ix0, iy0, ix1, iy1, ring, use_median=False)
    win = patch[iy0:iy1, ix0:ix1]
    xs = np.arange(wx0, wx1, dtype=np.float64) + 0.5  # u of the window's columns
    ys = np.arange(wy0, wy1, dtype=np.float64) + 0.5  # v of the window's rows
    xc, yc = 0.5 * (wx0 + wx1), 0.5 * (wy0 + wy1)  # (u, v) of the plane's reference point
    weights = win - (level + gx * (xs[None, :] - xc) + gy * (ys[:, None] - yc))
    flux = float(_sum(weights, axis=None))
    if not flux > 0.0:
        return None
    col, row = _sum(weights, axis=0), _sum(weights, axis=1)
    u = float(_sum(col * xs) / flux)
    v = float(_sum(row * ys) / flux)
    if not (wx0 <= u <= wx1 and wy0 <= v <= wy1):
        return None
    var = 0.5 * float(_sum(col * (xs - u) ** 2) + _sum(row * (ys - v) ** 2)) / flux
    sigma_obj = math.sqrt(var) if var > 0 else 0.0
    if params.centroid_window_sigma_px > 0:
        wu, wv, wtouch = _windowed_centroid(image, u, v, sigma_obj, (level, gx, gy, xc, yc), params)
        if wu is not None and abs(wu - u) <= 0.5 * bw + m and abs(wv - v) <= 0.5 * bh + m:
            u, v, touches = wu, wv, touches or wtouch
    contrast = float(_max(weights, axis=None))
    peak = float(_max(win, axis=None))
    saturated = peak >= (_DTYPE_MAX.get(image.dtype) or float(np.iinfo(image.dtype).max))
    snr = contrast / noise_sigma if noise_sigma > 0 else math.inf
    return Detection(u, v, blob.area_px, contrast, flux, blob.bbox, peak, snr, touches, saturated)


WINDOWED_MAX_ITERATIONS = 20
WINDOWED_TOLERANCE_PX = 1e-3
WINDOWED_EXTENT_SIGMAS = 4.0  # the window is cut at 4 sigma (weight 3e-4) around the start


def _windowed_centroid(image, u0, v0, sigma_obj, plane, params):
    """Gaussian-windowed centroid (SExtractor's XWIN_IMAGE; Bertin & Arnouts 1996, A&AS 117, 393).

    Fixed point of ``c = sum W(x - c) I(x) x / sum W(x - c) I(x)`` with ``W`` a Gaussian of
    sigma ``sw = max(centroid_window_sigma_px, sigma_obj)``, iterated as
    ``c += k * (m - c)``, ``k = 1 + sigma_obj^2 / sw^2`` (exact in one step for a Gaussian blob).
    For any blob symmetric about c and a window centred on c, the first moment vanishes, so the
    fixed point is the blob's centre whatever a constant background error is; far pixels, which
    carry mostly noise, get little weight.  The weights are separable, so each iteration is
    three small matrix-vector products over one background-subtracted patch cut at
    ``WINDOWED_EXTENT_SIGMAS`` around the start.  Returns (u, v, touched_border) or
    (None, None, touched_border).
    """
    h, w = image.shape
    level, gx, gy, xc, yc = plane
    sw = max(params.centroid_window_sigma_px, sigma_obj)
    k = 1.0 + min(sigma_obj, sw) ** 2 / sw**2
    half = int(math.ceil(WINDOWED_EXTENT_SIGMAS * sw)) + 1
    j0, j1 = int(math.floor(u0)) - half, int(math.floor(u0)) + half + 1
    i0, i1 = int(math.floor(v0)) - half, int(math.floor(v0)) + half + 1
    touched = j0 < 0 or i0 < 0 or j1 > w or i1 > h
    j0, i0, j1, i1 = max(j0, 0), max(i0, 0), min(j1, w), min(i1, h)
    xs = np.arange(j0, j1, dtype=np.float64) + 0.5
    ys = np.arange(i0, i1, dtype=np.float64) + 0.5
    resid = image[i0:i1, j0:j1] - (level + gx * (xs[None, :] - xc) + gy * (ys[:, None] - yc))
    u, v = u0, v0
    inv2 = -0.5 / (sw * sw)
    for _ in range(WINDOWED_MAX_ITERATIONS):
        wx = np.exp(inv2 * (xs - u) ** 2)
        wy = np.exp(inv2 * (ys - v) ** 2)
        col = wy @ resid  # sum over rows, weighted
        s = float(col @ wx)
        if not s > 0.0:
            return None, None, touched
        mu = float(col @ (wx * xs)) / s
        mv = float((wy * ys) @ resid @ wx) / s
        du, dv = k * (mu - u), k * (mv - v)
        u, v = u + du, v + dv
        if abs(du) < WINDOWED_TOLERANCE_PX and abs(dv) < WINDOWED_TOLERANCE_PX:
            break
    return u, v, touched


def detect_targets(
    image: np.ndarray, params: ImagingParams, region: Region | None = None
) -> tuple[list[Detection], Preprocessed]:
    """All accepted detections in ``region`` (None: full frame), largest flux first, and the
    pre-processing they came from.  Raises :class:`InputError` for a frame that is not 2-D
    uint8/uint16 (see :func:`check_frame`)."""
    image = check_frame(image)
    pre = preprocess_frame(image, params, region)
    dets = [d for b in find_blobs(pre, params) if (d := measure_blob(image, b, params, pre.noise_sigma)) is not None]
    dets.sort(key=lambda d: -d.flux)
    return dets, pre
