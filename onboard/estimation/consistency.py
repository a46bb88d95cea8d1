"""A consistency monitor on the published estimates: does the estimate published a moment ago, carried to
now, predict the bearing measured now, within its own covariance?

The sliding window's verdict is taken at its model selections; between them (up to 20 s once selections
agree) a target that starts to turn leaves a stiff constant-velocity model confidently wrong along range
while the spline still follows every bearing (on synthetic racetrack targets under RTK, 2-minute flights
published 7 % of their positions beyond 3 sigma, all of them called observable, errors 4-30 % of range
with a range sigma of 0.3-5 %).  A bearing predicted over ``horizon_s`` by an estimate whose velocity and
motion model are wrong misses by more than that estimate's covariance allows, long before the window's
own innovations call a new selection.  While the normalised innovation squared (2 degrees of freedom:
the bearing's two angles) of that prediction exceeds ``nis_threshold``, and for ``hold_s`` after, the
estimate is demoted: called unobservable, with the estimator's range floor applied (honest, not
confident), through ``demote``.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["ConsistencyMonitor"]


#: an :class:`~onboard.estimation.sliding.TrackEstimate` (its ``t_s``, ``observable``, ``model``,
#: ``motion_prior``, ``cov_p_ned_m2`` and ``propagated``): sliding calls this monitor, so it is not imported here
TrackEstimate = Any


class ConsistencyMonitor:
    """``bearing_sigma_rad``: one bearing's 1-sigma per axis without the attitude's constant bias (common to the
    carried estimate and the new bearing); ``horizon_s``: how old the estimate that predicts the bearing is
    (over 1 s a target turning at 0.7 m/s^2 leaves its constant-velocity prediction by 0.35 m, less than
    RTK navigation's bearing noise at 250 m; over 2 s by 1.4 m); ``model_hold_s``: how long an estimate
    is demoted after the selected motion model (family or intensity) changed (0: not at all), a new
    selection being unconfirmed (a constant-velocity model selected over a window that holds a turn can
    be a wrong-range solution that explains every bearing, which no bearing innovation shows)."""

    def __init__(
        self,
        bearing_sigma_rad: float,
        horizon_s: float = 2.0,
        nis_threshold: float = 13.8,  # chi-square(2) at 1e-3
        hold_s: float = 3.0,
        model_hold_s: float = 0.0,
    ):
        self.bearing_sigma_rad = float(bearing_sigma_rad)
        self.horizon_s = float(horizon_s)
        self.nis_threshold = float(nis_threshold)
        self.hold_s = float(hold_s)
        self.model_hold_s = float(model_hold_s)
        self._model: str | None = None
        self._past: deque[TrackEstimate] = deque()
        self._inconsistent_until = -math.inf
        self.last_nis = math.nan
        self.demoted = 0

    def nis(self, est_then: TrackEstimate, t_s: float, p_cam_ned_m, los_unit_ned) -> float:
        """The normalised innovation squared of the bearing ``los_unit_ned`` seen from ``p_cam_ned_m`` at
        ``t_s`` against ``est_then`` carried to ``t_s``."""
        pred = est_then.propagated(t_s, p_cam_ned_m)
        d = pred.p_ned_m - np.asarray(p_cam_ned_m, dtype=float)
        rng = float(np.linalg.norm(d))
        if rng <= 0:
            return math.nan
        u = d / rng
        # the tangent plane of the predicted direction: two unit vectors across it
        a = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(u, a)
        T = np.stack([a, b])
        m = np.asarray(los_unit_ned, dtype=float)
        innov = T @ m / max(float(u @ m), 1e-9)  # the measured direction's tangent-plane offset, radians
        S = T @ pred.cov_p_ned_m2 @ T.T / rng**2 + self.bearing_sigma_rad**2 * np.eye(2)
        return float(innov @ np.linalg.solve(S, innov))

    def check(
        self,
        est: TrackEstimate,
        p_cam_ned_m,
        los_unit_ned,
        demote: Callable[[TrackEstimate], TrackEstimate],
    ) -> TrackEstimate:
        """``est`` as published: demoted (``demote``) while the estimate of ``horizon_s`` ago fails to predict
        this bearing, and for ``hold_s`` after."""
        t = est.t_s
        then = None
        while self._past and self._past[0].t_s <= t - self.horizon_s:
            then = self._past.popleft()
        if then is not None:
            self._past.appendleft(then)  # the newest one at least horizon_s old serves the next frame too
            self.last_nis = self.nis(then, t, p_cam_ned_m, los_unit_ned)
            if self.last_nis > self.nis_threshold:
                self._inconsistent_until = t + self.hold_s
        self._past.append(est)
        model = f"{est.model}:{est.motion_prior}"
        if self._model is not None and model != self._model:
            self._inconsistent_until = max(self._inconsistent_until, t + self.model_hold_s)
        self._model = model
        if est.observable and t <= self._inconsistent_until:
            self.demoted += 1
            return demote(dataclasses.replace(est, observable=False))
        return est
