"""The object tracker's searches beneath the whole-frame threshold: where a track or the gimbal's aim gives a prior,
a lower threshold or the background difference finds what the whole frame's CFAR threshold misses.

:class:`BelowThreshold` is :class:`onboard.imaging.objects.ObjectTracker`'s base: track-aided detection inside
each held track's gate (:meth:`~BelowThreshold._aided_candidates`), the background difference where the gimbal
points while there is no primary (:meth:`~BelowThreshold._difference_search`), the primary's occlusion signature
learned and used (:meth:`~BelowThreshold._learn_signature`, :mod:`onboard.imaging.signature`), and the test that a
track held by these alone still moves unlike its background (:meth:`~BelowThreshold._moves_unlike_background`).
They read and extend the tracker's state; the tracker's own module keeps association, confirmation and the primary.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.clutter import ClutterParams, PointCandidate, point_candidates
from onboard.imaging.objects_association import in_own_gate, owning_tracks, track_gate
from onboard.imaging.objects_detection import DIFFERENCE_GATE_PX, DIFFERENCE_HALF_PX, ObjectDetector
from onboard.imaging.objects_model import ObjectParams, TrackRecord, fit_constant_velocity
from onboard.imaging.signature import Signature

__all__ = ["BelowThreshold"]

SIGNATURE_MAX_RUN = 30  # frames in a row a primary may be measured by its signature alone (C2's roofs: 20-27)
SIGNATURE_EVERY = 4  # frames between the primary's signature samples (a difference square each, ~0.5 ms)
DIFFERENCE_SEARCH_MAX = 8  # points tried a frame by the background difference while there is no primary (0.2 ms each)
AIDED_FIT_TRIM = 2  # positions the aided run's motion test may leave out (its worst, one at a time) ...
AIDED_FIT_MIN_KEPT = 8  # ... keeping at least these


class BelowThreshold:
    """The searches (module docstring), over the state :class:`~onboard.imaging.objects.ObjectTracker` keeps."""

    K: PinholeIntrinsics
    params: ObjectParams
    clutter: ClutterParams
    detector: ObjectDetector
    _tracks: list[TrackRecord]
    _primary: int | None
    _frame_index: int
    _difference_ids: set[int]  # id() of this frame's background-difference candidates
    _signature_ids: set[int]  # ... and those of them its occlusion signature found

    def _predicted_px(self, R: np.ndarray) -> list[tuple[float, float] | None]:
        raise NotImplementedError  # the tracker's: each track's predicted pixel on this frame

    def _aided_candidates(self, cands: list[PointCandidate], R: np.ndarray) -> list[PointCandidate]:
        """Track-aided detection: inside the gate of each confirmed track (measured or coasting), and of
        each tentative one with ``confirm_hits`` hits for at most ``aided_tentative_max_run`` frames in a
        row, that no candidate falls in, the strongest component of the point contrast above
        ``aided_threshold_factor`` times the window mean's CFAR threshold (:attr:`ObjectDetector.lowered_base`;
        a confirmed track's, failing that, the background difference).  Where an object is already known the
        prior is strong and a lower threshold costs few false alarms (a gate is ~0.1 % of the frame); it
        bridges the frames where a dim or flickering object dips below the whole-frame threshold.  Candidates
        are added to ``cands`` (a new list)."""
        p = self.params
        contrast = self.detector.contrast
        if contrast is None or self.detector.threshold is None or p.aided_threshold_factor >= 1.0:
            return cands
        h, w = contrast.shape
        out = list(cands)
        # the predictions of the confirmed tracks measured on the last frame: a candidate within OWNED_PX of
        # another's is that one's, and leaves a track's gate open (C3: the second target, 3-5 px beside
        # the primary, coasted while the primary's candidate lay in its gate)
        pred = self._predicted_px(R)
        held = [(t, q) for t, q in zip(self._tracks, pred) if t.confirmed and t.misses == 0 and q is not None]
        owners = [owning_tracks(c.u_px, c.v_px, held) for c in out]  # mostly none
        for t, puv in zip(self._tracks, pred):
            # a track held only by aided detections for long may have slid onto clutter: it must be
            # seen by the whole-frame threshold again, unless it still moves unlike its textured
            # background (a fragment of terrain or cloud it slid onto would move with it); beyond
            # aided_max_run_moving frames only the background difference, which cancels whatever moves
            # with the background, measures it
            if not t.confirmed:
                # a tentative track with confirm_hits hits may bridge single misses (a target near the
                # threshold, detected on two frames of three, never reached 12 of 15: C3 seed 1's second
                # target, frames 30-124); two aided frames in a row confirmed a terrain fragment on C2
                if t.hits < p.confirm_hits or t.aided_run >= p.aided_tentative_max_run:
                    continue
            elif t.aided_run >= p.aided_max_run and not self._moves_unlike_background(t, R):
                continue
            if puv is None:
                continue
            gate = float(track_gate(p, t.misses))
            if any(
                math.hypot(c.u_px - puv[0], c.v_px - puv[1]) <= gate and all(o is t for o in ow)
                for c, ow in zip(out, owners)
            ):
                continue
            if t.confirmed and t.aided_run >= p.aided_max_run_moving:
                # C2's clean twin's target, 2 grey of point contrast on flat ground whose pixels toggle
                # between two grey levels (the threshold 5.5 x 0.5 grey), is never over the whole-frame
                # threshold after ~14 s; the difference finds it on 91-99 % of the frames
                best = self._difference_candidate(t, puv, gate, R)
                if best is not None:
                    self._difference_ids.add(id(best))
                    out.append(best)
                    owners.append(owning_tracks(best.u_px, best.v_px, held))
                continue
            others = [q for o, q in held if o is not t]
            r = int(math.ceil(gate)) + 2
            x0, y0 = max(int(puv[0]) - r, 0), max(int(puv[1]) - r, 0)
            x1, y1 = min(int(puv[0]) + r + 1, w), min(int(puv[1]) + r + 1, h)
            if x1 - x0 < 3 or y1 - y0 < 3:
                continue
            threshold = self.detector.lowered_base_block(y0, y1, x0, x1)  # the gate's block alone
            assert threshold is not None
            roi = point_candidates(
                contrast[y0:y1, x0:x1],
                # a coasting track's widened gate holds more noise peaks (12 px: 9 times a measured track's
                # area; over C1-C5 25 of 41 aided re-finds after 2 or more misses lay off every object): the
                # threshold rises with the gate's side
                threshold * np.float32(p.aided_threshold_factor * math.sqrt(gate / p.gate_px)),
                self.clutter,
            )
            best = None
            for c in roi:
                u, v = c.u_px + x0, c.v_px + y0
                if in_own_gate(u, v, puv, gate, others) and (best is None or c.score > best.score):
                    best = dataclasses.replace(
                        c, u_px=u, v_px=v, bbox=(c.bbox[0] + x0, c.bbox[1] + y0, c.bbox[2], c.bbox[3])
                    )
            if best is None and t.confirmed:
                best = self._difference_candidate(t, puv, gate, R)
                if best is not None:
                    self._difference_ids.add(id(best))
            if best is not None:
                out.append(best)
                owners.append(owning_tracks(best.u_px, best.v_px, held))
        return out

    def _difference_search(self, found: list[PointCandidate], R: np.ndarray) -> list[PointCandidate]:
        """While there is no primary target: the background difference as a detector where the gimbal points.
        Of the points within ``primary_max_off_axis_rad`` of the optical axis whose point contrast is over
        ``aided_threshold_factor`` times the window mean's CFAR threshold but under it, none within ``gate_px``
        of a candidate already found nor with a confirmed track in its square, on texture, the
        ``DIFFERENCE_SEARCH_MAX`` strongest are tried (:meth:`ObjectDetector.difference_candidate`, 5 of its
        own sigmas within ``DIFFERENCE_GATE_PX`` of the point); what it finds is a candidate like any (it may
        start a track, which must still pass every confirmation test).  Over textured ground the point
        contrast of a look-down target falls under a threshold the texture sets (C2 seeds 1 and 2: median 0.58
        and 0.53 of it), while the difference, registered on the point's surroundings 8 frames back, cancels
        what moves with the ground; on a clear sky the whole-frame threshold is the detector."""
        p, K = self.params, self.K
        contrast = self.detector.contrast
        if contrast is None or self.detector.threshold is None:
            return []
        h, w = contrast.shape
        reach = math.tan(p.primary_max_off_axis_rad)
        x0, x1 = max(int(K.cx_px - K.fx_px * reach), 0), min(int(K.cx_px + K.fx_px * reach) + 1, w)
        y0, y1 = max(int(K.cy_px - K.fy_px * reach), 0), min(int(K.cy_px + K.fy_px * reach) + 1, h)
        if x1 - x0 < 3 or y1 - y0 < 3:
            return []
        factor = np.float32(p.aided_threshold_factor)
        threshold = self.detector.lowered_base_block(y0, y1, x0, x1)
        assert threshold is not None
        weak = point_candidates(contrast[y0:y1, x0:x1], threshold * factor, self.clutter)
        out: list[PointCandidate] = []
        tried = 0
        for c in sorted(weak, key=lambda c: -c.score):  # score: contrast over the lowered threshold
            if tried >= DIFFERENCE_SEARCH_MAX:
                break
            u, v = c.u_px + x0, c.v_px + y0
            off = math.hypot((u - K.cx_px) / K.fx_px, (v - K.cy_px) / K.fy_px)
            if c.score * p.aided_threshold_factor >= 1.0 or off > reach:
                continue  # a candidate of the whole-frame threshold already, or outside the circle
            if any(math.hypot(f.u_px - u, f.v_px - v) <= p.gate_px for f in found):
                continue
            if any(o.confirmed and max(abs(o.uv[0] - u), abs(o.uv[1] - v)) <= DIFFERENCE_HALF_PX for o in self._tracks):
                continue
            if not self.detector.textured((u, v)):
                continue
            tried += 1
            d, _ = self.detector.difference_candidate((u, v), DIFFERENCE_GATE_PX, R)
            if d is not None:
                self._difference_ids.add(id(d))
                out.append(d)
        return out

    def _difference_candidate(
        self, t: TrackRecord, puv: tuple[float, float], gate: float, R: np.ndarray
    ) -> PointCandidate | None:
        """Track-aided detection against the background (:meth:`ObjectDetector.difference_candidate`)."""
        # another object in the square moves unlike the background too: whose difference is whose is
        # ambiguous (at C3's crossing it swapped the two targets' ids)
        if any(
            o is not t and o.confirmed and max(abs(o.uv[0] - puv[0]), abs(o.uv[1] - puv[1])) <= DIFFERENCE_HALF_PX
            for o in self._tracks
        ):
            return None
        # a track measured on the frame before is searched at 4 sigmas within 1.5 px of its prediction: C2 seed 3's
        # target, at one grey level of point contrast over its roofs, stood at 4-5 sigmas of the difference there
        # on most of its single missed frames
        # the primary, failing the 2 x 2 test, by its occlusion signature: over a roof warmer than it a target hides
        # hot roof and cooler ground within two pixels, and only a test signed by what it hides adds both halves
        # (C2 seeds 1 and 5: the target colder than the roofs it crosses on 8-18 % of the frames)
        # ... for at most SIGNATURE_MAX_RUN frames in a row: then it must be found again by the 2 x 2 test or a point
        # (in the loop a run of them slid off C2 seed 1's target after its roof and held it there)
        fit = None
        if t.object_id == self._primary and t.signature is not None and t.signature_run < SIGNATURE_MAX_RUN:
            fit = t.signature.fit()
        c, by_signature = self.detector.difference_candidate(
            puv, gate, R, held=t.confirmed and t.misses == 0, signature=fit
        )
        if c is not None and by_signature:
            self._signature_ids.add(id(c))
        # its square is taken with the frame's edge pixels repeated beyond it, so a prediction at the edge can peak
        # off the frame: no measurement (the frame pipeline refuses a measured centre off the frame, and with it
        # the frame's track: tracker_output_invalid)
        if c is not None and not (0.0 <= c.u_px <= self.K.width_px and 0.0 <= c.v_px <= self.K.height_px):
            return None
        return c

    def _learn_signature(self, R: np.ndarray, measured: set[int]) -> None:
        """Every ``SIGNATURE_EVERY`` frames the primary is measured on (by a candidate that is not weak) over
        texture, its difference square there is added to its signature (:class:`onboard.imaging.signature.Signature`).
        Not on a clear sky: there the 2 x 2 test has nothing to lose the target to, and the background's motion the
        square needs would be measured for it alone (0.6 ms a frame on C1)."""
        if self._frame_index % SIGNATURE_EVERY:
            return
        t = next((t for t in self._tracks if t.object_id == self._primary), None)
        if t is None or not t.confirmed or t.misses or t.weak_hit or t.object_id not in measured:
            return
        if not self.detector.textured(t.uv):
            return
        if t.signature is None:
            t.signature = Signature()
        self.detector.learn_signature(t.signature, t.uv, R)

    def _moves_unlike_background(self, t: TrackRecord, R: np.ndarray) -> bool:
        """The background's motion is known (no: a clear sky) and the track's last ``confirm_window``
        frames' positions (``confirm_hits`` at least; a track coasting with fewer: its last ``confirm_hits``
        measured positions) fit a constant velocity within ``aided_max_fit_rms_px`` differing from it by
        ``min_relative_speed_pxpf``."""
        p = self.params
        need = max(p.confirm_hits, 3)
        recent = [h for h in t.history if h[0] > self._frame_index - p.confirm_window]
        if len(recent) < need:
            # coasting: its last measured positions, however long ago (within the coast), or the test could
            # never pass again while it coasts, and a primary coasting over textured ground lost its aided
            # search for good (C2 seed 1); a track that slid onto clutter still fails, its last positions
            # moving with the background.  Only the last few: a longer span would fit a turn it made badly
            recent = t.history[-need:]
        if len(recent) < need:
            return False
        bg = self.detector.background_over_window()  # measured when asked for: only after the cheap test
        if bg is None:
            return False
        sigma = self.params.attitude_white_sigma_rad
        vel, rms = fit_constant_velocity(self.K, [recent], R, sigma)
        for _ in range(min(AIDED_FIT_TRIM, len(recent) - AIDED_FIT_MIN_KEPT)):
            if rms[0] <= p.aided_max_fit_rms_px:
                break
            # the fit without its worst position: a single measurement a few px off (an extended bird's
            # difference peaking at its far edge, C3 seed 5) would otherwise fail the test for as long as
            # it stays in the window, and a coasting track's last positions keep it for good
            vels, rmss = fit_constant_velocity(
                self.K, [recent[:i] + recent[i + 1 :] for i in range(len(recent))], R, sigma
            )
            i = int(np.argmin(rmss))
            recent, vel, rms = recent[:i] + recent[i + 1 :], vels[i : i + 1], rmss[i : i + 1]
        rel = math.hypot(float(vel[0, 0]) - bg[0], float(vel[0, 1]) - bg[1])
        return bool(rms[0] <= p.aided_max_fit_rms_px and rel >= p.min_relative_speed_pxpf)
