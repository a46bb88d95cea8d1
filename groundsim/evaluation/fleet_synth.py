"""Synthetic lines of sight of several vehicles on one target, for the fleet fusion's tests and bench.

Truth: each vehicle flies at constant velocity (``SynthVehicle``), the target too (``SynthTarget``), all
in one local NED frame.  A measured line of sight is the true one rotated by the vehicle's constant
attitude error ``phi`` (``R_meas = Exp(phi) R_true``, the convention of :mod:`onboard.core.frames`) plus
white angular noise across the ray; the measured camera position is the true one plus the vehicle's
constant position error and white noise.  The published sigmas are what the daemon would publish: the
white angular noise and the attitude bias's prior together (:func:`onboard.core.track.line_of_sight_ned`).

:func:`track_payload` wraps one such line of sight in an ``irtrack.track/2`` message (with the
``time_unix_us`` a daemon with a common clock adds), as :mod:`onboard.core.track` writes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from onboard.core.frames import GeodeticOrigin, rotmat_from_rotvec
from onboard.core.track import LineOfSight, Track, track_to_json

__all__ = ["SynthVehicle", "SynthTarget", "SynthLos", "measure", "track_payload"]


@dataclass(frozen=True)
class SynthVehicle:
    """A vehicle's true camera track ``p0_ned_m + v_ned_mps t`` and its constant navigation errors:
    ``offset_ned_m`` (measured minus true camera position) and ``attitude_error_rad`` (NED rotation vector)."""

    name: str
    p0_ned_m: tuple[float, float, float]
    v_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    attitude_error_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def camera_ned_m(self, t_s: float) -> np.ndarray:
        return np.asarray(self.p0_ned_m, float) + np.asarray(self.v_ned_mps, float) * t_s


@dataclass(frozen=True)
class SynthTarget:
    """A target at ``p0_ned_m + v_ned_mps t``."""

    p0_ned_m: tuple[float, float, float]
    v_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def p_ned_m(self, t_s: float) -> np.ndarray:
        return np.asarray(self.p0_ned_m, float) + np.asarray(self.v_ned_mps, float) * t_s


@dataclass(frozen=True)
class SynthLos:
    """One measured line of sight: camera position and unit direction (NED) and the published sigmas."""

    p_cam_ned_m: np.ndarray
    los_ned: np.ndarray
    sigma_az_rad: float
    sigma_el_rad: float
    truth_p_ned_m: np.ndarray = field(repr=False)


def measure(
    vehicle: SynthVehicle,
    target: SynthTarget,
    t_s: float,
    rng: np.random.Generator,
    white_sigma_rad: float,
    bias_sigma_rad: float = 0.0,
    camera_white_sigma_m: float = 0.0,
) -> SynthLos:
    """The line of sight ``vehicle`` measures on ``target`` at ``t_s`` (module docstring).
    ``bias_sigma_rad``: the attitude bias's prior sigma, only published (the error itself is the vehicle's)."""
    c_true = vehicle.camera_ned_m(t_s)
    p = target.p_ned_m(t_s)
    d = p - c_true
    u = rotmat_from_rotvec(np.asarray(vehicle.attitude_error_rad, float)) @ (d / np.linalg.norm(d))
    n, e, dd = u
    h = math.hypot(n, e)
    if white_sigma_rad > 0:
        if h < 1e-9:
            raise ValueError("measure: a vertical line of sight has no azimuth to add noise to")
        e_az = np.array([-e / h, n / h, 0.0])
        e_el = np.array([dd * n / h, dd * e / h, -h])
        a, b = rng.normal(0.0, white_sigma_rad, 2)
        u = u + a * e_az + b * e_el
        u /= np.linalg.norm(u)
    c = c_true + np.asarray(vehicle.offset_ned_m, float)
    if camera_white_sigma_m > 0:
        c = c + rng.normal(0.0, camera_white_sigma_m, 3)
    sigma = math.hypot(white_sigma_rad, bias_sigma_rad)
    h = math.hypot(u[0], u[1])
    return SynthLos(c, u, min(sigma / max(h, 1e-12), math.pi), sigma, p)


def track_payload(
    vehicle: str,
    seq: int,
    time_boot_us: int,
    los: SynthLos,
    origin: GeodeticOrigin,
    time_unix_us: int | None = None,
    track_id: int = 1,
    bias_sigma_rad: float | None = None,
) -> dict:
    """The ``irtrack.track/2`` dict a daemon would publish for ``los`` (no 3-D position), plus
    ``time_unix_us`` when given; ``bias_sigma_rad``: the attitude bias's share of its sigmas the line of sight states
    (``los_sigma_bias_deg``; None: states none, as a daemon before the key)."""
    u = los.los_ned
    az = math.degrees(math.atan2(u[1], u[0]))
    el = math.degrees(math.atan2(-u[2], math.hypot(u[0], u[1])))
    track = Track(
        vehicle=vehicle,
        seq=seq,
        time_boot_us=time_boot_us,
        state="tracking",
        track_id=track_id,
        measurement_valid=True,
        u_px=320.0,
        v_px=256.0,
        pose_valid=True,
        los=LineOfSight(
            u_ned=tuple(u.tolist()),
            azimuth_deg=az,
            elevation_deg=el,
            sigma_azimuth_deg=min(math.degrees(los.sigma_az_rad), 180.0),
            sigma_elevation_deg=math.degrees(los.sigma_el_rad),
            p_cam_ned_m=tuple(los.p_cam_ned_m.tolist()),
            sigma_bias_deg=None if bias_sigma_rad is None else math.degrees(bias_sigma_rad),
        ),
        origin=origin,
    )
    out = track_to_json(track)
    if time_unix_us is not None:
        out["time_unix_us"] = int(time_unix_us)
    return out
