"""The ``pose`` section of the daemon's configuration: the one declaration of the pose buffer's settings
(:class:`PoseConfig`, :class:`OriginConfig`), which :class:`onboard.core.pose.PoseBuffer` takes as is, and
the extrapolation horizons they give (:meth:`PoseConfig.extrapolation_horizons`, with the error model of
:func:`extrapolation_sigma`: the module docstring of :mod:`onboard.core.pose` derives them).

Units: the file's (milliseconds, seconds, degrees) in the fields, the buffer's (microseconds on the boot
clock, radians) in the properties.  Pure: no I/O.
"""

from __future__ import annotations

import functools
import math
from typing import Annotated, Literal, NamedTuple

from onboard.core.frames import GeodeticOrigin
from onboard.core.schema import Bool, Integer, Invalid, Number, Text, config_dataclass

__all__ = [
    "PoseConfig",
    "OriginConfig",
    "ExtrapolationHorizons",
    "extrapolation_sigma",
    "attitude_horizon_us",
    "position_step_check",
]

US_PER_S = 1_000_000


def extrapolation_sigma(horizon_s: float, rate_sigma: float, accel_sigma: float) -> float:
    """1-sigma error of a constant-rate extrapolation over ``horizon_s``:
    ``sqrt((rate_sigma h)^2 + (accel_sigma h^2 / 2)^2)`` (rate error over the horizon plus an
    unmodelled second derivative; units of the rate times s: rad from rad/s and rad/s^2, m from
    m/s and m/s^2)."""
    h = max(float(horizon_s), 0.0)
    return math.hypot(rate_sigma * h, 0.5 * accel_sigma * h * h)


def position_step_check(config: PoseConfig, dt_s: float, p0, v0, p1, v1) -> tuple[float, float] | None:
    """``(miss_m, tolerance_m)``: how far the position ``p1`` lies from ``p0`` moved ``dt_s`` later by the mean of the
    reported velocities ``v0`` and ``v1`` (exact under a constant acceleration; NED m, m/s), and how far it may:
    ``config.max_position_step_m`` plus three :func:`extrapolation_sigma` of the velocities' error and an unmodelled
    acceleration over ``dt_s``.  None without both velocities (NaN: unknown) or for ``dt_s`` <= 0."""
    if dt_s <= 0 or not (math.isfinite(v1[0]) and math.isfinite(v0[0])):
        return None
    half = 0.5 * dt_s
    # hypot, not the root of a sum of squares: a position far out of range (refused, but kept to judge the next one
    # by) squares past the largest float, which ** raises on
    miss_m = math.hypot(*(p1[k] - (p0[k] + half * (v0[k] + v1[k])) for k in range(3)))
    sigma_m = extrapolation_sigma(dt_s, config.velocity_sigma_mps, config.accel_sigma_mps2)
    return miss_m, config.max_position_step_m + 3.0 * sigma_m


def attitude_horizon_us(limit: float, rate_sigma: float, accel_sigma: float, cap_us: int) -> int:
    """The longest horizon (us, at most ``cap_us``) whose :func:`extrapolation_sigma` stays <= ``limit``.

    Solves ``rate^2 h^2 + accel^2 h^4 / 4 = limit^2`` for ``h^2`` (a quadratic; monotone in h), in
    the cancellation-free form ``h^2 = 2 limit^2 / (rate^2 + sqrt(rate^4 + accel^2 limit^2))``.
    """
    if limit <= 0.0:
        return 0
    a, b = 0.25 * accel_sigma**2, rate_sigma**2
    den = b + math.sqrt(b * b + 4.0 * a * limit**2)
    h2 = math.inf if den == 0.0 else 2.0 * limit**2 / den
    return int(min(cap_us, math.floor(math.sqrt(h2) * US_PER_S))) if math.isfinite(h2) else int(cap_us)


def _us(ms: float) -> int:
    """Milliseconds as whole microseconds, at least 1."""
    return max(1, int(round(ms * 1000.0)))


class ExtrapolationHorizons(NamedTuple):
    """How far past its newest sample each stream is extrapolated (us; 0: not at all)."""

    attitude_us: int
    position_us: int
    gimbal_us: int


@config_dataclass
class OriginConfig:
    """``pose.origin`` of the daemon's configuration: a fixed local NED origin (degrees, metres).  All three are
    required: a field left out is an error, not 0 (a latitude alone would put the origin on the prime meridian,
    thousands of kilometres from the vehicle, with the geofence and altitude band relative to it)."""

    lat_deg: Annotated[float, Number(-90.0, 90.0)]
    lon_deg: Annotated[float, Number(-180.0, 180.0)]
    alt_m: Annotated[float, Number(-1000.0, 100000.0)]

    def geodetic(self) -> GeodeticOrigin:
        return GeodeticOrigin(self.lat_deg, self.lon_deg, self.alt_m)


@config_dataclass
class PoseConfig:
    """The ``pose`` section of the daemon's configuration (``config/onboard.yaml``; composed by
    :class:`onboard.app.config.OnboardConfig`), which :class:`~onboard.core.pose.PoseBuffer` takes as is: its
    tolerances in the file's units (milliseconds, seconds, degrees), read by the buffer in microseconds and radians
    through the properties below (``window_us``, ``att_max_gap_us`` ..., ``body_rate_sigma_rps`` ...).

    ``*_max_gap_ms``: the widest bracket a lookup accepts (the "pose tolerance": a frame whose bracket
    is wider has no pose and is not used for 3-D).  ``reboot_threshold_s``: a sample more than this
    before or after its stream's newest one is far from the running clock: an outlier, refused
    (``<stream>_time_outlier``), unless :data:`~onboard.core.pose.TIME_CONFIRM_COUNT` consecutive such
    samples agree with each other (each after the previous, by at most the threshold): then it is a clock
    step, backwards an autopilot reboot (buffers cleared, ``reboot``), forwards a gap
    (``<stream>_time_step``).  One bad stamp costs one sample.  ``max_speed_mps``: a position implying a faster move from the previous one
    is a jump; so is one farther than ``max_position_step_m`` (plus the velocity error and acceleration the
    ``*_sigma_*`` fields allow) from where the previous one and the two reported velocities put it, within a
    position bracket; ``jump_reset_count`` consecutive jumps restart the position stream.
    ``position_interp``: ``"hermite"`` (uses velocity) or ``"linear"``.  Extrapolation past the newest
    sample (the docstring of :mod:`onboard.core.pose`): :meth:`extrapolation_horizons`; the error model of
    :attr:`~onboard.core.pose.PoseAt.sigma_extrapolation_rad` / ``_m``: the ``*_sigma_*`` fields.
    ``dead_reckoning_max_s``: how long position is carried on with the last reported velocity through a
    gap in the position stream (a GNSS dropout), its sigma growing as ``velocity_sigma_mps`` and
    ``accel_sigma_mps2`` say; 0: not at all.
    """

    window_s: Annotated[float, Number(0.1, 600.0)] = 5.0
    attitude_max_gap_ms: Annotated[float, Number(0.0, 10000.0, lo_open=True)] = 100.0
    position_max_gap_ms: Annotated[float, Number(0.0, 10000.0, lo_open=True)] = 300.0
    gimbal_max_gap_ms: Annotated[float, Number(0.0, 10000.0, lo_open=True)] = 300.0
    reboot_threshold_s: Annotated[float, Number(0.0, 3600.0, lo_open=True)] = 1.0
    max_speed_mps: Annotated[float, Number(0.0, 10000.0, lo_open=True)] = 200.0
    max_position_step_m: Annotated[float, Number(0.0, 10000.0, lo_open=True)] = 1.0
    jump_reset_count: Annotated[int, Integer(1, 1000)] = 5
    keep_origin_on_reboot: Bool = True
    position_interp: Annotated[Literal["hermite", "linear"], Text()] = "hermite"
    wait_ms: Annotated[float, Number(0.0, 1000.0)] = 5.0
    max_extrapolation_ms: Annotated[float, Number(0.0, 10000.0)] = 50.0
    extrapolation_noise_fraction: Annotated[float, Number(0.0, 10.0)] = 0.25
    body_rate_sigma_dps: Annotated[float, Number(0.0, 1000.0)] = 0.1
    gimbal_rate_sigma_dps: Annotated[float, Number(0.0, 1000.0)] = 0.5
    angular_accel_sigma_dps2: Annotated[float, Number(0.0, 100000.0)] = 20.0
    velocity_sigma_mps: Annotated[float, Number(0.0, 1000.0)] = 0.1
    accel_sigma_mps2: Annotated[float, Number(0.0, 1000.0)] = 2.0
    dead_reckoning_max_s: Annotated[float, Number(0.0, 60.0)] = 10.0
    origin: OriginConfig | None = None

    def __post_init__(self) -> None:
        for name in ("attitude_max_gap_ms", "position_max_gap_ms", "gimbal_max_gap_ms"):
            if getattr(self, name) > self.window_s * 1000.0:
                raise Invalid(name, f"a gap <= pose.window_s ({self.window_s:g} s)", getattr(self, name))

    # the buffer's units, computed once per section
    @functools.cached_property
    def window_us(self) -> int:
        return _us(self.window_s * 1000.0)

    @functools.cached_property
    def att_max_gap_us(self) -> int:
        return _us(self.attitude_max_gap_ms)

    @functools.cached_property
    def pos_max_gap_us(self) -> int:
        return _us(self.position_max_gap_ms)

    @functools.cached_property
    def gimbal_max_gap_us(self) -> int:
        return _us(self.gimbal_max_gap_ms)

    @functools.cached_property
    def reboot_threshold_us(self) -> int:
        return _us(self.reboot_threshold_s * 1000.0)

    @functools.cached_property
    def dead_reckoning_us(self) -> int:
        return _us(self.dead_reckoning_max_s * 1000.0)

    @functools.cached_property
    def body_rate_sigma_rps(self) -> float:
        return math.radians(self.body_rate_sigma_dps)

    @functools.cached_property
    def gimbal_rate_sigma_rps(self) -> float:
        return math.radians(self.gimbal_rate_sigma_dps)

    @functools.cached_property
    def angular_accel_sigma_rps2(self) -> float:
        return math.radians(self.angular_accel_sigma_dps2)

    def extrapolation_horizons(self, bearing_white_sigma_rad: float | None = None) -> ExtrapolationHorizons:
        """How far each stream is extrapolated, each capped by its stream's max gap: position
        ``max_extrapolation_ms``; attitude and gimbal the same, shortened so that their added 1-sigma stays
        <= ``extrapolation_noise_fraction`` x ``bearing_white_sigma_rad`` (:func:`attitude_horizon_us`; the
        service passes ``OnboardConfig.bearing_white_sigma_rad()``; None: not shortened)."""
        cap_us = int(round(self.max_extrapolation_ms * 1000.0))
        if bearing_white_sigma_rad is None:
            att_us = gim_us = cap_us
        else:
            limit = self.extrapolation_noise_fraction * bearing_white_sigma_rad
            att_us = attitude_horizon_us(limit, self.body_rate_sigma_rps, self.angular_accel_sigma_rps2, cap_us)
            gim_us = attitude_horizon_us(limit, self.gimbal_rate_sigma_rps, self.angular_accel_sigma_rps2, cap_us)
        return ExtrapolationHorizons(
            attitude_us=min(att_us, self.att_max_gap_us),
            position_us=min(cap_us, self.pos_max_gap_us),
            gimbal_us=min(gim_us, self.gimbal_max_gap_us),
        )

    def geodetic_origin(self) -> GeodeticOrigin | None:
        return None if self.origin is None else self.origin.geodetic()
