"""Analytic observation synthesis: perfect-geometry truth plus the reference noise cases.

This is the "perfect centroid" path used by the estimator benchmark and the demo of the
foundation: the observer and target follow their analytic motion models exactly, the camera is
pointed at the target with the reference study's slowly varying pointing error, and the target's
true pixel is corrupted by the noise case (``config/noise_cases.yaml``):

- pixel noise: white, ``pixel_sigma_px`` per axis;
- attitude: white ``attitude_white_sigma`` and a constant bias ``attitude_bias_sigma`` per NED
  axis, applied as ``R_meas = Exp(phi) R_true`` (navigation-frame error, ``onboard.core.frames``);
- camera position: white ``camera_position_white_sigma_m`` per axis, a constant offset of
  magnitude ``camera_position_offset_m`` in a random direction, and a drift of
  ``camera_position_drift_mps`` in a random direction.

Frames follow ``onboard.core.frames``; the camera looks along +z (x right, y down).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from groundsim.world.motion import KinematicState
from onboard.core.frames import PinholeIntrinsics, quat_from_rotmat, rotmat_from_rotvec
from onboard.estimation.map_estimator import NoiseModel
from onboard.estimation.observations import Observations

__all__ = [
    "Truth",
    "look_at_R_ned_from_cam",
    "pointing_offsets_ned_m",
    "synthesize",
    "synthesize_scenario",
    "estimator_noise_model",
    "Racetrack",
    "Weave",
]


@dataclass(frozen=True)
class Truth:
    """True states at the observation times (F rows)."""

    t_s: np.ndarray
    p_target_ned_m: np.ndarray
    v_target_ned_mps: np.ndarray
    p_cam_ned_m: np.ndarray
    R_ned_from_cam: np.ndarray
    uv_px: np.ndarray

    @property
    def range_m(self) -> np.ndarray:
        return np.linalg.norm(self.p_target_ned_m - self.p_cam_ned_m, axis=1)


def look_at_R_ned_from_cam(p_cam_ned_m: np.ndarray, p_aim_ned_m: np.ndarray) -> np.ndarray:
    """Camera attitudes (F, 3, 3) looking from p_cam at p_aim with the image's x axis level (no roll)."""
    z = p_aim_ned_m - p_cam_ned_m
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    down = np.array([0.0, 0.0, 1.0])
    x = np.cross(down, z)
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def pointing_offsets_ned_m(t_s, range_m, frac=(0.03, 0.02, 0.015), period_s=(7.0, 5.0, 3.0)) -> np.ndarray:
    """The reference study's gimbal pointing error: per-axis sinusoids as a fraction of range."""
    t = np.asarray(t_s, dtype=float)[:, None]
    return np.asarray(range_m, dtype=float)[:, None] * np.asarray(frac) * np.sin(2 * np.pi * t / np.asarray(period_s))


def estimator_noise_model(noise_case, pixel_sigma_px: float | None = None) -> NoiseModel:
    """The noise model an estimator should assume for a noise case (offsets as per-axis sigmas);
    ``pixel_sigma_px`` replaces the case's pixel noise (the ``exact`` navigation case has none, the
    closed loop's pixel noise is the image chain's)."""
    return NoiseModel(
        pixel_sigma_px=noise_case.pixel_sigma_px if pixel_sigma_px is None else pixel_sigma_px,
        attitude_white_sigma_rad=noise_case.attitude_white_sigma_rad,
        attitude_bias_sigma_rad=noise_case.attitude_bias_sigma_rad,
        camera_position_white_sigma_m=noise_case.camera_position_white_sigma_m,
        camera_position_offset_sigma_m=noise_case.camera_position_offset_m / np.sqrt(3.0),
        camera_position_drift_sigma_mps=noise_case.camera_position_drift_mps / np.sqrt(3.0),
    )


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def synthesize(
    observer_motion,
    target_motion,
    t_s,
    intrinsics: PinholeIntrinsics,
    noise_case,
    rng: np.random.Generator,
    pointing_frac=(0.03, 0.02, 0.015),
    pointing_period_s=(7.0, 5.0, 3.0),
) -> tuple[Truth, Observations]:
    """Truth and noisy observations at times ``t_s`` (the camera centre is the observer's position)."""
    t = np.asarray(t_s, dtype=float)
    cam = observer_motion.state(t).p_ned_m
    tgt = target_motion.state(t)
    rng_m = np.linalg.norm(tgt.p_ned_m - cam, axis=1)
    aim = tgt.p_ned_m + pointing_offsets_ned_m(t, rng_m, pointing_frac, pointing_period_s)
    R_true = look_at_R_ned_from_cam(cam, aim)
    p_cam_frame = np.einsum("fji,fj->fi", R_true, tgt.p_ned_m - cam)
    uv_true = intrinsics.project(p_cam_frame)
    truth = Truth(t, tgt.p_ned_m, tgt.v_ned_mps, cam, R_true, uv_true)

    F = t.size
    uv = uv_true + noise_case.pixel_sigma_px * rng.standard_normal((F, 2))
    phi = noise_case.attitude_bias_sigma_rad * rng.standard_normal(
        3
    ) + noise_case.attitude_white_sigma_rad * rng.standard_normal((F, 3))
    R_meas = np.einsum("fij,fjk->fik", rotmat_from_rotvec(phi), R_true)
    offset = noise_case.camera_position_offset_m * _random_unit(rng)
    drift = noise_case.camera_position_drift_mps * _random_unit(rng)
    cam_meas = (
        cam
        + offset
        + (t - t[0])[:, None] * drift
        + noise_case.camera_position_white_sigma_m * rng.standard_normal((F, 3))
    )
    obs = Observations.from_intrinsics(t, uv, intrinsics, cam_meas, quat_from_rotmat(R_meas))
    return truth, obs


def synthesize_scenario(
    scenario, noise_case, seed: int, t_s=None, rng: np.random.Generator | None = None
) -> tuple[Truth, Observations]:
    """:func:`synthesize` for a :class:`groundsim.world.scenario.Scenario`: its motions for ``seed``, its camera and
    gimbal pointing error (none without a gimbal), at its frame times unless ``t_s`` is given; the noise
    stream is the scenario's ``synth.noise`` stream for ``seed`` unless ``rng`` is given."""
    t = scenario.frame_times_s() if t_s is None else np.asarray(t_s, dtype=float)
    gimbal = scenario.camera.gimbal
    frac = gimbal.pointing_error_frac_of_range if gimbal else (0.0, 0.0, 0.0)
    period = gimbal.pointing_error_period_s if gimbal else (1.0, 1.0, 1.0)
    rng = scenario.rng("synth.noise", seed) if rng is None else rng
    return synthesize(
        scenario.observer_motion(seed),
        scenario.target_motion(seed),
        t,
        scenario.camera.intrinsics,
        noise_case,
        rng,
        frac,
        period,
    )


@dataclass(frozen=True)
class Racetrack:
    """A target switching motion model every leg: straight legs (constant velocity) joined by half-turns
    (constant turn rate) around ``center_ned_m``, long axis north, flown counter-clockwise seen from above at
    ``speed_mps`` and constant height.  Bounded for any duration, so minutes-long flights keep their
    range; each corner is a model change a sliding window must follow."""

    center_ned_m: tuple
    straight_m: float
    radius_m: float
    speed_mps: float

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)
        L, r, v = self.straight_m, self.radius_m, self.speed_mps
        t_leg, t_turn = L / v, np.pi * r / v
        lap = 2 * (t_leg + t_turn)
        tau = np.mod(t, lap)
        c = np.asarray(self.center_ned_m, dtype=float)
        # leg 1: east side heading north; turn 1 about the north end; leg 2: west side heading south;
        # turn 2 about the south end
        p = np.zeros(t.shape + (3,))
        vel = np.zeros_like(p)
        acc = np.zeros_like(p)
        seg_ends = np.cumsum([t_leg, t_turn, t_leg, t_turn])
        for k, (start, end) in enumerate(zip(np.concatenate([[0.0], seg_ends[:-1]]), seg_ends)):
            m = (tau >= start) & (tau < end)
            s = tau[m] - start
            if k in (0, 2):
                sign = 1.0 if k == 0 else -1.0
                p[m, 0] = c[0] + sign * (-L / 2 + v * s)
                p[m, 1] = c[1] + sign * r
                vel[m, 0] = sign * v
            else:
                n0 = c[0] + (L / 2 if k == 1 else -L / 2)
                # the turn's centre is (n0, c_e); az_c is the azimuth from it (from north towards east)
                az_c = (np.pi / 2 if k == 1 else 3 * np.pi / 2) - v * s / r
                p[m, 0] = n0 + r * np.cos(az_c)
                p[m, 1] = c[1] + r * np.sin(az_c)
                w = -v / r
                vel[m, 0] = -r * w * np.sin(az_c)
                vel[m, 1] = r * w * np.cos(az_c)
                acc[m, 0] = -r * w * w * np.cos(az_c)
                acc[m, 1] = -r * w * w * np.sin(az_c)
        p[..., 2] = c[2]
        return KinematicState(p, vel, acc)


@dataclass(frozen=True)
class Weave:
    """An observer flying S-turns: ``p0 + v t`` plus ``amplitude_m sin(2 pi t / period_s)`` along
    ``across_ned`` (a unit vector across the mean track): the manoeuvre that keeps range observable while
    following a target."""

    p0_ned_m: tuple
    v_ned_mps: tuple
    across_ned: tuple
    amplitude_m: float
    period_s: float

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)[..., None]
        w = 2 * np.pi / self.period_s
        u = np.asarray(self.across_ned, dtype=float)
        u = u / np.linalg.norm(u)
        v0 = np.asarray(self.v_ned_mps, dtype=float)
        p = np.asarray(self.p0_ned_m, dtype=float) + v0 * t + self.amplitude_m * np.sin(w * t) * u
        v = v0 + self.amplitude_m * w * np.cos(w * t) * u
        a = -self.amplitude_m * w * w * np.sin(w * t) * u
        return KinematicState(p, v, a)
