"""The simulated vehicle's GUIDED-like mode: a reference path that follows the scenario's scripted motion until the
first velocity setpoint arrives, then the setpoints, within the vehicle's own limits.

A setpoint ``(t_s, v_ned_mps, valid_until_s)`` starts a new segment at ``t_s`` from the reference's own state
there (continuous position and velocity): the velocity slews towards the setpoint (clamped to the vehicle's
speed and climb-rate limits) at constant acceleration ``max_accel_mps2`` along ``v_sp - v_k``, then holds it,
the law :func:`onboard.estimation.guidance.candidate_path` predicts with::

    v(t) = v_k + a e (t - t_k)   until |v - v_k| = |v_sp - v_k|,   then v_sp;   p its exact integral.

Past ``valid_until_s`` (None: never) without a newer setpoint the vehicle brakes to a hover at ``max_accel_mps2``, as
ArduCopter's GUIDED mode does when velocity setpoints stop (``GUIDED_SETPOINT_TIMEOUT_S`` after the last; the
real-time flow and the lockstep eval, which runs the daemon's setpoint gate, both pass that).  The JSBSim guidance of
:class:`groundsim.world.flight.FlownVehicle` follows this reference like any scripted one
(:meth:`FlownVehicle.reference_changed` after each setpoint).  Frames and units: local NED metres, m/s (see
:mod:`onboard.core.frames`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from groundsim.world.motion import KinematicState

__all__ = ["GUIDED_SETPOINT_TIMEOUT_S", "GuidedLimits", "GuidedReference"]

#: ArduCopter GUIDED: a velocity setpoint not followed by another within this long (s) ends in a stop (GUID_TIMEOUT)
GUIDED_SETPOINT_TIMEOUT_S = 3.0


@dataclass(frozen=True)
class GuidedLimits:
    """What the simulated vehicle itself accepts in its guided mode (a setpoint beyond is clamped)."""

    max_speed_mps: float = 15.0
    max_climb_rate_mps: float = 3.0
    max_accel_mps2: float = 2.0


class GuidedReference:
    """A :class:`~groundsim.world.motion.Motion`: ``base`` until the first :meth:`command`, then the setpoints."""

    def __init__(self, base, limits: GuidedLimits | None = None) -> None:
        self.base = base
        self.limits = limits if limits is not None else GuidedLimits()
        # segments: start time, position and velocity there, setpoint velocity, when it lapses (inf: never)
        self._t: list[float] = []
        self._p: list[np.ndarray] = []
        self._v: list[np.ndarray] = []
        self._sp: list[np.ndarray] = []
        self._until: list[float] = []
        self.commands = 0

    @property
    def guided_since_s(self) -> float | None:
        """When the first setpoint took over (None: still on the scripted motion)."""
        return self._t[0] if self._t else None

    def clamp(self, v_ned_mps) -> np.ndarray:
        """The setpoint within the vehicle's speed (horizontal) and climb-rate limits."""
        v = np.asarray(v_ned_mps, dtype=float).reshape(3).copy()
        lim = self.limits
        s = math.hypot(v[0], v[1])
        if s > lim.max_speed_mps:
            v[:2] *= lim.max_speed_mps / s
        v[2] = min(max(v[2], -lim.max_climb_rate_mps), lim.max_climb_rate_mps)
        return v

    def command(self, t_s: float, v_ned_mps, valid_until_s: float | None = None) -> None:
        """A velocity setpoint from ``t_s`` on (not before the last one's start), braked to a hover from
        ``valid_until_s`` on unless a newer one comes first (None: held until then)."""
        v_sp = self.clamp(v_ned_mps)
        if not np.all(np.isfinite(v_sp)) or not math.isfinite(t_s):
            raise ValueError(f"setpoint must be finite, got t {t_s!r} v {v_ned_mps!r}")
        if self._t and t_s < self._t[-1]:
            raise ValueError(f"setpoint at {t_s} s goes back before the last one ({self._t[-1]} s)")
        until = math.inf if valid_until_s is None else max(float(valid_until_s), float(t_s))
        st = self.state(np.array([t_s]))
        if self._t and t_s == self._t[-1]:  # replaces a setpoint given at the same instant
            self._sp[-1] = v_sp
            self._until[-1] = until
        else:
            self._t.append(float(t_s))
            self._p.append(st.p_ned_m[0].copy())
            self._v.append(st.v_ned_mps[0].copy())
            self._sp.append(v_sp)
            self._until.append(until)
        self.commands += 1

    def _slew(self, p0: np.ndarray, v0: np.ndarray, vs: np.ndarray, dt: np.ndarray):
        """Position, velocity and acceleration ``dt`` (n, 1) after ``(p0, v0)`` slewing to ``vs`` (module
        docstring)."""
        dv = vs - v0
        n = float(np.linalg.norm(dv))
        if n < 1e-9:
            return p0 + v0 * dt, np.broadcast_to(v0, dt.shape[:1] + (3,)), np.zeros(dt.shape[:1] + (3,))
        T = n / self.limits.max_accel_mps2
        acc = dv / T
        ts = np.minimum(dt, T)
        return p0 + v0 * ts + 0.5 * acc * ts * ts + vs * (dt - ts), v0 + acc * ts, np.where(dt < T, acc, 0.0)

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)
        base = self.base.state(t)
        if not self._t:
            return base
        shape = t.shape
        tf = t.reshape(-1)
        p = np.asarray(base.p_ned_m, dtype=float).reshape(-1, 3).copy()
        v = np.asarray(base.v_ned_mps, dtype=float).reshape(-1, 3).copy()
        a = np.asarray(base.a_ned_mps2, dtype=float).reshape(-1, 3).copy()
        k = np.searchsorted(np.asarray(self._t), tf, side="right") - 1
        for seg in np.unique(k[k >= 0]):
            t0, until = self._t[seg], self._until[seg]
            p0, v0, vs = self._p[seg], self._v[seg], self._sp[seg]
            m = (k == seg) & (tf <= until)
            p[m], v[m], a[m] = self._slew(p0, v0, vs, (tf[m] - t0)[:, None])
            late = (k == seg) & (tf > until)
            if late.any():  # lapsed: from the state there, a slew to a hover
                pu, vu, _ = self._slew(p0, v0, vs, np.array([[until - t0]]))
                p[late], v[late], a[late] = self._slew(pu[0], vu[0], np.zeros(3), (tf[late] - until)[:, None])
        return KinematicState(p.reshape(shape + (3,)), v.reshape(shape + (3,)), a.reshape(shape + (3,)))
