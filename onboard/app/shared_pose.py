"""The pose buffer shared by the MAVLink thread (the writer) and the pipeline thread (the reader)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from onboard.core.counters import RejectCounter
from onboard.core.frames import CameraMount, GeodeticOrigin
from onboard.core.pose import GimbalReference, PoseBuffer
from onboard.core.pose_types import PoseAt, PoseLookup

__all__ = ["SharedPoseBuffer"]


class SharedPoseBuffer:
    """A :class:`PoseBuffer` shared by the MAVLink thread (writer) and the pipeline (reader).

    Each ``add_*``, ``clear``, ``lookup`` and ``pose_at`` runs under one lock, held for one call
    (microseconds), so a look-up never blocks MAVLink for long; every stored sample notifies
    :meth:`wait_for`.  A :class:`~onboard.core.pose_sink.PoseSink` for the MAVLink link, a pose source
    for the frame pipeline.
    """

    def __init__(self, buffer: PoseBuffer) -> None:
        self._buffer = buffer
        self._cond = threading.Condition(threading.Lock())
        # the last look-up and the buffer's version it was made at: a frame's wait and its pose_at ask the
        # same question, and a full look-up (brackets, SLERP, Hermite, gimbal, camera pose) made twice per
        # frame would be a large share of the pipeline thread's CPU
        self._version = 0
        self._memo: tuple[int, bool, int, PoseLookup] | None = None  # (time_boot_us, extrapolate, version, result)

    # ------------------------------------------------------------------ read through (set once, or counters)

    @property
    def mount(self) -> CameraMount:
        return self._buffer.mount

    @property
    def origin(self) -> GeodeticOrigin | None:
        return self._buffer.origin

    @property
    def counter(self) -> RejectCounter:
        return self._buffer.counter

    @property
    def reboots(self) -> int:
        return self._buffer.reboots

    @property
    def last_miss_reason(self) -> str | None:
        """Why the last :meth:`pose_at` found no pose (the pipeline tells a GNSS outage past dead reckoning by it)."""
        return self._buffer.last_miss_reason

    @property
    def epoch(self) -> int:
        return self._buffer.epoch

    # ------------------------------------------------------------------ writers (the MAVLink thread)

    def _stored(self, stored: bool) -> bool:
        """After a write, under the lock: the memo is stale, the waiters are woken."""
        self._version += 1
        self._cond.notify_all()
        return stored

    def add_attitude(self, time_boot_us: int, q_ned_from_body: Any, omega_frd_rps: Any = None) -> bool:
        with self._cond:
            return self._stored(self._buffer.add_attitude(time_boot_us, q_ned_from_body, omega_frd_rps))

    def add_position(
        self, time_boot_us: int, lat_deg: float, lon_deg: float, alt_m: float, v_ned_mps: Any = None
    ) -> bool:
        with self._cond:
            return self._stored(self._buffer.add_position(time_boot_us, lat_deg, lon_deg, alt_m, v_ned_mps))

    def add_position_ned(self, time_boot_us: int, p_ned_m: Any, v_ned_mps: Any = None) -> bool:
        with self._cond:
            return self._stored(self._buffer.add_position_ned(time_boot_us, p_ned_m, v_ned_mps))

    def add_gimbal(self, time_boot_us: int, q_mount_from_gimbal: Any) -> bool:
        with self._cond:
            return self._stored(self._buffer.add_gimbal(time_boot_us, q_mount_from_gimbal))

    def add_gimbal_status(
        self, time_boot_us: int, q_ref_from_gimbal: Any, reference: GimbalReference, omega_ref_rps: Any = None
    ) -> bool:
        with self._cond:
            return self._stored(
                self._buffer.add_gimbal_status(time_boot_us, q_ref_from_gimbal, reference, omega_ref_rps)
            )

    def clear(self) -> None:
        with self._cond:
            self._buffer.clear()
            self._stored(True)

    # ------------------------------------------------------------------ readers (the pipeline and main threads)

    def newest_time_boot_us(self) -> int | None:
        with self._cond:
            return self._buffer.newest_time_boot_us()

    def newest_rotation_time_boot_us(self) -> int | None:
        with self._cond:
            return self._buffer.newest_rotation_time_boot_us()

    def _lookup(self, time_boot_us: int, extrapolate: bool) -> PoseLookup:
        """PoseBuffer.lookup, memoised for the buffer's current version (call under the lock)."""
        m = self._memo
        if m is not None and m[0] == time_boot_us and m[1] == extrapolate and m[2] == self._version:
            return m[3]
        res = self._buffer.lookup(time_boot_us, extrapolate)
        self._memo = (time_boot_us, extrapolate, self._version, res)
        return res

    def lookup(self, time_boot_us: int, extrapolate: bool = False) -> PoseLookup:
        with self._cond:
            return self._lookup(time_boot_us, extrapolate)

    def pose_at(self, time_boot_us: int, extrapolate: bool = True) -> PoseAt | None:
        with self._cond:
            return self._buffer.pose_at(time_boot_us, extrapolate, result=self._lookup(time_boot_us, extrapolate))

    def wait_for(
        self, time_boot_us: int, timeout_s: float, clock: Callable[[], float] = time.monotonic, bracket: bool = False
    ) -> bool:
        """Wait until a lookup at ``time_boot_us`` is decided by the data (the telemetry reaches that
        time, or a miss that waiting cannot fix) or ``timeout_s`` passed.  True when the telemetry
        covers the time (``pose_at`` then answers; it may still be a gap; with ``bracket``, its position may be
        extrapolated), False otherwise (then
        ``pose_at`` extrapolates within its horizon).  Never longer than ``timeout_s``, and not at
        all once the newest samples can be extrapolated to the time: waiting would buy a bracket
        whose gain (a few thousandths of a degree, :mod:`onboard.core.pose`) is not worth the latency;
        it waits only for streams that cannot be extrapolated (no rates, no velocity, beyond the
        horizon).  ``bracket``: wait for the rotation's samples (attitude, gimbal) that bracket the time even
        where the newest ones could be extrapolated (the objects image chain's registration of frames, whose
        error an extrapolated attitude's noise dominates: ``imaging.pose_wait_ms``); not for a bracket of the
        position, which comes half as often and moves the rotation by microradians (the local level), only for
        a position the look-up can use at all."""
        deadline = clock() + max(timeout_s, 0.0)
        buf = self._buffer
        cheap = not buf.mount.gimballed  # newest_time_boot_us covers attitude and position only
        with self._cond:
            while True:
                if bracket:
                    newest = buf.newest_rotation_time_boot_us()
                    if newest is not None and newest >= time_boot_us:
                        # the rotation's samples bracket the time; the position may be extrapolated, but a look-up
                        # needs one at all (the rotation is the pose's): wait on only while there is none yet
                        if self._lookup(time_boot_us, True).pose is not None:
                            return True
                    plain = buf.lookup(time_boot_us)
                    left = deadline - clock()
                    if plain.pose is not None or not plain.retry or left <= 0:
                        return plain.pose is not None
                    self._cond.wait(left)
                    continue
                if cheap:
                    newest = buf.newest_time_boot_us()
                    if newest is not None and newest >= time_boot_us:
                        return True  # bracketed (or decided): the caller's pose_at tells which
                res = self._lookup(time_boot_us, True)  # memoised: the caller's pose_at asks the same
                if res.pose is not None:
                    return not res.pose.extrapolated  # bracketed, or decided: pose_at extrapolates
                plain = buf.lookup(time_boot_us)  # no pose even extrapolating: can waiting bring a bracket?
                if plain.pose is not None:
                    return True
                left = deadline - clock()
                if not plain.retry or left <= 0:
                    return False
                self._cond.wait(left)
