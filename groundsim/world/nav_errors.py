"""Navigation errors of the simulated autopilot: what an INS/GNSS reports instead of the truth (pure core).

The simulator's state is exact; the vehicle's *telemetry* is not.  A :class:`NavErrorModel` is
built once per run from a noise case of ``config/noise_cases.yaml`` (:class:`groundsim.world.scenario.NoiseCase`;
its ``pixel_sigma_px`` is not used here: pixels come from the renderer) and a generator
(``scenario.rng(NAV_ERROR_STREAM, run_seed)``, a stream of its own so no other stream shifts), and
gives the error injected at every simulator tick ``i`` (time ``t_s[i]`` since the scenario start):

* attitude: ``phi_ned_rad[i] = b + w_att[i]``, a rotation vector in NED (navigation-frame error, the
  convention of ``onboard.core.frames`` and of the estimator's noise model): the reported attitude is
  ``R_rep = Exp(phi) R_true``, i.e. ``q_rep = q(phi) (x) q_true``.  ``b`` ~ N(0, attitude_bias_sigma^2 I)
  is drawn once per run (constant bias), ``w_att[i]`` ~ N(0, attitude_white_sigma^2 I) per tick.
  The same ``phi`` is applied to the body attitude (#31 ATTITUDE_QUATERNION) and, for a gimballed pod,
  to the gimbal's earth-frame attitude (#285 GIMBAL_DEVICE_ATTITUDE_STATUS): the camera attitude the
  daemon rebuilds carries the INS error, as on a gimbal stabilised on the autopilot's attitude.
  The reported heading moves with the attitude's yaw; body rates are reported exact.
* position: ``dp_ned_m[i] = o + d * t_s[i] + w_pos[i]``: a constant offset ``o`` of size
  ``camera_position_offset_m`` and a drift rate ``d`` of size ``camera_position_drift_mps``, each in a
  direction drawn uniformly on the sphere once per run, plus white ``w_pos[i]`` ~
  N(0, camera_position_white_sigma_m^2 I) per tick.  Applied to the reported latitude, longitude and
  altitude (#33 GLOBAL_POSITION_INT), as a NED offset about the true point.
* velocity: ``dv_ned_mps = d`` (the derivative of the offset and drift; white position noise has no
  derivative, as from a GNSS/INS whose velocity is filtered): the reported velocity is consistent
  with the reported position.

Draw order (fixed, so a run is a function of (case, generator, tick count)): ``b`` (3), offset
direction (3), drift direction (3), then ``w_att`` (N, 3), then ``w_pos`` (N, 3).  A case whose sigma
is zero still draws (so ``exact`` and ``RTK`` share the generator's sequence shape).

:func:`reported_state` applies one tick's error to the keyword arguments of
``MavlinkVehicle.update_state`` (the dict ``SimCore.vehicle_state`` returns); it is the one place the
errors are applied, used by the simulated MAVLink vehicle and by the lockstep evaluation's telemetry.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from groundsim.world.noise_cases import load_noise_cases, noise_cases_path
from groundsim.world.scenario import DEFAULT_NAV_NOISE  # "RTK"
from onboard.core.checks import is_nonnegative_number
from onboard.core.errors import ConfigError, InputError
from onboard.core.frames import (
    GeodeticOrigin,
    euler_from_quat,
    geodetic_from_ned,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
)

__all__ = [
    "DEFAULT_NAV_NOISE",
    "NAV_ERROR_STREAM",
    "NavErrorSample",
    "NavErrorModel",
    "offset_geodetic",
    "GnssDropout",
    "parse_gnss_dropout",
    "CameraClockError",
    "parse_camera_time_offset",
    "resolve_nav_noise",
    "run_nav_case",
    "InjectedErrors",
    "reported_state",
]


@dataclass(frozen=True)
class GnssDropout:
    """A window of the flight without GNSS: ``start_s`` (scenario time) for ``duration_s``.

    The simulated autopilot then withholds GLOBAL_POSITION_INT (#33) and reports GPS_RAW_INT (#24)
    with no fix, while attitude, the gimbal and the frames go on (what a daemon sees of an autopilot
    that does not dead-reckon through a GNSS gap).  ``--gnss-dropout START_S:DURATION_S``.
    """

    start_s: float
    duration_s: float

    def __post_init__(self) -> None:
        for name in ("start_s", "duration_s"):
            v = getattr(self, name)
            if not is_nonnegative_number(v):
                raise ConfigError(f"--gnss-dropout: {name} must be a finite number >= 0 s, got {v!r}")
            object.__setattr__(self, name, float(v))

    def check_within(self, duration_s: float) -> None:
        """Refuses a dropout that starts at or after the end of a run of ``duration_s`` (it would never happen)."""
        if self.start_s >= duration_s:
            raise ConfigError(
                f"--gnss-dropout: expected a start before the run's end ({duration_s:g} s), got {self.start_s:g} s"
            )

    def active(self, t_s: float) -> bool:
        """No GNSS at scenario time ``t_s``."""
        return self.start_s <= t_s < self.start_s + self.duration_s

    def boot_window_us(self, boot_start_us: int) -> tuple[int, int]:
        """The window on the vehicle's boot clock, ``[start, end)`` microseconds."""
        t0 = boot_start_us + round(self.start_s * 1e6)
        return t0, t0 + round(self.duration_s * 1e6)


def parse_gnss_dropout(text: str) -> GnssDropout:
    """``"START_S:DURATION_S"`` (e.g. ``"8:5"``) -> :class:`GnssDropout`; ConfigError naming the option."""
    start, sep, duration = str(text).partition(":")
    try:
        if not sep:
            raise ValueError
        return GnssDropout(float(start), float(duration))
    except ValueError:
        raise ConfigError(f"--gnss-dropout: expected START_S:DURATION_S (e.g. 8:5), got {text!r}") from None


@dataclass(frozen=True)
class CameraClockError:
    """The camera's clock against the autopilot's: frames stamped ``offset_ms + drift_ppm * 1e-6 * t``
    late (positive: the stamp is later than the true capture), ``t`` the scenario time.  What an unmeasured
    USB/CSI buffer or encoder latency, and a free-running camera oscillator, do.
    ``--camera-time-offset-ms MS[:DRIFT_PPM]``."""

    offset_ms: float
    drift_ppm: float = 0.0

    def __post_init__(self) -> None:
        for name in ("offset_ms", "drift_ppm"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > 1e6:
                raise ConfigError(f"--camera-time-offset-ms: {name} must be a finite number within 1e6, got {v!r}")
            object.__setattr__(self, name, float(v))

    def stamp_us(self, time_boot_us: int, t_s: float) -> int | None:
        """The stamp a frame captured at ``time_boot_us`` (scenario time ``t_s``) carries; None when an early
        camera clock would stamp it before the autopilot's boot (no boot-clock stamp says that: such a frame
        is not sent, as a companion drops a frame it cannot place)."""
        stamp = int(time_boot_us) + round(self.offset_ms * 1000.0 + self.drift_ppm * t_s)
        return stamp if stamp >= 0 else None


def parse_camera_time_offset(text: str) -> CameraClockError:
    """``"MS"`` or ``"MS:DRIFT_PPM"`` (e.g. ``"50"``, ``"50:20"``) -> :class:`CameraClockError`."""
    offset, _, drift = str(text).partition(":")
    try:
        return CameraClockError(float(offset), float(drift) if drift else 0.0)
    except ValueError:
        raise ConfigError(f"--camera-time-offset-ms: expected MS or MS:DRIFT_PPM (e.g. 50:20), got {text!r}") from None


#: The scenario random stream the errors are drawn from (``Scenario.rng(NAV_ERROR_STREAM, run_seed)``).
NAV_ERROR_STREAM = "nav.errors"


@dataclass(frozen=True)
class NavErrorSample:
    """The error injected at one sample.

    ``att_err_ned_rad`` (3,): rotation vector of ``R_reported R_true^T`` in NED, radians;
    ``p_err_ned_m`` (3,): reported minus true position, NED metres; ``v_err_ned_mps`` (3,): reported
    minus true velocity, NED m/s.
    """

    att_err_ned_rad: np.ndarray
    p_err_ned_m: np.ndarray
    v_err_ned_mps: np.ndarray

    def __post_init__(self) -> None:
        for name in ("att_err_ned_rad", "p_err_ned_m", "v_err_ned_mps"):
            a = np.array(getattr(self, name), dtype=float)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise InputError(f"NavErrorSample.{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        # per-tick hot path (reported_state at 120 Hz): which parts are non-zero, computed once
        object.__setattr__(self, "has_attitude_error", bool(self.att_err_ned_rad.any()))
        object.__setattr__(self, "has_position_error", bool(self.p_err_ned_m.any()))
        object.__setattr__(self, "has_velocity_error", bool(self.v_err_ned_mps.any()))

    @property
    def is_zero(self) -> bool:
        return not (self.has_attitude_error or self.has_position_error or self.has_velocity_error)


ZERO_ERROR = NavErrorSample(np.zeros(3), np.zeros(3), np.zeros(3))


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else np.array([1.0, 0.0, 0.0])


class NavErrorModel:
    """One run's navigation errors on a tick grid (see the module docstring).

    ``case``: a :class:`groundsim.world.scenario.NoiseCase`; ``rng``: the run's generator; ``t_s`` (N,): tick
    times, seconds since the scenario start.  Arrays (read-only): ``bias_ned_rad`` (3,),
    ``offset_ned_m`` (3,), ``drift_ned_mps`` (3,), ``att_white_ned_rad`` (N, 3), ``p_white_ned_m`` (N, 3).
    """

    def __init__(self, case, rng: np.random.Generator, t_s) -> None:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if not np.all(np.isfinite(t)):
            raise InputError("NavErrorModel t_s must be finite")
        self.case = case
        self.name = str(getattr(case, "name", ""))
        self.t_s = t
        n = t.size
        self.bias_ned_rad = case.attitude_bias_sigma_rad * rng.standard_normal(3)
        self.offset_ned_m = case.camera_position_offset_m * _unit(rng)
        self.drift_ned_mps = case.camera_position_drift_mps * _unit(rng)
        self.att_white_ned_rad = case.attitude_white_sigma_rad * rng.standard_normal((n, 3))
        self.p_white_ned_m = case.camera_position_white_sigma_m * rng.standard_normal((n, 3))
        for a in (
            self.t_s,
            self.bias_ned_rad,
            self.offset_ned_m,
            self.drift_ned_mps,
            self.att_white_ned_rad,
            self.p_white_ned_m,
        ):
            a.setflags(write=False)

    def __len__(self) -> int:
        return self.t_s.size

    def att_err_ned_rad(self) -> np.ndarray:
        """(N, 3) attitude error rotation vectors at every tick."""
        return self.bias_ned_rad + self.att_white_ned_rad

    def p_err_ned_m(self) -> np.ndarray:
        """(N, 3) position errors at every tick."""
        return self.offset_ned_m + self.t_s[:, None] * self.drift_ned_mps + self.p_white_ned_m

    def sample(self, i: int) -> NavErrorSample:
        """The error at tick ``i``."""
        if not 0 <= i < self.t_s.size:
            raise IndexError(f"tick {i} outside the navigation-error grid of {self.t_s.size}")
        return NavErrorSample(
            att_err_ned_rad=self.bias_ned_rad + self.att_white_ned_rad[i],
            p_err_ned_m=self.offset_ned_m + self.t_s[i] * self.drift_ned_mps + self.p_white_ned_m[i],
            v_err_ned_mps=self.drift_ned_mps,
        )


def resolve_nav_noise(name: str, path=None, option: str = "--nav-noise"):
    """The :class:`~groundsim.world.scenario.NoiseCase` called ``name`` in ``config/noise_cases.yaml`` (or ``path``).

    An unknown name is a :class:`ConfigError` (one line, exit code 2) naming the file and the allowed names.
    """
    p = Path(path) if path is not None else noise_cases_path()
    cases = load_noise_cases(p)
    if name in cases:
        return cases[name]
    lower = {k.lower(): k for k in cases}
    hint = (
        [lower[str(name).lower()]]
        if str(name).lower() in lower
        else difflib.get_close_matches(str(name), list(cases), n=1)
    )
    hint_text = f"; did you mean '{hint[0]}'?" if hint else ""
    raise ConfigError(f"{p}: {option}: expected one of {', '.join(cases)}, got {name!r}{hint_text}")


def _option_number(x: float) -> str:
    """A float as an option's text that reads back to the same float (``8.0`` -> ``"8"``)."""
    return repr(float(x)).removesuffix(".0")


def run_nav_case(scenario, nav_noise=None):
    """The navigation-error case a run of ``scenario`` flies: ``nav_noise`` (a case, or its name in
    ``config/noise_cases.yaml``), or the scenario's own when None.  The one rule for the simulator, the dataset's
    sequence names and the demo's plan."""
    nav = scenario.nav_noise if nav_noise is None else nav_noise
    return resolve_nav_noise(nav) if isinstance(nav, str) else nav


@dataclass(frozen=True)
class InjectedErrors:
    """What a simulated run makes the daemon's inputs get wrong, beside the world itself: ``nav_noise``, the
    telemetry's navigation-error case (a name of ``config/noise_cases.yaml``; None: the scenario's own);
    ``gnss_dropout`` (:class:`GnssDropout`) and ``camera_clock`` (:class:`CameraClockError`), None: none.

    One group for ``groundsim run`` (``RunConfig.injected``), the lockstep evaluation (``EvalOptions.injected``,
    hence ``eval`` and ``campaign``) and ``demo`` (which passes it on to its ``groundsim run``): options
    ``--nav-noise``, ``--gnss-dropout``, ``--camera-time-offset-ms`` (:meth:`from_options`,
    :meth:`run_options`).  An unknown case name fails at construction, naming the file and the choices.
    """

    nav_noise: str | None = None
    gnss_dropout: GnssDropout | None = None
    camera_clock: CameraClockError | None = None

    def __post_init__(self) -> None:
        if self.nav_noise is not None:
            resolve_nav_noise(self.nav_noise)
        for name, cls in (("gnss_dropout", GnssDropout), ("camera_clock", CameraClockError)):
            value = getattr(self, name)
            if value is not None and not isinstance(value, cls):
                raise ConfigError(f"InjectedErrors.{name} must be a {cls.__name__} or None, got {type(value).__name__}")

    @classmethod
    def from_options(
        cls,
        nav_noise: str | None = None,
        gnss_dropout: str | None = None,
        camera_time_offset_ms: str | None = None,
    ) -> InjectedErrors:
        """From the options' text (``--nav-noise NAME``, ``--gnss-dropout START_S:DURATION_S``,
        ``--camera-time-offset-ms MS[:DRIFT_PPM]``; None or empty: not given); ConfigError naming the option."""
        return cls(
            nav_noise,
            parse_gnss_dropout(gnss_dropout) if gnss_dropout else None,
            parse_camera_time_offset(camera_time_offset_ms) if camera_time_offset_ms else None,
        )

    def run_options(self) -> list[str]:
        """The ``groundsim run`` options that inject these errors (what :meth:`from_options` reads back)."""
        out = [] if self.nav_noise is None else ["--nav-noise", self.nav_noise]
        if self.gnss_dropout is not None:
            g = self.gnss_dropout
            out += ["--gnss-dropout", f"{_option_number(g.start_s)}:{_option_number(g.duration_s)}"]
        if self.camera_clock is not None:
            c = self.camera_clock
            out += ["--camera-time-offset-ms", f"{_option_number(c.offset_ms)}:{_option_number(c.drift_ppm)}"]
        return out


def offset_geodetic(lat_deg: float, lon_deg: float, alt_m: float, d_ned_m) -> tuple[float, float, float]:
    """WGS84 point moved by a NED offset ``d_ned_m`` (3,) expressed at that point: the geodesy of
    :func:`onboard.core.frames.geodetic_from_ned` about the point itself.  Longitude wraps into [-180, 180)."""
    lat2, lon2, alt2 = geodetic_from_ned(np.asarray(d_ned_m, dtype=float), GeodeticOrigin(lat_deg, lon_deg, alt_m))
    lon2 = (float(lon2) + 180.0) % 360.0 - 180.0
    return float(lat2), lon2, float(alt2)


def reported_state(state: dict, err: NavErrorSample | None) -> dict:
    """What the autopilot reports for the true ``state`` with navigation error ``err`` (pure; a new dict).

    ``state``: keyword arguments of ``MavlinkVehicle.update_state`` (``lat_deg``, ``lon_deg``,
    ``alt_amsl_m``, ``alt_rel_m``, ``v_ned_mps``, ``q_ned_from_body``, ``heading_rad``, ``q_gimbal``,
    ...).  Position: the true point moved by ``err.p_err_ned_m`` in the NED frame at that point
    (WGS84); velocity + ``err.v_err_ned_mps``; attitudes (body and gimbal, both relative to the local level at the vehicle)
    pre-multiplied by ``q(err.att_err_ned_rad)``; heading shifted by the yaw change.  ``None`` or a
    zero error returns an unchanged copy.
    """
    out = dict(state)
    if err is None or err.is_zero:
        return out
    if err.has_position_error:
        lat, lon, alt = offset_geodetic(
            float(state["lat_deg"]), float(state["lon_deg"]), float(state["alt_amsl_m"]), err.p_err_ned_m
        )
        out["lat_deg"], out["lon_deg"], out["alt_amsl_m"] = lat, lon, alt
        out["alt_rel_m"] = float(state["alt_rel_m"]) + (alt - float(state["alt_amsl_m"]))
    out["v_ned_mps"] = np.asarray(state["v_ned_mps"], dtype=float) + err.v_err_ned_mps
    if err.has_attitude_error:
        dq = quat_from_rotvec(err.att_err_ned_rad)
        q_true = np.asarray(state["q_ned_from_body"], dtype=float)
        q_rep = quat_normalize(quat_multiply(dq, q_true))
        out["q_ned_from_body"] = q_rep
        h = state.get("heading_rad")
        if h is not None and math.isfinite(float(h)):
            dyaw = float(euler_from_quat(q_rep)[2]) - float(euler_from_quat(q_true)[2])
            out["heading_rad"] = float(h) + math.remainder(dyaw, 2.0 * math.pi)
        g = state.get("q_gimbal")
        if g is not None:
            out["q_gimbal"] = quat_normalize(quat_multiply(dq, np.asarray(g, dtype=float)))
    return out
