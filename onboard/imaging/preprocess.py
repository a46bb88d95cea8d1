"""Pre-processing of one IR frame: mean filter, background removal, double threshold.

The paper (PAPER.md s.3) smooths the frame with a mean filter over a neighbourhood S,
``g_m(x, y) = (1/|S|) * sum_S g``, then applies a double threshold ``Th_low`` / ``Th_high`` that
keeps the target's grey band and suppresses the background.  Made robust here:

* Background.  A sky that varies with elevation, a horizon or a ground edge defeats one absolute
  threshold, so thresholds apply to the *residual* of a white top-hat (Serra, Image Analysis and
  Mathematical Morphology, 1982; the classic small-IR-target detector)::

      r = mean_filter(g - open_B(g)) - median(...)

  ``open_B`` is a grey opening (erosion then dilation) by a ``background_opening_px`` square.
  It removes anything narrower than the square (the target) and reproduces exactly any
  background that is a monotone function of a linear combination of x and y: a gradient sky, a
  (tilted) horizon step, a quantised staircase.  So the residual is the target plus noise; the
  opening's own noise bias (a lower envelope) is a near-constant offset removed by the median.
  Beyond the image edge the frame is replicated, so a slope rising towards the edge is
  reproduced there too.
* Thresholds relative to the noise.  ``sigma`` is the robust 1-sigma of ``r``
  (1.4826 * MAD, Hampel's estimator) and::

      Th_low  = max(threshold_low_sigma  * sigma, min_threshold_low_lsb)
      Th_high = max(threshold_high_sigma * sigma, min_threshold_high_lsb)

  The floors, in least significant bits of the input, keep a nearly noise-free frame (MAD about
  0) from detecting its own rounding.  The top-hat of noise is not quite Gaussian (the opening
  is a lower envelope that wanders with the noise): measured on 640 x 512 frames of 0.5-4 grey
  noise, the fraction of pixels above ``k * sigma`` is 3e-4 at k = 4, 8e-6 at 5, 5e-8 at 6
  (Gaussian: 3e-5, 3e-7, 1e-9) and none of 5e7 at 7, hence ``threshold_high_sigma = 7``.
* Quantisation flicker.  When the sensor noise is well below one grey step (mono8 over a wide
  temperature span: 40 mK NETD is 0.13 grey over 80 K), the background flickers between two
  neighbouring grey values: the raw top-hat is 0 or 1 step, so its mean filter never exceeds
  1 step, yet its MAD sigma is that flicker's spread (1/9 or 2/9 of a step times 1.4826 for a
  3 x 3 mean: 0.16 or 0.33, jumping from region to region) and ``7 sigma`` (2.3 steps) would
  ask a faint target for more than twice what the background can ever reach.  A region is in
  this regime when its raw top-hat reaches 2 steps on at most ``FLICKER_MAX_FRACTION`` of the
  sampled pixels (a faint target's few pixels fit within it); there ``Th_high`` is the floor
  alone, half a step above what flicker can reach.  Measured on 640 x 512 mono8 skies with
  white noise, 0.6 px blur, 4 frames each: the regime holds up to 0.27 grey of noise, where the
  background's residual reaches 1.3 steps at most; at 0.3 grey (1 % of pixels at 2 steps) the
  region is back on ``7 sigma``.  On the simulator's P1 flight this keeps the default target
  (4-6 grey of contrast, a residual peak of 1.7-2.2) tracked from 225 m to about 300 m.
* Hysteresis instead of a band.  A blob is an 8-connected set of ``r >= Th_low`` containing at
  least one pixel ``r >= Th_high`` (see :mod:`onboard.imaging.detect`).  The paper's upper cut
  would punch a hole into a saturated (hottest) target and bias its centroid, so it is not used.

All grey values are in the input's own units (0..255 for mono8, 0..65535 for mono16).
Pixel indices are ``(row i, column j)``; the frames.py pixel centre of (i, j) is (j+0.5, i+0.5).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import cv2
import numpy as np

from onboard.core.errors import InputError
from onboard.core.schema import (
    Bool,
    Integer,
    Invalid,
    Number,
    SchemaError,
    Text,
    build,
    config_dataclass,
)

__all__ = [
    "ImagingParams",
    "Region",
    "Preprocessed",
    "check_frame",
    "tophat_residual",
    "flicker_bounded",
    "ring_plane",
    "fast_median",
    "robust_sigma",
    "preprocess_frame",
    "kcf_image_u8",
]

log = logging.getLogger(__name__)

MAD_TO_SIGMA = 1.4826  # 1-sigma of a normal distribution per unit median absolute deviation
MIN_FRAME_SIDE_PX = 16
MAX_IMAGE_PX = 4096  # beyond the largest thermal imager's side: the bound of the parameters' pixel sizes
NOISE_SUBSAMPLE_FULL_FRAME = 8  # every 8th row/column for the full-frame noise estimate (~5k px)
NOISE_SUBSAMPLE_REGION = 2  # every 2nd row/column of a region of interest (~1k px)
SUPPORTED_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))
MEDIAN_SORT_MAX_ELEMENTS = 1500  # a median of up to this many elements sorts, above it partitions
FLICKER_MAX_FRACTION = 0.005  # sampled pixels whose raw top-hat reaches 2 grey steps, at most, in a flicker region


@config_dataclass
class ImagingParams:
    """Parameters of the image chain (config section ``imaging``; build it with
    :meth:`from_mapping`); lengths in pixels, grey values in the input's units.

    Pre-processing (module docstring): ``mean_kernel_px`` square mean filter; white top-hat by a
    ``background_opening_px`` square, which must be wider than the largest target (a target
    within about half of it from a brighter region is measured against that region); double
    threshold ``threshold_low_sigma`` / ``threshold_high_sigma`` times the residual's robust
    noise, floored at ``min_threshold_low_lsb`` / ``min_threshold_high_lsb``.

    Blob acceptance: ``min_area_px <= area <= max_area_px`` (pixels at or above ``Th_low`` in
    the mean-filtered residual), bounding-box side <= ``max_blob_side_px``, long/short side
    <= ``max_aspect_ratio`` (rejects ridge lines); at most ``max_candidates`` per region.

    Centre (:mod:`onboard.imaging.detect`): raw pixels minus a plane through a ring
    ``background_ring_px`` wide around the blob's box grown by ``centroid_margin_px``; plain
    centroid there, then a Gaussian-windowed centroid of sigma
    ``max(centroid_window_sigma_px, blob rms radius)``.

    Tracking (:mod:`onboard.imaging.tracker`): the KCF box side is
    ``clip(kcf_box_scale * blob side, kcf_box_px, kcf_max_box_px)`` and KCF reports a miss below
    a peak response of ``kcf_detect_threshold``; the detection region of interest is the KCF
    search patch (twice the box) grown by ``roi_margin_px``.  KCF's answer is ignored when its
    centre is farther than ``kcf_gate_px`` from the constant-velocity prediction (a jump onto
    noise); KCF is re-seeded on the blob when it missed or its centre is farther than
    ``max_drift_px`` from the centroid.  After a frame without a blob the track is ``coasting``;
    a target re-acquired within ``coast_frames`` frames and ``reacquire_gate_px`` of the
    prediction keeps its track id; after ``lost_frames`` frames without a blob it is ``lost``.

    ``chain``: ``objects`` (the default) detects against clutter and tracks every object, the primary one
    reported as the track (:class:`onboard.imaging.objects_chain.ObjectChain`; measured with ``python -m
    bench.imaging --scene``); ``single`` is the one-target chain above (:class:`onboard.imaging.TargetTracker`):
    cheaper and exact on a clear sky, but the first cloud edge, roof or hot pixel captures it.
    ``tbd`` (objects chain): search for dim points by track-before-detect while no target is held
    (:mod:`onboard.imaging.tbd`), thresholded at ``tbd_threshold_sigma`` local sigmas of the integrated
    image, over image velocities up to ``tbd_max_speed_pxpf`` px per frame per axis (the camera's rotation
    removed).  ``pose_wait_ms`` (objects chain, in the daemon): how long the chain waits for the telemetry
    that brackets its frame before it takes the camera's rotation (0: never; then it takes the newest
    samples extrapolated, or the last rotation when they are too old).  The chain registers frames with
    those rotations (track-before-detect's integration, the tracks' motion fit); an extrapolated or held
    rotation misplaces a dim target's integrated peak by about a pixel (docs/perception.md, "C4 and C5 in the loop").
    ``primary_max_off_axis_rad`` (objects chain, auto mode): no track farther off the optical axis becomes the
    primary target: a gimbal centres its target, and a confirmed fragment of terrain in a corner handed to the
    3-D estimator would be a confident wrong object; a fixed pod, whose target crosses the frame, needs it
    larger (an operator's selection is never bounded).
    """

    # upper bounds: sizes within the largest thermal imager (4096 px), counts and thresholds far beyond any use;
    # a value past them is a typo that would make the chain find nothing, refused at start rather than flown
    mean_kernel_px: Annotated[int, Integer(1, 31)] = 3
    threshold_low_sigma: Annotated[float, Number(0.0, 1000.0)] = 3.0
    threshold_high_sigma: Annotated[float, Number(0.0, 1000.0)] = 7.0
    min_threshold_low_lsb: Annotated[float, Number(0.0, 65535.0)] = 1.0
    min_threshold_high_lsb: Annotated[float, Number(0.0, 65535.0)] = 1.5
    background_opening_px: Annotated[int, Integer(3, 255)] = 21
    min_area_px: Annotated[int, Integer(1, MAX_IMAGE_PX**2)] = 2
    max_area_px: Annotated[int, Integer(1, MAX_IMAGE_PX**2)] = 1024
    max_blob_side_px: Annotated[int, Integer(3, MAX_IMAGE_PX)] = 48
    max_aspect_ratio: Annotated[float, Number(1.0, 1000.0)] = 6.0
    max_candidates: Annotated[int, Integer(1, 1000)] = 8
    centroid_margin_px: Annotated[int, Integer(0, 64)] = 1
    centroid_window_sigma_px: Annotated[float, Number(0.0, 64.0)] = 1.0
    background_ring_px: Annotated[int, Integer(1, 64)] = 3
    kcf_box_px: Annotated[int, Integer(4, 1024)] = 16
    kcf_box_scale: Annotated[float, Number(0.0, 100.0)] = 1.0
    kcf_max_box_px: Annotated[int, Integer(4, 1024)] = 32
    kcf_detect_threshold: Annotated[float, Number(0.0, 1.0, what="a number in [0, 1] (KCF peak response)")] = 0.3
    roi_margin_px: Annotated[int, Integer(0, MAX_IMAGE_PX)] = 12
    max_drift_px: Annotated[float, Number(0.0, MAX_IMAGE_PX)] = 3.0
    kcf_gate_px: Annotated[float, Number(0.0, MAX_IMAGE_PX)] = 8.0
    reacquire_gate_px: Annotated[float, Number(0.0, MAX_IMAGE_PX)] = 64.0
    coast_frames: Annotated[int, Integer(0, 100_000)] = 5
    lost_frames: Annotated[int, Integer(1, 100_000)] = 15
    chain: Annotated[Literal["single", "objects"], Text()] = "objects"
    tbd: Bool = True
    tbd_threshold_sigma: Annotated[float, Number(1.0, 1000.0)] = 6.0
    tbd_max_speed_pxpf: Annotated[float, Number(0.0, 100.0)] = 0.3
    pose_wait_ms: Annotated[float, Number(0.0, 1000.0)] = 40.0
    primary_max_off_axis_rad: Annotated[float, Number(0.0, 1.5707963267948966, lo_open=True, hi_open=True)] = 0.15

    def __post_init__(self) -> None:
        if self.mean_kernel_px % 2 != 1:
            raise Invalid("mean_kernel_px", "an odd integer (a centred neighbourhood)", self.mean_kernel_px)
        if self.background_opening_px % 2 != 1:
            raise Invalid("background_opening_px", "an odd integer (a centred square)", self.background_opening_px)
        if self.threshold_high_sigma < self.threshold_low_sigma:
            raise Invalid(
                "threshold_high_sigma",
                f"a number >= threshold_low_sigma ({self.threshold_low_sigma:g})",
                self.threshold_high_sigma,
            )
        if self.min_threshold_high_lsb < self.min_threshold_low_lsb:
            raise Invalid(
                "min_threshold_high_lsb",
                f"a number >= min_threshold_low_lsb ({self.min_threshold_low_lsb:g})",
                self.min_threshold_high_lsb,
            )
        if self.threshold_high_sigma <= 0 and self.min_threshold_high_lsb <= 0:
            raise Invalid(
                "threshold_high_sigma",
                "a number > 0 when min_threshold_high_lsb is 0 (else every pixel would seed a blob)",
                self.threshold_high_sigma,
            )
        if self.max_area_px < self.min_area_px:
            raise Invalid("max_area_px", f"an integer >= min_area_px ({self.min_area_px})", self.max_area_px)
        if self.kcf_max_box_px < self.kcf_box_px:
            raise Invalid("kcf_max_box_px", f"an integer >= kcf_box_px ({self.kcf_box_px})", self.kcf_max_box_px)
        if self.lost_frames < self.coast_frames:
            raise Invalid("lost_frames", f"an integer >= coast_frames ({self.coast_frames})", self.lost_frames)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any] | None, where: str = "imaging") -> ImagingParams:
        """Build from a config mapping (e.g. the ``imaging:`` section of onboard.yaml; None: the defaults)
        by the one config system (:func:`onboard.core.schema.build`: strict, unknown keys refused).
        Raises :class:`~onboard.core.schema.SchemaError` ``<where>: imaging.<field>: expected ..., got ...``."""
        try:
            return build(cls, mapping, "imaging")
        except SchemaError as exc:
            raise exc.as_(SchemaError, source=where) from None


@dataclass(frozen=True)
class Region:
    """A rectangle of whole pixels ``[x0_px, x1_px) x [y0_px, y1_px)`` (columns x, rows y)."""

    x0_px: int
    y0_px: int
    x1_px: int
    y1_px: int

    def __post_init__(self) -> None:
        if not (self.x1_px > self.x0_px and self.y1_px > self.y0_px):
            raise InputError(
                f"Region must be non-empty, got x [{self.x0_px}, {self.x1_px}) y [{self.y0_px}, {self.y1_px})"
            )

    @property
    def width_px(self) -> int:
        return self.x1_px - self.x0_px

    @property
    def height_px(self) -> int:
        return self.y1_px - self.y0_px

    @classmethod
    def around(cls, u_px: float, v_px: float, half_px: int, width_px: int, height_px: int) -> Region:
        """Square of side ``2 * half_px`` centred on (u, v), clipped to a width x height image."""
        cx, cy = int(math.floor(u_px)), int(math.floor(v_px))
        x0 = min(max(cx - half_px, 0), width_px - 1)
        y0 = min(max(cy - half_px, 0), height_px - 1)
        x1 = max(min(cx + half_px, width_px), x0 + 1)
        y1 = max(min(cy + half_px, height_px), y0 + 1)
        return cls(x0, y0, x1, y1)

    def union(self, other: Region) -> Region:
        return Region(
            min(self.x0_px, other.x0_px),
            min(self.y0_px, other.y0_px),
            max(self.x1_px, other.x1_px),
            max(self.y1_px, other.y1_px),
        )

    def slices(self) -> tuple[slice, slice]:
        return slice(self.y0_px, self.y1_px), slice(self.x0_px, self.x1_px)


@dataclass(frozen=True)
class Preprocessed:
    """The thresholding input of one region.

    ``residual``: float32 (height, width) mean-filtered top-hat minus its median, input grey units;
    ``region``: where it sits in the full frame; ``noise_sigma``: robust 1-sigma of the residual;
    ``threshold_low`` / ``threshold_high``: the double threshold applied to it (input grey units);
    ``frame_shape``: (height, width) of the full frame the region was cut from.
    """

    residual: np.ndarray
    region: Region
    noise_sigma: float
    threshold_low: float
    threshold_high: float
    frame_shape: tuple[int, int]


def check_frame(image: Any) -> np.ndarray:
    """Return ``image`` as a C-contiguous 2-D uint8/uint16 array, or raise :class:`InputError`.

    Accepts (H, W) and (H, W, 1); H and W must be >= 16.  The input is not modified.
    """
    if not isinstance(image, np.ndarray):
        raise InputError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype not in SUPPORTED_DTYPES:
        raise InputError(f"image.dtype must be uint8 (mono8) or uint16 (mono16), got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        raise InputError(f"image.shape must be (height, width) mono, got {image.shape}")
    if image.shape[0] < MIN_FRAME_SIDE_PX or image.shape[1] < MIN_FRAME_SIDE_PX:
        raise InputError(f"image.shape must be at least {MIN_FRAME_SIDE_PX} x {MIN_FRAME_SIDE_PX}, got {image.shape}")
    return np.ascontiguousarray(image)


_SQUARES: dict[int, np.ndarray] = {}


def tophat_residual(image: np.ndarray, region: Region, params: ImagingParams) -> np.ndarray:
    """``mean_filter(g - open_B(g))`` of ``image`` inside ``region``, float32 (region shape).

    The region is grown by the opening's reach (``background_opening_px - 1``) plus half the
    mean kernel, from the image where it exists and by replicating the image's edge beyond it,
    so the result does not depend on where the region was cut, and a background still rising
    towards the image edge (a gradient, a horizon leaving the frame) is reproduced there too.
    The top-hat is exact integer arithmetic in the input dtype.
    """
    return _tophat(image, region, params)[1]


def _tophat(image: np.ndarray, region: Region, params: ImagingParams) -> tuple[np.ndarray, np.ndarray]:
    """(raw top-hat ``g - open_B(g)`` in the input dtype, :func:`tophat_residual`) inside ``region``."""
    h, w = image.shape
    k, m = params.background_opening_px, params.mean_kernel_px
    pad = (k - 1) + m // 2
    ex0, ey0 = max(region.x0_px - pad, 0), max(region.y0_px - pad, 0)
    ex1, ey1 = min(region.x1_px + pad, w), min(region.y1_px + pad, h)
    src = image[ey0:ey1, ex0:ex1]
    top, left = pad - (region.y0_px - ey0), pad - (region.x0_px - ex0)
    bottom, right = pad - (ey1 - region.y1_px), pad - (ex1 - region.x1_px)
    if top or left or bottom or right:
        src = cv2.copyMakeBorder(src, top, bottom, left, right, cv2.BORDER_REPLICATE)
    square = _SQUARES.get(k)
    if square is None:
        square = _SQUARES.setdefault(k, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    tophat = cv2.morphologyEx(src, cv2.MORPH_TOPHAT, square)
    raw = tophat[pad : pad + region.height_px, pad : pad + region.width_px]
    if m == 1:
        return raw, raw.astype(np.float32)
    out = cv2.boxFilter(tophat, cv2.CV_32F, (m, m), normalize=True, borderType=cv2.BORDER_REPLICATE)
    return raw, out[pad : pad + region.height_px, pad : pad + region.width_px]


def flicker_bounded(raw_tophat: np.ndarray, step: int = 1) -> bool:
    """True when ``raw_tophat[::step, ::step]`` (an integer top-hat) reaches 2 grey steps on at most
    ``FLICKER_MAX_FRACTION`` of its pixels: the background is quantisation flicker, whose mean filter
    cannot exceed 1 step (module docstring)."""
    r = raw_tophat[::step, ::step] if step > 1 else raw_tophat
    return int(np.count_nonzero(r >= 2)) <= FLICKER_MAX_FRACTION * r.size


def ring_plane(values: np.ndarray, x0: int, y0: int, x1: int, y1: int, ring_px: int, use_median: bool = True):
    """Plane through a ring around the rectangle ``[x0, x1) x [y0, y1)`` of ``values`` (index coords).

    The ring is four strips ``ring_px`` wide just outside the rectangle (clipped to the array):
    left/right span the rectangle's rows, top/bottom its columns, so each strip's median (or mean)
    estimates the background at the strip's centre.  Returns ``(level, gx, gy)`` with the plane
    ``b(x, y) = level + gx * (x - xc) + gy * (y - yc)``, ``xc = (x0 + x1 - 1) / 2``,
    ``yc = (y0 + y1 - 1) / 2``; an axis with a strip on one side only gets gradient 0; no strip
    at all returns the median of ``values`` and zero gradients.  Exact for a noise-free plane.
    """
    h, w = values.shape
    stat = fast_median if use_median else _mean
    xc, yc = 0.5 * (x0 + x1 - 1), 0.5 * (y0 + y1 - 1)
    lx0, ry1 = max(x0 - ring_px, 0), min(x1 + ring_px, w)
    ty0, by1 = max(y0 - ring_px, 0), min(y1 + ring_px, h)
    left = values[y0:y1, lx0:x0] if x0 > lx0 else None
    right = values[y0:y1, x1:ry1] if ry1 > x1 else None
    top = values[ty0:y0, x0:x1] if y0 > ty0 else None
    bottom = values[y1:by1, x0:x1] if by1 > y1 else None
    level_x, gx = _ring_axis(left, right, 0.5 * (lx0 + x0 - 1), 0.5 * (x1 + ry1 - 1), xc, stat)
    level_y, gy = _ring_axis(top, bottom, 0.5 * (ty0 + y0 - 1), 0.5 * (y1 + by1 - 1), yc, stat)
    levels = [v for v in (level_x, level_y) if v is not None]
    if not levels:
        return fast_median(values), 0.0, 0.0
    return float(sum(levels) / len(levels)), gx, gy


def _ring_axis(near, far, c_near: float, c_far: float, c: float, stat) -> tuple[float | None, float]:
    """One axis of :func:`ring_plane`: the strips before (``near``, centred at ``c_near``) and after
    (``far``, at ``c_far``) the rectangle, None where clipped away.  Both: the line through their
    levels, at ``c``, and its gradient; one: its level and gradient 0; none: (None, 0)."""
    if near is not None and far is not None:
        a, b = float(stat(near)), float(stat(far))
        g = (b - a) / (c_far - c_near)
        return a + g * (c - c_near), g
    if near is not None or far is not None:
        return float(stat(near if near is not None else far)), 0.0
    return None, 0.0


def _mean(values: np.ndarray) -> float:
    """``np.mean(values)`` of a float64 array, bit for bit (np.mean's own ``np.add.reduce``, then
    the division by the count) without its Python-level wrappers, which dominate on the few
    pixels of a ring strip."""
    return float(np.add.reduce(values, axis=None)) / values.size


def fast_median(values: np.ndarray) -> float:
    """Median of all elements (np.median's result) via one sort or partition of a copy
    (:func:`_median_in_place`); far less overhead on the small arrays of a region of interest."""
    return _median_in_place(np.asarray(values).ravel().copy())


def _median_in_place(a: np.ndarray) -> float:
    """Median of a 1-D array the caller owns (it is sorted or partitioned in place); InputError when empty.

    Up to ``MEDIAN_SORT_MAX_ELEMENTS`` a full sort (numpy's vectorised, branch-free sort) puts
    the same order statistics at the middle as a partition and is faster: measured on x86-64
    with numpy 2.4 on fresh data, 784 float32 sort in 4.6 us against 5.3 us for
    ``partition(k)`` (and 10.9 us for ``partition((k - 1, k))``), about 2x less inside the
    tracker, where the selection's branches mispredict; above it a partition wins.
    """
    n = a.size
    if n == 0:
        raise InputError("median of an empty array")
    k = n // 2
    if n <= MEDIAN_SORT_MAX_ELEMENTS:
        a.sort()
    elif n % 2:
        a.partition(k)
    else:
        a.partition((k - 1, k))
    if n % 2:
        return float(a[k])
    return 0.5 * (float(a[k - 1]) + float(a[k]))


def robust_sigma(residual: np.ndarray, step: int = 1) -> tuple[float, float]:
    """(median, 1.4826 * median absolute deviation) of ``residual[::step, ::step]`` (Hampel 1974)."""
    r = residual[::step, ::step] if step > 1 else residual
    a = np.array(r, dtype=np.float32).ravel()  # a private copy: reordered and overwritten below
    med = _median_in_place(a)
    np.subtract(a, np.float32(med), out=a)  # the same values as before the reordering, so the same MAD
    np.abs(a, out=a)
    return med, float(MAD_TO_SIGMA * _median_in_place(a))


def preprocess_frame(image: np.ndarray, params: ImagingParams, region: Region | None = None) -> Preprocessed:
    """Top-hat residual, its noise and the double threshold of ``image`` (checked 2-D uint8/uint16)
    over ``region`` (None: the full frame; the noise is then estimated on every
    ``NOISE_SUBSAMPLE_FULL_FRAME``-th row and column)."""
    h, w = image.shape
    full = region is None
    if region is None:
        region = Region(0, 0, w, h)
    raw, tophat = _tophat(image, region, params)
    step = NOISE_SUBSAMPLE_FULL_FRAME if full else NOISE_SUBSAMPLE_REGION
    med, sigma = robust_sigma(tophat, step)
    residual = np.subtract(tophat, np.float32(med))  # C-contiguous (tophat is a view into a padded array)
    low = max(params.threshold_low_sigma * sigma, params.min_threshold_low_lsb)
    # flicker of one grey step inflates sigma but never reaches the floor: the floor alone seeds there
    seed_sigma = 0.0 if flicker_bounded(raw, step) else params.threshold_high_sigma * sigma
    high = max(seed_sigma, params.min_threshold_high_lsb, low)
    return Preprocessed(residual, region, sigma, float(low), float(high), (h, w))


def kcf_image_u8(pre: Preprocessed, full_scale: float, out: np.ndarray | None = None) -> np.ndarray:
    """The double-thresholded residual as the 8-bit image KCF tracks (the paper's KCF input).

    Residual below ``threshold_low`` (background) becomes 0; above, ``255 * r / full_scale``
    clipped to 255 and truncated to an integer, so a hot target is bright on black whatever the
    input depth (mono16 needs no separate display scaling).  ``full_scale`` > 0 in input grey
    units; the tracker uses 2 * Th_high at seeding, so KCF sees the blob's shape rather than its
    heat and still locks on a target fading between Th_low and Th_high.  ``out``: a uint8 array
    (or view) of the residual's shape to write into (the tracker's frame buffer), else a new one.
    """
    r = pre.residual
    gain = np.float32(255.0 / max(full_scale, 1e-6))
    scaled = np.zeros(r.shape, dtype=np.float32)
    np.multiply(r, gain, out=scaled, where=r >= np.float32(pre.threshold_low))  # below (or NaN): 0
    np.maximum(scaled, np.float32(0.0), out=scaled)  # np.clip's two comparisons, without its wrapper
    np.minimum(scaled, np.float32(255.0), out=scaled)
    if out is None:
        return scaled.astype(np.uint8)
    np.copyto(out, scaled, casting="unsafe")  # the same truncation as astype
    return out
