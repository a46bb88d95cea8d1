"""Point-target detection against clutter: fixed-pattern clean-up, directional local contrast, CFAR.

Pure functions over one frame (plus a small per-pixel state for the defect map); grey values in the
input's units, pixel indices ``(row i, column j)``, the frames.py pixel centre of (i, j) is
``(j + 0.5, i + 0.5)``.

1. **Column stripes** (:func:`column_offsets`): an uncooled core's columns carry offsets that drift
   slowly; each column's offset is the median over (sub-sampled) rows of the frame minus its
   horizontal running mean, which a scene's own structure averages out of but a stripe does not.
   Subtracted before anything else, so a stripe never reaches the threshold.
2. **Dead and hot pixels** (:class:`DefectMap`): a pixel that is an isolated outlier against all eight
   neighbours on most of the recent frames while the scene moves is a defect (a target covers at least
   two pixels after the optics' blur, so it is never a one-pixel outlier); defects are replaced by their
   neighbours' median.
3. **Background suppression** (:func:`local_contrast`): the minimum over eight directions of the centre
   cell's mean minus the mean of a cell ``guard_px`` away in that direction (a multi-directional
   local-contrast measure; Wei, You & Li, Pattern Recognition 58 (2016) 216, "MPCM").  A point target
   is warmer than its surround in every direction, so all eight differences are positive; a cloud
   edge, the horizon or a terrain boundary is warmer than its surround on one side only, and a road
   along its length, so the minimum is <= 0 there; a smooth gradient cancels between opposite cells.
4. **CFAR threshold** (:func:`cfar_threshold`): the local noise is the mean absolute deviation of the
   frame about its 3 x 3 mean over a ``noise_window_px`` square (x 1.25: a normal's sigma per unit of
   mean absolute deviation), so textured cloud or terrain raises the threshold where it is and the
   false-alarm rate stays near constant across the frame (cell-averaging CFAR; Rohling 1983, IEEE
   TAES 19, 608).  The threshold takes the window's median deviation where that is lower, down to
   ``median_noise_floor`` of the mean (:func:`median_window_noise`; an order-statistic CFAR, Rohling's
   OS-CFAR in the same paper): a cloud edge or a roof in a few of the window's cells lifts the mean but
   not the median, and a bird over the clear sky beside it stays over its threshold (the searches that
   lower the threshold by a track's prior keep the mean's).  Until the tracker's first primary, where the
   gimbal points, the threshold's noise is at most that of the window's quietest ``quiet_block_px`` square
   (:func:`quietest_block_noise`): a roof or a warmer field filling part of the window lifts the window's
   mean deviation (C2 seed 1: 3.5-4.1 grey thresholds over the fields its target crosses at 1-2 grey) but
   not that of the ground beside it.  Floored at ``min_threshold_lsb`` levels (8-bit quantisation leaves a
   flat sky noiseless).  Capped at ``two_level_cap_lsb`` levels where the ground quantises to two adjacent
   grey levels (:func:`two_level_cap`): a sensor noise well under one level that straddles a level boundary
   toggles pixels between the two, which the mean absolute deviation reads as ~0.45 grey of noise
   (a 2.5 grey threshold), yet no contrast of pixels on two levels exceeds one level.  A level is the
   frame's own quantisation step (:func:`grey_level`): one grey of an 8-bit frame, 257 of an 8-bit frame
   widened to 16 bits, so the two are thresholded alike.
5. **Flat-field events** (:func:`frame_event`): a frame identical to the previous one is frozen (the
   shutter is closed: no measurement on it); a jump of the frame's median by more than
   ``step_lsb`` is an offset step (the defect and stripe statistics restart).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.imaging import kernels

__all__ = [
    "ClutterParams",
    "PointCandidate",
    "Scratch",
    "TRANSIENT_A",
    "TRANSIENT_B",
    "column_offsets",
    "remove_column_offsets",
    "isolated_outliers",
    "DefectMap",
    "local_contrast",
    "point_contrast",
    "local_noise",
    "local_noise_coarse",
    "noise_cells",
    "noise_window_cells",
    "window_noise",
    "median_window_noise",
    "MEDIAN_CELLS",
    "quietest_block_noise",
    "cfar_threshold",
    "GREY16_PER_GREY8",
    "grey_level",
    "two_level_cap",
    "point_candidates",
    "label_points",
    "frame_event",
]

GREY16_PER_GREY8 = 257.0  # 65535 / 255: one 8-bit grey level widened to 16-bit full scale
GREY_LEVEL_SAMPLE = 8  # grey_level reads every this many rows and columns first
MEAN_ABS_TO_SIGMA = math.sqrt(math.pi / 2)  # 1.2533: a normal's sigma per unit of mean absolute deviation
SPARSE_LABEL_MAX_PX = 256  # up to this many thresholded pixels are labelled among themselves
FEW_PX = 64  # up to this many in plain Python: numpy's ~25 calls cost more (C3, 24-48 px: 0.21 against 0.15 ms)
TRANSIENT_A, TRANSIENT_B = "transient_a", "transient_b"  # Scratch names of intermediates no function returns
_RINGS: dict[int, np.ndarray] = {}  # guard_px -> the dilation kernel of the eight surround cells
_DIRECTIONS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


@dataclass(frozen=True)
class ClutterParams:
    """Knobs of the clutter-robust detector (lengths in pixels, grey in the input's units, but the ``_lsb`` ones:
    ``min_threshold_lsb`` and ``two_level_cap_lsb`` in levels of the frame's quantisation, :func:`grey_level`;
    ``step_lsb`` in 8-bit grey).

    ``cell_px``: side of the centre and surround cells of the local contrast (odd); ``guard_px``:
    centre-to-surround distance (a target up to about ``2 * guard_px - cell_px`` wide is kept whole);
    ``sharp_guard_px``: the distance of the second, one-pixel surround that a point must also beat
    (0: none);
    ``noise_window_px``: side of the CFAR noise window (odd); ``threshold_sigma``: the local
    contrast's threshold in local noise sigmas; ``min_threshold_lsb``: its floor; ``max_area_px``: a
    larger component is not point-like; ``max_candidates``: strongest kept per frame; ``destripe``:
    remove column offsets; ``stripe_window_px``: the horizontal running mean they are measured
    against (odd); ``defect_outlier_sigma``, ``defect_fraction``, ``defect_frames``: a pixel more than
    that many sigmas above or below all its neighbours on that fraction of ``defect_frames`` frames
    is a defect; ``step_lsb``: a frame median jump that is an offset step; ``two_level_cap_lsb``: the
    threshold's cap where an integer frame's noise window lies on two adjacent levels (0: no cap),
    ``two_level_fraction``: the least fraction of the window's cells that must (:func:`two_level_cap`);
    ``quiet_block_px``: until the first primary, the CFAR threshold's noise near the optical axis is at most that
    of the quietest square of this side within the noise window (:func:`quietest_block_noise`; 0: the
    window's mean everywhere; where and when: ``ObjectDetector``'s rule); ``median_noise_floor``: the CFAR
    threshold's noise is the window's median (:func:`median_window_noise`) where that is under its mean, but
    at least this fraction of the mean (1: the mean alone).
    """

    cell_px: int = 3
    guard_px: int = 4
    noise_window_px: int = 31
    sharp_guard_px: int = 2
    threshold_sigma: float = 5.5
    min_threshold_lsb: float = 0.8
    max_area_px: int = 64
    max_candidates: int = 32
    destripe: bool = True
    stripe_window_px: int = 15
    defect_outlier_sigma: float = 4.0
    defect_fraction: float = 0.6
    defect_frames: int = 30
    step_lsb: float = 3.0
    two_level_cap_lsb: float = 1.0
    two_level_fraction: float = 0.9
    quiet_block_px: int = 12
    median_noise_floor: float = 0.5

    def __post_init__(self) -> None:
        for name in ("cell_px", "noise_window_px", "stripe_window_px"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1 and v % 2 == 1):
                raise ValueError(f"ClutterParams.{name} must be an odd integer >= 1, got {v!r}")
        if self.guard_px < 1:
            raise ValueError(f"ClutterParams.guard_px must be >= 1, got {self.guard_px!r}")
        if not self.threshold_sigma > 0:
            raise ValueError(f"ClutterParams.threshold_sigma must be > 0, got {self.threshold_sigma!r}")
        if not 0 < self.defect_fraction <= 1:
            raise ValueError(f"ClutterParams.defect_fraction must be in (0, 1], got {self.defect_fraction!r}")
        if not (self.two_level_cap_lsb == 0 or self.two_level_cap_lsb >= self.min_threshold_lsb):
            raise ValueError(
                "ClutterParams.two_level_cap_lsb must be 0 (no cap) or >= min_threshold_lsb "
                f"({self.min_threshold_lsb!r}), got {self.two_level_cap_lsb!r}"
            )
        if not 0 < self.median_noise_floor <= 1:
            raise ValueError(f"ClutterParams.median_noise_floor must be in (0, 1], got {self.median_noise_floor!r}")
        if not (self.quiet_block_px == 0 or 1 <= self.quiet_block_px < self.noise_window_px):
            raise ValueError(
                "ClutterParams.quiet_block_px must be 0 (the window's mean) or in [1, noise_window_px "
                f"({self.noise_window_px!r})), got {self.quiet_block_px!r}"
            )
        if not 0 < self.two_level_fraction <= 1:
            raise ValueError(f"ClutterParams.two_level_fraction must be in (0, 1], got {self.two_level_fraction!r}")

    @property
    def reach_px(self) -> int:
        """How far from a pixel its point contrast reads (the surround cells' far side): the band along the frame's
        edges where :func:`point_contrast` measures none, and the margin a crop needs about a pixel it measures."""
        return self.guard_px + self.cell_px // 2


class Scratch:
    """Arrays kept from one frame to the next, by name: a function given one writes its full-frame
    intermediates and its result there instead of into fresh arrays.  A fresh 640 x 512 float32 array
    (1.3 MB) is above the allocator's threshold for memory it returns to the system when freed, and
    the next frame's faults it back in page by page: on the same frames the chain took 0 or ~930 page
    faults a frame depending on where earlier arrays happened to lie, 3.9 against 7.1 CPU ms.  A result
    written into one is valid until the next call that writes the same name.  The intermediates no
    function returns share the names :data:`TRANSIENT_A` and :data:`TRANSIENT_B`: fewer distinct arrays a
    frame, fewer of them evicted from the caches by the time they are read again."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray:
        """The array ``name`` of that shape and dtype (uninitialised when new or reshaped)."""
        a = self._arrays.get(name)
        if a is None or a.shape != tuple(shape) or a.dtype != dtype:
            a = self._arrays[name] = np.empty(shape, dtype)
        return a


def _dst(scratch: Scratch | None, name: str, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray | None:
    """``scratch``'s array ``name`` as an OpenCV ``dst`` (None: OpenCV allocates a new one)."""
    return None if scratch is None else scratch.get(name, shape, dtype)


@dataclass(frozen=True)
class PointCandidate:
    """One point-like component of the thresholded local contrast: ``u_px, v_px`` its contrast-weighted
    centre (frames.py convention), ``bbox`` (x, y, w, h) whole pixels, ``area_px``, ``peak`` the largest
    local contrast (grey), ``score`` peak over the local threshold (>= 1); ``weak``: a background difference
    taken only at the lower threshold near a held prediction (:func:`onboard.imaging.background_difference.difference_peak`'s ``near_k_sigma``)."""

    u_px: float
    v_px: float
    bbox: tuple[int, int, int, int]
    area_px: int
    peak: float
    score: float
    weak: bool = False


def column_offsets(image: np.ndarray, window_px: int = 15, row_step: int = 4) -> np.ndarray:
    """Per-column offset (float32, shape (W,)): median over every ``row_step``-th row of the frame
    minus its ``1 x window_px`` horizontal running mean, minus the median of those (a zero-mean set)."""
    rows = np.asarray(image[::row_step], dtype=np.float32)
    hmean = cv2.blur(rows, (window_px, 1), borderType=cv2.BORDER_REFLECT)
    # np.median(rows - hmean, axis=0), from each column's sorted values (a frame's grey is never nan): a
    # partition down the strided columns cost ~3x the sort of the transposed copy (1.3 against 0.4 ms)
    cols = np.ascontiguousarray((rows - hmean).T)
    cols.sort(axis=1)
    n = cols.shape[1]
    off = cols[:, n // 2].copy() if n % 2 else (cols[:, n // 2 - 1] + cols[:, n // 2]) / 2
    off = off.astype(np.float32)
    off -= np.float32(np.median(off))
    return off


def remove_column_offsets(image: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``image`` as float32 minus each column's offset (a new array)."""
    return np.asarray(image, dtype=np.float32) - offsets[None, :]


_RING3 = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.uint8)  # the eight neighbours


def isolated_outliers(image: np.ndarray, sigma: float, scratch: Scratch | None = None) -> np.ndarray:
    """Bool mask of pixels more than ``sigma`` above the largest, or below the smallest, of their eight
    neighbours (a one-pixel spike or hole).  ``scratch``: the arrays to work in (the mask is one)."""
    img = np.asarray(image, dtype=np.float32)
    nmax = cv2.dilate(img, _RING3, dst=_dst(scratch, TRANSIENT_A, img.shape), borderType=cv2.BORDER_REPLICATE)
    nmin = cv2.erode(img, _RING3, dst=_dst(scratch, TRANSIENT_B, img.shape), borderType=cv2.BORDER_REPLICATE)
    # numpy's float32 arithmetic as ``img > nmax + sigma`` does it (sigma rounded to float32 first), in place
    s = np.float32(sigma)
    above = np.greater(img, np.add(nmax, s, out=nmax), out=_dst(scratch, "outlier_above", img.shape, np.bool_))
    below = np.less(img, np.subtract(nmin, s, out=nmin), out=_dst(scratch, "outlier_below", img.shape, np.bool_))
    return np.logical_or(above, below, out=above)


class DefectMap:
    """Dead and hot pixels from temporal statistics (see the module docstring).

    ``update(image, sigma)`` counts the frame's isolated outliers; ``mask`` is True at pixels that were
    outliers on at least ``fraction`` of the last ``frames`` frames (counts decay geometrically, so a
    pixel that recovers leaves the map); ``repair(image)`` returns a float32 copy with the defects
    replaced by their 3 x 3 median.  ``reset()`` after an offset step.  ``scratch``: the arrays to work
    in (a detector's own, so that its frame's intermediates and the update's are the same arrays)."""

    def __init__(
        self, shape: tuple[int, int], frames: int = 30, fraction: float = 0.6, scratch: Scratch | None = None
    ) -> None:
        self._decay = np.float32(1.0 - 1.0 / frames)
        self._rate = np.zeros(shape, np.float32)  # decayed fraction of frames as an outlier
        self._fraction = np.float32(fraction)
        self._seen = 0
        self.mask = np.zeros(shape, bool)
        self._where = np.nonzero(self.mask)
        self._scratch = Scratch() if scratch is None else scratch

    def reset(self) -> None:
        self._rate[:] = 0
        self._seen = 0
        self.mask[:] = False
        self._where = np.nonzero(self.mask)

    def update(self, image: np.ndarray, sigma: float) -> None:
        self._seen += 1
        gain = np.float32(1.0) - self._decay
        # from the first frame on: repairing a pixel that was an outlier once costs nothing (a target
        # covers several pixels, never an isolated one), and a hot pixel is repaired before it is tracked
        level = self._fraction * np.float32(1.0 - self._decay**self._seen)
        img = np.asarray(image)
        # the outliers, the rates and the map in one compiled pass (the numpy and OpenCV formulation below
        # made eleven passes over the frame, the eight-neighbour dilation and erosion most of them), bit for bit
        if not kernels.defect_rate(img, np.float32(sigma), self._decay, gain, level, self._rate, self.mask):
            out = isolated_outliers(image, sigma, self._scratch)
            self._rate *= self._decay
            np.add(self._rate, gain, out=self._rate, where=out)  # rate[out] += ..., no gather
            np.greater_equal(self._rate, level, out=self.mask)
        # repair() runs every frame, the map changes only here; OpenCV's scan of the mask costs ~1/40 of
        # numpy's nonzero (0.6 ms on a 640 x 512 frame), in the same row-major order
        pts = cv2.findNonZero(self.mask.view(np.uint8))
        if pts is None:
            self._where = (np.zeros(0, np.intp), np.zeros(0, np.intp))
        else:
            pts = pts.reshape(-1, 2)
            self._where = (pts[:, 1].astype(np.intp), pts[:, 0].astype(np.intp))

    def repair(self, image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``image`` (float32) with the defects replaced, written to ``out`` (``image`` itself may be
        given: the medians are gathered before any pixel is written); a copy when None and there are
        defects, ``image`` itself when there are none."""
        img = np.asarray(image, dtype=np.float32)
        ii, jj = self._where
        if ii.size == 0:
            if out is None or out is img:
                return img
            np.copyto(out, img)
            return out
        # the 3 x 3 median at the few defects only (a whole-frame median filter costs ~0.3 ms a frame)
        h, w = img.shape
        di, dj = np.mgrid[-1:2, -1:2]
        ni = np.clip(ii[:, None] + di.ravel()[None, :], 0, h - 1)
        nj = np.clip(jj[:, None] + dj.ravel()[None, :], 0, w - 1)
        medians = np.median(img[ni, nj], axis=1)
        if out is None:
            out = img.copy()
        elif out is not img:
            np.copyto(out, img)
        out[ii, jj] = medians
        return out


def _centre(
    img: np.ndarray, centre_px: int, dst: np.ndarray | None = None, mean_dst: np.ndarray | None = None
) -> np.ndarray:
    """The largest ``centre_px`` box mean covering each pixel: ``mc(i, j)`` is the mean of the square
    starting at (i, j), dilated over the squares holding (i, j) (anchors chosen so that no half-pixel
    shift creeps in).  ``dst``, ``mean_dst``: where to write it and ``mc`` (None: new arrays)."""
    if centre_px == 1:
        return img
    mc = cv2.blur(img, (centre_px, centre_px), dst=mean_dst, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
    a = centre_px - 1
    kernel = np.ones((centre_px, centre_px), np.uint8)
    return cv2.dilate(mc, kernel, dst=dst, anchor=(a, a), borderType=cv2.BORDER_REPLICATE)


def _surround_max(
    img: np.ndarray, cell_px: int, guard_px: int, box_mean: np.ndarray | None = None, dst: np.ndarray | None = None
) -> np.ndarray:
    """The largest of the eight ``cell_px`` box means ``guard_px`` away, in one dilation by a kernel
    holding the eight offsets (``box_mean``: those box means, when already computed; ``dst``: where to
    write the result, None: a new array)."""
    if box_mean is not None:
        m = box_mean
    else:
        m = img if cell_px == 1 else cv2.blur(img, (cell_px, cell_px), borderType=cv2.BORDER_REPLICATE)
    kernel = _RINGS.get(guard_px)
    if kernel is None:
        kernel = np.zeros((2 * guard_px + 1, 2 * guard_px + 1), np.uint8)
        for di, dj in _DIRECTIONS:
            kernel[guard_px + di * guard_px, guard_px + dj * guard_px] = 1
        kernel = _RINGS.setdefault(guard_px, kernel)
    return cv2.dilate(m, kernel, dst=dst, borderType=cv2.BORDER_REPLICATE)


def local_contrast(image: np.ndarray, cell_px: int = 3, guard_px: int = 4, centre_px: int = 2) -> np.ndarray:
    """Multi-directional local contrast (float32, image shape): ``min_d (c(x) - m(x + guard_px * d))``
    over the eight directions ``d``, ``m`` the ``cell_px`` box mean, ``c`` the largest ``centre_px``
    box mean covering x (a 2 x 2 target is not diluted by a 3 x 3 mean); frame edges replicated."""
    img = np.asarray(image, dtype=np.float32)
    return cv2.subtract(_centre(img, centre_px), _surround_max(img, cell_px, guard_px))


def point_contrast(
    image: np.ndarray, params: ClutterParams, box_mean: np.ndarray | None = None, scratch: Scratch | None = None
) -> np.ndarray:
    """The smaller of two local contrasts: ``cell_px`` cells ``guard_px`` away, and single pixels
    ``sharp_guard_px`` away.  A protrusion of a cloud edge a few pixels wide beats a surround 4 px away
    but not one 2 px away, which lies inside it; a blurred 2 x 2 target beats both.  Measured on the
    reference scenes' frames (threshold 5 sigma): C1's candidates per frame fall from ~100 (guard 4
    alone) to ~7, the target still detected on every frame.  ``box_mean``: the image's ``cell_px``
    box mean (edges replicated), when the caller has it already (the noise estimate uses the 3 x 3 one).
    ``scratch``: the arrays to work in (the result is its ``contrast``)."""
    img = np.asarray(image, dtype=np.float32)
    surround = _surround_max(img, params.cell_px, params.guard_px, box_mean, _dst(scratch, "contrast", img.shape))
    spare = None
    if params.sharp_guard_px > 0:  # min over both contrasts = the centre minus the larger surround
        spare = _surround_max(img, 1, params.sharp_guard_px, dst=_dst(scratch, TRANSIENT_B, img.shape))
        cv2.max(surround, spare, dst=surround)
    # the sharp surround's array, done with, takes the centre (one full-size array less)
    if spare is None:
        spare = _dst(scratch, TRANSIENT_B, img.shape)
    centre = _centre(img, 2, spare, _dst(scratch, TRANSIENT_A, img.shape))
    contrast = cv2.subtract(centre, surround, dst=surround)  # in place: one full-size array less
    # where the surround cells reach beyond the frame they read the edge's own pixels (replicated), and the part
    # of a roof or a cloud the frame's edge cuts off looks like a point: no contrast is measured there (under the
    # median threshold, C2 seeds 3 and 5: a track 0-1 px from the right edge, confirmed for 10-32 frames)
    b = min(params.reach_px, *contrast.shape)
    contrast[:b] = 0.0
    contrast[-b:] = 0.0
    contrast[:, :b] = 0.0
    contrast[:, -b:] = 0.0
    return contrast


def local_noise(image: np.ndarray, window_px: int = 31) -> np.ndarray:
    """Local noise sigma (float32, image shape): 1.2533 x the ``window_px`` box mean of
    ``|g - mean3x3(g)|`` (see the module docstring)."""
    img = np.asarray(image, dtype=np.float32)
    dev = cv2.absdiff(img, cv2.blur(img, (3, 3), borderType=cv2.BORDER_REPLICATE))
    return cv2.blur(dev, (window_px, window_px), borderType=cv2.BORDER_REPLICATE) * np.float32(MEAN_ABS_TO_SIGMA)


def local_noise_coarse(
    image: np.ndarray,
    window_px: int = 31,
    factor: int = 4,
    full: bool = True,
    box3: np.ndarray | None = None,
    scratch: Scratch | None = None,
) -> np.ndarray:
    """:func:`local_noise` with its window mean taken on a ``factor`` times coarser grid (the
    deviations averaged over ``factor`` x ``factor`` cells, a ``window_px / factor`` box mean there,
    bilinear back to full size): the noise field varies over tens of pixels, and the full-size
    31 x 31 box mean was a third of the chain's cost.  Float32, image shape (``full``) or the coarse
    grid's (``H // factor, W // factor``: cell (i, j) covers pixels ``factor * i ...``).  ``box3``: the
    image's 3 x 3 box mean (edges replicated), when the caller has it already; ``scratch``: the arrays to
    work in (the coarse grid's result is a new array)."""
    h, w = image.shape
    coarse = window_noise(noise_cells(image, factor, box3, scratch), noise_window_cells(window_px, factor))
    return cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR) if full else coarse


def noise_window_cells(window_px: int, factor: int) -> int:
    """The noise window's side in cells of ``factor`` px: odd, at least 1."""
    return max(window_px // factor, 1) | 1


def window_noise(cells: np.ndarray, window_cells: int) -> np.ndarray:
    """The local noise sigma on the cells' grid (float32): the mean of :func:`noise_cells` over each
    ``window_cells`` square (edges replicated), x 1.2533."""
    return cv2.blur(cells, (window_cells, window_cells), borderType=cv2.BORDER_REPLICATE) * np.float32(
        MEAN_ABS_TO_SIGMA
    )


MEDIAN_CELLS = 5  # median_window_noise's window side in its own cells (OpenCV's fast median filters go to 5 x 5)


def median_window_noise(cells: np.ndarray, window_cells: int) -> np.ndarray:
    """The local noise sigma on the cells' grid (float32) as a median over each ``window_cells`` square,
    x 1.2533: :func:`window_noise` with a median for the mean.  A cloud edge, a roof or a field boundary
    filling a few of the window's cells moves the median little and the mean much (C3 over 30 s: a bird 3
    grey over clear sky 4-8 px from a cloud's edge, under a 4.3 grey threshold from the window's mean).
    The cells are regridded to ``MEDIAN_CELLS`` a window side (area means: 6 px cells for a 31 px window of
    4 px cells) and the median of the ``MEDIAN_CELLS`` squared taken there, then interpolated back: a 7 x 7
    median on the 4 px grid costs ~0.5 ms in OpenCV (8-bit codes only), this ~0.1 (with the clip to the mean,
    the detector's "noise, threshold" stage 0.43 -> 0.56 ms p50 on C1)."""
    c = np.asarray(cells, dtype=np.float32)
    k = np.float32(MEAN_ABS_TO_SIGMA)
    if window_cells <= MEDIAN_CELLS:  # within OpenCV's fast median filters: on the cells as they are
        small_enough = window_cells > 1 and min(c.shape) >= window_cells
        return (cv2.medianBlur(c, window_cells) if small_enough else c) * k
    hc, wc = c.shape
    scale = MEDIAN_CELLS / window_cells
    size = (max(int(round(wc * scale)), 1), max(int(round(hc * scale)), 1))
    coarse = cv2.resize(c, size, interpolation=cv2.INTER_AREA)
    if min(coarse.shape) >= MEDIAN_CELLS:
        coarse = cv2.medianBlur(coarse, MEDIAN_CELLS)
    if coarse.shape == c.shape:
        return coarse * k
    out = cv2.resize(coarse, (wc, hc), interpolation=cv2.INTER_LINEAR)
    np.multiply(out, k, out=out)
    return out


def noise_cells(
    image: np.ndarray, factor: int = 4, box3: np.ndarray | None = None, scratch: Scratch | None = None
) -> np.ndarray:
    """The mean of ``|g - mean3x3(g)|`` over each ``factor`` x ``factor`` cell (float32, ``H // factor,
    W // factor``; :func:`local_noise_coarse`'s grid, before its window mean).  ``box3``, ``scratch``: as
    there."""
    img = np.asarray(image, dtype=np.float32)
    if box3 is None:
        box3 = cv2.blur(img, (3, 3), dst=_dst(scratch, "noise_box3", img.shape), borderType=cv2.BORDER_REPLICATE)
    dev = cv2.absdiff(img, box3, dst=_dst(scratch, TRANSIENT_A, img.shape))
    h, w = img.shape
    hc, wc = max(h // factor, 1), max(w // factor, 1)
    return cv2.resize(dev, (wc, hc), interpolation=cv2.INTER_AREA)


def quietest_block_noise(cells: np.ndarray, window_cells: int, block_cells: int) -> np.ndarray:
    """The local noise sigma of the quietest ``block_cells`` square of cells within each ``window_cells``
    window (float32, ``cells``' grid; :func:`noise_cells`'): the least, over the window, of the blocks'
    mean deviation, x 1.2533.  A roof, a warmer field or a cloud edge in part of the window raises its
    mean deviation, which the point contrast of the ground beside it does not share; the quietest block
    is the ground's own (a low quantile of the window, in two passes on the coarse grid: 0.04 ms on
    the whole 128 x 160 grid).  Lower than the window's mean wherever texture is uneven: beside a cloud
    the quietest block is the clear sky's, not the cloud texture a point on the cloud's edge lies in, so
    the detector takes it only until the first primary, near the axis.  Measured in docs/perception.md ("Robust
    noise and surround (an experiment)")."""
    b = max(block_cells, 1)
    blocks = cv2.blur(cells, (b, b), borderType=cv2.BORDER_REPLICATE) if b > 1 else cells
    span = max(window_cells - b + 1, 1)  # block centres whose block lies inside the window
    quiet = cv2.erode(blocks, np.ones((span, span), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return quiet * np.float32(MEAN_ABS_TO_SIGMA)


def grey_level(image: np.ndarray) -> float:
    """The grey of one quantisation level of ``image`` (its own units), the unit of the detector's floors and
    caps (``ClutterParams.min_threshold_lsb``, ``two_level_cap_lsb``): 1 for an 8-bit (or a float) frame; for a
    16-bit frame the greatest common divisor of its values' differences, at most ``GREY16_PER_GREY8``: 257 for
    an 8-bit frame widened to full scale, 256 for one shifted by 8 bits, 16 for 12-bit counts left-aligned, 1
    for native counts (the noise fills every level) and for a flat frame.  In single counts, a widened frame's
    flat sky had its lone pixels a level up over a 0.8 count floor (points, where the 8-bit frame's 0.25 grey
    of 2 x 2 contrast is under it), and its two-level ground was never capped (its levels are not adjacent
    counts).  At most 257 because an 8-bit frame is one grey even when its values skip levels: the same frame
    x 257 is then 257.  Every ``GREY_LEVEL_SAMPLE``-th row and column first: their divisor is a multiple of the
    frame's, so a native frame is settled there."""
    if image.dtype != np.uint16 or image.size == 0:
        return 1.0
    sample = image[::GREY_LEVEL_SAMPLE, ::GREY_LEVEL_SAMPLE]
    # the differences from the least value (uint16: none negative); their divisor is every pair's
    if int(np.gcd.reduce((sample - sample.min()).ravel())) == 1:
        return 1.0
    g = int(np.gcd.reduce((image - image.min()).ravel()))
    return float(min(g, GREY16_PER_GREY8)) if g > 1 else 1.0


def cfar_threshold(noise: np.ndarray, k_sigma: float, floor: float, cap: np.ndarray | None = None) -> np.ndarray:
    """``max(k_sigma * noise, floor)`` (float32), then at most ``cap`` (same shape; None: no cap)."""
    thr = np.maximum(noise * np.float32(k_sigma), np.float32(floor))
    return thr if cap is None else np.minimum(thr, cap, out=thr)


def two_level_cap(
    image: np.ndarray, window_px: int, factor: int, cap_lsb: float, min_fraction: float, level: float = 1.0
) -> np.ndarray | None:
    """Where the noise window of an integer frame lies on two adjacent grey levels, the most its point
    contrast can owe to noise: ``cap_lsb`` levels, elsewhere +inf (float32, on :func:`local_noise_coarse`'s
    ``H // factor, W // factor`` grid; None for a float frame or ``cap_lsb`` 0).  ``level``: the grey of one
    level (:func:`grey_level`; 1: one count).

    A sensor noise well under one grey level on flat ground whose radiance sits near a level boundary
    toggles pixels between the two levels: the mean absolute deviation reads it as ~0.45 grey (sigma 0.13
    on C2 seed 2, mono8), a CFAR threshold of ~2.5 grey, but the centre mean minus the largest surround
    mean of pixels on levels {L, L+1} is at most 1, and reaches 1 only if the 2 x 2 centre is all on L+1
    and the 8 surround pixels and 72 surround-cell pixels all on L: with a fraction q of pixels on L+1,
    ``q**4 (1 - q)**80`` a pixel, ~1e-7 at its worst (q = 0.05), 0.03 a 640 x 512 frame.  A point warmer
    than both levels (a target 1-3 grey over such ground, under the 2.5 grey threshold) passes.

    A ``factor`` x ``factor`` cell is two-level if its pixels lie within one level of the lowest level
    of the 7 x 7 cells about it (``window_px / factor``, the noise window); the window is, and is
    capped, if at least ``min_fraction`` of its cells are (so a target's own few cells do not lift the
    cap off it).  Measured on C2 seed 2's cached frames (mono8): the target's point contrast median 1.25
    grey under thresholds of median 2.30; capped, a candidate on 187 of its 270 frames (0 before), no
    candidate more elsewhere on C1, C2 (seeds 0-2) or C3.  Frame sizes not a multiple of ``factor``:
    the last rows and columns are left out of the cells (the noise grid's cells span them)."""
    h, w = image.shape
    if cap_lsb <= 0 or not np.issubdtype(image.dtype, np.integer) or min(h, w) < factor:
        return None
    hc, wc = max(h // factor, 1), max(w // factor, 1)
    img = image if image.dtype in (np.uint8, np.uint16) else image.astype(np.float32)
    # each cell's extremes, compiled in one pass over the frame (kernels.cell_extremes), else its rows' first
    # (whole contiguous rows, numpy), then every factor-th of a dilation along the row anchored at the cell's
    # first column (4x less to dilate than a factor x factor dilation of the whole frame)
    extremes = kernels.cell_extremes(img, factor)
    if extremes is not None:
        hi, lo = extremes
    else:
        rows = [img[r : hc * factor : factor] for r in range(factor)]
        hi_rows, lo_rows = rows[0].copy(), rows[0].copy()
        for r in rows[1:]:
            np.maximum(hi_rows, r, out=hi_rows)
            np.minimum(lo_rows, r, out=lo_rows)
        kernel = np.ones((1, factor), np.uint8)
        hi = cv2.dilate(hi_rows, kernel, anchor=(0, 0))[:, : wc * factor : factor]
        lo = cv2.erode(lo_rows, kernel, anchor=(0, 0))[:, : wc * factor : factor]
    k = noise_window_cells(window_px, factor)
    lowest = cv2.erode(np.ascontiguousarray(lo), np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    # hi >= lo >= lowest, so the difference never saturates; 1 where two-level (uint8)
    two = np.less_equal(cv2.subtract(np.ascontiguousarray(hi), lowest), level).view(np.uint8)
    # the two-level cells of each window, counted exactly (k * k <= 255 here: the noise window's cells)
    if k * k > 255:
        share = cv2.blur(two.astype(np.float32), (k, k), borderType=cv2.BORDER_REPLICATE)
        return np.where(share >= np.float32(min_fraction), np.float32(cap_lsb * level), np.float32(np.inf))
    count = cv2.boxFilter(two, -1, (k, k), normalize=False, borderType=cv2.BORDER_REPLICATE)
    table = np.full(256, np.inf, np.float32)
    table[math.ceil(min_fraction * k * k - 1e-9) :] = cap_lsb * level
    return cv2.LUT(count, table)


def label_points(jj: np.ndarray, ii: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected components of a few pixels (columns ``jj``, rows ``ii``, intp): each pixel's label
    (1 ...) and the number of labels plus one (the background's 0), as ``cv2.connectedComponents``
    labels the same pixels in a mask: its block-based scan numbers the components in the order of the
    first 2 x 2 block (row-major) holding one of their pixels (checked on random masks).  Labelling
    the pixels among themselves costs O(n^2) for n pixels instead of a pass over the whole frame (~1
    ms on a loaded 640 x 512 frame for 30 pixels): minimum-label propagation over the adjacency
    matrix, with pointer jumping."""
    n = len(jj)
    adjacent = np.maximum(np.abs(jj[:, None] - jj[None, :]), np.abs(ii[:, None] - ii[None, :])) <= 1
    root = np.arange(n)
    while True:
        new = np.where(adjacent, root[None, :], n).min(axis=1)  # the least label among itself and neighbours
        new = new[new]
        if np.array_equal(new, root):
            break
        root = new
    comps, inv = np.unique(root, return_inverse=True)
    block = (ii // 2) * (int(jj.max()) // 2 + 1) + jj // 2
    first = np.full(len(comps), np.iinfo(np.intp).max, np.intp)
    np.minimum.at(first, inv, block)
    rank = np.empty(len(comps), np.intp)
    rank[np.argsort(first)] = np.arange(len(comps))  # two components never share a 2 x 2 block
    return rank[inv] + 1, len(comps) + 1


def point_candidates(
    contrast: np.ndarray, threshold: np.ndarray, params: ClutterParams, scratch: Scratch | None = None
) -> list[PointCandidate]:
    """Components (8-connected) of ``contrast >= threshold`` of at most ``max_area_px`` pixels,
    strongest ``score`` first, at most ``max_candidates``.

    The component statistics are gathered over the thresholded pixels only (a few hundred): OpenCV's
    ``connectedComponentsWithStats`` scans the whole frame again for them and costs ~8x the labelling.
    Up to ``SPARSE_LABEL_MAX_PX`` thresholded pixels (C1-C3: 20-40 a frame) are labelled among
    themselves (:func:`label_points`, OpenCV's labels and their order) instead of over the whole frame.
    Up to ``FEW_PX`` (C1, C2: ~5 a frame) go through plain Python instead (:func:`_few_candidates`).
    ``scratch``: where the thresholded mask goes (None: a new array)."""
    mask = np.greater_equal(contrast, threshold, out=_dst(scratch, "candidates_mask", contrast.shape, np.bool_))
    mask = mask.view(np.uint8)
    found = cv2.findNonZero(mask)  # (x, y) row-major; several times faster than numpy's nonzero
    if found is None:
        return []
    pts = found.reshape(-1, 2)
    jj = pts[:, 0].astype(np.intp)
    ii = pts[:, 1].astype(np.intp)
    sel = ii * contrast.shape[1] + jj
    if len(pts) <= FEW_PX:
        c_few = contrast.ravel()[sel]
        return _few_candidates(
            ii.tolist(), jj.tolist(), c_few.tolist(), (c_few / threshold.ravel()[sel]).tolist(), params
        )
    lab_px: np.ndarray
    if len(pts) <= SPARSE_LABEL_MAX_PX:
        lab_px, n = label_points(jj, ii)
    else:
        n, labels = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_32S)
        lab_px = np.asarray(labels.ravel()[sel], dtype=np.intp)
    areas = np.bincount(lab_px, minlength=n)
    keep = np.flatnonzero(areas[1:] <= params.max_area_px) + 1
    if keep.size == 0:
        return []
    c_px = contrast.ravel()[sel]
    r_px = c_px / threshold.ravel()[sel]
    # per-component extremes by segments of the pixels sorted by label (ufunc.at, one call per
    # statistic, cost ~0.1 ms a frame more); components 1..n-1 all have pixels, in label order
    order = np.argsort(lab_px, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(lab_px[order]) != 0])
    best = np.zeros(n, np.float32)  # the strongest pixel of each component: contrast over threshold
    best[1:] = np.maximum.reduceat(r_px[order], starts)
    peak = np.zeros(n, np.float32)
    peak[1:] = np.maximum.reduceat(c_px[order], starts)
    i0 = np.zeros(n, np.intp)
    j0 = np.zeros(n, np.intp)
    i1 = np.zeros(n, np.intp)
    j1 = np.zeros(n, np.intp)
    i0[1:] = np.minimum.reduceat(ii[order], starts)
    j0[1:] = np.minimum.reduceat(jj[order], starts)
    i1[1:] = np.maximum.reduceat(ii[order], starts)
    j1[1:] = np.maximum.reduceat(jj[order], starts)
    # contrast-weighted centre over the component's pixels (frames.py: pixel (i, j) centred at j + 0.5, i + 0.5)
    s = np.bincount(lab_px, weights=c_px, minlength=n)
    su = np.bincount(lab_px, weights=c_px * (jj + 0.5), minlength=n)
    sv = np.bincount(lab_px, weights=c_px * (ii + 0.5), minlength=n)
    keep = keep[np.argsort(-best[keep], kind="stable")][: params.max_candidates]
    out: list[PointCandidate] = []
    for lab in keep:
        if not s[lab] > 0:
            continue
        x, y = int(j0[lab]), int(i0[lab])
        bbox = (x, y, int(j1[lab]) - x + 1, int(i1[lab]) - y + 1)
        out.append(
            PointCandidate(
                float(su[lab] / s[lab]),
                float(sv[lab] / s[lab]),
                bbox,
                int(areas[lab]),
                float(peak[lab]),
                float(best[lab]),
            )
        )
    return out


def _few_candidates(
    ii: list[int], jj: list[int], c_px: list[float], r_px: list[float], params: ClutterParams
) -> list[PointCandidate]:
    """:func:`point_candidates` on a few thresholded pixels (row-major: rows ``ii``, columns ``jj``, their
    contrast ``c_px`` and contrast over threshold ``r_px``, float32 values) in plain Python, the same
    candidates bit for bit: components (union-find over the 8-neighbours) numbered in OpenCV's order
    (:func:`label_points`), sums in pixel order as ``np.bincount`` takes them."""
    n = len(ii)
    index = {(i, j): q for q, (i, j) in enumerate(zip(ii, jj))}
    parent = list(range(n))

    def root(q: int) -> int:
        while parent[q] != q:
            parent[q] = parent[parent[q]]
            q = parent[q]
        return q

    for q in range(n):
        i, j = ii[q], jj[q]
        for o in (index.get((i - 1, j - 1)), index.get((i - 1, j)), index.get((i - 1, j + 1)), index.get((i, j - 1))):
            if o is not None:
                a, b = root(q), root(o)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    members: dict[int, list[int]] = {}
    for q in range(n):
        members.setdefault(root(q), []).append(q)
    # OpenCV's order: by the first 2 x 2 block (row-major) holding one of the component's pixels
    comps = sorted(members.values(), key=lambda m: min((ii[q] // 2, jj[q] // 2) for q in m))
    kept = [m for m in comps if len(m) <= params.max_area_px]
    best = [max(r_px[q] for q in m) for m in kept]
    order = sorted(range(len(kept)), key=lambda x: -best[x])[: params.max_candidates]  # stable: label order
    out: list[PointCandidate] = []
    for x in order:
        m = kept[x]
        s = su = sv = 0.0
        for q in m:
            c = c_px[q]
            s += c
            su += c * (jj[q] + 0.5)
            sv += c * (ii[q] + 0.5)
        if not s > 0:
            continue
        i0, i1 = min(ii[q] for q in m), max(ii[q] for q in m)
        j0, j1 = min(jj[q] for q in m), max(jj[q] for q in m)
        out.append(
            PointCandidate(su / s, sv / s, (j0, i0, j1 - j0 + 1, i1 - i0 + 1), len(m), max(c_px[q] for q in m), best[x])
        )
    return out


def frame_event(image: np.ndarray, previous: np.ndarray | None, previous_median: float | None, step_lsb: float):
    """``("frozen" | "step" | "ok", median)`` of ``image`` against the previous frame (see the module
    docstring); the median is of every 8th row and column."""
    med = float(np.median(image[::8, ::8]))
    # the sampled pixels first: a regular frame differs there, and the whole-frame comparison is skipped
    if (
        previous is not None
        and previous.shape == image.shape
        and np.array_equal(previous[::8, ::8], image[::8, ::8])
        and np.array_equal(previous, image)
    ):
        return "frozen", med
    if previous_median is not None and abs(med - previous_median) > step_lsb:
        return "step", med
    return "ok", med
