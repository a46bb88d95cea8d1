"""Track-before-detect: dim point targets found by integrating frames along motion hypotheses.

``TrackBeforeDetect(K).update(image, R_ned_from_cam, focus_uv) -> list[PointCandidate]`` once per frame,
on the objects chain's cleaned frame (column offsets removed, defects repaired; float, the input's grey).

A target a few NETD above its background is below any single-frame threshold that keeps the false alarms
down, but its signal adds coherently over frames along its path while the noise adds in quadrature
(docs/perception.md has the figures on scene C4).  The stage:

1. **Background suppression**: the frame's ``decimation`` x ``decimation`` block means (1: full
   resolution), their ``smooth_cells`` box mean (about a blurred point's size: the matched filter's
   cheap stand-in), minus the local background (a box mean ``background_px`` wide, taken on a coarser
   grid): a linear high-pass, so the noise stays zero-mean and integrates down as ``1/sqrt(frames)``.
2. **Integration along hypotheses** (a bank of image velocities ``v_h`` in px per frame, on a grid of step
   ``speed_step_pxpf`` up to ``max_speed_pxpf`` per axis): one recursive mean per hypothesis,
   ``A_h <- (1 - gain) shift(A_h, s_rot + v_h) + gain F``, where ``s_rot`` is the image shift the camera's
   own rotation made at the window's centre (from the two frames' ``R_ned_from_cam``, the infinite
   homography: a point at infinity there moves so; the roll's share across the window is ignored: a search
   where the gimbal points keeps it small).  Shifts are applied in whole cells and the remainder carried
   to the next frame (never interpolated, so the integrated image is not blurred frame after frame); the
   misregistration this leaves (under half a cell per frame, signal-weighted over the memory) is tracked
   per hypothesis and removed from the reported centre, and so is the lag of a hypothesis slower or faster
   than the target (the peak's velocity interpolated between hypotheses, times the content's mean age).
   Memory ~``1 / gain`` frames (the recursive form of a sliding sum; Reed, Gagliardi & Shao 1983, IEEE
   TAES 19, 898 (the 3-D matched filter); Blostein & Huang 1991, IEEE TSP 39, 1611 (velocity hypotheses)).
3. **CFAR on the integrated image**: ``M = max_h A_h`` is thresholded at its local mean plus
   ``threshold_sigma`` local standard deviations (both over ``noise_window_px``, on a 4x coarser grid):
   the threshold follows whatever survives integration (noise down by ``sqrt(gain / (2 - gain))``,
   static cloud structure not), so the false-alarm rate stays near constant over sky and cloud.  A
   search skips peaks where the frame's own local rms is ``TEXTURED_RATIO`` times the window's quietest
   tenth: static cloud or terrain integrates as well as a target does, and a dim target is sought on sky.
4. **Confirmation**: a peak above ``threshold_sigma`` starts a pending peak; one above the lower
   ``track_threshold_sigma`` within ``confirm_radius_px`` of where a pending peak's velocity puts it
   continues it (hysteresis: a dim target's integrated peak hovers about the threshold); seen on
   ``confirm_frames`` frames in a row it is reported on every frame it is seen, to the multi-object
   tracker (which still applies its own M-of-N, fit and relative-motion tests).  Peaks within
   ``confirm_radius_px`` of a point the single-frame detector found are not reported (no duplicates).

The stage searches only while ``focus_uv`` is None (the chain has no primary target), over the
``search_px`` square about the principal point (where a pointing gimbal holds its target, and where the
chain's primary rule looks first; 0: the whole frame).  While the primary is the object this stage
confirmed, it integrates only a ``roi_px`` window about the primary's prediction (carrying the
integration over) and reports the strongest peak within ``focus_radius_px`` of it above
``track_threshold_sigma`` against the window's own statistics; with any other primary it is idle (and
forgets).  So its cost falls on the frames where no target is held, and on a dim target's window.

Positions are full-resolution pixels in the frames.py convention (pixel (i, j) centred at (j + 0.5,
i + 0.5)); decimated cell (i, j) covers pixels ``decimation * i ...``, centred at ``decimation * (j + 0.5)``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.core.errors import InputError
from onboard.imaging.background_difference import rotation_shift_px
from onboard.imaging.clutter import PointCandidate, noise_window_cells
from onboard.imaging.detect import Detection

__all__ = ["TbdParams", "TrackBeforeDetect", "frame_steps"]

log = logging.getLogger(__name__)

KNOWN_MARGIN_PX = 3  # about a known point's box, left out of the integration (its blur and sub-pixel motion)
TEXTURED_RATIO = 2.0  # a search skips cells whose local rms is this many times the window's quietest
TEXTURE_FLOOR_PERCENT = 10.0  # ... tenth's (the clear sky's noise where there is any clear sky)
FOCUS_RADIUS_PX = 6.0  # a primary this close to a peak this stage confirmed is that peak's object
CONFIRMED_MISSES = 3  # frames a confirmed peak may go unseen before it is forgotten
MAX_ABOVE_CELLS = 2000  # more cells above the threshold than this: a frame-wide change, not point targets
NMS_CELLS = 2  # peaks closer than this (cells, per axis) to a stronger one are the same peak
STATS_FACTOR = 4  # the CFAR's local mean and deviation are taken on a grid this many cells coarser
MAX_FRAME_STEPS = 30  # a gap between two frames counts as at most this many frame periods (1 s at 30 Hz)
US_PER_S = 1_000_000


def frame_steps(last_us: int | None, now_us: int | None, frame_rate_hz: float) -> int:
    """Frame periods from a frame stamped ``last_us`` to one stamped ``now_us`` (us): 1 without both stamps or
    when time goes back, at most ``MAX_FRAME_STEPS``.  A daemon on a loaded computer drops frames (its queue
    full), and a track's motion counted per frame must cover the time that passed: a bright target crossing at
    1 px a frame is 5 px off a one-frame prediction after 4 drops.  :mod:`onboard.imaging.objects` predicts its
    tracks over the gap as over frozen frames (time passes, nothing measured), except a track measured mostly
    by this stage: a dim target's rate, from integrated centres that scatter by a pixel, is too noisy to carry
    over a long gap (0.3 px/frame of noise, 14 frames: lost in a replay of C4 in the loop), and this stage
    does not scale its hypotheses either (see :meth:`TrackBeforeDetect.update`)."""
    if last_us is None or now_us is None or now_us <= last_us:
        return 1
    return min(max(round((now_us - last_us) * frame_rate_hz / US_PER_S), 1), MAX_FRAME_STEPS)


@dataclass(frozen=True)
class TbdParams:
    """Knobs of :class:`TrackBeforeDetect` (pixels are full-resolution; see the module docstring):
    ``decimation`` (cells of that many pixels a side), ``smooth_cells``, ``background_px``,
    ``search_px``; ``gain`` of the recursive means; the bank ``max_speed_pxpf``, ``speed_step_pxpf``;
    ``threshold_sigma`` to start and ``track_threshold_sigma`` to continue a peak; ``noise_window_px``
    of the CFAR statistics; ``confirm_frames``, ``confirm_radius_px``; ``roi_px`` the window about a
    followed target; ``max_candidates`` reported per frame; ``max_area_cells`` of the 5 x 5 about a peak
    above the threshold (a larger blob is not a point)."""

    decimation: int = 1
    smooth_cells: int = 2
    background_px: int = 15
    search_px: int = 256
    gain: float = 0.125
    max_speed_pxpf: float = 0.3
    speed_step_pxpf: float = 0.3
    threshold_sigma: float = 6.0
    track_threshold_sigma: float = 4.0
    noise_window_px: int = 64
    confirm_frames: int = 6
    confirm_radius_px: float = 3.0
    roi_px: int = 96
    max_candidates: int = 4
    max_area_cells: int = 23

    def __post_init__(self) -> None:
        if self.decimation < 1 or self.smooth_cells < 1 or self.background_px < 3 * self.decimation:
            raise InputError(
                "TbdParams decimation >= 1, smooth_cells >= 1 and background_px >= 3 cells, got "
                f"{self.decimation}, {self.smooth_cells}, {self.background_px}"
            )
        if not 0 < self.track_threshold_sigma <= self.threshold_sigma:
            raise InputError(
                "TbdParams 0 < track_threshold_sigma <= threshold_sigma, got "
                f"{self.track_threshold_sigma}, {self.threshold_sigma}"
            )
        if not 0 < self.gain <= 1:
            raise InputError(f"TbdParams gain in (0, 1], got {self.gain}")
        if self.max_speed_pxpf < 0 or (self.max_speed_pxpf > 0 and not self.speed_step_pxpf > 0):
            raise InputError(
                f"TbdParams max_speed_pxpf >= 0 and speed_step_pxpf > 0, got {self.max_speed_pxpf}, {self.speed_step_pxpf}"
            )
        if self.confirm_frames < 1 or self.roi_px < 8 * self.decimation:
            raise InputError(
                f"TbdParams confirm_frames >= 1 and roi_px >= 8 cells, got {self.confirm_frames}, {self.roi_px}"
            )

    def velocities_pxpf(self) -> np.ndarray:
        """The hypotheses' image velocities (n, 2), px per frame: a square grid, (0, 0) included."""
        if self.max_speed_pxpf <= 0:
            return np.zeros((1, 2))
        n = int(math.floor(self.max_speed_pxpf / self.speed_step_pxpf + 1e-9))
        axis = np.arange(-n, n + 1) * self.speed_step_pxpf
        vu, vv = np.meshgrid(axis, axis)
        return np.stack([vu.ravel(), vv.ravel()], axis=1)


@dataclass
class _Pending:
    u_px: float
    v_px: float
    velocity_pxpf: tuple[float, float]
    count: int
    seen: bool = True
    misses: int = 0


class TrackBeforeDetect:
    """See the module docstring.  ``intrinsics``: :class:`onboard.core.frames.PinholeIntrinsics`."""

    def __init__(self, intrinsics, params: TbdParams | None = None) -> None:
        self.K = intrinsics
        self.params = params or TbdParams()
        self._v_cells = self.params.velocities_pxpf() / self.params.decimation
        self._acc: np.ndarray | None = None  # (n_hyp, h, w) recursive means, this frame's window
        self._resid = np.zeros_like(self._v_cells)  # shift not yet applied, cells
        self._misreg = np.zeros_like(self._v_cells)  # signal-weighted misplacement of the content, cells
        self._weight = 0.0  # the recursive mean's total weight (1 - (1 - gain)^frames)
        self._age = 0.0  # the signal-weighted mean age of its content, frames
        self._texture: np.ndarray | None = None  # this frame's textured cells (coarse grid), while searching
        self._n_axis = int(round(math.sqrt(len(self._v_cells))))  # hypotheses per velocity axis
        self._step_cells = self.params.speed_step_pxpf / self.params.decimation
        self._origin = (0, 0)  # the window's top-left cell (row, column)
        self._R: np.ndarray | None = None
        self._rotation_px = np.zeros(2)  # the image shift the camera's rotation made since the last frame (px)
        self._pending: list[_Pending] = []
        self._mode = "search"  # search (no primary), window (the primary is this stage's), idle (another's)
        self._reports: list[tuple[PointCandidate, float]] = []  # this frame's reports and their local sigmas
        self.searched_frames = 0
        self.windowed_frames = 0
        self.confirmed = 0  # peaks seen on confirm_frames frames in a row, reported on that frame or held back

    def reset(self) -> None:
        """Forget the integration and the pending peaks (the next frame starts afresh)."""
        self._acc = None
        self._pending = []

    # ------------------------------------------------------------------ step

    def update(
        self,
        image: np.ndarray,
        R_ned_from_cam: np.ndarray,
        focus_uv: tuple[float, float] | None = None,
        known: Sequence[PointCandidate] = (),
    ) -> list[PointCandidate]:
        """One frame (float or integer (H, W) grey, the frame's pose): the confirmed candidates, strongest
        first.  ``focus_uv``: the chain's primary target's predicted centre (None: no primary; see the
        module docstring); ``known``: the points the single-frame detection found on this frame: left out
        of the integration (their box and ``KNOWN_MARGIN_PX`` about it: a bright point moving faster
        than the bank would leave a trail of peaks behind it) and never reported.  Frames the daemon dropped
        count as one period here (the camera's rotation over them is removed all the same): scaling the
        hypotheses' motion by the gap moved the content of the hypotheses off the target's speed away from
        the new frame's, and confirmed C4 later in a replay of the loop (1.90 -> 2.27 s)."""
        p = self.params
        if focus_uv is None:
            if self._mode != "search":
                self.reset()  # no primary any more: search the whole frame again, from nothing
                self._mode = "search"
        elif self._mode == "search":
            mine = self._acc is not None and any(
                q.count >= p.confirm_frames
                and math.hypot(q.u_px - focus_uv[0], q.v_px - focus_uv[1]) <= FOCUS_RADIUS_PX
                for q in self._pending
            )
            self._mode = "window" if mine else "idle"
            if not mine:
                self.reset()  # a primary this stage did not find: nothing to do until it is gone
        self._reports = []
        if self._mode == "idle":
            self._R = None
            return []
        R = np.asarray(R_ned_from_cam, dtype=np.float64)
        d = p.decimation
        h, w = image.shape[0] // d, image.shape[1] // d
        if focus_uv is None:
            win = self._search_window(h, w)
            self.searched_frames += 1
        else:
            side = max(p.roi_px // d, 8)
            i0 = min(max(int(focus_uv[1] / d) - side // 2, 0), max(h - side, 0))
            j0 = min(max(int(focus_uv[0] / d) - side // 2, 0), max(w - side, 0))
            win = (i0, j0, min(side, h), min(side, w))
            self.windowed_frames += 1
        frame = self._suppressed(image, win)
        self._mask_known(frame, win, known)
        self._texture = self._texture_map(frame) if focus_uv is None else None
        self._integrate(frame, R, win)
        self._R = R
        focus_cell = None if focus_uv is None else (focus_uv[1] / d - win[0], focus_uv[0] / d - win[1])
        found = self._peaks(focus_cell)
        found = [f for f in found if all(math.hypot(f[1] - c.u_px, f[2] - c.v_px) > p.confirm_radius_px for c in known)]
        if focus_uv is not None:
            return self._in_focus(found, focus_uv)
        return self._confirm(found)

    @property
    def following(self) -> bool:
        """True while the stage integrates a window about the primary it confirmed: what it reports is then
        the strongest peak within ``focus_radius_px`` of the primary's prediction."""
        return self._mode == "window"

    @property
    def focus_radius_px(self) -> float:
        """How far from the primary's prediction a peak it reports while :attr:`following` may lie."""
        return 2.0 * self.params.confirm_radius_px

    def _search_window(self, h: int, w: int) -> tuple[int, int, int, int]:
        """The searched window (top row, left column, rows, columns; cells): ``search_px`` square about
        the principal point (the whole frame when 0 or larger)."""
        p, d, K = self.params, self.params.decimation, self.K
        if p.search_px <= 0:
            return 0, 0, h, w
        sh, sw = min(p.search_px // d, h), min(p.search_px // d, w)
        i0 = min(max(int(K.cy_px / d) - sh // 2, 0), h - sh)
        j0 = min(max(int(K.cx_px / d) - sw // 2, 0), w - sw)
        return i0, j0, sh, sw

    def _suppressed(self, image: np.ndarray, win: tuple[int, int, int, int]) -> np.ndarray:
        """Block means of the window (grown by the background margin, clipped to the frame) minus their
        local box mean, cropped back to the window (float32, (wh, ww) cells)."""
        p = self.params
        d = p.decimation
        bc = max(p.background_px // d, 3)
        m = bc // 2 + p.smooth_cells
        i0, j0, wh, ww = win
        h, w = image.shape[0] // d, image.shape[1] // d
        a0, b0 = max(i0 - m, 0), max(j0 - m, 0)
        a1, b1 = min(i0 + wh + m, h), min(j0 + ww + m, w)
        crop = np.asarray(image[a0 * d : a1 * d, b0 * d : b1 * d], dtype=np.float32)
        cells = cv2.resize(crop, (b1 - b0, a1 - a0), interpolation=cv2.INTER_AREA) if d > 1 else crop
        if p.smooth_cells > 1:  # a box about the size of a blurred point: its mean, anchored at the top left
            cells = cv2.blur(cells, (p.smooth_cells, p.smooth_cells), anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
        # the local background: a 3 x 3 box mean on a grid background_px / 3 times coarser, interpolated
        # back (a full-size box mean costs ~5x more; the background is smooth)
        ch, cw = cells.shape
        f = max(bc // 3, 1)
        coarse = cv2.resize(cells, (max(cw // f, 1), max(ch // f, 1)), interpolation=cv2.INTER_AREA)
        bg = cv2.resize(
            cv2.blur(coarse, (3, 3), borderType=cv2.BORDER_REFLECT), (cw, ch), interpolation=cv2.INTER_LINEAR
        )
        hp = cv2.subtract(cells, bg)
        return hp[i0 - a0 : i0 - a0 + wh, j0 - b0 : j0 - b0 + ww]

    def _texture_map(self, frame: np.ndarray) -> np.ndarray:
        """Per ``STATS_FACTOR`` cells, whether this frame's local rms (over ``noise_window_px``) is above
        ``TEXTURED_RATIO`` times the window's quietest tenth: cloud or terrain, where static structure
        integrates as well as a target does (bool, coarse grid)."""
        p = self.params
        h, w = frame.shape
        f = STATS_FACTOR if min(h, w) >= 4 * STATS_FACTOR else 1
        k = noise_window_cells(p.noise_window_px, p.decimation * f)
        sq = cv2.resize(cv2.multiply(frame, frame), (max(w // f, 1), max(h // f, 1)), interpolation=cv2.INTER_AREA)
        ms = cv2.blur(sq, (k, k), borderType=cv2.BORDER_REFLECT)
        # the box filter keeps running sums (adds the entering column, subtracts the leaving one): where the
        # window leaves texture for an exactly flat area (a flat frame or part of one) it leaves a rounding
        # residue instead of 0, which may be negative: its sqrt NaN made the percentile NaN, the map all False
        rms = np.sqrt(np.maximum(ms, np.float32(0.0)))
        return rms > TEXTURED_RATIO * float(np.percentile(rms, TEXTURE_FLOOR_PERCENT))

    def _mask_known(self, frame: np.ndarray, win: tuple[int, int, int, int], known: Sequence[PointCandidate]) -> None:
        """Zero the suppressed window (in place) over each known point's box grown by ``KNOWN_MARGIN_PX``."""
        d = self.params.decimation
        i0, j0, wh, ww = win
        m = KNOWN_MARGIN_PX + self.params.smooth_cells * d  # the smoothing box reaches back that far
        for c in known:
            x, y, w, h = c.bbox
            a0, a1 = max((y - m) // d - i0, 0), min((y + h + KNOWN_MARGIN_PX) // d + 1 - i0, wh)
            b0, b1 = max((x - m) // d - j0, 0), min((x + w + KNOWN_MARGIN_PX) // d + 1 - j0, ww)
            if a1 > a0 and b1 > b0:
                frame[a0:a1, b0:b1] = 0.0

    def _rotation_shift_cells(self, R: np.ndarray, win: tuple[int, int, int, int]) -> np.ndarray:
        """Where a point at infinity seen at the window's centre on the previous frame is now, minus
        where it was (cells)."""
        if self._R is None:
            return np.zeros(2)
        d = self.params.decimation
        i0, j0, wh, ww = win
        shift = rotation_shift_px(self.K, d * (j0 + ww / 2), d * (i0 + wh / 2), self._R, R)
        return np.zeros(2) if shift is None else np.array(shift) / d

    def _integrate(self, frame: np.ndarray, R: np.ndarray, win: tuple[int, int, int, int]) -> None:
        p = self.params
        i0, j0, wh, ww = win
        acc = self._acc
        self._rotation_px = np.zeros(2)
        if acc is None:
            self._acc = acc = np.zeros((len(self._v_cells), wh, ww), np.float32)
            self._resid[:] = 0.0
            self._misreg[:] = 0.0
            self._weight = 0.0
            self._age = 0.0
        else:
            # content moves by the rotation and the hypothesis' own motion; the window's move (cells)
            # shifts it the other way
            rot = self._rotation_shift_cells(R, win)
            self._rotation_px = rot * p.decimation
            moved = rot[None, :] + self._v_cells
            moved -= np.array([j0 - self._origin[1], i0 - self._origin[0]], dtype=float)[None, :]
            self._resid += moved
            whole = np.rint(self._resid)
            self._resid -= whole
            # the placed content is off its true place by (applied - true) shift, kept as a weighted mean
            self._misreg += whole - moved
            if acc.shape[1:] != (wh, ww):  # the window changed size: cut the new one out of the old
                old, acc = acc, np.zeros((len(self._v_cells), wh, ww), np.float32)
                for h_i, (du, dv) in enumerate(whole.astype(int)):
                    _shift_into(acc[h_i], old[h_i], int(dv), int(du))
                self._acc = acc
            else:
                for h_i, (du, dv) in enumerate(whole.astype(int)):
                    if du or dv:
                        _shift_in_place(acc[h_i], int(dv), int(du))
        # A <- (1 - g) A + g F, in place per hypothesis
        g = float(p.gain)
        for a in acc:
            cv2.addWeighted(a, 1.0 - g, frame, g, 0.0, dst=a)
        w_old = self._weight * (1 - p.gain)
        self._weight = w_old + p.gain
        self._misreg *= w_old / self._weight  # the new frame's content sits where it belongs
        self._age = (self._age + 1.0) * w_old / self._weight
        self._origin = (i0, j0)

    def _peaks(self, focus_cell: tuple[float, float] | None) -> list[tuple]:
        """This frame's peaks above the (lower, ``track_threshold_sigma``) CFAR threshold, strongest first:
        (local sigmas, u, v, velocity, bbox, area, peak) tuples, one per local maximum (non-maximum
        suppression over ``NMS_CELLS``).  ``focus_cell`` (row, column in the window; None: a search):
        only peaks within ``FOCUS_RADIUS_PX`` of it, against the window's own mean and deviation (the
        window is about one CFAR window wide)."""
        p = self.params
        search = focus_cell is None
        acc = self._acc
        if acc is None or self._weight < 0.5:  # under ~5 frames integrated: the statistics mean little
            return []
        best = acc[0].copy()
        for a in acc[1:]:
            cv2.max(best, a, dst=best)
        k = p.track_threshold_sigma  # the lower one: a peak already pending continues above it
        if search:
            thr, mean, sd = self._threshold(best, k)
        else:
            m, sdev = cv2.meanStdDev(best)
            mean, sd = (
                _Coarse(np.full((1, 1), m[0, 0], np.float32), 1 << 30),
                _Coarse(np.full((1, 1), sdev[0, 0], np.float32), 1 << 30),
            )
            thr = np.full_like(best, m[0, 0] + k * sdev[0, 0])
        mask = (best >= thr).view(np.uint8)
        # a border as wide as the fastest hypothesis' drift over the memory: cells there hold fewer frames
        b = 1 + int(math.ceil(float(np.abs(self._v_cells).max(initial=0.0)) / p.gain))
        if search:
            mask[:b] = 0
            mask[-b:] = 0
            mask[:, :b] = 0
            mask[:, -b:] = 0
        pts = cv2.findNonZero(mask)
        if pts is None:
            return []
        pts = pts.reshape(-1, 2)
        if len(pts) > MAX_ABOVE_CELLS:  # a flood (a frame-wide change): no point-like peak to find
            return []
        vals = best[pts[:, 1], pts[:, 0]]
        order = np.argsort(-vals, kind="stable")
        d = p.decimation
        i0, j0 = self._origin
        h, w = best.shape
        focus_cells = FOCUS_RADIUS_PX / d + p.smooth_cells
        found: list[tuple] = []
        taken: list[tuple[int, int]] = []
        for n in order:
            c, r = int(pts[n, 0]), int(pts[n, 1])
            if any(abs(r - tr) <= NMS_CELLS and abs(c - tc) <= NMS_CELLS for tr, tc in taken):
                continue
            taken.append((r, c))
            if focus_cell is not None and max(abs(r - focus_cell[0]), abs(c - focus_cell[1])) > focus_cells:
                continue  # a peak away from the followed target: of no use, not measured
            tex = self._texture
            if (
                tex is not None
                and tex[min(r // STATS_FACTOR, tex.shape[0] - 1), min(c // STATS_FACTOR, tex.shape[1] - 1)]
            ):
                continue  # on cloud or terrain: their static structure integrates like a target
            g = NMS_CELLS
            area = int(np.count_nonzero(mask[max(r - g, 0) : r + g + 1, max(c - g, 0) : c + g + 1]))
            if area > p.max_area_cells:
                continue  # a blob filling its surround: structure, not a point
            r0, r1, c0, c1 = max(r - 1, 0), min(r + 2, h), max(c - 1, 0), min(c + 2, w)
            hyp = int(np.argmax(acc[:, r, c]))
            cu, cv_ = _centroid(acc[hyp], r, c)
            vel_cells = self._velocity_cells(hyp, r, c)
            # content k frames old sits (v_h - v) k off: corrected over the content's mean age
            lag = (vel_cells - self._v_cells[hyp]) * self._age
            cu += lag[0] - self._misreg[hyp, 0]
            cv_ += lag[1] - self._misreg[hyp, 1]
            # cell (i, j) holds the smoothing box from (i, j) on: its centre is (smooth - 1) / 2 cells on
            off = 0.5 * p.smooth_cells
            u, v = d * (j0 + cu + off), d * (i0 + cv_ + off)
            z = float((best[r, c] - mean[r, c]) / max(float(sd[r, c]), 1e-12))
            vel = (float(vel_cells[0]) * d, float(vel_cells[1]) * d)
            bbox = (d * (j0 + c0), d * (i0 + r0), d * (c1 - c0), d * (r1 - r0))
            found.append((z, u, v, vel, bbox, area * d * d, float(best[r, c])))
            if len(found) >= 4 * p.max_candidates:
                break
        found.sort(key=lambda f: -f[0])
        return found

    def _velocity_cells(self, hyp: int, r: int, c: int) -> np.ndarray:
        """The peak's velocity (cells per frame) between the bank's hypotheses: per axis, the vertex of the
        parabola through the best hypothesis' and its two neighbours' largest values about (r, c) (a
        neighbour's peak lies a little off: it integrated the path at another speed)."""
        acc, n = self._acc, self._n_axis
        assert acc is not None
        v = self._v_cells[hyp].copy()
        if n < 2:
            return v
        r0, r1, c0, c1 = max(r - NMS_CELLS, 0), r + NMS_CELLS + 1, max(c - NMS_CELLS, 0), c + NMS_CELLS + 1
        f0 = float(acc[hyp, r, c])
        iu, iv = hyp % n, hyp // n
        for axis, i, stride in ((0, iu, 1), (1, iv, n)):
            if 0 < i < n - 1:
                fm = float(acc[hyp - stride, r0:r1, c0:c1].max())
                fp = float(acc[hyp + stride, r0:r1, c0:c1].max())
                den = fm - 2.0 * f0 + fp
                if den < 0:
                    v[axis] += min(max(0.5 * (fm - fp) / den, -0.5), 0.5) * self._step_cells
        return v

    def detection_at(self, uv: tuple[float, float], image: np.ndarray) -> Detection | None:
        """This frame's report at ``uv`` (the very centre a track took from it) as a
        :class:`~onboard.imaging.detect.Detection`, else None.  A dim target's single-frame centroid fails
        or wanders on most frames; the integrated centre is its measurement: ``contrast`` the integrated
        mean contrast (grey, over the smoothing box), ``snr`` its local sigmas in the integrated image,
        ``peak`` the raw grey at the centre."""
        for c, z in self._reports:
            if c.u_px == uv[0] and c.v_px == uv[1]:
                h, w = image.shape
                i, j = min(max(int(c.v_px), 0), h - 1), min(max(int(c.u_px), 0), w - 1)
                x, y, bw, bh = c.bbox
                border = x <= 0 or y <= 0 or x + bw >= w or y + bh >= h
                flux = c.peak * self.params.smooth_cells**2 * self.params.decimation**2
                return Detection(c.u_px, c.v_px, c.area_px, c.peak, flux, c.bbox, float(image[i, j]), z, border)
        return None

    def _in_focus(self, found: list, focus_uv: tuple[float, float]) -> list[PointCandidate]:
        p = self.params
        near = [f for f in found if math.hypot(f[1] - focus_uv[0], f[2] - focus_uv[1]) <= self.focus_radius_px]
        if not near:
            return []
        # the strongest, not the nearest: the prediction follows what this stage reports, so a noise peak beside
        # the target, once taken, draws the prediction after it and the nearest rule keeps it (C4 seed 5 over
        # 30 s: a z 6.9 peak 4.5 px off, then the target's z 5.6-5.8 ignored 3-6 px from the drifting focus)
        z, u, v, _, bbox, area, peak = max(near, key=lambda f: f[0])
        c = PointCandidate(u, v, bbox, area, peak, max(z / p.track_threshold_sigma, 1.0))
        self._reports = [(c, z)]
        return [c]

    def _confirm(self, found: list) -> list[PointCandidate]:
        """Match this frame's peaks to the pending ones (moved by their hypothesis' velocity); those
        seen on ``confirm_frames`` frames in a row are reported."""
        p = self.params
        # a pending peak moves with the camera's rotation as well as by its own velocity: a frame-to-frame
        # rotation is well inside the matching radius, but a frame the daemon dropped (its queue full on a
        # loaded computer) lets it grow past it, and the peak would start over from nothing
        rot_u, rot_v = (float(x) for x in self._rotation_px)
        for q in self._pending:
            q.u_px += q.velocity_pxpf[0] + rot_u
            q.v_px += q.velocity_pxpf[1] + rot_v
            q.misses = 0 if q.seen else q.misses + 1
            q.seen = False
        out: list[PointCandidate] = []
        for z, u, v, vel, bbox, area, peak in found:
            near = min(
                (q for q in self._pending if not q.seen),
                key=lambda q: math.hypot(q.u_px - u, q.v_px - v),
                default=None,
            )
            if near is None or math.hypot(near.u_px - u, near.v_px - v) > p.confirm_radius_px:
                if z < p.threshold_sigma:  # only a peak above the full threshold starts one (hysteresis)
                    continue
                near = _Pending(u, v, vel, 0)
                self._pending.append(near)
            q = near
            q.u_px, q.v_px, q.velocity_pxpf, q.seen = u, v, vel, True
            q.count += 1
            if q.count == p.confirm_frames:  # counted once, whether or not this frame's reports have room
                self.confirmed += 1
                log.debug("track-before-detect: peak confirmed at (%.1f, %.1f), %.1f sigma", u, v, z)
            if q.count >= p.confirm_frames and len(out) < p.max_candidates:
                out.append(PointCandidate(u, v, bbox, area, peak, max(z / p.threshold_sigma, 1.0)))
                self._reports.append((out[-1], z))
        # a confirmed peak survives a few frames unseen (a dim target dips), a pending one none
        self._pending = [
            q for q in self._pending if q.seen or (q.count >= p.confirm_frames and q.misses < CONFIRMED_MISSES)
        ]
        return out

    def _threshold(self, img: np.ndarray, k_sigma: float) -> tuple[np.ndarray, _Coarse, _Coarse]:
        """The CFAR threshold ``mean + k_sigma * sd`` of ``img`` over ``noise_window_px`` (full size,
        float32), and the local mean and sd (read at full-size indices): the moments are taken on a
        ``STATS_FACTOR`` times coarser grid, the threshold interpolated back."""
        p = self.params
        h, w = img.shape
        f = STATS_FACTOR if min(h, w) >= 4 * STATS_FACTOR else 1
        hc, wc = max(h // f, 1), max(w // f, 1)
        k = noise_window_cells(p.noise_window_px, p.decimation * f)
        m1 = cv2.blur(cv2.resize(img, (wc, hc), interpolation=cv2.INTER_AREA), (k, k), borderType=cv2.BORDER_REFLECT)
        sq = cv2.multiply(img, img)
        m2 = cv2.blur(cv2.resize(sq, (wc, hc), interpolation=cv2.INTER_AREA), (k, k), borderType=cv2.BORDER_REFLECT)
        sd = np.sqrt(np.maximum(m2 - m1 * m1, np.float32(0.0)))
        thr = m1 + np.float32(k_sigma) * sd
        if (hc, wc) != (h, w):
            thr = np.asarray(cv2.resize(thr, (w, h), interpolation=cv2.INTER_LINEAR))
        return thr, _Coarse(m1, f), _Coarse(sd, f)


class _Coarse:
    """A coarse grid read at full-size indices (``grid[i // f, j // f]``)."""

    def __init__(self, grid: np.ndarray, factor: int) -> None:
        self.grid, self.factor = grid, factor

    def __getitem__(self, ij: tuple[int, int]) -> float:
        g = self.grid
        return float(g[min(ij[0] // self.factor, g.shape[0] - 1), min(ij[1] // self.factor, g.shape[1] - 1)])


def _shift_in_place(a: np.ndarray, di: int, dj: int) -> None:
    """``a[i + di, j + dj] = a[i, j]``, the cells left behind zeroed (numpy copies overlapping views safely)."""
    h, w = a.shape
    if abs(di) >= h or abs(dj) >= w:
        a[:] = 0
        return
    a[max(di, 0) : h + min(di, 0), max(dj, 0) : w + min(dj, 0)] = a[
        max(-di, 0) : h - max(di, 0), max(-dj, 0) : w - max(dj, 0)
    ]
    if di > 0:
        a[:di] = 0
    elif di < 0:
        a[h + di :] = 0
    if dj > 0:
        a[:, :dj] = 0
    elif dj < 0:
        a[:, w + dj :] = 0


def _shift_into(dst: np.ndarray, src: np.ndarray, di: int, dj: int) -> None:
    """``dst[i + di, j + dj] = src[i, j]`` where both are inside (the rest of ``dst`` untouched; the
    shapes may differ: a window cut from the whole frame)."""
    hs, ws = src.shape
    hd, wd = dst.shape
    si0, si1 = max(-di, 0), min(hs, hd - di)
    sj0, sj1 = max(-dj, 0), min(ws, wd - dj)
    if si1 > si0 and sj1 > sj0:
        dst[si0 + di : si1 + di, sj0 + dj : sj1 + dj] = src[si0:si1, sj0:sj1]


def _centroid(img: np.ndarray, r: int, c: int) -> tuple[float, float]:
    """The centre (column, row; cells, float) of the positive part of the 3 x 3 about (r, c)."""
    h, w = img.shape
    r0, r1, c0, c1 = max(r - 1, 0), min(r + 2, h), max(c - 1, 0), min(c + 2, w)
    win = np.maximum(img[r0:r1, c0:c1], 0.0)
    s = float(win.sum())
    if s <= 0:
        return float(c), float(r)
    rr, cc = np.mgrid[r0:r1, c0:c1]
    return float((win * cc).sum() / s), float((win * rr).sum() / s)
