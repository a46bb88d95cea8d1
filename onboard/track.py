"""The ``Track`` noun, its wire schema ``irtrack.track/1``, the status JSON and the MAVLink mapping.

Pure: no zenoh, no pymavlink, no clocks.  The pipeline builds one :class:`Track` per processed frame;
the service serialises it with :func:`track_to_json` onto ``irtrack/<vehicle>/track`` and maps it
onto CAMERA_TRACKING_IMAGE_STATUS (#275) / CAMERA_TRACKING_GEO_STATUS (#276) with
:func:`image_status_fields` / :func:`geo_status_fields`.

Schema ``irtrack.track/1`` (one UTF-8 JSON object per processed frame)
---------------------------------------------------------------------
==================  ===========================  ===================================================
key                 type                         meaning
==================  ===========================  ===================================================
schema              "irtrack.track/1"
vehicle             string                       vehicle name (the key's ``<vehicle>``)
seq                 integer                      the IR frame's sequence number
time_boot_us        integer                      the frame's capture time, us on the autopilot boot clock
track_id            integer >= 1 or null         current track (a new id = a new target association)
state               string                       ``searching`` | ``tracking`` | ``coasting`` | ``lost``
measurement_valid   bool                         (u, v) is a blob centroid fit for 3-D (fed to the estimator)
u_px, v_px          number or null               target centre, pixels (u right, v down, origin at the
                                                 top-left corner of the top-left pixel; onboard.frames)
bbox                [x, y, w, h] or null         tracking box, pixels
pose_valid          bool                         the camera pose at ``time_boot_us`` was known
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
observable          bool                         the window's geometry makes range observable
window_frames       integer >= 0                 observations in the estimator's window
model               string or null               the estimator's motion model for this estimate
==================  ===========================  ===================================================

Position fields (``lat_deg .. model`` except ``observable``/``window_frames``) are null while no
3-D estimate is valid: no estimate yet, the track lost, or the estimate unobservable (unless the
daemon's ``output.unobservable_positions`` is true, in which case ``observable`` says so).
Non-finite numbers are never written (JSON has no NaN): they become null.

Schema ``irtrack.status/1`` is built by :func:`build_status` (see its docstring).

MAVLink accuracies (#276) are 1-sigma, root-sum-square over axes as PX4 reports ``eph``/``evh``:
``h_acc = sqrt(C_nn + C_ee)``, ``v_acc = sqrt(C_dd)``, ``vel_acc = sqrt(trace C_v)``; the heading
``hdg = atan2(v_e, v_n)`` with ``hdg_acc = sqrt(J C_v,ne J^T)``, ``J = (-v_e, v_n) / |v_h|^2``
(first-order propagation), NaN when the horizontal speed is below twice its own sigma.
"""

from __future__ import annotations

import json
import math
import os
from collections import deque
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from onboard.errors import InputError
from onboard.frames import GeodeticOrigin

__all__ = [
    "TRACK_SCHEMA",
    "STATUS_SCHEMA",
    "TRACK_STATES",
    "Track",
    "track_to_json",
    "track_to_bytes",
    "track_from_json",
    "image_status_fields",
    "geo_status_fields",
    "RollingStats",
    "build_status",
]

TRACK_SCHEMA = "irtrack.track/1"
STATUS_SCHEMA = "irtrack.status/1"
TRACK_STATES = ("searching", "tracking", "coasting", "lost")

# MAVLink CAMERA_TRACKING_* enums (common.xml); numbers, so this module needs no pymavlink
CAMERA_TRACKING_STATUS_FLAGS_IDLE = 0
CAMERA_TRACKING_STATUS_FLAGS_ACTIVE = 1
CAMERA_TRACKING_STATUS_FLAGS_COASTING = 8
CAMERA_TRACKING_MODE_NONE = 0
CAMERA_TRACKING_MODE_POINT = 1
CAMERA_TRACKING_MODE_RECTANGLE = 2
CAMERA_TRACKING_TARGET_DATA_IN_STATUS = 4

_POSITION_FIELDS = ("lat_deg", "lon_deg", "alt_m", "p_ned_m", "v_ned_mps", "cov_p_ned_m2", "range_m")
_U64_MAX = 2**64 - 1


def _finite(x: float, what: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)) or not math.isfinite(x):
        raise InputError(f"Track.{what} must be a finite number, got {x!r}")
    return float(x)


def _vec(v, n: int, what: str) -> tuple[float, ...]:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"Track.{what} must be {n} finite numbers, got {v!r}") from None
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise InputError(f"Track.{what} must be {n} finite numbers, got {v!r}")
    return tuple(float(x) for x in a)


def _cov(c, what: str) -> np.ndarray:
    try:
        a = np.array(c, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"Track.{what} must be a 3 x 3 matrix, got {c!r}") from None
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise InputError(f"Track.{what} must be a finite 3 x 3 matrix, got shape {a.shape}")
    if np.any(np.diag(a) < 0):
        raise InputError(f"Track.{what} has a negative variance on its diagonal: {np.diag(a).tolist()}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Track:
    """The daemon's answer for one frame (see the module docstring for the meaning of each field).

    Vectors are tuples of floats; covariances read-only (3, 3) arrays.  The position group
    (``lat_deg, lon_deg, alt_m, p_ned_m, v_ned_mps, cov_p_ned_m2, range_m``) is either all set or
    all None; ``cov_v_ned_m2ps2``, ``range_sigma_ratio`` and ``model`` are optional within it.
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
    window_frames: int = 0
    model: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.vehicle, str) or not self.vehicle:
            raise InputError(f"Track.vehicle must be a non-empty string, got {self.vehicle!r}")
        for name, hi in (("seq", 2**32 - 1), ("time_boot_us", _U64_MAX), ("window_frames", 2**31)):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 0 <= v <= hi:
                raise InputError(f"Track.{name} must be an integer in [0, {hi}], got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.state not in TRACK_STATES:
            raise InputError(f"Track.state must be one of {', '.join(TRACK_STATES)}, got {self.state!r}")
        tid = self.track_id
        if tid is not None:
            if isinstance(tid, (bool, np.bool_)) or not isinstance(tid, (int, np.integer)) or tid < 1:
                raise InputError(f"Track.track_id must be None or an integer >= 1, got {tid!r}")
            object.__setattr__(self, "track_id", int(tid))
        for name in ("measurement_valid", "pose_valid", "observable"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"Track.{name} must be a bool, got {getattr(self, name)!r}")
            object.__setattr__(self, name, bool(getattr(self, name)))
        if (self.u_px is None) != (self.v_px is None):
            raise InputError("Track.u_px and Track.v_px must both be set or both be None")
        if self.u_px is not None:
            object.__setattr__(self, "u_px", _finite(self.u_px, "u_px"))
            object.__setattr__(self, "v_px", _finite(self.v_px, "v_px"))
        if self.measurement_valid and self.u_px is None:
            raise InputError("Track.measurement_valid requires u_px and v_px")
        if self.bbox is not None:
            bb = _vec(self.bbox, 4, "bbox")
            if bb[2] < 0 or bb[3] < 0:
                raise InputError(f"Track.bbox width and height must be >= 0, got {bb}")
            object.__setattr__(self, "bbox", bb)
        if self.origin is not None and not isinstance(self.origin, GeodeticOrigin):
            raise InputError(f"Track.origin must be a GeodeticOrigin or None, got {type(self.origin).__name__}")
        have = [getattr(self, n) is not None for n in _POSITION_FIELDS]
        if any(have) and not all(have):
            missing = [n for n, h in zip(_POSITION_FIELDS, have) if not h]
            raise InputError(f"Track position fields must be all set or all None; missing {missing}")
        if all(have):
            for name in ("lat_deg", "lon_deg", "alt_m", "range_m"):
                object.__setattr__(self, name, _finite(getattr(self, name), name))
            if not -90.0 <= self.lat_deg <= 90.0 or not -180.0 <= self.lon_deg <= 180.0:
                raise InputError(f"Track lat/lon out of range: {self.lat_deg}, {self.lon_deg}")
            if self.range_m < 0:
                raise InputError(f"Track.range_m must be >= 0, got {self.range_m}")
            object.__setattr__(self, "p_ned_m", _vec(self.p_ned_m, 3, "p_ned_m"))
            object.__setattr__(self, "v_ned_mps", _vec(self.v_ned_mps, 3, "v_ned_mps"))
            object.__setattr__(self, "cov_p_ned_m2", _cov(self.cov_p_ned_m2, "cov_p_ned_m2"))
            if self.cov_v_ned_m2ps2 is not None:
                object.__setattr__(self, "cov_v_ned_m2ps2", _cov(self.cov_v_ned_m2ps2, "cov_v_ned_m2ps2"))
            if self.origin is None:
                raise InputError("Track with a position needs its origin")
        elif self.cov_v_ned_m2ps2 is not None:
            raise InputError("Track.cov_v_ned_m2ps2 without a position")
        if self.range_sigma_ratio is not None:
            r = self.range_sigma_ratio
            if isinstance(r, bool) or not isinstance(r, (int, float, np.floating)) or math.isnan(r) or r < 0:
                raise InputError(f"Track.range_sigma_ratio must be None or >= 0 (inf allowed), got {r!r}")
            object.__setattr__(self, "range_sigma_ratio", float(r))
        if self.model is not None and not isinstance(self.model, str):
            raise InputError(f"Track.model must be a string or None, got {self.model!r}")

    @property
    def has_position(self) -> bool:
        return self.p_ned_m is not None

    @property
    def sigma_ned_m(self) -> tuple[float, float, float] | None:
        if self.cov_p_ned_m2 is None:
            return None
        return tuple(float(math.sqrt(max(d, 0.0))) for d in np.diag(self.cov_p_ned_m2))

    @property
    def sigma_vel_ned_mps(self) -> tuple[float, float, float] | None:
        if self.cov_v_ned_m2ps2 is None:
            return None
        return tuple(float(math.sqrt(max(d, 0.0))) for d in np.diag(self.cov_v_ned_m2ps2))


# --------------------------------------------------------------------------- JSON


def _num(x) -> float | None:
    """A JSON-safe number: non-finite -> None."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _list(v) -> list | None:
    return None if v is None else [_num(x) for x in v]


def track_to_json(track: Track) -> dict[str, Any]:
    """The ``irtrack.track/1`` object of ``track`` (a dict ready for ``json.dumps``)."""
    o = track.origin
    return {
        "schema": TRACK_SCHEMA,
        "vehicle": track.vehicle,
        "seq": track.seq,
        "time_boot_us": track.time_boot_us,
        "track_id": track.track_id,
        "state": track.state,
        "measurement_valid": track.measurement_valid,
        "u_px": _num(track.u_px),
        "v_px": _num(track.v_px),
        "bbox": _list(track.bbox),
        "pose_valid": track.pose_valid,
        "lat_deg": _num(track.lat_deg),
        "lon_deg": _num(track.lon_deg),
        "alt_m": _num(track.alt_m),
        "ned_m": _list(track.p_ned_m),
        "origin": None if o is None else {"lat_deg": o.lat_deg, "lon_deg": o.lon_deg, "alt_m": o.alt_m},
        "vel_ned_mps": _list(track.v_ned_mps),
        "sigma_ned_m": _list(track.sigma_ned_m),
        "sigma_vel_ned_mps": _list(track.sigma_vel_ned_mps),
        "cov_ned_m2": None if track.cov_p_ned_m2 is None else [_list(r) for r in track.cov_p_ned_m2],
        "range_m": _num(track.range_m),
        "range_sigma_ratio": _num(track.range_sigma_ratio),
        "observable": track.observable,
        "window_frames": track.window_frames,
        "model": track.model,
    }


def track_to_bytes(track: Track) -> bytes:
    """Compact UTF-8 JSON of :func:`track_to_json` (``allow_nan=False``: never emits NaN)."""
    return json.dumps(track_to_json(track), separators=(",", ":"), allow_nan=False).encode()


def track_from_json(obj: Mapping[str, Any] | str | bytes) -> Track:
    """Parse and validate an ``irtrack.track/1`` message (dict, str or bytes) back into a :class:`Track`.

    Raises :class:`InputError` naming the offending key.  Extra keys are ignored (forward
    compatibility within version 1); ``sigma_*`` are derived and not read back.
    """
    if isinstance(obj, (bytes, bytearray, str)):
        try:
            obj = json.loads(obj)
        except (ValueError, UnicodeDecodeError) as exc:
            raise InputError(f"track message is not JSON: {exc}") from None
    if not isinstance(obj, Mapping):
        raise InputError(f"track message must be a JSON object, got {type(obj).__name__}")
    if obj.get("schema") != TRACK_SCHEMA:
        raise InputError(f"track message schema: expected {TRACK_SCHEMA!r}, got {obj.get('schema')!r}")
    required = ("vehicle", "seq", "time_boot_us", "state", "observable", "window_frames")
    for key in required:
        if key not in obj:
            raise InputError(f"track message: missing key {key!r}")
    o = obj.get("origin")
    try:
        origin = None if o is None else GeodeticOrigin(float(o["lat_deg"]), float(o["lon_deg"]), float(o["alt_m"]))
    except (TypeError, KeyError, ValueError) as exc:
        raise InputError(f"track message origin: expected {{lat_deg, lon_deg, alt_m}}, got {o!r} ({exc})") from None
    cov = obj.get("cov_ned_m2")
    sig_v = obj.get("sigma_vel_ned_mps")
    cov_v = None if sig_v is None else np.diag(np.square(np.asarray(sig_v, dtype=float)))
    bbox = obj.get("bbox")
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
        window_frames=obj["window_frames"],
        model=obj.get("model"),
    )


# --------------------------------------------------------------------------- MAVLink mapping (pure)


def _unit(x: float, size: float) -> float:
    return min(max(x / size, 0.0), 1.0)


def image_status_fields(track: Track | None, width_px: int, height_px: int) -> dict[str, Any]:
    """Keyword arguments of ``MavlinkLink.send_tracking_image_status`` for ``track`` (None = idle).

    Normalised image coordinates: ``x = u_px / width_px``, ``y = v_px / height_px``, clipped to
    [0, 1].  Status ACTIVE while tracking, ACTIVE | COASTING while coasting, IDLE otherwise; mode
    RECTANGLE with a box, POINT with only a centre, NONE without either.
    """
    nan = math.nan
    out = dict(
        tracking_status=CAMERA_TRACKING_STATUS_FLAGS_IDLE,
        tracking_mode=CAMERA_TRACKING_MODE_NONE,
        target_data=CAMERA_TRACKING_TARGET_DATA_IN_STATUS,
        point_x=nan, point_y=nan, radius=nan,
        rec_top_x=nan, rec_top_y=nan, rec_bottom_x=nan, rec_bottom_y=nan,
    )
    if track is None or track.state in ("searching", "lost"):
        return out
    out["tracking_status"] = CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    if track.state == "coasting":
        out["tracking_status"] |= CAMERA_TRACKING_STATUS_FLAGS_COASTING
    if track.u_px is not None:
        out["tracking_mode"] = CAMERA_TRACKING_MODE_POINT
        out["point_x"] = _unit(track.u_px, width_px)
        out["point_y"] = _unit(track.v_px, height_px)
    if track.bbox is not None:
        x, y, w, h = track.bbox
        out["tracking_mode"] = CAMERA_TRACKING_MODE_RECTANGLE
        out["rec_top_x"], out["rec_top_y"] = _unit(x, width_px), _unit(y, height_px)
        out["rec_bottom_x"], out["rec_bottom_y"] = _unit(x + w, width_px), _unit(y + h, height_px)
    return out


def geo_status_fields(track: Track | None) -> dict[str, Any] | None:
    """Keyword arguments of ``MavlinkLink.send_tracking_geo_status``, or None without a position.

    Accuracies are 1-sigma root-sum-squares (module docstring); unknown values are NaN.
    """
    if track is None or not track.has_position:
        return None
    C = track.cov_p_ned_m2
    v = np.asarray(track.v_ned_mps)
    nan = math.nan
    vel_acc = hdg = hdg_acc = nan
    speed_h = float(math.hypot(v[0], v[1]))
    if speed_h > 0:
        hdg = math.atan2(v[1], v[0])
    if track.cov_v_ned_m2ps2 is not None:
        Cv = track.cov_v_ned_m2ps2
        vel_acc = math.sqrt(max(float(np.trace(Cv)), 0.0))
        if speed_h > 0:
            J = np.array([-v[1], v[0]]) / speed_h**2
            hdg_acc = math.sqrt(max(float(J @ Cv[:2, :2] @ J), 0.0))
            u = v[:2] / speed_h
            sigma_speed = math.sqrt(max(float(u @ Cv[:2, :2] @ u), 0.0))
            if speed_h < 2.0 * sigma_speed or hdg_acc > math.pi:
                hdg = hdg_acc = nan
    tracking_status = CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    if track.state == "coasting":
        tracking_status |= CAMERA_TRACKING_STATUS_FLAGS_COASTING
    return dict(
        lat_deg=track.lat_deg,
        lon_deg=track.lon_deg,
        alt_m=track.alt_m,
        h_acc_m=math.sqrt(max(float(C[0, 0] + C[1, 1]), 0.0)),
        v_acc_m=math.sqrt(max(float(C[2, 2]), 0.0)),
        vel_n_mps=float(v[0]),
        vel_e_mps=float(v[1]),
        vel_d_mps=float(v[2]),
        vel_acc_mps=vel_acc,
        dist_m=track.range_m,
        hdg_rad=hdg,
        hdg_acc_rad=hdg_acc,
        tracking_status=tracking_status,
    )


# --------------------------------------------------------------------------- status


class RollingStats:
    """The last ``maxlen`` samples of a quantity; percentiles on demand (thread-safe appends)."""

    def __init__(self, maxlen: int = 1000) -> None:
        if isinstance(maxlen, bool) or not isinstance(maxlen, int) or maxlen < 1:
            raise InputError(f"RollingStats.maxlen must be a positive integer, got {maxlen!r}")
        self._d: deque[float] = deque(maxlen=maxlen)

    def add(self, x: float) -> None:
        self._d.append(float(x))

    def __len__(self) -> int:
        return len(self._d)

    def values(self) -> np.ndarray:
        return np.array(list(self._d), dtype=float)

    def summary(self) -> dict[str, float | int | None]:
        """``{n, p50, p99, max}`` over the window; None values when empty."""
        a = self.values()
        if a.size == 0:
            return {"n": 0, "p50": None, "p99": None, "max": None}
        p50, p99 = np.percentile(a, [50, 99])
        return {"n": int(a.size), "p50": _num(p50), "p99": _num(p99), "max": _num(a.max())}


def build_status(
    *,
    vehicle: str,
    uptime_s: float,
    frames_in: int,
    frames_processed: int,
    frames_dropped: int,
    frames_rejected: int,
    tracks_published: int,
    processing_ms: Mapping[str, Any],
    latency_ms: Mapping[str, Any],
    pose_wait_ms: Mapping[str, Any],
    capture_to_track_ms: Mapping[str, Any] | None,
    rejected: Mapping[str, int],
    link: Mapping[str, Any] | None,
    cpu_share: float | None,
    pipeline_cpu_share: float | None,
    last_track: Track | None,
    estimator: str,
    queue_length: int,
    queue_wait_ms: Mapping[str, Any] | None = None,
    publish_ms: Mapping[str, Any] | None = None,
    stages_ms: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """The ``irtrack.status/1`` object (published at 1 Hz on ``irtrack/<vehicle>/status``).

    ``frames``: ``in`` (payloads received), ``processed`` (a Track was produced), ``dropped``
    (oldest frames dropped because the pipeline was behind), ``rejected`` (invalid frames: sum of the
    ``frame_*`` reasons), ``published`` (track messages put on zenoh).  ``processing_ms``: decode +
    imaging + pose + estimator per frame; ``latency_ms``: frame receipt to track published (local
    monotonic clock); ``queue_wait_ms``: receipt to the start of processing; ``publish_ms``: the
    zenoh ``put`` of the track; ``stages_ms``: parts of the processing (``imaging``, ``estimator``);
    ``pose_wait_ms``: time a frame waited for lagging telemetry;
    ``capture_to_track_ms``: capture (boot clock) to track published, via TIMESYNC (null until
    synced).  Each is ``{n, p50, p99, max}`` over the last samples.  ``rejected``: every counted
    rejection by reason (frames, telemetry, MAVLink, estimator).  ``link``: the MAVLink link state.
    ``cpu``: ``share`` = process CPU time / wall time over the last interval (1.0 = one core),
    ``pipeline_share`` = the pipeline thread's, ``cores`` = CPUs in the machine.  ``track``: the
    latest track's state in short.
    """
    t = last_track
    return {
        "schema": STATUS_SCHEMA,
        "vehicle": vehicle,
        "uptime_s": _num(uptime_s),
        "frames": {
            "in": int(frames_in),
            "processed": int(frames_processed),
            "dropped": int(frames_dropped),
            "rejected": int(frames_rejected),
            "published": int(tracks_published),
            "queue_length": int(queue_length),
        },
        "processing_ms": dict(processing_ms),
        "latency_ms": dict(latency_ms),
        "pose_wait_ms": dict(pose_wait_ms),
        "queue_wait_ms": None if queue_wait_ms is None else dict(queue_wait_ms),
        "publish_ms": None if publish_ms is None else dict(publish_ms),
        "stages_ms": None if stages_ms is None else {k: dict(v) for k, v in stages_ms.items()},
        "capture_to_track_ms": None if capture_to_track_ms is None else dict(capture_to_track_ms),
        "rejected": {str(k): int(v) for k, v in sorted(rejected.items())},
        "link": None if link is None else _jsonable(link),
        "cpu": {"share": _num(cpu_share), "pipeline_share": _num(pipeline_cpu_share), "cores": _cores()},
        "estimator": estimator,
        "track": None if t is None else {
            "time_boot_us": t.time_boot_us,
            "state": t.state,
            "track_id": t.track_id,
            "has_position": t.has_position,
            "observable": t.observable,
            "window_frames": t.window_frames,
        },
    }


def _cores() -> int | None:
    return os.cpu_count()


def _jsonable(v):
    if isinstance(v, Mapping):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, set, frozenset)):
        return [_jsonable(x) for x in (sorted(v) if isinstance(v, (set, frozenset)) else v)]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _num(v)
    if v is None or isinstance(v, str):
        return v
    return str(v)

