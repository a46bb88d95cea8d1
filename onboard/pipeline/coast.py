"""Coasting the 3-D estimate through a navigation gap, pure: no estimator state is touched.

While the vehicle's position is dead-reckoned (a GNSS dropout: :mod:`onboard.core.pose`, "Dead
reckoning"), the camera position of a frame carries metres of error where the sliding-window
estimator assumes centimetres (``estimator.camera_position_white_sigma_m``).  Such a frame is not
added to the window -- its error is the same bias frame after frame, which a window of white-noise
rows would average into a confident wrong answer -- but its estimate is the last one the window
solved, carried to the frame's time and corrected by the frame's own line of sight:

1. propagate at constant velocity (:meth:`~onboard.estimation.sliding.TrackEstimate.propagated`:
   ``p + v dt``, ``P + dt^2 V``) plus the target's unmodelled acceleration, white, ``a`` per axis:
   ``P += (a dt^2 / 2)^2 I`` (Bar-Shalom, Li & Kirubarajan 2001, 6.2: the discrete white-noise
   acceleration model's position term);
2. one bearing update (:meth:`~onboard.estimation.sliding.TrackEstimate.with_bearing`): the target on
   the ray from the dead-reckoned camera, with noise ``(r sigma_bearing)^2 + sigma_cam^2`` per axis
   across the ray, ``sigma_cam`` the pose's dead-reckoning sigma.  Each frame starts again from the
   window's estimate (the updates are not chained: the camera's error is one bias over the gap, and
   chained updates would count it once per frame).  A bearing the estimate's gate refuses is not
   fused (the propagated estimate stands).  An unobservable estimate is not updated: the update is
   linear across the ray, and a covariance stretched along the range (the floor of an unobservable
   estimate, tens of per cent of the range) tilts against a ray a few degrees off its axis, so the
   update would pull the point along the old ray and shrink the range sigma it has not measured (P1g,
   seed 0, a 5 s dropout: 19 % of the gap's positions beyond 3 sigma before this rule, 0 % after);
   it is placed on the frame's ray at its last range instead (:func:`_on_the_ray`).

The covariance therefore grows with the gap; the verdict ``observable`` holds only while the window's
verdict did and the coasted range sigma stays below :data:`OBSERVABLE_MAX_RANGE_SIGMA_RATIO`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from onboard.estimation.map_estimator import MapConfig

__all__ = ["OBSERVABLE_MAX_RANGE_SIGMA_RATIO", "coast_estimate"]

#: the estimator's verdict threshold on the range sigma (the daemon's window keeps MapConfig's)
OBSERVABLE_MAX_RANGE_SIGMA_RATIO = MapConfig().observability_max_sigma_range_ratio


def coast_estimate(
    est,
    t_s: float,
    p_cam_ned_m,
    cam_sigma_m: float,
    u_ned=None,
    bearing_sigma_rad: float = 0.0,
    accel_sigma_mps2: float = 0.0,
):
    """``est`` (a :class:`~onboard.estimation.sliding.TrackEstimate`) carried to ``t_s`` and, with a line of
    sight ``u_ned`` (unit, NED), corrected by it as seen from ``p_cam_ned_m`` (module docstring).
    ``cam_sigma_m``: the camera position's 1-sigma per axis; ``bearing_sigma_rad``: the bearing's;
    ``accel_sigma_mps2``: the target's unmodelled acceleration.  Returns a new estimate; ``est`` is not
    changed."""
    dt = float(t_s) - float(est.t_s)
    out = est.propagated(t_s, p_cam_ned_m)
    q = 0.5 * accel_sigma_mps2 * dt * dt
    P = np.asarray(out.cov_p_ned_m2, dtype=float) + (q * q) * np.eye(3)
    out = dataclasses.replace(out, cov_p_ned_m2=P)
    if u_ned is not None and est.observable:
        fused = out.with_bearing(p_cam_ned_m, u_ned, bearing_sigma_rad, cam_sigma_m)
        if fused is not None:
            out = fused
    elif u_ned is not None:
        out = _on_the_ray(est, out, p_cam_ned_m, u_ned, cam_sigma_m, bearing_sigma_rad, dt, q)
    los = np.asarray(out.p_ned_m, dtype=float) - np.asarray(p_cam_ned_m, dtype=float)
    rng = float(np.linalg.norm(los))
    ratio = math.sqrt(max(float(los @ out.cov_p_ned_m2 @ los), 0.0)) / (rng * rng) if rng > 0 else math.inf
    observable = bool(est.observable and ratio < OBSERVABLE_MAX_RANGE_SIGMA_RATIO)
    return dataclasses.replace(out, range_m=rng, range_sigma_ratio=ratio, observable=observable)


def _on_the_ray(est, out, p_cam_ned_m, u_ned, cam_sigma_m: float, bearing_sigma_rad: float, dt: float, q: float):
    """An unobservable estimate placed on the frame's ray at the window's last range: its velocity is as
    unknown as its range, so propagating it drifts the point off the ray by hundreds of metres (P2 under a
    5 s dropout: median error 280 % of range, honest only through its covariance).  Along the ray the
    window's range sigma (the unobservable floor) grown by ``dt^2 V + (a dt^2 / 2)^2``; across it the bearing
    and the camera's dead-reckoning sigma."""
    u = np.asarray(u_ned, dtype=float)
    u = u / np.linalg.norm(u)
    r = float(est.range_m)
    V = np.asarray(est.cov_v_ned_m2ps2, dtype=float)
    var_r = (float(est.range_sigma_ratio) * r) ** 2 + dt * dt * float(u @ V @ u) + q * q
    var_c = (r * bearing_sigma_rad) ** 2 + cam_sigma_m**2 + q * q
    uu = np.outer(u, u)
    P = var_r * uu + var_c * (np.eye(3) - uu)
    return dataclasses.replace(out, p_ned_m=np.asarray(p_cam_ned_m, dtype=float) + r * u, cov_p_ned_m2=P)
