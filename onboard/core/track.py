"""The ``Track`` noun and its wire schema ``irtrack.track/2``.

Pure: no zenoh, no pymavlink, no clocks, no message of any protocol.  The pipeline builds one
:class:`Track` per processed frame; the service serialises it with :func:`track_to_json` onto
``irtrack/<vehicle>/track``; :mod:`onboard.io.mavlink_wire` maps it onto CAMERA_TRACKING_IMAGE_STATUS
(#275) / CAMERA_TRACKING_GEO_STATUS (#276) (``image_status_fields`` / ``geo_status_fields``, with the
accuracy and heading formulas).

Schema ``irtrack.track/2`` (one UTF-8 JSON object per processed frame)
---------------------------------------------------------------------
==================  ===========================  ===================================================
key                 type                         meaning
==================  ===========================  ===================================================
schema              "irtrack.track/2"
vehicle             string                       vehicle name (the key's ``<vehicle>``)
seq                 integer                      the IR frame's sequence number
time_boot_us        integer                      the frame's stamp, us on the autopilot boot clock: its
                                                 capture time unless the camera's clock runs late; then,
                                                 with ``time_offset.compensate``, the line of sight and the
                                                 3-D fields are those of ``time_boot_us`` minus
                                                 ``compensated_us`` (the status's
                                                 ``camera_time_offset.compensated_ms``; the stamp is kept so
                                                 that track times never step back)
track_id            integer >= 1 or null         current track (a new id = a new target association)
state               string                       ``searching`` | ``tracking`` | ``coasting`` | ``lost``
measurement_valid   bool                         (u, v) is a blob centroid fit for 3-D (fed to the estimator)
u_px, v_px          number or null               target centre, pixels (u right, v down, origin at the
                                                 top-left corner of the top-left pixel; onboard.core.frames)
bbox                [x, y, w, h] or null         tracking box, pixels
pose_valid          bool                         the camera pose at ``time_boot_us`` was known
los_ned             [n, e, d] or null            (new in /2) unit line of sight camera -> target, local NED
los_az_deg          number or null               (new in /2) its azimuth, degrees from north towards east,
                                                 (-180, 180]
los_el_deg          number or null               (new in /2) its elevation, degrees, positive up, [-90, 90]
los_sigma_az_deg    number or null               (new in /2) 1-sigma of ``los_az_deg`` (formula below)
los_sigma_el_deg    number or null               (new in /2) 1-sigma of ``los_el_deg``
los_sigma_bias_deg  number or null               (new, optional; null when absent) the share of the line of
                                                 sight's sigma that is a constant attitude bias, 1 sigma per
                                                 axis, degrees: the daemon's ``estimator.attitude_bias_sigma_deg``
                                                 (``s_b`` below); null without a line of sight.  A fleet fusion
                                                 takes it as the vehicle's attitude-bias prior
camera_ned_m        [n, e, d] or null            (new in /2) the line of sight's origin: the camera, local NED
lat_deg, lon_deg    number or null               target WGS84 latitude / longitude, degrees
alt_m               number or null               target altitude, metres AMSL (treated as WGS84, see frames)
ned_m               [n, e, d] or null            target position in the local NED frame, metres
origin              {lat_deg, lon_deg, alt_m}    the local NED frame's origin, or null before one is known
                    or null
vel_ned_mps         [n, e, d] or null            target velocity, m/s
sigma_ned_m         [n, e, d] or null            1-sigma position uncertainty per axis, metres
sigma_vel_ned_mps   [n, e, d] or null            1-sigma velocity uncertainty per axis, m/s
cov_ned_m2          3 x 3 list or null           position covariance, m^2
range_m             number or null               camera-to-target distance, metres
range_sigma_ratio   number or null               posterior range sigma / range (observability measure)
observable          bool                         quality verdict on the 3-D position: the window's geometry
                                                 makes range observable and the model fits (changed in /2:
                                                 no longer a condition for the position to be present)
residual_rms_norm   number or null               (new in /2) RMS of the standardised residuals at the
                                                 estimator's last model selection (~1 when the camera model
                                                 and noise model match; null when unknown)
window_frames       integer >= 0                 observations in the estimator's window
model               string or null               the estimator's motion model for this estimate
time_unix_us        integer or null              (new, optional) ``time_boot_us`` in UTC, microseconds since
                                                 1970 (``time_boot_us`` through the autopilot's SYSTEM_TIME,
                                                 :mod:`onboard.core.utc_clock`); null until that mapping exists
time_unix_sigma_us  integer or null              (new, optional) 1-sigma of ``time_unix_us``, microseconds
                                                 (null: unknown; never set without ``time_unix_us``)
compensated_us      integer                      (new, optional; 0 when absent) the camera clock's lateness
                                                 compensated on this frame, us: the line of sight and the 3-D
                                                 fields are those of ``time_boot_us`` (and ``time_unix_us``)
                                                 minus this; 0 without compensation
estimate_epoch      integer >= 0                 (new, optional; 0 when absent) the 3-D estimator's restarts
                                                 since the daemon started: a new value says the estimate
                                                 started again and holds nothing from before (a change of
                                                 selection or track, a pose discontinuity, an autopilot
                                                 reboot; the reason is in the daemon's log)
run_id              string or null               (new, optional; null when absent) the daemon's run: 16 hex
                                                 digits drawn at its start, the same on every track and
                                                 status of that run.  A new value says the daemon restarted:
                                                 its ``track_id``, ``estimate_epoch`` and local NED
                                                 ``origin`` start again; two values taking turns are two
                                                 daemons publishing as one vehicle
==================  ===========================  ===================================================

What changed from ``irtrack.track/1``: every key of /1 keeps its name, type and unit.  The meaning of
"position present" changed: position fields (``lat_deg .. model`` except ``observable``/
``window_frames``) are set whenever the estimator has a finite solution and a local origin is
known, observable or not; ``observable`` grades that position (trust it when true; when false it is
the best estimate with its honest covariance, typically with a large range sigma).  They are null
with no estimate (none yet, the track lost, the estimator off).  The daemon's
``output.unobservable_positions: false`` restores the /1 behaviour (positions only when observable).
The line-of-sight keys (``los_*``, ``camera_ned_m``) are set on every frame with a measured target centre
(``measurement_valid``) and a pose, with or without a 3-D estimate: they need no range.  A coasting frame's
centre is the tracker's prediction, whose error no pixel sigma bounds: it gets none.
Non-finite numbers are never written (JSON has no NaN): they become null.  :func:`track_from_json`
reads /1 and /2.  The keys marked optional were added to /2 without a new name: a reader ignores keys it does not
know (:func:`track_from_json`; the recorded JSON Schema lists its keys without closing the object to others, and
a recording carries the schema of the messages beside it), and reads a missing one as its stated default.

Line of sight and its 1-sigma (:func:`line_of_sight_ned`): the ideal normalised image point
``(x, y)`` of ``(u_px, v_px)`` (distortion removed) gives ``l = R_ned_from_cam (x, y, 1) / |(x, y, 1)|``;
its covariance is ``C_l = s_px^2 J J^T + (s_w^2 + s_b^2) (I - l l^T)``, with ``J = dl/d(u, v)`` (pinhole:
``R (I - b b^T) / |(x, y, 1)| [[1/fx, 0], [0, 1/fy], [0, 0]]``, ``b`` the unit camera bearing),
``s_px`` the configured ``estimator.pixel_sigma_px``, ``s_w`` / ``s_b`` the attitude white and bias
sigmas (rad) of the estimator's noise model (an attitude error ``phi`` in NED moves ``l`` by
``phi x l``; see frames, small-angle errors).  Azimuth ``az = atan2(l_e, l_n)`` and elevation
``el = atan2(-l_d, hypot(l_n, l_e))`` get first-order sigmas ``sqrt(g C_l g^T)`` with
``g_az = (-l_e, l_n, 0) / h^2`` and ``g_el = (l_d l_n / h, l_d l_e / h, -h)``, ``h = hypot(l_n, l_e)``.
Near the optical axis this is ``s_el = sqrt((s_px / f)^2 + s_w^2 + s_b^2)`` and ``s_az = s_el / cos(el)``
(capped at 180 deg).  Camera position noise does not enter a direction.

The status JSON ``irtrack.status/1`` is :mod:`onboard.core.status`'s.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin, PinholeIntrinsics, rotmat_from_quat
from onboard.core.json_schema import object_schema

__all__ = [
    "TRACK_SCHEMA",
    "READABLE_TRACK_SCHEMAS",
    "TRACK_STATES",
    "TRACK_JSON_KEYS",
    "track_json_schema",
    "LineOfSight",
    "line_of_sight_ned",
    "Track",
    "track_to_json",
    "track_to_bytes",
    "track_from_json",
    "json_number",
    "RUN_ID_HEX_DIGITS",
    "is_run_id",
    "new_run_id",
]

TRACK_SCHEMA = "irtrack.track/2"
READABLE_TRACK_SCHEMAS = ("irtrack.track/1", TRACK_SCHEMA)  # /1 has the same keys minus the /2 additions
TRACK_STATES = ("searching", "tracking", "coasting", "lost")
#: a camera clock compensated by more than this (a minute) is no clock the time-offset estimator reports
MAX_COMPENSATED_US = 60_000_000
#: a daemon run's id: 64 random bits, lower-case hex (a restart draws another; two runs share one with odds 2^-64)
RUN_ID_HEX_DIGITS = 16


#: run ids already found well formed (a few: the daemon's own, a fusion's vehicles'), so that each track's check is
#: a set look-up
_RUN_IDS_CHECKED: set[str] = set()


def new_run_id() -> str:
    """A fresh run id (:data:`RUN_ID_HEX_DIGITS` hex digits from the OS's random source)."""
    import secrets

    return secrets.token_hex(RUN_ID_HEX_DIGITS // 2)


def is_run_id(value: object) -> bool:
    """Whether ``value`` is a run id as :func:`new_run_id` makes them."""
    return isinstance(value, str) and len(value) == RUN_ID_HEX_DIGITS and all(c in "0123456789abcdef" for c in value)


#: the altitudes (WGS84, m) a vehicle's local origin can have: below the lowest land to above any balloon; a garbage
#: altitude beyond them (1e200) makes no frame anyone can compute in
ORIGIN_ALT_RANGE_M = (-1_000.0, 100_000.0)

_POSITION_FIELDS = ("lat_deg", "lon_deg", "alt_m", "p_ned_m", "v_ned_mps", "cov_p_ned_m2", "range_m")
_U64_MAX = 2**64 - 1


def _finite(x: float, what: str) -> float:
    # a finite Python float, the pipeline's case, checked in two operations (x - x is NaN for inf and NaN): a
    # Track is made every frame, and its checks were a large share of the pipeline thread's Python
    if type(x) is float and x - x == 0.0:
        return x
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)) or not math.isfinite(x):
        raise InputError(f"Track.{what} must be a finite number, got {x!r}")
    return float(x)


def _finite_floats(v: tuple, n: int) -> bool:
    """``v`` is already what :func:`_vec` returns: a tuple of ``n`` finite Python floats."""
    if len(v) != n:
        return False
    for c in v:
        if type(c) is not float or c - c != 0.0:
            return False
    return True


def _vec(v, n: int, what: str) -> tuple[float, ...]:
    if type(v) is tuple and _finite_floats(v, n):
        return v
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"Track.{what} must be {n} finite numbers, got {v!r}") from None
    values = a.tolist()  # floats: math on them beats numpy's reductions on a few numbers, per frame
    if a.shape != (n,) or not all(map(math.isfinite, values)):
        raise InputError(f"Track.{what} must be {n} finite numbers, got {v!r}")
    return tuple(values)


def _vec3(v, what: str) -> tuple[float, float, float]:
    x, y, z = _vec(v, 3, what)
    return x, y, z


def _cov(c, what: str) -> np.ndarray:
    try:
        a = np.array(c, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"Track.{what} must be a 3 x 3 matrix, got {c!r}") from None
    values = a.ravel().tolist() if a.shape == (3, 3) else []  # nine floats: math beats numpy's calls on them
    if not values or not all(map(math.isfinite, values)):
        raise InputError(f"Track.{what} must be a finite 3 x 3 matrix, got shape {a.shape}")
    if min(values[0], values[4], values[8]) < 0:
        raise InputError(f"Track.{what} has a negative variance on its diagonal: {np.diag(a).tolist()}")
    if not _positive_semidefinite(values):
        raise InputError(
            f"Track.{what} must be symmetric positive semi-definite (within {COV_RTOL:g} of its largest entry), "
            f"got {a.tolist()}"
        )
    a.setflags(write=False)
    return a


#: how far a covariance may be from symmetric, and an eigenvalue below 0, relative to its largest entry: round-off
#: of the estimators' own arithmetic is about 1e-16 of it, and an EKF's accumulated round-off stays many decades
#: below this; a covariance beyond it claims a confidence no distribution has
COV_RTOL = 1e-6


def _positive_semidefinite(v: list[float]) -> bool:
    """The row-major 3 x 3 ``v`` (finite floats) is symmetric and has no eigenvalue below ``-COV_RTOL`` times its
    largest entry: a Cholesky factorisation of the matrix shifted by that much, in floats (nine numbers: numpy's
    per-call costs would be most of the check, every frame)."""
    s = max(map(abs, v))
    if s == 0.0:
        return True
    tol = COV_RTOL * s
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = v
    if abs(a01 - a10) > tol or abs(a02 - a20) > tol or abs(a12 - a21) > tol:
        return False
    # the matrix plus tol * I is positive definite exactly when no eigenvalue is below -tol
    d0 = a00 + tol
    if not d0 > 0.0:
        return False
    l10, l20 = a01 / d0, a02 / d0
    d1 = a11 + tol - l10 * a01
    if not d1 > 0.0:
        return False
    l21 = (a12 - l20 * a01) / d1
    d2 = a22 + tol - l20 * a02 - l21 * l21 * d1
    return d2 > 0.0


def _sigmas3(cov) -> tuple[float, float, float]:
    """The 1-sigma per axis of a (3, 3) covariance (negative round-off on the diagonal read as 0)."""
    dx, dy, dz = cov.diagonal().tolist()
    return math.sqrt(max(dx, 0.0)), math.sqrt(max(dy, 0.0)), math.sqrt(max(dz, 0.0))


def _utc_fields(time_unix_us, time_unix_sigma_us) -> tuple[int | None, int | None]:
    """A track's UTC stamp checked: None or integers in [0, 2**63); no sigma without a time."""
    if time_unix_us is None and time_unix_sigma_us is not None:
        raise InputError("Track.time_unix_sigma_us without a time_unix_us")
    out = []
    for name, v in (("time_unix_us", time_unix_us), ("time_unix_sigma_us", time_unix_sigma_us)):
        if v is not None:
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 0 <= v < 2**63:
                raise InputError(f"Track.{name} must be None or an integer in [0, 2**63), got {v!r}")
            v = int(v)
        out.append(v)
    return out[0], out[1]


SIGMA_AZ_CAP_DEG = 180.0  # an azimuth near the zenith/nadir is unknown, not infinitely uncertain
#: an attitude bias beyond a right angle is no attitude solution at all (the fusion's --attitude-bias-deg bound)
SIGMA_BIAS_MAX_DEG = 90.0
_UNIT_TOL = 1e-6


@dataclass(frozen=True)
class LineOfSight:
    """The target's direction from the camera in local NED at one frame; needs no range.

    ``u_ned``: unit vector (3,) camera -> target.  ``azimuth_deg``: from north towards east,
    (-180, 180]; ``elevation_deg``: positive up, [-90, 90] (conventions in :mod:`onboard.core.frames`).
    ``sigma_azimuth_deg`` / ``sigma_elevation_deg``: 1-sigma (module docstring).  ``p_cam_ned_m``:
    the camera's position (3,), the ray's origin.  ``sigma_bias_deg``: the share of those sigmas that is a constant
    attitude bias, 1 sigma per axis (``s_b``, module docstring), or None where not stated (a reader of a track from a
    daemon before the key).
    """

    u_ned: tuple[float, float, float]
    azimuth_deg: float
    elevation_deg: float
    sigma_azimuth_deg: float
    sigma_elevation_deg: float
    p_cam_ned_m: tuple[float, float, float]
    sigma_bias_deg: float | None = None

    def __post_init__(self) -> None:
        # each field set again only when its checked value is another object (a list made a tuple, an int a
        # float): one made every frame from checked floats costs its checks only
        u = _vec(self.u_ned, 3, "los.u_ned")
        x, y, z = u
        if abs(math.sqrt(x * x + y * y + z * z) - 1.0) > _UNIT_TOL:
            raise InputError(f"LineOfSight.u_ned must be a unit vector, got {u}")
        if u is not self.u_ned:
            object.__setattr__(self, "u_ned", u)
        p = _vec(self.p_cam_ned_m, 3, "los.p_cam_ned_m")
        if p is not self.p_cam_ned_m:
            object.__setattr__(self, "p_cam_ned_m", p)
        az = _finite(self.azimuth_deg, "los.azimuth_deg")
        el = _finite(self.elevation_deg, "los.elevation_deg")
        if not -180.0 <= az <= 180.0 or not -90.0 <= el <= 90.0:
            raise InputError(f"LineOfSight azimuth/elevation out of range: {az}, {el} deg")
        if az is not self.azimuth_deg:
            object.__setattr__(self, "azimuth_deg", az)
        if el is not self.elevation_deg:
            object.__setattr__(self, "elevation_deg", el)
        for name in ("sigma_azimuth_deg", "sigma_elevation_deg"):
            given = getattr(self, name)
            v = _finite(given, f"los.{name}")
            if not 0 <= v <= SIGMA_AZ_CAP_DEG:  # a sigma beyond the circle is no direction at all
                raise InputError(f"LineOfSight.{name} must be in [0, {SIGMA_AZ_CAP_DEG:g}] deg, got {v}")
            if v is not given:
                object.__setattr__(self, name, v)
        given = self.sigma_bias_deg
        if given is not None:
            v = _finite(given, "los.sigma_bias_deg")
            if not 0 <= v <= SIGMA_BIAS_MAX_DEG:
                raise InputError(
                    f"LineOfSight.sigma_bias_deg must be None or in [0, {SIGMA_BIAS_MAX_DEG:g}] deg, got {v}"
                )
            if v is not given:
                object.__setattr__(self, "sigma_bias_deg", v)


def line_of_sight_ned(
    uv_px,
    intrinsics: PinholeIntrinsics,
    q_ned_from_cam,
    p_cam_ned_m,
    pixel_sigma_px: float,
    attitude_sigma_rad: float,
    attitude_bias_sigma_rad: float | None = None,
) -> LineOfSight:
    """The line of sight of pixel ``uv_px`` seen by a camera at ``(p_cam_ned_m, q_ned_from_cam)``.

    ``attitude_sigma_rad``: the total 1-sigma attitude error per axis, ``sqrt(s_w^2 + s_b^2)``;
    ``attitude_bias_sigma_rad``: its bias ``s_b``, stated as the result's ``sigma_bias_deg`` (None: not stated).
    First-order covariance propagation as in the module docstring; raises :class:`InputError` on
    non-finite input.
    """
    uv = np.asarray(uv_px, dtype=float).reshape(2)
    if not np.isfinite(uv).all():
        raise InputError(f"line_of_sight_ned: pixel must be finite, got {uv.tolist()}")
    # in floats (one pixel: numpy's per-call overhead was most of the cost), with the covariance's
    # quadratic forms expanded: g^T C g = s_px^2 |J^T g|^2 + s_att^2 (|g|^2 - (l.g)^2), J^T g =
    # dxy^T M^T R^T g, M = ((I - b b^T) / |b|)[:, :2]
    R = rotmat_from_quat(np.asarray(q_ned_from_cam, dtype=float)).tolist()
    x, y = np.asarray(intrinsics.normalized_from_pixel(uv), dtype=float).tolist()
    if intrinsics.has_distortion:
        step = 0.5  # px, central differences of the undistortion
        cols = [
            (
                np.asarray(intrinsics.normalized_from_pixel(uv + d))
                - np.asarray(intrinsics.normalized_from_pixel(uv - d))
            )
            / (2 * step)
            for d in (np.array([step, 0.0]), np.array([0.0, step]))
        ]
        dxy = [[float(cols[0][0]), float(cols[1][0])], [float(cols[0][1]), float(cols[1][1])]]
    else:
        dxy = [[1.0 / intrinsics.fx_px, 0.0], [0.0, 1.0 / intrinsics.fy_px]]
    nb = math.sqrt(x * x + y * y + 1.0)
    b = (x / nb, y / nb, 1.0 / nb)
    los = tuple(r[0] * b[0] + r[1] * b[1] + r[2] * b[2] for r in R)
    n, e, d = los
    var_px, var_att = pixel_sigma_px**2, attitude_sigma_rad**2

    def quad(g: tuple[float, float, float]) -> float:  # g^T C g
        w = [R[0][i] * g[0] + R[1][i] * g[1] + R[2][i] * g[2] for i in range(3)]
        bw = b[0] * w[0] + b[1] * w[1] + b[2] * w[2]
        m0, m1 = (w[0] - b[0] * bw) / nb, (w[1] - b[1] * bw) / nb
        j0, j1 = dxy[0][0] * m0 + dxy[1][0] * m1, dxy[0][1] * m0 + dxy[1][1] * m1
        lg = n * g[0] + e * g[1] + d * g[2]
        return var_px * (j0 * j0 + j1 * j1) + var_att * (g[0] * g[0] + g[1] * g[1] + g[2] * g[2] - lg * lg)

    h = math.hypot(n, e)
    az = math.degrees(math.atan2(e, n)) if h > 0 else 0.0
    if az == -180.0:  # atan2(-0.0, n < 0): due south is +180 in the documented (-180, 180]
        az = 180.0
    el = math.degrees(math.atan2(-d, h))
    s_el = math.degrees(math.sqrt(max(quad((d * n / h, d * e / h, -h) if h > 0 else (0.0, 0.0, -1.0)), 0.0)))
    if h > 1e-9:
        s_az = min(math.degrees(math.sqrt(max(quad((-e / h**2, n / h**2, 0.0)), 0.0))), SIGMA_AZ_CAP_DEG)
    else:
        s_az = SIGMA_AZ_CAP_DEG
    return LineOfSight(
        u_ned=_vec3(los, "los.u_ned"),
        azimuth_deg=az,
        elevation_deg=el,
        sigma_azimuth_deg=s_az,
        sigma_elevation_deg=s_el,
        p_cam_ned_m=_vec3(p_cam_ned_m, "los.p_cam_ned_m"),
        sigma_bias_deg=None if attitude_bias_sigma_rad is None else math.degrees(attitude_bias_sigma_rad),
    )


@dataclass(frozen=True, eq=False)
class Track:
    """The daemon's answer for one frame (see the module docstring for the meaning of each field).

    Vectors are tuples of floats; covariances read-only (3, 3) arrays.  The position group
    (``lat_deg, lon_deg, alt_m, p_ned_m, v_ned_mps, cov_p_ned_m2, range_m``) is either all set or
    all None; ``cov_v_ned_m2ps2``, ``range_sigma_ratio`` and ``model`` are optional within it.
    ``los`` (the line of sight) needs ``pose_valid`` and ``u_px``; it is independent of the position.
    """

    vehicle: str
    seq: int
    time_boot_us: int
    state: str
    track_id: int | None = None
    measurement_valid: bool = False
    u_px: float | None = None
    v_px: float | None = None
    bbox: tuple[float, float, float, float] | None = None
    pose_valid: bool = False
    los: LineOfSight | None = None
    origin: GeodeticOrigin | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    p_ned_m: tuple[float, float, float] | None = None
    v_ned_mps: tuple[float, float, float] | None = None
    cov_p_ned_m2: np.ndarray | None = None
    cov_v_ned_m2ps2: np.ndarray | None = None
    range_m: float | None = None
    range_sigma_ratio: float | None = None
    observable: bool = False
    residual_rms_norm: float | None = None
    window_frames: int = 0
    model: str | None = None
    time_unix_us: int | None = None
    time_unix_sigma_us: int | None = None
    compensated_us: int = 0
    estimate_epoch: int = 0
    run_id: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.vehicle, str) or not self.vehicle:
            raise InputError(f"Track.vehicle must be a non-empty string, got {self.vehicle!r}")
        # A field is set again only when its checked value is another object (an np.int64 made an int, a list a
        # tuple): a Track is made every frame from values of the right types, and the checks alone were a large
        # share of the pipeline thread's Python.  Same checks, same messages.
        setattr_ = object.__setattr__
        for name, hi in (
            ("seq", 2**32 - 1),
            ("time_boot_us", _U64_MAX),
            ("window_frames", 2**31),
            ("estimate_epoch", 2**31 - 1),
        ):
            v = getattr(self, name)
            if type(v) is int and 0 <= v <= hi:
                continue
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 0 <= v <= hi:
                raise InputError(f"Track.{name} must be an integer in [0, {hi}], got {v!r}")
            setattr_(self, name, int(v))
        if self.state not in TRACK_STATES:
            raise InputError(f"Track.state must be one of {', '.join(TRACK_STATES)}, got {self.state!r}")
        tid = self.track_id
        if tid is not None and not (type(tid) is int and tid >= 1):
            if isinstance(tid, (bool, np.bool_)) or not isinstance(tid, (int, np.integer)) or tid < 1:
                raise InputError(f"Track.track_id must be None or an integer >= 1, got {tid!r}")
            setattr_(self, "track_id", int(tid))
        for name in ("measurement_valid", "pose_valid", "observable"):
            flag = getattr(self, name)
            if type(flag) is bool:
                continue
            if not isinstance(flag, (bool, np.bool_)):
                raise InputError(f"Track.{name} must be a bool, got {flag!r}")
            setattr_(self, name, bool(flag))
        u_px, v_px = self.u_px, self.v_px
        if (u_px is None) != (v_px is None):
            raise InputError("Track.u_px and Track.v_px must both be set or both be None")
        if u_px is not None and v_px is not None:
            u, v = _finite(u_px, "u_px"), _finite(v_px, "v_px")
            if u is not u_px:
                setattr_(self, "u_px", u)
            if v is not v_px:
                setattr_(self, "v_px", v)
        if self.measurement_valid and u_px is None:
            raise InputError("Track.measurement_valid requires u_px and v_px")
        if self.bbox is not None:
            bb = _vec(self.bbox, 4, "bbox")
            if bb[2] < 0 or bb[3] < 0:
                raise InputError(f"Track.bbox width and height must be >= 0, got {bb}")
            if bb is not self.bbox:
                setattr_(self, "bbox", bb)
        if self.los is not None:
            if not isinstance(self.los, LineOfSight):
                raise InputError(f"Track.los must be a LineOfSight or None, got {type(self.los).__name__}")
            if not self.pose_valid or self.u_px is None:
                raise InputError("Track.los needs a pose (pose_valid) and a target centre (u_px, v_px)")
        rr = self.residual_rms_norm
        if rr is not None:
            if (
                isinstance(rr, bool)
                or not isinstance(rr, (int, float, np.integer, np.floating))
                or math.isnan(rr)
                or rr < 0
            ):
                raise InputError(f"Track.residual_rms_norm must be None or >= 0, got {rr!r}")
            if type(rr) is not float:
                setattr_(self, "residual_rms_norm", float(rr))
        if self.origin is not None and not isinstance(self.origin, GeodeticOrigin):
            raise InputError(f"Track.origin must be a GeodeticOrigin or None, got {type(self.origin).__name__}")
        have = [getattr(self, n) is not None for n in _POSITION_FIELDS]
        if any(have) and not all(have):
            missing = [n for n, h in zip(_POSITION_FIELDS, have) if not h]
            raise InputError(f"Track position fields must be all set or all None; missing {missing}")
        if have[0]:  # all set
            lat, lon, alt, rng = (_finite(getattr(self, n), n) for n in ("lat_deg", "lon_deg", "alt_m", "range_m"))
            for name, value in (("lat_deg", lat), ("lon_deg", lon), ("alt_m", alt), ("range_m", rng)):
                if value is not getattr(self, name):
                    setattr_(self, name, value)
            if not -90.0 <= lat <= 90.0 or not -180.0 <= lon <= 180.0:
                raise InputError(f"Track lat/lon out of range: {lat}, {lon}")
            if rng < 0:
                raise InputError(f"Track.range_m must be >= 0, got {rng}")
            for name in ("p_ned_m", "v_ned_mps"):
                given = getattr(self, name)
                vec = _vec(given, 3, name)
                if vec is not given:
                    setattr_(self, name, vec)
            setattr_(self, "cov_p_ned_m2", _cov(self.cov_p_ned_m2, "cov_p_ned_m2"))
            if self.cov_v_ned_m2ps2 is not None:
                setattr_(self, "cov_v_ned_m2ps2", _cov(self.cov_v_ned_m2ps2, "cov_v_ned_m2ps2"))
            if self.origin is None:
                raise InputError("Track with a position needs its origin")
        elif self.cov_v_ned_m2ps2 is not None:
            raise InputError("Track.cov_v_ned_m2ps2 without a position")
        r = self.range_sigma_ratio
        if r is not None and not (type(r) is float and r >= 0):  # a float >= 0 (inf allowed) is kept as it is
            if isinstance(r, bool) or not isinstance(r, (int, float, np.floating)) or math.isnan(r) or r < 0:
                raise InputError(f"Track.range_sigma_ratio must be None or >= 0 (inf allowed), got {r!r}")
            setattr_(self, "range_sigma_ratio", float(r))
        if self.model is not None and not isinstance(self.model, str):
            raise InputError(f"Track.model must be a string or None, got {self.model!r}")
        if self.time_unix_us is not None or self.time_unix_sigma_us is not None:
            unix_us, sigma_us = _utc_fields(self.time_unix_us, self.time_unix_sigma_us)
            setattr_(self, "time_unix_us", unix_us)
            setattr_(self, "time_unix_sigma_us", sigma_us)
        c = self.compensated_us
        if type(c) is not int:
            if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or abs(int(c)) > MAX_COMPENSATED_US:
                raise InputError(f"Track.compensated_us must be an integer of microseconds, got {c!r}")
            setattr_(self, "compensated_us", int(c))
        elif abs(c) > MAX_COMPENSATED_US:
            raise InputError(f"Track.compensated_us must be within +-{MAX_COMPENSATED_US} us, got {c!r}")
        run = self.run_id
        # (a daemon's every track states the same one; a value that is no string, a list too, is checked and refused)
        if run is not None and not (type(run) is str and run in _RUN_IDS_CHECKED):
            if not is_run_id(run):
                raise InputError(f"Track.run_id must be {RUN_ID_HEX_DIGITS} lower-case hex digits or None, got {run!r}")
            if len(_RUN_IDS_CHECKED) < 64:
                _RUN_IDS_CHECKED.add(run)

    def with_time_unix(self, time_unix_us: int | None, time_unix_sigma_us: int | None) -> Track:
        """This track with its UTC stamp: the two fields checked as ``__post_init__`` checks them, every
        other field as it was checked when this track was made: ``dataclasses.replace`` would check them
        all again, once a frame, for more CPU than the rest of the frame's track output."""
        unix_us, sigma_us = _utc_fields(time_unix_us, time_unix_sigma_us)
        out = object.__new__(Track)
        fields = out.__dict__
        fields.update(self.__dict__)  # the checked values (the covariances are read-only: shared safely)
        fields["time_unix_us"], fields["time_unix_sigma_us"] = unix_us, sigma_us
        return out

    @property
    def has_position(self) -> bool:
        return self.p_ned_m is not None

    @property
    def geometry_withheld(self) -> bool:
        """A measured centre with a pose and no line of sight: the daemon withholds the frame's geometry (a zoom, a
        camera or gimbal mismatch: the status's ``geometry``), as every other such frame has one (module docstring)."""
        return self.measurement_valid and self.pose_valid and self.los is None

    @property
    def sigma_ned_m(self) -> tuple[float, float, float] | None:
        return None if self.cov_p_ned_m2 is None else _sigmas3(self.cov_p_ned_m2)

    @property
    def sigma_vel_ned_mps(self) -> tuple[float, float, float] | None:
        return None if self.cov_v_ned_m2ps2 is None else _sigmas3(self.cov_v_ned_m2ps2)


# --------------------------------------------------------------------------- JSON


def json_number(x) -> float | None:
    """A JSON-safe number: a float, or None for None and for a non-finite value (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def track_to_json(track: Track) -> dict[str, Any]:
    """The ``irtrack.track/2`` object of ``track`` (a dict ready for ``json.dumps``).

    A :class:`Track`'s numbers are Python floats, finite where they must be (``__post_init__``), so they go
    out as they are: only ``range_sigma_ratio`` and ``residual_rms_norm`` may be infinite (written as null).
    Once a frame, with cold caches, per-number conversions cost the daemon's pipeline thread more than the
    encoding itself."""
    o = track.origin
    los = track.los
    cov, cov_v = track.cov_p_ned_m2, track.cov_v_ned_m2ps2
    return {
        "schema": TRACK_SCHEMA,
        "vehicle": track.vehicle,
        "seq": track.seq,
        "time_boot_us": track.time_boot_us,
        "track_id": track.track_id,
        "state": track.state,
        "measurement_valid": track.measurement_valid,
        "u_px": track.u_px,
        "v_px": track.v_px,
        "bbox": None if track.bbox is None else list(track.bbox),
        "pose_valid": track.pose_valid,
        "los_ned": None if los is None else list(los.u_ned),
        "los_az_deg": None if los is None else los.azimuth_deg,
        "los_el_deg": None if los is None else los.elevation_deg,
        "los_sigma_az_deg": None if los is None else los.sigma_azimuth_deg,
        "los_sigma_el_deg": None if los is None else los.sigma_elevation_deg,
        "los_sigma_bias_deg": None if los is None else los.sigma_bias_deg,
        "camera_ned_m": None if los is None else list(los.p_cam_ned_m),
        "lat_deg": track.lat_deg,
        "lon_deg": track.lon_deg,
        "alt_m": track.alt_m,
        "ned_m": None if track.p_ned_m is None else list(track.p_ned_m),
        "origin": None if o is None else {"lat_deg": o.lat_deg, "lon_deg": o.lon_deg, "alt_m": o.alt_m},
        "vel_ned_mps": None if track.v_ned_mps is None else list(track.v_ned_mps),
        "sigma_ned_m": None if cov is None else list(_sigmas3(cov)),
        "sigma_vel_ned_mps": None if cov_v is None else list(_sigmas3(cov_v)),  # finite: checked by the Track
        "cov_ned_m2": None if cov is None else cov.tolist(),
        "range_m": track.range_m,
        "range_sigma_ratio": json_number(track.range_sigma_ratio),
        "observable": track.observable,
        "residual_rms_norm": json_number(track.residual_rms_norm),
        "window_frames": track.window_frames,
        "model": track.model,
        "time_unix_us": track.time_unix_us,
        "time_unix_sigma_us": track.time_unix_sigma_us,
        "compensated_us": track.compensated_us,
        "estimate_epoch": track.estimate_epoch,
        "run_id": track.run_id,
    }


_NUM = {"type": ["number", "null"]}
_INT = {"type": ["integer", "null"]}
_BOOL = {"type": "boolean"}


def _vec3_schema(description: str) -> dict[str, Any]:
    return {
        "type": ["array", "null"],
        "items": {"type": "number"},
        "minItems": 3,
        "maxItems": 3,
        "description": description,
    }


#: Every key :func:`track_to_json` writes, in its order, with its JSON Schema (the module docstring's table): the
#: recording's ``irtrack.track/2`` schema is made of this (:func:`track_json_schema`), and a test holds
#: :func:`track_to_json` to it key for key
TRACK_JSON_KEYS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("schema", {"type": "string", "const": TRACK_SCHEMA}),
    ("vehicle", {"type": "string", "description": "vehicle name (the key's <vehicle>)"}),
    ("seq", {"type": "integer", "description": "the IR frame's sequence number"}),
    (
        "time_boot_us",
        {
            "type": "integer",
            "description": "the frame's stamp, us on the autopilot boot clock (its capture time unless the camera's "
            "clock runs late: see the status's camera_time_offset.compensated_ms)",
        },
    ),
    ("track_id", {**_INT, "description": "current track (a new id = a new target association)"}),
    ("state", {"type": "string", "enum": list(TRACK_STATES)}),
    ("measurement_valid", {**_BOOL, "description": "(u, v) is a blob centroid fed to the estimator"}),
    ("u_px", {**_NUM, "description": "target centre, pixels (u right, origin at the top-left pixel's corner)"}),
    ("v_px", {**_NUM, "description": "target centre, pixels (v down)"}),
    (
        "bbox",
        {
            "type": ["array", "null"],
            "items": {"type": "number"},
            "minItems": 4,
            "maxItems": 4,
            "description": "tracking box [x, y, w, h], pixels",
        },
    ),
    ("pose_valid", {**_BOOL, "description": "the camera pose at time_boot_us was known"}),
    ("los_ned", _vec3_schema("unit line of sight camera -> target, local NED")),
    ("los_az_deg", {**_NUM, "description": "its azimuth, degrees from north towards east, (-180, 180]"}),
    ("los_el_deg", {**_NUM, "description": "its elevation, degrees, positive up, [-90, 90]"}),
    ("los_sigma_az_deg", {**_NUM, "description": "1-sigma of los_az_deg, degrees"}),
    ("los_sigma_el_deg", {**_NUM, "description": "1-sigma of los_el_deg, degrees"}),
    (
        "los_sigma_bias_deg",
        {
            **_NUM,
            "description": "the share of the line of sight's sigma that is a constant attitude bias, 1 sigma per "
            "axis, degrees (the daemon's estimator.attitude_bias_sigma_deg); null without a line of sight or when "
            "not stated",
        },
    ),
    ("camera_ned_m", _vec3_schema("the line of sight's origin: the camera, local NED, metres")),
    ("lat_deg", {**_NUM, "description": "target WGS84 latitude, degrees"}),
    ("lon_deg", {**_NUM, "description": "target WGS84 longitude, degrees"}),
    ("alt_m", {**_NUM, "description": "target altitude, metres AMSL"}),
    ("ned_m", _vec3_schema("target position, local NED, metres")),
    (
        "origin",
        {
            "type": ["object", "null"],
            "properties": {"lat_deg": {"type": "number"}, "lon_deg": {"type": "number"}, "alt_m": {"type": "number"}},
            "required": ["lat_deg", "lon_deg", "alt_m"],
            "description": "the local NED frame's origin (WGS84), null before one is known",
        },
    ),
    ("vel_ned_mps", _vec3_schema("target velocity, local NED, m/s")),
    ("sigma_ned_m", _vec3_schema("1-sigma position uncertainty per axis, metres")),
    ("sigma_vel_ned_mps", _vec3_schema("1-sigma velocity uncertainty per axis, m/s")),
    (
        "cov_ned_m2",
        {
            "type": ["array", "null"],
            "items": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
            "minItems": 3,
            "maxItems": 3,
            "description": "position covariance, local NED, m^2",
        },
    ),
    ("range_m", {**_NUM, "description": "camera-to-target distance, metres"}),
    ("range_sigma_ratio", {**_NUM, "description": "posterior range sigma / range"}),
    ("observable", {**_BOOL, "description": "the window's geometry makes range observable and the model fits"}),
    ("residual_rms_norm", {**_NUM, "description": "RMS of the standardised residuals at the last model selection"}),
    ("window_frames", {"type": "integer", "minimum": 0, "description": "observations in the estimator's window"}),
    ("model", {"type": ["string", "null"], "description": "the estimator's motion model"}),
    ("time_unix_us", {**_INT, "description": "time_boot_us in UTC, us since 1970; null until mapped"}),
    ("time_unix_sigma_us", {**_INT, "description": "1-sigma of time_unix_us, us"}),
    (
        "compensated_us",
        {
            "type": "integer",
            "description": "camera clock lateness compensated on this frame, us: the line of sight and 3-D are of "
            "time_boot_us (and time_unix_us) minus this",
        },
    ),
    (
        "estimate_epoch",
        {
            "type": "integer",
            "minimum": 0,
            "description": "the 3-D estimator's restarts since the daemon started: a new value, a new estimate",
        },
    ),
    (
        "run_id",
        {
            "type": ["string", "null"],
            "pattern": f"^[0-9a-f]{{{RUN_ID_HEX_DIGITS}}}$",
            "description": "the daemon's run, drawn at its start: a new value, a restarted daemon (track ids, "
            "estimate_epoch and origin start again); two taking turns, two daemons as one vehicle",
        },
    ),
)


def track_json_schema() -> dict[str, Any]:
    """The JSON Schema of an ``irtrack.track/2`` message as :func:`track_to_json` writes it: every key always
    present (null where the table allows it), so every key is required."""
    return object_schema(
        TRACK_SCHEMA, "One processed frame's track and 3-D estimate (table in onboard/core/track.py).", TRACK_JSON_KEYS
    )


#: ``json.dumps(..., separators=(",", ":"), allow_nan=False)`` made once: ``dumps`` with options builds an encoder
#: per call (an encoder keeps no state between calls)
_COMPACT_JSON = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def track_to_bytes(track: Track) -> bytes:
    """Compact UTF-8 JSON of :func:`track_to_json` (``allow_nan=False``: never emits NaN)."""
    return _COMPACT_JSON.encode(track_to_json(track)).encode()


def track_from_json(obj: Mapping[str, Any] | str | bytes) -> Track:
    """Parse and validate an ``irtrack.track/2`` (or ``/1``) message (dict, str or bytes) into a :class:`Track`.

    Raises :class:`InputError` naming the offending key, and only that, whatever the message holds (a field of
    the wrong shape or type, nesting too deep for the parser: a bad message is the sender's, never the reader's
    crash).  Extra keys are ignored (forward compatibility within a version); ``sigma_*`` are derived and not
    read back, except the line of sight's, which are read as sent.  A /1 message has no line of sight.
    """
    try:
        return _track_from_json(obj)
    except InputError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError, OverflowError, RecursionError) as exc:
        raise InputError(f"track message: a field of the wrong type or shape ({type(exc).__name__}: {exc})") from None


def _track_from_json(obj: Mapping[str, Any] | str | bytes) -> Track:
    if isinstance(obj, (bytes, bytearray, str)):
        try:
            obj = json.loads(obj)
        except (ValueError, UnicodeDecodeError) as exc:
            raise InputError(f"track message is not JSON: {exc}") from None
    if not isinstance(obj, Mapping):
        raise InputError(f"track message must be a JSON object, got {type(obj).__name__}")
    if obj.get("schema") not in READABLE_TRACK_SCHEMAS:
        raise InputError(
            f"track message schema: expected one of {', '.join(READABLE_TRACK_SCHEMAS)}, got {obj.get('schema')!r}"
        )
    required = ("vehicle", "seq", "time_boot_us", "state", "observable", "window_frames")
    for key in required:
        if key not in obj:
            raise InputError(f"track message: missing key {key!r}")
    o = obj.get("origin")
    try:
        origin = None if o is None else GeodeticOrigin(float(o["lat_deg"]), float(o["lon_deg"]), float(o["alt_m"]))
    except (TypeError, KeyError, ValueError) as exc:
        raise InputError(f"track message origin: expected {{lat_deg, lon_deg, alt_m}}, got {o!r} ({exc})") from None
    if origin is not None and not ORIGIN_ALT_RANGE_M[0] <= origin.alt_m <= ORIGIN_ALT_RANGE_M[1]:
        lo, hi = ORIGIN_ALT_RANGE_M
        raise InputError(f"track message origin.alt_m: expected a number in [{lo:g}, {hi:g}] m, got {origin.alt_m!r}")
    cov = obj.get("cov_ned_m2")
    sig_v = obj.get("sigma_vel_ned_mps")
    cov_v = None if sig_v is None else np.diag(np.square(np.asarray(sig_v, dtype=float)))
    bbox = obj.get("bbox")
    los = None
    if obj.get("los_ned") is not None:
        try:
            los = LineOfSight(
                u_ned=obj["los_ned"],
                azimuth_deg=obj["los_az_deg"],
                elevation_deg=obj["los_el_deg"],
                sigma_azimuth_deg=obj["los_sigma_az_deg"],
                sigma_elevation_deg=obj["los_sigma_el_deg"],
                p_cam_ned_m=obj["camera_ned_m"],
                sigma_bias_deg=obj.get("los_sigma_bias_deg"),  # optional: a daemon before it states none
            )
        except KeyError as exc:
            raise InputError(f"track message: los_ned without {exc.args[0]!r}") from None
    return Track(
        vehicle=obj["vehicle"],
        seq=obj["seq"],
        time_boot_us=obj["time_boot_us"],
        state=obj["state"],
        track_id=obj.get("track_id"),
        measurement_valid=obj.get("measurement_valid", False),
        u_px=obj.get("u_px"),
        v_px=obj.get("v_px"),
        bbox=None if bbox is None else tuple(bbox),
        pose_valid=obj.get("pose_valid", False),
        los=los,
        origin=origin,
        lat_deg=obj.get("lat_deg"),
        lon_deg=obj.get("lon_deg"),
        alt_m=obj.get("alt_m"),
        p_ned_m=obj.get("ned_m"),
        v_ned_mps=obj.get("vel_ned_mps"),
        cov_p_ned_m2=cov,
        cov_v_ned_m2ps2=cov_v if obj.get("ned_m") is not None else None,
        range_m=obj.get("range_m"),
        range_sigma_ratio=obj.get("range_sigma_ratio"),
        observable=obj["observable"],
        residual_rms_norm=obj.get("residual_rms_norm"),
        window_frames=obj["window_frames"],
        model=obj.get("model"),
        time_unix_us=obj.get("time_unix_us"),
        time_unix_sigma_us=obj.get("time_unix_sigma_us"),
        compensated_us=obj.get("compensated_us", 0),
        estimate_epoch=obj.get("estimate_epoch", 0),
        run_id=obj.get("run_id"),
    )
