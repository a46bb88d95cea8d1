"""What withholds a frame's line of sight and 3-D position in the frame pipeline
(:class:`~onboard.pipeline.frame_pipeline.FramePipeline`, its module docstring, step 1): the warnings the daemon
sets from its watchdog (``gimbal_mismatch``, ``camera_mismatch``, and ``camera_time_offset`` while the offset is not
compensated: :func:`clock_offset_withholds`), and the frame's own stated zoom
(:data:`ZOOM_MISMATCH`: IRF1's zoom field, :func:`~onboard.core.irframe.zoom_off_calibration`), decided frame by
frame; with the log lines that say when it begins and ends."""

from __future__ import annotations

import logging

from onboard.core.counters import RejectCounter
from onboard.core.irframe import IrFrame, zoom_off_calibration

__all__ = ["ZOOM_MISMATCH", "CLOCK_OFFSET", "clock_offset_withholds", "Withholding"]

log = logging.getLogger("onboard.pipeline.frame_pipeline")  # the pipeline's lines, as they were written there

#: the warning code a frame's own zoom withholds its geometry under
ZOOM_MISMATCH = "zoom_mismatch"
#: the warning code a camera clock offset left uncompensated withholds the geometry under (:func:`clock_offset_withholds`)
CLOCK_OFFSET = "camera_time_offset"


def clock_offset_withholds(estimate, threshold_ms: float, was_withholding: bool = False) -> bool:
    """Whether the camera clock's offset, while its warning (:data:`CLOCK_OFFSET`) holds, leaves more than
    ``threshold_ms`` uncompensated (a :class:`~onboard.estimation.time_offset.TimeOffsetEstimate`; None: no
    estimator, False): beyond ``time_offset.max_offset_ms``, with ``time_offset.compensate`` off, or a compensation
    the offset has moved away from.  Each line of sight is then made with the pose of another instant, off by the
    camera's rotation over the offset, which no covariance states: a constant 300 ms left 3-D positions 270 m off at
    a Mahalanobis d^2 up to 4495 against their own covariance.  The daemon withholds them, as for a mismatch.

    ``was_withholding``: once withheld, until at most half the threshold is left (hysteresis): an estimate near the
    threshold moves by a few ms with each 3 s block, and each end of a withholding restarts the 3-D estimate."""
    if estimate is None or estimate.estimate_ms is None:
        return False
    left_ms = abs(float(estimate.estimate_ms) - float(estimate.compensated_ms))
    return left_ms > (0.5 * threshold_ms if was_withholding else threshold_ms)


class Withholding:
    """The frame pipeline's withholding state: :attr:`codes` now, :meth:`follow_zoom` for each frame taken,
    :meth:`follow` once per frame before its row goes to the estimator."""

    def __init__(self) -> None:
        # the warnings the daemon withholds the geometry for (set_by_daemon); another thread sets them
        self._by_daemon: tuple[str, ...] = ()
        self._last: tuple[str, ...] = ()  # what withheld the last frame's geometry (follow)
        # the sets of codes whose withholding has begun and ended once, logged then: again, at DEBUG (follow)
        self._told: set[tuple[str, ...]] = set()
        #: the zoom the last frame taken stated (IRF1's field, relative to the calibrated one); None: not stated
        self.last_zoom: float | None = None
        #: the last frame taken stated a zoom camera.intrinsics are not for
        self.zoom_off = False
        #: frames whose line of sight and 3-D position were withheld for their stated zoom
        self.frames_withheld_zoom = 0

    @property
    def codes(self) -> tuple[str, ...]:
        """The daemon's codes, then :data:`ZOOM_MISMATCH` while the last frame taken states a zoom the intrinsics
        are not for."""
        daemon = self._by_daemon
        return (*daemon, ZOOM_MISMATCH) if self.zoom_off else daemon

    def set_by_daemon(self, codes: tuple[str, ...]) -> None:
        # the zoom is the frames' to say: a caller handing back what it read must not pin it past them
        self._by_daemon = tuple(c for c in codes if c != ZOOM_MISMATCH)

    def follow_zoom(self, frame: IrFrame, counter: RejectCounter) -> None:
        """Take the zoom a frame states (module docstring, step 1): withhold its geometry when the intrinsics are
        not for it; a zoom field no zoom can hold is counted and read as not stated."""
        if frame.zoom_invalid:
            counter.count(
                "frame_zoom_invalid",
                f"frame seq {frame.seq} states a zoom of {frame.zoom!r}, which no zoom can be: taken as not stated "
                "(the frame is tracked as before the field); check the sender's IRF1 header, offset 28 (float32)",
            )
        self.last_zoom = frame.stated_zoom
        self.zoom_off = zoom_off_calibration(self.last_zoom, was_off=self.zoom_off)
        if self.zoom_off:
            self.frames_withheld_zoom += 1

    def follow(self) -> tuple[tuple[str, ...], tuple[str, ...], int]:
        """What withholds this frame's line of sight and 3-D position (:attr:`codes`, read once), logged as it
        starts and ends; (those codes, the codes whose withholding ended with this frame (empty: none), the level
        it was said at).  At such an end the caller starts the estimator again, before this frame's row, which is
        the new window's first: the window holds rows made with the wrong camera (a ``camera_mismatch``'s), or its
        newest estimate is as old as the frames withheld (a zoom's rows never reach it), so that an estimate carried
        from it would be withheld as stale (counted ``estimate_after_gap``, as if the frames had stopped coming).

        Logged at WARNING and INFO the first time for each set of codes, at DEBUG after: a zoom decides it frame by
        frame, and one that flips every frame (two senders on the key, a lens at the tolerance's edge) would log a
        WARNING every other frame; the watchdog's warning and the status's ``geometry`` say it goes on."""
        codes = self.codes
        before, self._last = self._last, codes
        if codes and not before:
            level = logging.DEBUG if codes in self._told else logging.WARNING
            log.log(level, "line of sight and 3-D positions withheld: %s", ", ".join(codes))
        elif before and not codes:
            level = logging.DEBUG if before in self._told else logging.INFO
            self._told.add(before)
            log.log(level, "line of sight and 3-D positions published again")
            return codes, before, level
        return codes, (), logging.INFO
