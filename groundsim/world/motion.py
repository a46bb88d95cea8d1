"""Analytic motion models for scenario trajectories, in local NED (see ``onboard.core.frames``).

Every model maps times ``t_s`` (seconds since scenario start, any shape) to a
:class:`KinematicState` of positions, velocities and accelerations, shape ``t_s.shape + (3,)``.
These are the *commanded* paths: the JSBSim guidance follows them, and the analytic evaluation
(``groundsim.evaluation.synth``) uses them directly as truth.

Models (``model:`` in a scenario file)
    ``uniform_linear``        p0 + v0 t
    ``uniform_acceleration``  p0 + v0 t + a0 t^2 / 2
    ``cubic``                 p0 + v0 t + a0 t^2 / 2 + j t^3 / 6   (the paper's "third order")
    ``circular``              centre + r (cos az, sin az, 0), az = az0 + rate t;  az is measured
                              from north towards east, so rate > 0 turns clockwise seen from above
    ``figure_eight``          centre + A1 sin(w t) + A2 sin(2 w t), w = 2 pi / period
    ``waypoints``             straight legs between points at constant speed (corners are sharp)

A :class:`SingerPerturbation` adds the random (Singer) acceleration of a realistic target:
first-order Gauss-Markov acceleration with standard deviation ``sigma`` and correlation time
``tau`` per axis (Singer, IEEE TAES 6(4), 1970), integrated exactly on a fine grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

__all__ = [
    "KinematicState",
    "Motion",
    "Cubic",
    "Circular",
    "FigureEight",
    "Waypoints",
    "SingerPerturbation",
    "Perturbed",
]


class KinematicState(NamedTuple):
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    a_ned_mps2: np.ndarray


class Motion(Protocol):
    def state(self, t_s) -> KinematicState: ...


def _vec3(x) -> np.ndarray:
    return np.asarray(x, dtype=float).reshape(3)


@dataclass(frozen=True)
class Cubic:
    """p0 + v0 t + a0 t^2/2 + j t^3/6; uniform linear and uniform acceleration are special cases."""

    p0_ned_m: tuple
    v0_ned_mps: tuple = (0.0, 0.0, 0.0)
    a0_ned_mps2: tuple = (0.0, 0.0, 0.0)
    j_ned_mps3: tuple = (0.0, 0.0, 0.0)

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)[..., None]
        p0, v0, a0, j = (_vec3(x) for x in (self.p0_ned_m, self.v0_ned_mps, self.a0_ned_mps2, self.j_ned_mps3))
        p = p0 + v0 * t + a0 * t**2 / 2 + j * t**3 / 6
        v = v0 + a0 * t + j * t**2 / 2
        a = a0 + j * t + 0.0 * t
        return KinematicState(p, v, a)


@dataclass(frozen=True)
class Circular:
    """Horizontal circle at constant speed: centre + r (cos az, sin az, 0), az = az0 + rate t."""

    center_ned_m: tuple
    radius_m: float
    azimuth0_rad: float
    rate_radps: float

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)
        az = self.azimuth0_rad + self.rate_radps * t
        c, s = np.cos(az), np.sin(az)
        r, w = self.radius_m, self.rate_radps
        z = np.zeros_like(t)
        p = _vec3(self.center_ned_m) + np.stack([r * c, r * s, z], axis=-1)
        v = np.stack([-r * w * s, r * w * c, z], axis=-1)
        a = np.stack([-r * w * w * c, -r * w * w * s, z], axis=-1)
        return KinematicState(p, v, a)


@dataclass(frozen=True)
class FigureEight:
    """centre + A1 sin(w t) + A2 sin(2 w t), w = 2 pi / period_s."""

    center_ned_m: tuple
    amp1_ned_m: tuple
    amp2_ned_m: tuple
    period_s: float

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)[..., None]
        w = 2 * np.pi / self.period_s
        a1, a2 = _vec3(self.amp1_ned_m), _vec3(self.amp2_ned_m)
        p = _vec3(self.center_ned_m) + a1 * np.sin(w * t) + a2 * np.sin(2 * w * t)
        v = a1 * w * np.cos(w * t) + a2 * 2 * w * np.cos(2 * w * t)
        a = -a1 * w * w * np.sin(w * t) - a2 * 4 * w * w * np.sin(2 * w * t)
        return KinematicState(p, v, a)


@dataclass(frozen=True)
class Waypoints:
    """Straight legs through ``points_ned_m`` at ``speed_mps``; holds the last point afterwards."""

    points_ned_m: tuple
    speed_mps: float

    def state(self, t_s) -> KinematicState:
        pts = np.asarray(self.points_ned_m, dtype=float).reshape(-1, 3)
        t = np.asarray(t_s, dtype=float)
        legs = np.diff(pts, axis=0)
        leg_len = np.linalg.norm(legs, axis=1)
        t_knots = np.concatenate([[0.0], np.cumsum(leg_len / self.speed_mps)])
        tt = np.clip(t, 0.0, t_knots[-1])
        k = np.clip(np.searchsorted(t_knots, tt, side="right") - 1, 0, len(legs) - 1)
        frac = (tt - t_knots[k]) / np.maximum(t_knots[k + 1] - t_knots[k], 1e-12)
        p = pts[k] + frac[..., None] * legs[k]
        moving = (t < t_knots[-1])[..., None]
        v = np.where(moving, legs[k] / np.maximum(leg_len[k], 1e-12)[..., None] * self.speed_mps, 0.0)
        return KinematicState(p, v, np.zeros_like(p))


class SingerPerturbation:
    """Random acceleration: per axis a first-order Gauss-Markov process (Singer 1970).

    ``da = -a / tau dt + sqrt(2 sigma^2 / tau) dW``, started from its stationary distribution,
    sampled exactly on a grid of ``dt_s`` and integrated to velocity and position (both zero at
    t = 0); between grid points the acceleration is linear, so velocity and position stay
    consistent.  Deterministic for a given ``rng``.
    """

    def __init__(self, duration_s: float, sigma_ned_mps2, tau_s: float, rng: np.random.Generator, dt_s: float = 0.01):
        sigma = _vec3(sigma_ned_mps2)
        n = int(np.ceil(duration_s / dt_s)) + 2
        self._t = np.arange(n) * dt_s
        phi = np.exp(-dt_s / tau_s)
        a = np.empty((n, 3))
        a[0] = sigma * rng.standard_normal(3)
        drive = sigma * np.sqrt(1 - phi**2)
        for k in range(1, n):
            a[k] = phi * a[k - 1] + drive * rng.standard_normal(3)
        v = np.zeros((n, 3))
        p = np.zeros((n, 3))
        for k in range(1, n):
            v[k] = v[k - 1] + 0.5 * (a[k - 1] + a[k]) * dt_s
            p[k] = p[k - 1] + v[k - 1] * dt_s + (2 * a[k - 1] + a[k]) * dt_s**2 / 6
        self._a, self._v, self._p = a, v, p

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)
        cols = lambda arr: np.stack([np.interp(t, self._t, arr[:, i]) for i in range(3)], axis=-1)  # noqa: E731
        return KinematicState(cols(self._p), cols(self._v), cols(self._a))


@dataclass(frozen=True)
class Perturbed:
    """A base motion plus a perturbation (both with ``state``)."""

    base: Motion
    perturbation: Motion

    def state(self, t_s) -> KinematicState:
        b, d = self.base.state(t_s), self.perturbation.state(t_s)
        return KinematicState(b.p_ned_m + d.p_ned_m, b.v_ned_mps + d.v_ned_mps, b.a_ned_mps2 + d.a_ned_mps2)
