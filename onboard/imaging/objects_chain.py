"""The objects chain behind the daemon's single-target interface: :class:`ObjectChain` runs
:class:`~onboard.imaging.objects.ObjectTracker` and reports its primary target as
:class:`~onboard.imaging.TargetTracker` reports its one track, every object beside it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from onboard.core.errors import InputError
from onboard.imaging.objects import ObjectTracker
from onboard.imaging.objects_model import ObjectsUpdate
from onboard.imaging.preprocess import ImagingParams, check_frame

__all__ = ["ObjectChain"]


class ObjectChain:
    """:class:`ObjectTracker` behind :class:`~onboard.imaging.TargetTracker`'s interface: the primary
    target as a :class:`~onboard.imaging.TrackUpdate` (``track_id`` = its object id, so a change of
    selection is a new track id and the frame pipeline restarts the 3-D estimate and says so), every
    object in :attr:`last_objects`.  ``uses_pose``: the frame pipeline passes each frame's
    ``R_ned_from_cam`` to :meth:`update` (None when it has no pose: the last one is kept, the
    camera taken as still since), or a function that returns it once the frame's detection is done
    (:meth:`ObjectTracker.update`).

    A gap in the telemetry (a router restarting, a serial link's hiccup: seconds without a pose while the frames
    go on) is bridged in the tracker's own frame.  Over the gap the tracker took the camera as still, so the
    lines of sight it holds (its tracks, their histories, the detector's and track-before-detect's registration)
    are of the rotation it was last given, not of the camera's, which went on turning after its target.  The
    first rotation after the gap is therefore not handed over as it is, which would read as the camera turning
    by all of the gap's rotation in one frame period (a few degrees in a second or two: every prediction tens of
    pixels or more off its object, and the primary coasted out and was chosen again under a new id, on which the
    frame pipeline restarts the 3-D estimate):
    the tracker's frame is turned instead, ``R_ned_from_tracker`` such that the camera's rotation in it
    continues the one it was last given, and every rotation after is handed over in that frame.  Only what the
    tracker held is taken to be of the gap's last frame (off by one frame period's turn); the rotations between
    frames after the gap are the telemetry's, as before it.  The objects' lines of sight leave in local NED
    (:attr:`last_objects`): turned back by ``R_ned_from_tracker``."""

    uses_pose = True

    def __init__(
        self,
        intrinsics,
        params: ImagingParams | None = None,
        mode: str = "auto",
        frame_rate_hz: float = 30.0,
        attitude_white_sigma_rad: float | None = None,
    ) -> None:
        # the attitude error its fits allow for: the estimator's, as configured (None: ObjectParams' default)
        changes = {} if attitude_white_sigma_rad is None else {"attitude_white_sigma_rad": attitude_white_sigma_rad}
        params_obj = ObjectTracker.default_params(params, **changes)
        self.objects = ObjectTracker(intrinsics, frame_rate_hz, params=params_obj, imaging=params, mode=mode)
        self.mode = mode
        self.last_objects: ObjectsUpdate | None = None
        self.rejected_frames = 0
        self._R: np.ndarray | None = None  # the rotation last handed to the tracker, in its frame
        # the tracker's frame in local NED: None while it is local NED (no frame has gone without a rotation since
        # the first rotation came), else turned at the end of each gap in the rotations (class docstring)
        self._R_ned_from_tracker: np.ndarray | None = None
        self._held = False  # the last frame went to the tracker without a rotation of its own
        self._last_primary: int | None = None
        # (frame, its update) a selection measured: a second request decided on the same frame (a double click within
        # a frame period, a click then a box) selects on it, and the frame's update after selections that selected
        # nothing returns it; measuring the frame again would read as a frozen frame (every track predicted one step
        # more, coasting)
        self._measured: tuple | None = None

    @property
    def holding(self) -> bool:
        """True after :meth:`stop` in auto mode until the next selection (no automatic choice meanwhile), as
        :attr:`TargetTracker.holding`."""
        return self.mode == "auto" and self.objects.mode == "operator"

    def update(self, image: np.ndarray, R_ned_from_cam: np.ndarray | None = None, time_boot_us: int | None = None):
        measured, self._measured = self._measured, None
        if measured is not None and measured[0] is image:
            return measured[1]  # measured by a selection on this frame that selected nothing (select_point)
        try:
            image = check_frame(image)
        except InputError:
            self.rejected_frames += 1
            raise

        given = R_ned_from_cam
        rotation = (lambda: self._in_tracker_frame(given())) if callable(given) else self._in_tracker_frame(given)
        out = self.objects.update(image, rotation, time_boot_us)
        self.last_objects = self._in_ned(out)
        return self._track_update(out)

    def _in_tracker_frame(self, R_ned_from_cam) -> np.ndarray | None:
        """The rotation to hand the tracker for a frame: ``R_ned_from_cam`` in the tracker's frame; without one,
        the last handed over (None before any: the tracker takes the identity).  The first rotation after frames
        without one turns the tracker's frame so that it continues the rotation those frames were given (class
        docstring)."""
        if R_ned_from_cam is None:
            self._held = True
            return self._R
        R = np.asarray(R_ned_from_cam, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            return R  # the tracker refuses it, naming it (ObjectTracker._rotation)
        if self._held:
            held = np.eye(3) if self._R is None else self._R  # the tracker's identity for None
            self._R_ned_from_tracker = R @ held.T
            self._held = False
        turn = self._R_ned_from_tracker
        self._R = R if turn is None else turn.T @ R
        return self._R

    def _in_ned(self, out: ObjectsUpdate) -> ObjectsUpdate:
        """``out`` with its objects' lines of sight in local NED (made in the tracker's frame)."""
        turn = self._R_ned_from_tracker
        if turn is None:
            return out
        objects = tuple(
            o if o.los_ned is None else dataclasses.replace(o, los_ned=_turned(turn, o.los_ned)) for o in out.objects
        )
        return dataclasses.replace(out, objects=objects)

    def _track_update(self, out: ObjectsUpdate):
        from onboard.imaging.tracker import TrackState, TrackUpdate

        prim = next((o for o in out.objects if o.object_id == out.primary_id), None)
        lost = self._last_primary is not None and self._last_primary != out.primary_id
        self._last_primary = out.primary_id
        if prim is None:
            state = TrackState.LOST if lost else TrackState.SEARCHING
            return TrackUpdate(state, None, None, None, None, False, None, None, out.frame_index)
        if prim.state == "confirmed" and out.primary is not None:
            d = out.primary
            return TrackUpdate(
                TrackState.TRACKING,
                d.u_px,
                d.v_px,
                prim.bbox,
                d,
                not d.touches_border,
                prim.object_id,
                0,
                out.frame_index,
            )
        misses = max(prim.age_frames - prim.hits, 1)
        return TrackUpdate(
            TrackState.COASTING, prim.u_px, prim.v_px, prim.bbox, None, False, prim.object_id, misses, out.frame_index
        )

    def select_point(
        self,
        image: np.ndarray,
        u_px: float,
        v_px: float,
        radius_px: float,
        rect_px=None,
        R_ned_from_cam=None,
        time_boot_us: int | None = None,
    ):
        """Update on ``image`` (with its rotation and capture time, as :meth:`update` takes them: without, the
        tracks are predicted with the last frame's rotation, and an operator clicks while the gimbal slews), then
        make the object nearest (u, v) within ``radius_px`` (and, given ``rect_px``, inside that box) the primary;
        its TrackUpdate, or None (nothing there: the selection is unchanged)."""
        if self._measured is not None and self._measured[0] is image:
            upd = self._measured[1]  # a second request on this frame: measured by the first
        else:
            upd = self.update(image, R_ned_from_cam, time_boot_us)
            self._measured = (image, upd)
        sel = self.objects.select_point(u_px, v_px, radius_px, rect_px)
        if sel is None or self.last_objects is None:
            # the caller then tracks the frame as usual (a refused selection leaves the single chain's tracker
            # untouched): update() gives this frame's measurement back
            return None
        self.objects.mode = self.mode  # a selection ends a stop's hold
        # this frame measured the object already (before it was selected): reported from its track,
        # not fit for 3-D; the next frame measures it as the primary
        self.last_objects = dataclasses.replace(self.last_objects, primary_id=sel, primary=None, primary_changed=True)
        return self._track_update(self.last_objects)

    def select_rectangle(
        self,
        image: np.ndarray,
        rect_px: tuple[float, float, float, float],
        R_ned_from_cam=None,
        time_boot_us: int | None = None,
    ):
        """The object whose centre lies in ``rect_px`` = (x0, y0, x1, y1), the one nearest its centre when several
        do (the tracker's own choice of a point); None when none does."""
        x0, y0, x1, y1 = rect_px
        cx, cy, half_diagonal = 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * math.hypot(x1 - x0, y1 - y0)
        return self.select_point(image, cx, cy, half_diagonal, (x0, y0, x1, y1), R_ned_from_cam, time_boot_us)

    def stop(self) -> None:
        """Drop the selection and hold: no automatic choice until the next selection."""
        self.objects.mode = "operator"
        self.objects.clear_primary()

    def reset(self) -> None:
        """Forget every track (ids continue)."""
        self.objects.clear_tracks()


def _turned(R: np.ndarray, v) -> tuple[float, float, float]:
    n, e, d = (float(c) for c in R @ np.asarray(v, dtype=np.float64))
    return n, e, d
