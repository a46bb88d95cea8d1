"""The objects chain's detection side: each frame's point candidates and what the tracker asks of the background.

``ObjectDetector(intrinsics, params, clutter)``; per frame :meth:`ObjectDetector.detect` (column offsets
removed, dead/hot pixels repaired, the two-scale point contrast against the CFAR threshold,
:mod:`onboard.imaging.clutter`), then :meth:`ObjectDetector.background_motion` (the frame's dominant image
motion, the camera's rotation removed).  It keeps the recent frames and poses those need and answers the
tracker's questions about the background where a track is: is it textured (:meth:`textured`), did its
surroundings move with it (:meth:`surroundings_follow`), and, for track-aided detection, the difference
against the background moved with the camera (:meth:`difference_candidate`); about a bright neighbour,
the fainter points its light hid (:meth:`deblended_candidates`, :func:`symmetric_deblend`).  The tracker itself
(association, confirmation, the primary) is :mod:`onboard.imaging.objects`.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import cv2
import numpy as np

from onboard.imaging import kernels
from onboard.imaging.background_difference import (
    background_difference,
    difference_centre,
    difference_peak,
    rotation_shift_px,
    surround_residuals,
    two_level_difference_cap,
)
from onboard.imaging.clutter import (
    TRANSIENT_A,
    ClutterParams,
    DefectMap,
    PointCandidate,
    Scratch,
    cfar_threshold,
    column_offsets,
    grey_level,
    median_window_noise,
    noise_cells,
    noise_window_cells,
    point_candidates,
    point_contrast,
    quietest_block_noise,
    two_level_cap,
    window_noise,
)
from onboard.imaging.objects_model import ObjectParams, StageTimes, TrackRecord, los_from_pixel, pixel_from_los
from onboard.imaging.signature import Signature, signature_peak, square_sigma

__all__ = [
    "ObjectDetector",
    "DEBLEND_MIN_SCORE",
    "DEBLEND_RADIUS_PX",
    "DIFFERENCE_HALF_PX",
    "DIFFERENCE_SIGMA",
    "symmetric_deblend",
]

log = logging.getLogger(__name__)

BACKGROUND_SCALE = 4  # the background motion is measured on frames this many times smaller
NOISE_FACTOR = 4  # the local noise (CFAR) is estimated on a grid this many times coarser
TEXTURE_RING_PX = 32  # the texture about a track is sampled this far from it (beyond the noise window's half)
TEXTURE_REFERENCE_PERCENTILE = 10  # texture is judged against the frame's quietest tenth, not its median
DIFFERENCE_LAG = 8  # frames between the two frames of a track-aided background difference
DIFFERENCE_HALF_PX = 16  # half-side of its square
DIFFERENCE_SIGMA = 5.0  # its threshold in its own noise sigmas
# and within this of a held track's prediction: about 7 of the gate's 2 x 2 positions, which Gaussian noise passes at
# 4 sigmas once in ~5000 frames
DIFFERENCE_NEAR_PX, DIFFERENCE_NEAR_SIGMA = 1.5, 4.0
DIFFERENCE_GATE_PX = 3.0  # its gate about the track's prediction
# a held primary's signature (onboard.imaging.signature) is searched within this of its prediction, and must reach
# this z (robust spreads of its own output over the square): the ~13 whole pixels within 2 px pass 4 of Gaussian
# noise together about once in 2400 frames
SIGNATURE_GATE_PX, SIGNATURE_Z = 2.0, 4.0
SIGNATURE_MIN_SIGMA_LSB = 1.0 / math.sqrt(6.0)  # two frames' quantisation: each uniform over one level
DIFFERENCE_TWO_LEVEL_CAP = 1.25  # its threshold's cap on two-level ground, in levels: over one needs a third level
SURROUND_MATCH_RATIO = 1.5  # a track's own displacement must fit its surroundings that much better to call them one
STRIPE_EVERY = 8  # frames between column-offset measurements (and at once after an offset step)
DEBLEND_MIN_SCORE = 2.0  # a neighbour this many thresholds bright is deblended (C3's primary dips to 2.3 beside it)
DEBLEND_RADIUS_PX = 8.0  # fainter points searched again this far from it (C3: hidden at 3-8 px)
DEBLEND_CORE_PX = 2.0  # its own core: within this of its centre, the background
DEBLEND_MIN_SEPARATION_PX = 2.5  # a deblended point at least this far from it (nearer: its core's residual)
DEBLEND_SAME_PX = 2.0  # a deblended point this near a regular candidate is that one


class ObjectDetector:
    """See the module docstring.  ``intrinsics``: :class:`onboard.core.frames.PinholeIntrinsics`;
    ``params`` the tracker's (its windows: ``confirm_window``, ``defect_every``, ``background_frames``,
    ``textured_noise_ratio``); ``clutter`` the detector's.  After :meth:`detect`, ``contrast`` and
    ``threshold`` hold the frame's point contrast and CFAR threshold (full size, grey), ``clean`` the
    frame with its fixed pattern handled (float32) and ``level`` the grey of one of its quantisation levels
    (:func:`onboard.imaging.clutter.grey_level`: the unit of the clutter parameters' floors and caps); after
    :meth:`background_motion`, ``background_pxpf`` the frame's dominant background motion (px/frame, None when
    not measured)."""

    def __init__(
        self, intrinsics, params: ObjectParams, clutter: ClutterParams, stages: StageTimes | None = None
    ) -> None:
        self.K = intrinsics
        self.stages = stages or StageTimes()  # detect()'s stages, on the tracker's clock
        self.params = params
        self.clutter = clutter
        self.frame_index = -1  # the frame detect() saw last
        self.level = 1.0  # the grey of one quantisation level of that frame
        self.acquiring = True  # no primary target chosen yet (the tracker's to say): the quiet-block noise applies
        self.contrast: np.ndarray | None = None  # the last frame's point contrast and CFAR threshold
        self.threshold: np.ndarray | None = None
        # lowered_base's noise and cap (the coarse grid's), and its threshold once asked for on this frame
        self._mean_noise: tuple[np.ndarray, np.ndarray | None] | None = None
        self._mean_threshold: np.ndarray | None = None
        self.clean: np.ndarray | None = None  # the last frame, fixed pattern handled (float32)
        self._defects: DefectMap | None = None
        self._window: np.ndarray | None = None
        self._noise: np.ndarray | None = None  # the last frame's local noise sigma (grey), coarse grid
        self._noise_median = 0.0
        self._noise_floor = 0.0  # the least textured tenth of the frame's local noise (grey)
        self._noise_floor_frame = -1
        self._stripes: np.ndarray | None = None  # column offsets, re-measured every STRIPE_EVERY frames
        # the background motion, measured when asked for: frame -> R_ned_from_cam (the last
        # confirm_window + background_frames frames background_motion registered), -> the frame
        # BACKGROUND_SCALE times smaller (float32), -> its motion (px/frame, None: not measured)
        self._poses: dict[int, np.ndarray] = {}
        self._smalls: dict[int, np.ndarray] = {}
        self._motions: dict[int, tuple[float, float] | None] = {}
        self._registered: int | None = None  # the frame background_motion registered last
        # (frame, its pixels) of the last confirm_window + background_frames frames (raw; a 16-bit frame as float32)
        self._recent: list[tuple[int, np.ndarray]] = []
        # the full-frame arrays of detect(), written again each frame (clutter.Scratch: fresh ones cost
        # page faults); contrast, threshold and clean live there until the next frame
        self._scratch = Scratch()
        self._rows: dict[str, np.ndarray] = {}  # the compiled pass's row buffers, kept from frame to frame
        kernels.warm()  # compiled (or loaded from numba's cache) now, not on the first frame

    def restart(self) -> None:
        """An offset step (flat-field correction): the defect map and the column offsets start again."""
        if self._defects is not None:
            self._defects.reset()
        self._stripes = None

    def forget_frames(self) -> None:
        """A gap in the frames: the frames and poses kept are forgotten.  They are counted in frames, so across
        the gap a background difference would be taken against a frame seconds old and a background motion
        divided by the frames between, not the time."""
        self._recent = []
        self._poses, self._smalls, self._motions = {}, {}, {}
        self._registered = None

    def detect(self, image: np.ndarray, frame_index: int) -> list[PointCandidate]:
        """Frame ``frame_index``'s point candidates (fixed pattern handled first; updates the defect map)."""
        self.frame_index = frame_index
        p = self.clutter
        # the floors and caps are in levels, so that an 8-bit frame widened to 16 bits is thresholded as itself
        level = self.level = grey_level(image)
        sc = self._scratch
        k = self.frame_index
        # a confirming track's surroundings are compared over its window (the raw frames: the fixed
        # pattern stays put while the scene moves, adding alike to every displacement tried)
        held = self.params.confirm_window + self.params.background_frames  # the background motion's too
        kept = [r for r in self._recent if r[0] > k - held]
        kind = np.uint8 if image.dtype == np.uint8 else np.float32  # what surroundings_follow's sub-pixel reads take
        # the copy goes into a frame that left the window (a fresh 0.3-1.3 MB array a frame, freed 15
        # frames later, made the allocator return memory to the system and fault it back in)
        spare = next((a for q, a in self._recent if q <= k - held and a.shape == image.shape and a.dtype == kind), None)
        if spare is None:
            spare = np.empty(image.shape, kind)
        np.copyto(spare, image)
        self._recent = [*kept, (k, spare)]
        h, w = image.shape
        img = sc.get("clean", image.shape)  # the frame as float32, written over last frame's
        if p.destripe:
            if self._stripes is None or self._stripes.shape[0] != w or self.frame_index % STRIPE_EVERY == 0:
                self._stripes = column_offsets(image, p.stripe_window_px)  # they drift over minutes: every few frames
            # image.astype(np.float32) - the offsets (remove_column_offsets without its array): compiled in one
            # pass, else a cast, then an in-place float32 subtraction (~2/3 of numpy's mixed-type subtraction)
            if not kernels.minus_columns(image, self._stripes, img):
                np.copyto(img, image)
                np.subtract(img, self._stripes[None, :], out=img)
        else:
            np.copyto(img, image)
        if self._defects is None or self._defects.mask.shape != img.shape:
            frames = max(p.defect_frames // self.params.defect_every, 2)
            self._defects = DefectMap(img.shape, frames, p.defect_fraction, sc)
        if self.frame_index % self.params.defect_every == 0:
            # the outlier level from the previous frame's noise (the noise is measured after the repair)
            sigma = max(p.defect_outlier_sigma * self._noise_median, 2.0 * p.min_threshold_lsb * level)
            self._defects.update(img, sigma)
        img = self._defects.repair(img, out=img)
        self.clean = img
        self.stages.lap("fixed pattern")
        # one 3 x 3 box mean serves the noise estimate and the contrast's surround cells
        box3 = None
        if kernels.fits(img.shape, p.cell_px, p.guard_px, p.sharp_guard_px, NOISE_FACTOR):
            # the box mean, the contrast and the noise cells in one compiled pass over the rows, bit for bit the
            # OpenCV path below and cheaper (docs/perception.md, "The whole-frame statistics in one compiled pass")
            box3, contrast = sc.get("box3", img.shape), sc.get("contrast", img.shape)
            cells = sc.get("cells", (h // NOISE_FACTOR, w // NOISE_FACTOR))
            kernels.contrast_and_cells(
                img, p.guard_px, p.sharp_guard_px, NOISE_FACTOR, box3, contrast, cells, self._rows
            )
            self.stages.lap("point contrast")  # the noise cells' cost is here too
        else:
            if p.cell_px == 3:
                box3 = cv2.blur(img, (3, 3), dst=sc.get("box3", img.shape), borderType=cv2.BORDER_REPLICATE)
            # the contrast next to the box mean it reads, the threshold next to the comparison that reads it:
            # a 1.3 MB array read soon after it was written is partly still in the 2 MB L2 cache
            contrast = point_contrast(img, p, box3, sc)
            self.stages.lap("point contrast")  # the box mean's cost is here
            cells = noise_cells(img, NOISE_FACTOR, box3, sc)
        # the CFAR threshold on the coarse grid, then to full size: one full-size pass instead of three
        window_cells = noise_window_cells(p.noise_window_px, NOISE_FACTOR)
        # the window's mean deviation: the texture measure the tracker's tests and the defect level read
        mean = window_noise(cells, window_cells)
        self._noise = mean
        if p.quiet_block_px > 0 and self.acquiring:
            mean = self._quiet_noise(cells, mean, window_cells)
        if (self.frame_index + 1) % self.params.defect_every == 0:  # read by the next defect update only
            self._noise_median = float(np.median(self._noise))
        cap = two_level_cap(image, p.noise_window_px, NOISE_FACTOR, p.two_level_cap_lsb, p.two_level_fraction, level)
        noise = mean
        if p.median_noise_floor < 1.0:
            # the whole-frame threshold's: the median where an edge or a roof in part of the window lifts the mean
            median = median_window_noise(cells, window_cells)
            np.maximum(median, self._noise * np.float32(p.median_noise_floor), out=median)
            noise = np.minimum(median, mean, out=median)
        # the box mean is done with: its array takes the threshold (one distinct full-size array less)
        threshold = self._full_threshold(
            noise, cap, img.shape, sc.get("threshold", img.shape) if box3 is None else box3
        )
        self.stages.lap("noise, threshold")
        self.contrast, self.threshold = contrast, threshold
        # lowered_base's inputs, made into a threshold only when a search asks (None: the threshold is the mean's)
        self._mean_noise = None if noise is mean else (mean, cap)
        self._mean_threshold = None
        cands = point_candidates(contrast, threshold, p, sc)
        self.stages.lap("candidates")
        return cands

    @property
    def lowered_base(self) -> np.ndarray | None:
        """The CFAR threshold from the noise window's mean (full size; the last frame's), which the searches
        lowered by a track's or the axis' prior scale (track-aided detection, the difference search).  The
        whole-frame threshold may take the window's median (``ClutterParams.median_noise_floor``), lower beside
        an edge or a roof; lowered again inside a held track's gate, it let the track slide onto that texture
        (C2 seed 3 in the loop over 30 s: the primary carried 20 px off its target by the lowered searches'
        detections over field edges, frames 429-443; with the mean's there, on its target as before)."""
        if self._mean_noise is None or self.threshold is None:
            return self.threshold
        if self._mean_threshold is None:
            mean, cap = self._mean_noise
            self._mean_threshold = self._full_threshold(mean, cap, self.threshold.shape)
        return self._mean_threshold

    def lowered_base_block(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray | None:
        """``lowered_base[y0:y1, x0:x1]`` (the same values), computed for that block alone: the searches read a gate or
        the axis' square of it, not the frame.  Bilinear resizing gives each pixel from its own two rows and columns of
        cells with weights set by its place within its cell, so a block of cells with one cell of margin, resized by
        the same whole factor, gives the frame's values inside the margin (where the block meets the frame's edge, its
        edge is the frame's); ``tests/onboard/test_clutter_median_noise.py`` compares them with the frame's."""
        f = NOISE_FACTOR
        if self._mean_noise is not None and self._mean_threshold is None and self.threshold is not None:
            mean, cap = self._mean_noise
            (h, w), (hc, wc) = self.threshold.shape, mean.shape
            if hc * f == h and wc * f == w and 0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w:
                i0, j0 = max(y0 // f - 1, 0), max(x0 // f - 1, 0)
                i1, j1 = min((y1 - 1) // f + 2, hc), min((x1 - 1) // f + 2, wc)
                block_cap = None if cap is None else cap[i0:i1, j0:j1]
                block = self._full_threshold(mean[i0:i1, j0:j1], block_cap, ((i1 - i0) * f, (j1 - j0) * f))
                return block[y0 - i0 * f : y1 - i0 * f, x0 - j0 * f : x1 - j0 * f]
        base = self.lowered_base  # the frame's, made already, or the only one there is
        return None if base is None else base[y0:y1, x0:x1]

    def _full_threshold(
        self, noise: np.ndarray, cap: np.ndarray | None, shape: tuple[int, ...], dst: np.ndarray | None = None
    ) -> np.ndarray:
        """The CFAR threshold of the coarse grid's ``noise`` (and ``cap``), bilinear to the frame's ``shape``
        (into ``dst`` when given)."""
        c = self.clutter
        h, w = shape
        coarse = cfar_threshold(noise, c.threshold_sigma, c.min_threshold_lsb * self.level, cap)
        return cv2.resize(coarse, (w, h), dst=dst, interpolation=cv2.INTER_LINEAR)

    def _quiet_noise(self, cells: np.ndarray, noise: np.ndarray, window_cells: int) -> np.ndarray:
        """Until the first primary (``acquiring``), the CFAR threshold's noise where the gimbal points:
        within ``primary_max_off_axis_rad`` of the principal point (a square), the lesser of the window's
        mean and its quietest block (:func:`clutter.quietest_block_noise`, 0.01 ms for the central 66 x 66
        cells), so a roof, a warmer field or a cloud edge in part of the window no longer lifts the
        threshold over the ground the target crosses (C2 seed 1, frames 0-24: 2.8-3.4 grey over flat
        ground beside warmer fields against its 1.0-1.6 grey; with the block the 0.8 grey floor, and the
        target is the primary from frame 24 instead of 62).  A new array (``noise``, the window's mean,
        is the texture measure the tracker's tests read).

        Only while acquiring, and only there: taken over the whole frame on every frame, the quietest
        block gave C1 and C3 ~50x the candidates away from every object (0.16 -> 7.6-9.8 a frame,
        offline) and C3 seed 1's second target lost its track after the crossing, where the lower
        thresholds on the clouds' texture beside clear sky kept 5-15 tentative tracks about it (0-3
        before).  While acquiring, more candidates cost little: the confirmation tests reject clutter,
        and the primary rule chooses nothing farther off the axis than this square.  Not after a primary
        was lost: in the closed loop (RTK attitude, 30 s) re-acquiring so made C2 seed 1 select a terrain
        feature 19-25 s in, off the target for 6 s, where the window's mean re-acquired the target."""
        p = self.clutter
        f = NOISE_FACTOR
        hc, wc = cells.shape
        half_px = self.K.fx_px * math.tan(self.params.primary_max_off_axis_rad)
        margin = window_cells // 2  # cells whose windows reach into the square
        r0, r1 = int((self.K.cy_px - half_px) // f), int(math.ceil((self.K.cy_px + half_px) / f))
        c0, c1 = int((self.K.cx_px - half_px) // f), int(math.ceil((self.K.cx_px + half_px) / f))
        r0, r1 = max(min(r0, hc), 0), max(min(r1, hc), 0)
        c0, c1 = max(min(c0, wc), 0), max(min(c1, wc), 0)
        if r1 <= r0 or c1 <= c0:
            return noise
        # the square with its windows' margin, measured alone (its own edges replicated beyond the margin)
        m0, m1 = max(r0 - margin, 0), min(r1 + margin, hc)
        n0, n1 = max(c0 - margin, 0), min(c1 + margin, wc)
        quiet = quietest_block_noise(cells[m0:m1, n0:n1], window_cells, max(p.quiet_block_px // f, 1))
        out = noise.copy()
        inner = out[r0:r1, c0:c1]
        np.minimum(inner, quiet[r0 - m0 : r1 - m0, c0 - n0 : c1 - n0], out=inner)
        return out

    def deblended_candidates(
        self, cands: list[PointCandidate], bright_uv: list[tuple[float, float]], gate_px: float
    ) -> list[PointCandidate]:
        """After :meth:`detect` on the same frame: the points a bright neighbour's light hid.  A fainter
        object 3-8 px from a brighter one has the brighter one in its point-contrast surround (the larger
        of the cells 4 px away and the pixels 2 px away), so its contrast is negative however bright it
        is alone (C3: the second target beside the primary, 3x fainter).  About each of ``cands`` that
        scores ``DEBLEND_MIN_SCORE`` thresholds and lies within ``gate_px`` of one of ``bright_uv`` (the
        caller's confirmed tracks: clutter is not searched again), the frame with that object taken out
        (:func:`symmetric_deblend`) gets the point contrast again, against the same CFAR threshold.  Its
        components ``DEBLEND_MIN_SEPARATION_PX`` to ``DEBLEND_RADIUS_PX`` from the bright one are new
        candidates, or take the place of a fainter candidate within ``DEBLEND_SAME_PX`` (the same object,
        measured without the bright one's light, whose surround pulls the frame's contrast-weighted centre
        towards it).  Returns ``cands`` so amended (a new list; frame coordinates)."""
        img, threshold = self.clean, self.threshold
        if img is None or threshold is None or not bright_uv:
            return list(cands)
        p = self.clutter
        h, w = img.shape
        # the contrast of a pixel DEBLEND_RADIUS_PX away reads pixels reach_px beyond it
        half = int(math.ceil(DEBLEND_RADIUS_PX)) + p.reach_px + 1
        out = list(cands)
        bright = [
            c
            for c in cands
            if c.score >= DEBLEND_MIN_SCORE and any(math.hypot(c.u_px - u, c.v_px - v) <= gate_px for u, v in bright_uv)
        ]
        for c in bright:
            x0, y0 = max(int(c.u_px) - half, 0), max(int(c.v_px) - half, 0)
            x1, y1 = min(int(c.u_px) + half + 1, w), min(int(c.v_px) + half + 1, h)
            if x1 - x0 < 2 * p.guard_px + p.cell_px or y1 - y0 < 2 * p.guard_px + p.cell_px:
                continue  # at the frame's edge: too little left to measure a contrast in
            roi = img[y0:y1, x0:x1]
            # the square is mostly background: its median is the level the bright object stands on (every
            # other pixel's, by a partition: np.median's own overhead was most of its cost here)
            sample = roi[::2, ::2].ravel()
            background = float(np.partition(sample, sample.size // 2)[sample.size // 2])
            r2 = _squared_distances(roi.shape, (c.u_px - x0, c.v_px - y0))
            rest = _deblend(roi, (c.u_px - x0, c.v_px - y0), r2, DEBLEND_CORE_PX, DEBLEND_RADIUS_PX, background)
            con = point_contrast(rest, p)
            if self.contrast is not None:
                # the frame's contrast about it becomes the deblended one, so that track-aided detection
                # reads it too: a fainter object's track is measured through the frames where it dips below
                # the full threshold beside the bright one, and never on the bright one itself (its own
                # point, already a candidate, is gone from there)
                disc = r2 <= np.float32(DEBLEND_RADIUS_PX**2)
                self.contrast[y0:y1, x0:x1][disc] = con[disc]
            for f in point_candidates(con, threshold[y0:y1, x0:x1], p):
                u, v = f.u_px + x0, f.v_px + y0
                if not DEBLEND_MIN_SEPARATION_PX <= math.hypot(u - c.u_px, v - c.v_px) <= DEBLEND_RADIUS_PX:
                    continue
                f = dataclasses.replace(f, u_px=u, v_px=v, bbox=(f.bbox[0] + x0, f.bbox[1] + y0, f.bbox[2], f.bbox[3]))
                same = next(
                    (i for i, o in enumerate(out) if math.hypot(u - o.u_px, v - o.v_px) <= DEBLEND_SAME_PX), None
                )
                if same is None:
                    out.append(f)
                elif out[same] not in bright:  # a bright one stays as the frame measured it
                    out[same] = f
        return out

    def background_motion(self, R: np.ndarray) -> None:
        """After :meth:`detect` on the same frame (``R`` its R_ned_from_cam): registers the frame for the
        dominant image motion of the background over the last ``background_frames`` frames, the camera's
        rotation removed (px per frame, in this frame's image), by phase correlation of
        ``BACKGROUND_SCALE`` times smaller frames (Kuglin & Hines 1975); None on a featureless frame (a
        clear sky: the correlation peak is weak and the shift meaningless).  Measured when first asked
        for (:attr:`background_pxpf`, :meth:`background_over_window`), the same figures as every frame:
        most frames nobody asks (on 0-1 of the 300 frames of C1, C4, C5, P1-P3; ~110 of C2 and C3), and
        the correlation and its reduced frames were ~10 % of the chain's median frame."""
        k = self.frame_index
        if not self._recent or self._recent[-1][0] != k:
            return  # detect() has not seen this frame
        p = self.params
        oldest = k - p.confirm_window - p.background_frames  # a window's first motion looks this far back
        self._poses = {q: r for q, r in self._poses.items() if q > oldest}
        self._poses[k] = R
        self._motions = {q: m for q, m in self._motions.items() if q > oldest}
        self._smalls = {q: a for q, a in self._smalls.items() if q > oldest}
        self._registered = k

    @property
    def background_pxpf(self) -> tuple[float, float] | None:
        """The dominant background motion of the last frame :meth:`background_motion` registered (px per
        frame; None when not measured)."""
        return None if self._registered is None else self._motion(self._registered)

    def _small(self, q: int) -> np.ndarray | None:
        """Frame ``q`` ``BACKGROUND_SCALE`` times smaller (float32; None once it left the recent frames)."""
        a = self._smalls.get(q)
        if a is None:
            raw = next((f for i, f in self._recent if i == q), None)
            if raw is None:
                return None
            # the cells' means straight from the kept frame (OpenCV's values: exact sums of whole grey levels)
            a = kernels.area_mean(raw, BACKGROUND_SCALE)
            if a is None:
                h, w = raw.shape
                size = (w // BACKGROUND_SCALE, h // BACKGROUND_SCALE)
                full = self._scratch.get(TRANSIENT_A, raw.shape)  # raw.astype(np.float32), no fresh array
                np.copyto(full, raw)
                a = cv2.resize(full, size, interpolation=cv2.INTER_AREA)
            self._smalls[q] = a
        return a

    def _motion(self, q: int) -> tuple[float, float] | None:
        """Frame ``q``'s background motion against the earliest frame registered in the
        ``background_frames`` before it (memoised)."""
        if q in self._motions:
            return self._motions[q]
        p = self.params
        motion = None
        R = self._poses.get(q)
        k0 = min((i for i in self._poses if q - p.background_frames <= i < q), default=None)
        small = self._small(q)
        old = None if k0 is None else self._small(k0)
        if k0 is not None and R is not None and small is not None and old is not None and old.shape == small.shape:
            if self._window is None or self._window.shape != small.shape:
                self._window = cv2.createHanningWindow((small.shape[1], small.shape[0]), cv2.CV_32F)
            (du, dv), response = cv2.phaseCorrelate(old, small, self._window)
            if response >= p.background_min_response:
                # where a point at infinity seen at the image centre on frame k0 is now: the rotation's share
                shift = rotation_shift_px(self.K, self.K.cx_px, self.K.cy_px, self._poses[k0], R)
                if shift is not None:
                    ru, rv = shift
                    n = q - k0
                    motion = ((du * BACKGROUND_SCALE - ru) / n, (dv * BACKGROUND_SCALE - rv) / n)
        self._motions[q] = motion
        return motion

    def background_over_window(self) -> tuple[float, float] | None:
        """The frame's background motion averaged over the ``confirm_window`` frames a velocity is fitted
        over (one 4-frame estimate wanders by 0.1-0.2 px/frame); None unless measured on half of them."""
        k = self._registered
        if k is None:
            return None
        frames = sorted(q for q in self._poses if q > k - self.params.confirm_window)
        if 2 * len(frames) < self.params.confirm_window:
            return None  # too few frames, measured or not (no correlation needed to know)
        hist = [m for m in (self._motion(q) for q in frames) if m is not None]
        if 2 * len(hist) < self.params.confirm_window:
            return None
        m = np.mean(np.array(hist), axis=0)
        return float(m[0]), float(m[1])

    def textured(self, uv: tuple[float, float]) -> bool:
        """The point ``uv`` (px) lies where the local noise (texture) is ``textured_noise_ratio`` times the frame's
        median: cloud or terrain, whose motion the frame's background motion stands for; on a clear
        sky there is no background to differ from."""
        noise = self._noise
        if noise is None:
            return False
        h, w = noise.shape  # the coarse grid: NOISE_FACTOR pixels a cell
        # sampled on a ring about the track, not under it: a bright point raises its own local noise
        r = TEXTURE_RING_PX
        samples = [
            noise[
                min(max((int(uv[1]) + di) // NOISE_FACTOR, 0), h - 1),
                min(max((int(uv[0]) + dj) // NOISE_FACTOR, 0), w - 1),
            ]
            for di, dj in ((-r, 0), (r, 0), (0, -r), (0, r), (-r, -r), (-r, r), (r, -r), (r, r))
        ]
        if self._noise_floor_frame != self.frame_index:  # once a frame, and only when asked
            self._noise_floor = float(np.percentile(noise, TEXTURE_REFERENCE_PERCENTILE))
            self._noise_floor_frame = self.frame_index
        return bool(float(np.median(samples)) > self.params.textured_noise_ratio * self._noise_floor)

    def surroundings_follow(self, t: TrackRecord) -> bool:
        """The texture about the track on the oldest of its recent frames, moved by the track's own image
        displacement since, matches this frame's ``SURROUND_MATCH_RATIO`` times better than moved ~3 px
        otherwise (:meth:`surroundings_match`): the background's motion where the track is, which the
        frame-wide one misses (looking down at a slant the nearer ground flows ~30 % faster than the
        whole frame, C2) and no neighbour track always stands for."""
        return bool(self.surroundings_match(t) > SURROUND_MATCH_RATIO)  # False when nan

    def surroundings_match(self, t: TrackRecord) -> float:
        """How much better the track's own displacement fits its surroundings than any ~3 px away: ``alt /
        own`` of :func:`onboard.imaging.background_difference.surround_residuals` over the track's recent frames (nan:
        too few frames or pixels).  Carried by them well over 1; crossing them, or on a featureless sky,
        about 1 or under."""
        if len(t.history) < 2:
            return float("nan")
        k0, _, u0, v0 = t.history[0]
        old = next((img for k, img in self._recent if k == k0), None)
        cur = self._recent[-1][1] if self._recent and self._recent[-1][0] == self.frame_index else None
        if old is None or cur is None:
            return float("nan")
        # the displacement from a straight-line fit of its measured pixels (each jitters by tenths of a px)
        f = np.array([e[0] for e in t.history], dtype=np.float64)
        slope = np.polyfit(f, np.array([(e[2], e[3]) for e in t.history]), 1)[0] * (self.frame_index - k0)
        own, alt = surround_residuals(cur, old, t.uv, (float(slope[0]), float(slope[1])))
        log.debug("surroundings of %d: own %.3f alt %.3f", t.object_id, own, alt)
        if not own > 0:  # nan (too few pixels), or a perfect match
            return float("inf") if alt > 0 else float("nan")
        return alt / own

    def difference_square(self, puv: tuple[float, float], R: np.ndarray, measure: bool = True):
        """This frame minus the one ``DIFFERENCE_LAG`` frames earlier, registered on ``puv``'s surroundings
        (searched about the camera's rotation plus the background's own motion:
        :func:`onboard.imaging.background_difference.background_difference`): ``(diff, moved, previous)``,
        ``previous`` that earlier frame, or None without the frames or the motion it needs.  ``measure`` False: the
        background's motion only as far as it was measured already this window (none: the rotation's share
        alone, the registration's search finds the rest within its 6 px), no phase correlation for it."""
        k = self.frame_index
        old, R0 = dict(self._recent).get(k - DIFFERENCE_LAG), self._poses.get(k - DIFFERENCE_LAG)
        if old is None or R0 is None or not self._recent or self._recent[-1][0] != k:
            return None
        if measure:
            bg = self.background_over_window()  # measured when asked for: only once the frames are there
        else:
            known = [m for q, m in self._motions.items() if q > k - self.params.confirm_window and m is not None]
            bg = tuple(np.mean(np.array(known), axis=0)) if known else (0.0, 0.0)
        if bg is None:
            return None
        # where the background now at puv was DIFFERENCE_LAG frames ago: the rotation's share, then its own motion
        p0 = pixel_from_los(self.K, los_from_pixel(self.K, puv[0], puv[1], R), R0)
        if p0 is None:
            return None
        du, dv = puv[0] - p0[0] + bg[0] * DIFFERENCE_LAG, puv[1] - p0[1] + bg[1] * DIFFERENCE_LAG
        diff, moved = background_difference(self._recent[-1][1], old, puv, (du, dv), DIFFERENCE_HALF_PX)
        return diff, moved, old

    def _registered_earlier(self, puv: tuple[float, float], diff: np.ndarray) -> np.ndarray:
        """The earlier frame's square as :meth:`difference_square` registered it about ``puv``: this frame's square
        minus ``diff`` (taken only where the signature needs it)."""
        cu, cv_ = difference_centre(puv)
        side = 2 * DIFFERENCE_HALF_PX + 1
        now = cv2.getRectSubPix(self._recent[-1][1], (side, side), (cu - 0.5, cv_ - 0.5), patchType=cv2.CV_32F)
        return now - diff

    def difference_candidate(
        self,
        puv: tuple[float, float],
        gate: float,
        R: np.ndarray,
        held: bool = False,
        signature: tuple[float, float] | None = None,
    ) -> tuple[PointCandidate | None, bool]:
        """Track-aided detection against the background (where its motion is known): the
        :meth:`difference_square` about the prediction, its strongest 2 x 2 mean within the gate
        (:func:`onboard.imaging.background_difference.difference_peak`); failing that, with ``signature`` (a
        held primary's ``(A, T)``, :class:`onboard.imaging.signature.Signature`), the best place of its matched
        filter within ``SIGNATURE_GATE_PX`` if its z reaches ``SIGNATURE_Z`` (a weak candidate).  Returns
        ``(candidate, by_signature)``: the candidate None without a detection there (or without the frames or the
        motion it needs), ``by_signature`` whether the signature's filter found it.  The caller leaves out a
        prediction with another confirmed track within ``DIFFERENCE_HALF_PX``."""
        sq = self.difference_square(puv, R)
        if sq is None:
            return None, False
        diff, moved, previous = sq
        # the frames are this one's levels (a 16-bit frame kept as float32 still whole levels; the old one,
        # were it another quantisation, is off them and left uncapped)
        cap_lsb = DIFFERENCE_TWO_LEVEL_CAP * self.clutter.two_level_cap_lsb
        cap = two_level_difference_cap(self._recent[-1][1], previous, puv, moved, cap_lsb, level=self.level)
        # a tighter gate than the point's: the difference keeps residuals of sharp field edges a few px away
        near = (DIFFERENCE_NEAR_PX, DIFFERENCE_NEAR_SIGMA) if held else (0.0, math.inf)
        floor = self.clutter.min_threshold_lsb * self.level
        c = difference_peak(diff, puv, min(gate, DIFFERENCE_GATE_PX), DIFFERENCE_SIGMA, floor, cap, *near)
        if c is not None or signature is None:
            return c, False
        cu, cv_ = difference_centre(puv)
        origin = (cu - DIFFERENCE_HALF_PX, cv_ - DIFFERENCE_HALF_PX)
        found = signature_peak(
            diff,
            self._registered_earlier(puv, diff),
            (puv[0] - origin[0], puv[1] - origin[1]),
            min(gate, SIGNATURE_GATE_PX),
            signature,
            SIGNATURE_Z,
            origin,
        )
        return (None, False) if found is None else (found[0], True)

    def learn_signature(self, signature: Signature, uv: tuple[float, float], R: np.ndarray) -> None:
        """Add this frame's :meth:`difference_square` about a track measured at ``uv`` to its ``signature``."""
        sq = self.difference_square(uv, R, measure=False)
        if sq is None:
            return
        diff = sq[0]
        old = self._registered_earlier(uv, diff)
        cu, cv_ = difference_centre(uv)
        # no less than the quantisation of two frames: on whole grey levels most of a well registered flat square
        # differs by exactly nothing, and its median would weigh that frame without bound
        sigma = max(square_sigma(diff), SIGNATURE_MIN_SIGMA_LSB * self.level)
        signature.add(diff, old, (uv[0] - cu + DIFFERENCE_HALF_PX, uv[1] - cv_ + DIFFERENCE_HALF_PX), sigma)


def symmetric_deblend(
    image: np.ndarray, centre_uv: tuple[float, float], core_px: float, radius_px: float, background: float
) -> np.ndarray:
    """``image`` (float32, not modified) with a bright object centred at ``centre_uv`` (px, frames.py
    convention: pixel (i, j) centred at j + 0.5, i + 0.5) taken out, so that a fainter object beside it
    keeps its own light and its surround is the background's.  The object's template is symmetric about
    its centre (the SDSS deblender's: Lupton 2005, "The SDSS imaging pipelines", and Bosch et al. 2018,
    PASJ 70, S5, sec. 4.9): ``T(x) = max(min(I(x), I(2c - x)) - b, 0)``, the lesser of a pixel and its
    reflection through the centre (bilinear) above the background ``b``, within ``radius_px`` of it.  A
    fainter object at ``c + d`` adds light at ``c + d`` only, so the minimum is the bright one's own
    there; a linear background gradient reflects below itself and is left alone.  Within ``core_px`` of
    the centre the pixels are the bright object's alone and are set to ``b`` (a sub-pixel error in the
    centre would leave residuals on a core's steep sides, standing in the fainter object's surround again).
    Returns a new float32 array of ``image``'s shape."""
    img = np.asarray(image, dtype=np.float32)
    return _deblend(img, centre_uv, _squared_distances(img.shape, centre_uv), core_px, radius_px, background)


def _squared_distances(shape: tuple[int, ...], centre_uv: tuple[float, float]) -> np.ndarray:
    """Each pixel's squared distance (px^2, float32) from ``centre_uv`` (frames.py convention)."""
    jj = np.arange(shape[1], dtype=np.float32)[None, :] + np.float32(0.5 - centre_uv[0])
    ii = np.arange(shape[0], dtype=np.float32)[:, None] + np.float32(0.5 - centre_uv[1])
    return jj * jj + ii * ii


def _deblend(
    img: np.ndarray, centre_uv: tuple[float, float], r2: np.ndarray, core_px: float, radius_px: float, background: float
) -> np.ndarray:
    """:func:`symmetric_deblend` of a float32 ``img``, ``r2`` its pixels' squared distances from the centre."""
    h, w = img.shape
    # the centre in index coordinates (pixel index j at j); the reflection j -> 2 cj - j
    cj, ci = centre_uv[0] - 0.5, centre_uv[1] - 0.5
    m = np.array([[-1.0, 0.0, 2.0 * cj], [0.0, -1.0, 2.0 * ci]], dtype=np.float32)
    mirrored = cv2.warpAffine(
        img, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )
    template = np.minimum(img, mirrored) - np.float32(background)
    np.maximum(template, 0.0, out=template)
    template[r2 > np.float32(radius_px * radius_px)] = 0.0
    out = img - template
    out[r2 <= np.float32(core_px * core_px)] = np.float32(background)
    return out
