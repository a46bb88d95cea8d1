"""The daemon's status JSON ``irtrack.status/1`` and the rolling statistics it reports.

Pure: no zenoh, no clocks.  The service keeps a :class:`RollingStats` per measured quantity (latency,
processing, waits) and publishes :func:`build_status` once a second on ``irtrack/<vehicle>/status``;
the keys are :func:`build_status`'s docstring.  Non-finite numbers are written as null (JSON has no NaN).
"""

from __future__ import annotations

import math
import os
from collections import deque
from collections.abc import Mapping
from typing import Any

import numpy as np

from onboard.core.errors import InputError
from onboard.core.json_schema import object_schema
from onboard.core.track import Track, json_number

__all__ = [
    "STATUS_SCHEMA",
    "STATUS_JSON_KEYS",
    "STATUS_SECTION_KEYS",
    "RollingStats",
    "build_status",
    "status_json_schema",
]

STATUS_SCHEMA = "irtrack.status/1"

_SUMMARY = {
    "type": "object",
    "properties": {
        "n": {"type": "integer"},
        "p50": {"type": ["number", "null"]},
        "p99": {"type": ["number", "null"]},
        "max": {"type": ["number", "null"]},
    },
    "required": ["n", "p50", "p99", "max"],
    "description": "RollingStats.summary over the last samples",
}
_SUMMARY_OR_NULL = {**_SUMMARY, "type": ["object", "null"]}

_INT = {"type": "integer"}
_INT_N = {"type": ["integer", "null"]}
_NUM = {"type": "number"}
_NUM_N = {"type": ["number", "null"]}
_STR = {"type": "string"}
_STR_N = {"type": ["string", "null"]}
_BOOL = {"type": "boolean"}
_INTS = {"type": "array", "items": _INT}
_STRS = {"type": "array", "items": _STR}
_COUNTS = {"type": "object", "additionalProperties": _INT, "description": "count by reason or kind"}


def _section(description: str, properties: dict[str, Any], nullable: bool = False) -> dict[str, Any]:
    """A status section's schema: every key always written (``required``), ``nullable`` the section itself."""
    return {
        "type": ["object", "null"] if nullable else "object",
        "description": description,
        "properties": properties,
        "required": list(properties),
    }


# The sections other components make (the docstring of each producer says what a key holds); the tests hold each
# producer's dict to its schema key for key, and the recorded status of a real daemon to all of them
_LINK = _section(
    "the MAVLink link's state (onboard.io.mavlink_link.LinkStatus); null without a link",
    {
        "state": _STR,
        "autopilot_sysid": _INT_N,
        "heartbeat_age_s": _NUM_N,
        "rates_confirmed": _INTS,
        "rates_pending": _INTS,
        "rates_refused": _INTS,
        "clock_synced": _BOOL,
        "messages_rx": _INT,
        "link_losses": _INT,
        "reboots": _INT,
        "gnss": _section(
            "the latest GPS_RAW_INT (onboard.core.gnss.GnssState.summary); null until one",
            {
                "fix": _STR,
                "fix_type": _INT,
                "satellites": _INT_N,
                "hdop": _NUM_N,
                "vdop": _NUM_N,
                "h_acc_m": _NUM_N,
                "v_acc_m": _NUM_N,
                "age_s": _NUM_N,
                "degraded_s": _NUM_N,
            },
            nullable=True,
        ),
        "messages_refused": _INT,
        "streams": {
            "type": "object",
            "description": "per requested stream, by message name",
            "additionalProperties": _section(
                "a requested stream's rates, Hz (measured: null at first)",
                {"msg_id": _INT, "requested_hz": _NUM, "measured_hz": _NUM_N},
            ),
        },
    },
    nullable=True,
)
_TIME_OFFSET = _section(
    "the camera clock's offset estimate (onboard.estimation.time_offset); null when time_offset.enabled is false",
    {
        "estimate_ms": _NUM_N,
        "sigma_ms": _NUM_N,
        "state": _STR,
        "compensated_ms": _NUM,
        "blocks": _INT,
        "frames": _INT,
        "refused_blocks": _INT,
        "excitation_mradps": _NUM_N,
        "warn_threshold_ms": _NUM,
    },
    nullable=True,
)
_UTC = _section(
    "boot clock -> UTC (onboard.core.utc_clock.UtcClock.status): state none (numbers null) or ok",
    {
        "state": {"type": "string", "enum": ["none", "ok"]},
        "source": _STR_N,
        "offset_us": _INT_N,
        "sigma_us": _INT_N,
        "skew_ppm": _NUM_N,
        "samples": _INT,
        "newest_boot_us": _INT_N,
        "disputed_us": _INT_N,
        "steps": _INT,
    },
)
_CAMERA = _section(
    "the MAVLink camera component (onboard.io.camera_protocol.CameraProtocol.status and the selection's outcome)",
    {
        "component_id": _INT,
        "selection_mode": {"type": "string", "enum": ["none", "point", "rectangle"]},
        "default_image_status_interval_s": {
            **_NUM_N,
            "description": "#275's interval (s; null = off) on a link that set none (output.tracking_image_status_hz)",
        },
        "default_geo_status_interval_s": {
            **_NUM_N,
            "description": "#276's interval (s; null = off) on a link that set none (output.tracking_geo_status_hz)",
        },
        "link_intervals": {
            "type": "array",
            "description": "each link (a gcs endpoint, or a peer address on a udpin one) that set an interval of its "
            "own with SET_MESSAGE_INTERVAL, which applies to that link only; forgotten when the link goes away",
            "items": _section(
                "one link's intervals (s; null = off)",
                {"link": _STR, "image_status_interval_s": _NUM_N, "geo_status_interval_s": _NUM_N},
            ),
        },
        "pending_track_requests": _INT,
        "last_refusal": _STR_N,
        "counters": _COUNTS,
        "endpoints": _STRS,
        "tracker_mode": _STR,
        "tracker_holding": _BOOL,
        "last_selection": _section(
            "the operator's last selection; null before one",
            {"kind": _STR, "accepted": _BOOL, "reason": _STR_N},
            nullable=True,
        ),
    },
)
_VIDEO = _section(
    "the H.264 video stream (onboard.io.video)",
    {
        "destination": _STR,
        "transport": _STR,
        "frames_in": _INT,
        "encoded": _INT,
        "dropped": _INT,
        "errors": _INT,
        "datagrams": _INT,
        "send_errors": _INT,
        "refused": _INT,
        "clock_resets": _INT,
        "encode_ms_p50": _NUM_N,
        "encode_ms_p99": _NUM_N,
        "camera_rate_hz": _NUM_N,
    },
)
_RECORD = _section(
    "the flight recorder (onboard.io.record.FlightRecorder.stats)",
    {
        "path": _STR,
        "files": _INT,
        "current_file": _STR_N,
        "messages_written": _INT,
        "bytes_written": _INT,
        "dropped": _INT,
        "dropped_by_topic": _COUNTS,
        "dropped_at_close": _INT,
        "queue_bytes": _INT,
        "max_queue_bytes": _INT,
        "write_errors": _INT,
        "writer_cpu_s": _NUM,
        "syncs": _INT,
        "stopped": _STR_N,
        "lost_files": _STRS,
        "files_deleted": _INT,
    },
)
_LIVE_VIEW = _section(
    "the Foxglove live view (onboard.io.live_view.LiveView.stats): clients connected now, client_errors the "
    "server's errors about what clients sent by kind, clients_reset viewers gone without closing their WebSocket",
    {
        "port": _INT,
        "published": _INT,
        "dropped": _INT,
        "dropped_by_kind": _COUNTS,
        "errors": _INT,
        "clients": _INT,
        "client_errors": _COUNTS,
        "clients_reset": _INT,
    },
)
_GUIDANCE = _section(
    "the observer guidance (onboard.app.guidance_tap)",
    {
        "in_loop": _BOOL,
        "updates": _INT,
        "advised": _INT,
        "published": _INT,
        "publish_errors": _INT,
        "skipped": _COUNTS,
        "last_status": _STR_N,
        "last_manoeuvre": _STR_N,
        "setpoints": _section(
            "setpoints to the autopilot: the gate's state and why, what was sent, stops and advice ends by reason",
            {
                "state": _STR,
                "why": _STR,
                "resumes": {**_STR_N, "description": "while stopped: what ends the stop (the pilot's hand-over)"},
                "sent": _INT,
                "errors": _INT,
                "stops": _COUNTS,
                "advice_ends": _COUNTS,
            },
        ),
    },
)
_ZENOH = _section(
    "the zenoh session (onboard.app.service): the endpoints the daemon's zenoh section and options dial and listen on "
    "(a zenoh config file's own endpoints are not listed: config_file names it), and the routers and peers the "
    "session has now (counted every 0.5 s; null: not known yet or zenoh did not say)",
    {"connect": _STRS, "listen": _STRS, "config_file": _STR_N, "routers": _INT_N, "peers": _INT_N},
)

#: Every top-level key :func:`build_status` writes, in its order, with its JSON Schema (its docstring says what each
#: holds); a test holds :func:`build_status` to it key for key
STATUS_JSON_KEYS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("schema", {"type": "string", "const": STATUS_SCHEMA}),
    ("vehicle", {"type": "string"}),
    (
        "run_id",
        {
            "type": ["string", "null"],
            "description": "the daemon's run, drawn at its start, the same as its tracks' run_id: a new value, a "
            "restarted daemon; two taking turns on one key, two daemons publishing as one vehicle",
        },
    ),
    ("uptime_s", {"type": ["number", "null"]}),
    (
        "frames",
        {
            "type": "object",
            "properties": {
                k: {"type": "integer"}
                for k in ("in", "missing", "processed", "dropped", "rejected", "published", "queue_length")
            },
            "required": ["in", "missing", "processed", "dropped", "rejected", "published", "queue_length"],
        },
    ),
    (
        "geometry",
        {
            "type": "object",
            "properties": {
                "output": {"type": "string", "enum": ["published", "withheld"]},
                "withheld_because": {"type": "array", "items": {"type": "string"}},
                "zoom": {
                    "type": ["number", "null"],
                    "description": "the zoom the last frame taken stated (IRF1), relative to the one camera.intrinsics "
                    "were calibrated at; null: not stated",
                },
                "frames_withheld_zoom": {
                    "type": "integer",
                    "description": "frames whose line of sight and 3-D position were withheld for their stated zoom",
                },
            },
            "required": ["output", "withheld_because", "zoom", "frames_withheld_zoom"],
        },
    ),
    ("processing_ms", _SUMMARY),
    ("latency_ms", _SUMMARY),
    ("pose_wait_ms", _SUMMARY),
    ("queue_wait_ms", _SUMMARY_OR_NULL),
    ("publish_ms", _SUMMARY_OR_NULL),
    ("stages_ms", {"type": ["object", "null"], "additionalProperties": _SUMMARY}),
    ("capture_to_track_ms", _SUMMARY_OR_NULL),
    (
        "rejected",
        {
            "type": "object",
            "additionalProperties": {"type": "integer"},
            "description": "count by reason of every input refused, and of the events counted with them though the "
            "input was taken (pose_extrapolated, frame_time_reset, ...: frames.rejected sums only the refusals)",
        },
    ),
    ("link", _LINK),
    (
        "cpu",
        {
            "type": "object",
            "properties": {
                "share": {"type": ["number", "null"]},
                "pipeline_share": {"type": ["number", "null"]},
                "cores": {"type": ["integer", "null"]},
                # the service's (onboard.app.cpu_load), from /proc and the cgroup's cpu.stat
                "gets_share": {"type": ["number", "null"]},
                "throttled_share": {"type": ["number", "null"]},
                "needs_share": {"type": ["number", "null"]},
                "throttled_periods": {"type": ["integer", "null"]},
                "throttled_periods_share": {"type": ["number", "null"]},
                "quota_cores": {"type": ["number", "null"]},
            },
            "required": ["share", "pipeline_share", "cores"],
        },
    ),
    (
        "estimator",
        {
            "type": "string",
            "description": "what estimates the 3-D position, e.g. 'sliding window (process)'; '..., worker starting' while its"
            " worker process is being spawned (at start, or after a crash): estimates are carried meanwhile",
        },
    ),
    (
        "warnings",
        {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {"code": {"type": "string"}, "message": {"type": "string"}},
                "required": ["code", "message"],
            },
        },
    ),
    ("camera_time_offset", _TIME_OFFSET),
    (
        "track",
        {
            "type": ["object", "null"],
            "properties": {
                "time_boot_us": {"type": "integer"},
                "state": {"type": "string"},
                "track_id": {"type": ["integer", "null"]},
                "has_los": {"type": "boolean"},
                "has_position": {"type": "boolean"},
                "observable": {"type": "boolean"},
                "window_frames": {"type": "integer"},
                "age_s": {"type": ["number", "null"], "description": "seconds since it was published"},
            },
            "description": "the latest track in short",
        },
    ),
)

#: The sections the daemon's service adds to :func:`build_status`'s object (onboard.app.service ``status``):
#: ``utc`` always; ``zenoh`` once its session is open; ``camera`` with the MAVLink camera; each output tap's own
#: (``video``, ``record``, ``live_view``, ``guidance``) when configured
STATUS_SECTION_KEYS: tuple[tuple[str, dict[str, Any], bool], ...] = (
    ("utc", _UTC, True),
    ("zenoh", _ZENOH, False),
    ("camera", _CAMERA, False),
    ("video", _VIDEO, False),
    ("record", _RECORD, False),
    ("live_view", _LIVE_VIEW, False),
    ("guidance", _GUIDANCE, False),
)


def status_json_schema() -> dict[str, Any]:
    """The JSON Schema of the ``irtrack.status/1`` message the daemon publishes: :data:`STATUS_JSON_KEYS` (always
    present) and :data:`STATUS_SECTION_KEYS` (``utc`` always, the others when their part is configured)."""
    return object_schema(
        STATUS_SCHEMA,
        "The daemon's status, once a second (keys: onboard/core/status.py build_status).",
        [*STATUS_JSON_KEYS, *((key, schema) for key, schema, _always in STATUS_SECTION_KEYS)],
        [key for key, _ in STATUS_JSON_KEYS] + [key for key, _, always in STATUS_SECTION_KEYS if always],
    )


def _percentile(sorted_values: list[float], q: float) -> float:
    """``np.percentile(values, 100 q)`` (method ``linear``) of ascending floats, with numpy's interpolation
    (``_lerp``: from the upper value when the fraction is >= 0.5), so bit for bit the same."""
    n = len(sorted_values)
    v = (n - 1) * q
    i = math.floor(v)
    a, b = sorted_values[i], sorted_values[min(i + 1, n - 1)]
    t = v - i
    d = b - a
    return b - d * (1 - t) if t >= 0.5 else a + d * t


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
        """``{n, p50, p99, max}`` over the window; None values when empty.  The percentiles are numpy's
        (``np.percentile``, linear), computed on the values sorted in Python: eight of these make each status, and
        converting a thousand Python floats to an array and ``np.percentile``'s layers cost twice the sort."""
        s = sorted(self._d)  # one C call under the GIL: a consistent copy while the pipeline thread appends
        if not s:
            return {"n": 0, "p50": None, "p99": None, "max": None}
        total = sum(s)
        if total != total:  # a NaN (or inf - inf) among them: numpy's own path, whatever it makes of them
            a = np.array(s)
            p50, p99 = np.percentile(a, [50, 99])
            return {"n": len(s), "p50": json_number(p50), "p99": json_number(p99), "max": json_number(a.max())}
        return {
            "n": len(s),
            "p50": json_number(_percentile(s, 0.5)),
            "p99": json_number(_percentile(s, 0.99)),
            "max": json_number(s[-1]),
        }


def build_status(
    *,
    vehicle: str,
    run_id: str | None = None,
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
    warnings: list[Mapping[str, str]] | tuple = (),
    withheld_because: tuple[str, ...] | list[str] = (),
    zoom: float | None = None,
    frames_withheld_zoom: int = 0,
    camera_time_offset: Mapping[str, Any] | None = None,
    last_track_age_s: float | None = None,
    frames_missing: int = 0,
) -> dict[str, Any]:
    """The ``irtrack.status/1`` object (published at 1 Hz on ``irtrack/<vehicle>/status``).

    ``run_id``: the daemon's run (its tracks' ``run_id``: :func:`onboard.core.track.new_run_id`), None unstated.
    ``frames``: ``in`` (payloads received), ``missing`` (frames the camera numbered that never arrived: lost on the way,
    from the gaps in their sequence numbers, each sender's numbering apart: a restart's new numbering or a second
    sender's is no gap; :class:`onboard.pipeline.admission.ArrivalGaps`), ``processed`` (a Track
    was produced), ``dropped`` (oldest frames dropped because the pipeline was behind), ``rejected`` (invalid frames:
    sum of the ``frame_*`` reasons and of ``tracker_error`` / ``tracker_output_invalid``, frames the tracker failed
    on, and the frames a ``pipeline_error`` stopped before a Track), ``published`` (track messages put on zenoh).
    Every frame received is in one of them: ``in = processed + dropped + rejected + queue_length`` (the one frame being
    processed aside), and ``in + missing`` is what the camera sent. ``processing_ms``: decode +
    imaging + pose + estimator per frame; ``latency_ms``: frame receipt to track published (local
    monotonic clock); ``queue_wait_ms``: receipt to the start of processing; ``publish_ms``: the
    zenoh ``put`` of the track; ``stages_ms``: parts of the processing (``imaging``, ``estimator``);
    ``pose_wait_ms``: time a frame waited for lagging telemetry;
    ``capture_to_track_ms``: capture (boot clock) to track published, via TIMESYNC (null until
    synced).  Each is ``{n, p50, p99, max}`` over the last samples.  ``rejected``: every counted
    rejection by reason (frames, telemetry, MAVLink, estimator).  ``link``: the MAVLink link state, with
    ``gnss`` the autopilot's GNSS fix from GPS_RAW_INT (:meth:`onboard.core.gnss.GnssState.summary`; null until one)
    and ``streams``, per requested stream its ``requested_hz`` and ``measured_hz`` (:mod:`onboard.core.stream_rate`).
    ``cpu``: ``share`` = process CPU time / wall time over the last interval (1.0 = one core),
    ``pipeline_share`` = the pipeline thread's, ``cores`` = CPUs in the machine; the service adds
    ``gets_share``, ``throttled_share``, ``needs_share``, ``throttled_periods``, ``throttled_periods_share`` and
    ``quota_cores`` from
    ``/proc/self/stat`` and the cgroup's ``cpu.stat`` (:class:`onboard.app.cpu_load.CpuLoad`).  ``track``: the
    latest track's state in short, with ``age_s`` how long ago it was published (a state that stopped with the
    frames stays in this section: the age says so).  ``warnings``: the conditions active now that an operator must
    fix, each ``{code, message}`` with the message naming what to check (:mod:`onboard.app.watchdog`);
    empty when all is well.  ``geometry``: ``published`` (line of sight and 3-D positions go out) or
    ``withheld``, with ``withheld_because`` the warnings that withhold them (a configuration mismatch:
    the camera attitude the daemon computes is wrong, so is any direction or position made from it; ``zoom_mismatch``:
    the frames state a zoom ``camera.intrinsics`` are not for), ``zoom`` the zoom the last frame taken stated
    (IRF1, relative to the calibrated one; null: not stated) and ``frames_withheld_zoom`` the frames withheld for it.
    ``camera_time_offset``: the camera clock's offset against the autopilot's (:mod:`onboard.estimation.time_offset`),
    ``{estimate_ms, sigma_ms, state: unknown|estimating|confident, compensated_ms, blocks, frames, refused_blocks,
    excitation_mradps, warn_threshold_ms}`` (positive: frames stamped late); null when ``time_offset.enabled`` is false.
    """
    t = last_track
    return {
        "schema": STATUS_SCHEMA,
        "vehicle": vehicle,
        "run_id": run_id,
        "uptime_s": json_number(uptime_s),
        "frames": {
            "in": int(frames_in),
            "processed": int(frames_processed),
            "dropped": int(frames_dropped),
            "missing": int(frames_missing),
            "rejected": int(frames_rejected),
            "published": int(tracks_published),
            "queue_length": int(queue_length),
        },
        "geometry": {
            "output": "withheld" if withheld_because else "published",
            "withheld_because": list(withheld_because),
            "zoom": json_number(zoom),
            "frames_withheld_zoom": int(frames_withheld_zoom),
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
        "cpu": {"share": json_number(cpu_share), "pipeline_share": json_number(pipeline_cpu_share), "cores": _cores()},
        "estimator": estimator,
        "warnings": [{"code": str(w["code"]), "message": str(w["message"])} for w in warnings],
        "camera_time_offset": None if camera_time_offset is None else _jsonable(camera_time_offset),
        "track": None
        if t is None
        else {
            "time_boot_us": t.time_boot_us,
            "state": t.state,
            "track_id": t.track_id,
            "has_los": t.los is not None,
            "has_position": t.has_position,
            "observable": t.observable,
            "window_frames": t.window_frames,
            "age_s": json_number(last_track_age_s),
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
        return json_number(v)
    if v is None or isinstance(v, str):
        return v
    return str(v)
