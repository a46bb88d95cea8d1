"""Live view: the daemon's (or a replay's) channels served over the Foxglove WebSocket protocol (adapter).

``python -m onboard ... --live-view PORT`` (config ``live_view.port``), ``python -m onboard.replay FILE.mcap
--live-view PORT`` and ``make demo`` (``LIVE_VIEW=PORT``) start a WebSocket server (foxglove-sdk,
https://docs.foxglove.dev/docs/sdk/python; subprotocol ``foxglove.sdk.v1``, the SDK's name for the messages of
``foxglove.websocket.v1``; a client offering only the old name is refused) bound to ``live_view.host``
(127.0.0.1 unless configured otherwise).  Foxglove: *Open connection* -> *Foxglove WebSocket* ->
``ws://127.0.0.1:PORT``.

Channels: the recording's (:mod:`onboard.io.record`, same topics, schemas and encodings:
:mod:`onboard.io.foxglove_messages`) plus three for display:

=============================  ==========================  ==============================================
topic                          schema                      what
=============================  ==========================  ==============================================
``irtrack/<v>/ir/frame``       ``foxglove.RawImage``       the IR frames as received
``irtrack/<v>/track``          ``irtrack.track/2`` (JSON)  the tracks as published
``irtrack/<v>/status``         ``irtrack.status/1`` (JSON) the status as published
``/onboard/target_fix``        ``foxglove.LocationFix``    track positions (Map panel)
``/onboard/camera_fix``        ``foxglove.LocationFix``    camera positions
``/onboard/annotations``       ``foxglove.ImageAnnotations``  the box and centre on the frame (Image panel)
``irtrack/<v>/objects``        ``irtrack.objects/1`` (JSON) every object of the frame (image chain objects)
``/onboard/object_annotations``  ``foxglove.ImageAnnotations``  their boxes and ids, the target highlighted
``/onboard/scene``             ``foxglove.SceneUpdate``    3-D: camera frustum, line of sight, the target's
                                                           1-sigma ellipsoid, both trails (frame ``ned``)
``/tf``                        ``foxglove.FrameTransform`` ``ned`` in ``enu`` (so the 3-D panel shows up as up)
=============================  ==========================  ==============================================

**Never stalls the pipeline**: every ``on_*`` call appends to a bounded queue and returns; a publisher
thread encodes and hands the messages to the SDK (whose own per-client backlog, :data:`CLIENT_BACKLOG_MESSAGES`,
drops the oldest data for a slow client; the SDK's default, 1024 messages, is 1024 frames of 320 kB or more for each
client that stops reading).  Past ``queue_length`` queued items, or with more than one frame queued, a new item is
dropped and counted (:meth:`LiveView.stats`: ``dropped``, per kind).  Frames are only queued while a
client subscribes to them, and each message is only built for a channel a client subscribes to (the trails are
kept all the same).

**What clients get wrong is counted, not logged per message**: the SDK logs (Rust log records passed to Python's
logging, loggers ``foxglove.websocket.*``) one ERROR per malformed message or subscription to an unknown channel, so
any client could write megabytes a second into the daemon's log.  Those loggers' records go through
:class:`ClientLog` instead: each ERROR / WARNING is counted by kind (:func:`client_error_kind`) and only the first of
a kind reaches the log; the SDK's INFO lines on clients registering and leaving give the clients connected now.
A viewer that leaves without closing its WebSocket (a tab closed, a radio link lost), which the SDK reports as an
ERROR (in the handshake's words, or the socket's on a receive or a send: reset by peer, broken pipe), is a departure,
not an error: counted in ``clients_reset``, not logged.
:meth:`LiveView.stats`: ``client_errors`` (by kind), ``clients`` and ``clients_reset``.  A few refusals (a subscription repeated, a
channel advertised by a client without the capability) the SDK logs at DEBUG only, and are not counted: at DEBUG it
would copy every malformed message a client sends, whole, into a log record.

The geometry (frustum, line of sight, ellipsoid) is pure numpy, in the functions below.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import re
import threading
import time
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np

from onboard.core.errors import InputError
from onboard.core.frames import quat_from_rotmat, rotmat_from_quat
from onboard.core.schema import Integer, Number, Text, config_dataclass
from onboard.core.status import STATUS_SCHEMA
from onboard.core.track import TRACK_SCHEMA, track_to_bytes
from onboard.io.foxglove_messages import (
    JSON_SCHEMAS,
    OBJECTS_SCHEMA,
    camera_fix_fields,
    file_descriptor_set,
    location_fix_fields,
    objects_annotations,
    rawimage_fields,
    stamp_from_us,
)
from onboard.io.record import CAMERA_FIX_TOPIC, OBJECT_ANNOTATIONS_TOPIC, TARGET_FIX_TOPIC
from onboard.io.worker_queue import stop_and_join

if TYPE_CHECKING:
    from foxglove import Context
    from foxglove.websocket import WebSocketServer

__all__ = [
    "ClientLog",
    "client_error_kind",
    "LiveViewConfig",
    "FRUSTUM_DEPTH_M",
    "LiveView",
    "ellipsoid_of_cov",
    "frustum_lines_ned",
    "los_segment_ned",
    "SCENE_TOPIC",
    "ANNOTATIONS_TOPIC",
    "TF_TOPIC",
    "Q_ENU_FROM_NED",
]

log = logging.getLogger(__name__)

#: messages the SDK holds for one client before it drops the oldest: a second of frames at 30 Hz (a viewer behind by
#: more sees stale frames anyway), ~10 MB of 640 x 512 mono8 per client that stops reading
CLIENT_BACKLOG_MESSAGES = 32
SCENE_TOPIC = "/onboard/scene"
ANNOTATIONS_TOPIC = "/onboard/annotations"
TF_TOPIC = "/tf"
NED_FRAME_ID = "ned"
# x_enu = y_ned, y_enu = x_ned, z_enu = -z_ned; (w, x, y, z)
Q_ENU_FROM_NED = quat_from_rotmat(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))


#: the camera's drawn size: the depth of its field-of-view pyramid, m
FRUSTUM_DEPTH_M = 10.0

#: what the server's stop is given at least at close, whatever the publisher thread's join took of the budget
STOP_FLOOR_S = 0.2
#: the logger the SDK's WebSocket server logs under (its modules' loggers below it: .server, .connected_client, ...)
SDK_WEBSOCKET_LOGGER = "foxglove.websocket"
#: kinds of client error told apart; more (an SDK that words its errors with what the client sent) count as "other"
MAX_CLIENT_ERROR_KINDS = 32
_CLIENT_ADDRESS = re.compile(r"\[[0-9A-Fa-f:.%\w]*\]:\d+|\d{1,3}(?:\.\d{1,3}){3}:\d+")
_CLIENT_REGISTERED = re.compile(r"^(Registered|Unregistered) client (\S+)$")
# the SDK's ERRORs for a viewer gone without the WebSocket close (a browser tab or a radio link dropped): its reset
# in the handshake's words, or the socket's own on a receive or a send (ECONNRESET 104, EPIPE 32); not something the
# client sent wrong, so counted apart (clients_reset) and not logged
_CLIENT_RESETS = (
    "Connection reset without closing handshake",
    "Connection reset by peer",
    "Broken pipe",
    "(os error 104)",
    "(os error 32)",
)


@config_dataclass
class LiveViewConfig:
    """``live_view``: the Foxglove WebSocket server for watching live (the daemon's section, composed by
    :class:`onboard.app.config.OnboardConfig`).  ``port``: TCP port (null: off); ``host``: the address to
    bind, the server's only guard (it has no authentication, and foxglove-sdk offers no limit on a client's message
    size or on connections: loopback or a trusted link, deploy/README.md "Hostile links"); ``queue_length``: items the
    publisher may lag behind; ``los_length_m``: the line of sight drawn without a range; ``trail_points``: positions
    kept per trail."""

    port: Annotated[int | None, Integer(1, 65535)] = None
    host: Annotated[str, Text()] = "127.0.0.1"
    queue_length: Annotated[int, Integer(1, 10_000)] = 32
    los_length_m: Annotated[float, Number(0.0, 1_000_000.0, lo_open=True)] = 500.0
    trail_points: Annotated[int, Integer(2, 100_000)] = 600


# --------------------------------------------------------------------------- geometry (pure)


def ellipsoid_of_cov(cov_ned_m2, n_sigma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The ``n_sigma`` ellipsoid of a 3x3 position covariance (NED, m^2): ``(diameters_m (3,),
    q_ned_from_axes (w, x, y, z))``, the diameters along the axes the quaternion turns into NED
    (eigenvectors, right-handed).  Negative eigenvalues (round-off) count as zero."""
    c = np.asarray(cov_ned_m2, dtype=float)
    if c.shape != (3, 3):
        raise InputError(f"cov_ned_m2: expected a finite 3x3 matrix, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise InputError(
            f"cov_ned_m2: expected a finite 3x3 matrix, got {np.count_nonzero(~np.isfinite(c))} of 9 entries not finite"
        )
    w, V = np.linalg.eigh(0.5 * (c + c.T))
    if np.linalg.det(V) < 0:
        V[:, 2] = -V[:, 2]
    return 2.0 * n_sigma * np.sqrt(np.clip(w, 0.0, None)), quat_from_rotmat(V)


def los_segment_ned(p_cam_ned_m, u_ned, length_m: float) -> np.ndarray:
    """The two end points (2, 3) of the line of sight drawn ``length_m`` from the camera along ``u_ned``."""
    p = np.asarray(p_cam_ned_m, dtype=float)
    return np.stack([p, p + float(length_m) * np.asarray(u_ned, dtype=float)])


def frustum_lines_ned(
    p_cam_ned_m,
    q_ned_from_cam,
    width_px: int,
    height_px: int,
    fx_px: float,
    fy_px: float,
    cx_px: float,
    cy_px: float,
    depth_m: float,
) -> np.ndarray:
    """Line-list points (16, 3) of the camera's field of view as a pyramid ``depth_m`` deep (OpenCV
    camera frame: x right, y down, z forward): apex to each image corner, then the corners' rectangle."""
    corners_px = np.array([[0.0, 0.0], [width_px, 0.0], [width_px, height_px], [0.0, height_px]])
    rays_cam = np.column_stack([(corners_px[:, 0] - cx_px) / fx_px, (corners_px[:, 1] - cy_px) / fy_px, np.ones(4)])
    p = np.asarray(p_cam_ned_m, dtype=float)
    far = p + depth_m * rays_cam @ rotmat_from_quat(q_ned_from_cam).T
    out = []
    for i in range(4):
        out += [p, far[i]]
    for i in range(4):
        out += [far[i], far[(i + 1) % 4]]
    return np.array(out)


# --------------------------------------------------------------------------- the SDK's log records on clients


def client_error_kind(message: str) -> str:
    """The kind of one of the SDK's messages about a client: its words before the first colon, the client's address
    left out, lower case joined by ``_`` (``Invalid message from 127.0.0.1:5000: key must be a string`` ->
    ``invalid_message_from``; ``Client 127.0.0.1:5000 attempted to subscribe to unknown channel: 9`` ->
    ``client_attempted_to_subscribe_to_unknown_channel``); ``other`` when no word is left."""
    head = _CLIENT_ADDRESS.sub(" ", message).split(":", 1)[0]
    return "_".join(re.findall(r"[a-z]+", head.lower()))[:64] or "other"


class ClientLog(logging.Filter):
    """The SDK's log records about clients, counted (module docstring): :meth:`filter` is True for the first ERROR /
    WARNING of each kind (its message then says where the rest are counted), False for the rest and for every
    INFO / DEBUG record, of which "Registered client ADDR" / "Unregistered client ADDR" keep :attr:`clients`."""

    def __init__(self) -> None:
        super().__init__()
        self._lock = threading.Lock()
        self._errors: collections.Counter = collections.Counter()
        self._addresses: set[str] = set()
        self._resets = 0

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if record.levelno < logging.WARNING:
            m = _CLIENT_REGISTERED.match(message)
            if m is not None:
                with self._lock:
                    if m.group(1) == "Registered":
                        self._addresses.add(m.group(2))
                    else:
                        self._addresses.discard(m.group(2))
            return False
        if any(words in message for words in _CLIENT_RESETS):
            with self._lock:
                self._resets += 1
            return False
        kind = client_error_kind(message)
        with self._lock:
            if kind not in self._errors and len(self._errors) >= MAX_CLIENT_ERROR_KINDS:
                kind = "other"
            first = self._errors[kind] == 0
            self._errors[kind] += 1
        if first:
            record.msg, record.args = f"{message} (live view: the next ones counted in client_errors.{kind})", ()
        return first

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._addresses)

    @property
    def resets(self) -> int:
        """Viewers gone without closing their WebSocket."""
        with self._lock:
            return self._resets

    @property
    def errors(self) -> dict[str, int]:
        with self._lock:
            return dict(self._errors)


class _SdkLogRouter(logging.Handler):
    """The handler of the SDK's WebSocket logger, which passes its records no further itself: each goes through the
    running live view's :class:`ClientLog` (a filter on that logger would miss its children's records), and those
    it lets through on to the handlers above (the daemon's)."""

    def __init__(self) -> None:
        super().__init__()
        self.client_log = ClientLog()  # no live view running: the first of each kind still, counted for nobody

    def emit(self, record: logging.LogRecord) -> None:
        if self.client_log.filter(record):
            logging.getLogger(SDK_WEBSOCKET_LOGGER.rpartition(".")[0]).handle(record)


_sdk_log_router: _SdkLogRouter | None = None
_sdk_log_lock = threading.Lock()


def _route_sdk_log(client_log: ClientLog | None) -> None:
    """Send the SDK's WebSocket records through ``client_log`` (None: a fresh one of nobody's).  The first call sets
    the logger up, and must come before the SDK first logs: the SDK asks Python once per logger whether a level is
    enabled and keeps the answer, and its INFO lines on clients are wanted whatever the daemon's level."""
    global _sdk_log_router
    with _sdk_log_lock:
        if _sdk_log_router is None:
            _sdk_log_router = _SdkLogRouter()
            logger = logging.getLogger(SDK_WEBSOCKET_LOGGER)
            logger.addHandler(_sdk_log_router)
            logger.propagate = False
            logger.setLevel(logging.INFO)
        _sdk_log_router.client_log = client_log if client_log is not None else ClientLog()


# --------------------------------------------------------------------------- the server


class LiveView:
    """A foxglove-sdk WebSocket server fed by non-blocking ``on_*`` calls (module docstring).

    ``settings``: the ``live_view`` section; ``port`` overrides its port (``--live-view PORT``; 0: any free
    one, see :attr:`port`).  ``intrinsics``: a :class:`~onboard.core.frames.PinholeIntrinsics` for the
    frustum (None: no frustum)."""

    def __init__(
        self, settings: LiveViewConfig, *, port: int | None = None, vehicle: str = "uav1", intrinsics=None
    ) -> None:
        if not isinstance(settings, LiveViewConfig):
            raise InputError(f"LiveView needs a LiveViewConfig, got {type(settings).__name__}")
        bind_port = settings.port if port is None else port
        if isinstance(bind_port, bool) or not isinstance(bind_port, int) or not 0 <= bind_port <= 65535:
            raise InputError(f"live_view.port: expected 0..65535, got {bind_port!r}")
        self.settings = settings
        self._bind_port = bind_port
        self.vehicle = vehicle
        self.intrinsics = intrinsics
        self.frame_topic = f"irtrack/{vehicle}/ir/frame"
        self.track_topic = f"irtrack/{vehicle}/track"
        self.status_topic = f"irtrack/{vehicle}/status"
        self.objects_topic = f"irtrack/{vehicle}/objects"
        self._q: collections.deque = collections.deque()
        self._cond = threading.Condition(threading.Lock())
        self._frames_queued = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._server: WebSocketServer | None = None
        self._ctx: Context | None = None
        self._ch: dict[str, Any] = {}
        self.published = 0
        self.dropped = 0
        self.dropped_by_kind: collections.Counter = collections.Counter()
        self.errors = 0
        self.client_log = ClientLog()
        self._pose = None  # the last frame's pose (publisher thread)
        self._target_trail: collections.deque = collections.deque(maxlen=settings.trail_points)
        self._camera_trail: collections.deque = collections.deque(maxlen=settings.trail_points)

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Bind the server (an address in use raises :class:`InputError` naming the port, its option and field) and
        start the thread."""
        import foxglove
        from foxglove.channels import (
            FrameTransformChannel,
            ImageAnnotationsChannel,
            LocationFixChannel,
            RawImageChannel,
            SceneUpdateChannel,
        )

        _route_sdk_log(self.client_log)  # before the server's first log record (_route_sdk_log)
        ctx = self._ctx = foxglove.Context()  # held: a collected context closes its channels
        s = self.settings
        try:
            self._server = foxglove.start_server(
                name=f"irtrack {self.vehicle}",
                host=s.host,
                port=self._bind_port,
                context=ctx,
                message_backlog_size=CLIENT_BACKLOG_MESSAGES,
            )
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types for a bind failure
            where = f"live_view.port (--live-view) {s.host}:{self._bind_port}"
            if "os error 98" in str(exc) or "in use" in str(exc).lower():
                # the SDK's words ("FoxgloveError: Failed to bind port: Address already in use (os error 98)") named
                # neither the option nor what to do about it
                raise InputError(
                    f"{where}: port already in use (another daemon, replay or live view serving there?): stop it or "
                    "give another port"
                ) from None
            raise InputError(f"{where}: cannot serve: {exc}") from None

        def json_channel(topic: str, schema: str):
            return foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=schema, encoding="jsonschema", data=_json_bytes(JSON_SCHEMAS[schema])),
                message_encoding="json",
                context=ctx,
            )

        from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

        # the objects' annotations as the recording holds them (one encoder for both: the same boxes and colours)
        object_annotations = foxglove.Channel(
            OBJECT_ANNOTATIONS_TOPIC,
            schema=foxglove.Schema(
                name="foxglove.ImageAnnotations", encoding="protobuf", data=file_descriptor_set(ImageAnnotations)
            ),
            message_encoding="protobuf",
            context=ctx,
        )
        self._ch = {
            "frame": RawImageChannel(self.frame_topic, context=ctx),
            "objects": json_channel(self.objects_topic, OBJECTS_SCHEMA),
            "object_annotations": object_annotations,
            "track": json_channel(self.track_topic, TRACK_SCHEMA),
            "status": json_channel(self.status_topic, STATUS_SCHEMA),
            "target_fix": LocationFixChannel(TARGET_FIX_TOPIC, context=ctx),
            "camera_fix": LocationFixChannel(CAMERA_FIX_TOPIC, context=ctx),
            "annotations": ImageAnnotationsChannel(ANNOTATIONS_TOPIC, context=ctx),
            "scene": SceneUpdateChannel(SCENE_TOPIC, context=ctx),
            "tf": FrameTransformChannel(TF_TOPIC, context=ctx),
        }
        self._thread = threading.Thread(target=self._run, name="irtrack-live-view", daemon=True)
        self._thread.start()
        log.info("live view: ws://%s:%d (Foxglove WebSocket)", s.host, self.port)

    @property
    def port(self) -> int:
        return int(self._server.port) if self._server is not None else self._bind_port

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the publisher thread, then the server, both within ``timeout_s``.  The SDK's ``stop`` waits for
        every client's connection to close, which a client that stopped reading (its TCP window full), or a TCP
        connection that never completed its WebSocket handshake, holds up indefinitely: it runs on a thread of its own, and one still running at the deadline is left to end with
        the process (one WARNING), so that the daemon's shutdown keeps its budget."""
        deadline_s = time.monotonic() + timeout_s
        stop_and_join(self._cond, self._stop, self._thread, timeout_s)
        server, self._server = self._server, None
        if server is None:
            return
        with _sdk_log_lock:
            if _sdk_log_router is not None and _sdk_log_router.client_log is self.client_log:
                _sdk_log_router.client_log = ClientLog()
        stopper = threading.Thread(target=server.stop, name="irtrack-live-view-stop", daemon=True)
        stopper.start()
        # a floor: the publisher's join may have used the whole budget, and a server that stops at once is no warning
        stopper.join(max(deadline_s - time.monotonic(), STOP_FLOOR_S))
        if stopper.is_alive():
            # the SDK's stop waits on every connection, the ones still in their handshake too: a TCP client that
            # never sends a WebSocket upgrade (a port scan, an HTTP probe, a half-sent request) is held open with no
            # timeout, and stalled the stop as a viewer that stopped reading does
            log.warning(
                "live view: the server did not stop within %.1f s (a client not reading, or a TCP connection that never "
                "completed its WebSocket handshake); left to end with the process",
                timeout_s,
            )

    def stats(self) -> dict[str, Any]:
        with self._cond:
            return {
                "port": self.port,
                "published": self.published,
                "dropped": self.dropped,
                "dropped_by_kind": dict(self.dropped_by_kind),
                "errors": self.errors,
                "clients": self.client_log.clients,
                "client_errors": self.client_log.errors,
                "clients_reset": self.client_log.resets,
            }

    # ------------------------------------------------------------------ producers (any thread)

    def _put(self, kind: str, item: tuple) -> bool:
        with self._cond:
            if self._stop.is_set():
                return False
            if len(self._q) >= self.settings.queue_length or (kind == "frame" and self._frames_queued >= 1):
                self.dropped += 1
                self.dropped_by_kind[kind] += 1
                return False
            if kind == "frame":
                self._frames_queued += 1
            self._q.append((kind, item))
            self._cond.notify()
            return True

    def on_frame(self, frame) -> bool:
        """An :class:`~onboard.core.irframe.IrFrame` (its pixels must not change afterwards); only while watched."""
        ch = self._ch.get("frame")
        if ch is None or not ch.has_sinks():
            return False
        return self._put("frame", (frame,))

    def on_pose(self, frame, pose) -> bool:
        """The pose the pipeline used for ``frame`` (None when it had none): camera fix, frustum, trail."""
        return self._put("pose", (int(frame.time_boot_us), pose))

    def on_track(self, track, payload: bytes | None = None) -> bool:
        """A :class:`~onboard.core.track.Track` (``payload``: its published bytes, made here when None)."""
        return self._put("track", (track, payload))

    def on_status(self, payload: bytes) -> bool:
        return self._put("status", (bytes(payload),))

    def on_objects(self, message: dict[str, Any]) -> bool:
        """The ``irtrack.objects/1`` message of a frame (a dict, not changed afterwards): JSON and annotations."""
        return self._put("objects", (message,))

    # ------------------------------------------------------------------ publisher thread

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._q and not self._stop.is_set():
                    self._cond.wait()
                if not self._q:
                    return
                kind, item = self._q.popleft()
                if kind == "frame":
                    self._frames_queued -= 1
            try:
                getattr(self, f"_pub_{kind}")(*item)
                with self._cond:
                    self.published += 1
            except Exception as exc:  # noqa: BLE001 - the live view must not die on one message
                with self._cond:
                    self.errors += 1
                if self.errors == 1:
                    log.exception("live view: cannot publish a %s (%s: %s); counted", kind, type(exc).__name__, exc)

    def _pub_frame(self, frame) -> None:
        from foxglove.messages import RawImage

        f = rawimage_fields(frame)
        sec, nsec = f.pop("timestamp")
        self._ch["frame"].log(RawImage(timestamp=_ts(sec, nsec), **f))

    # Each message below is built only for a channel a client subscribes to (has_sinks): building the scene with its
    # trails of a few hundred points holds the GIL the pipeline needs, and nobody would read it.  The trails are kept
    # all the same, so that a client that joins sees them whole.

    def _pub_status(self, payload: bytes) -> None:
        if self._ch["status"].has_sinks():
            self._ch["status"].log(payload)

    def _pub_objects(self, message: dict[str, Any]) -> None:
        if self._ch["objects"].has_sinks():
            self._ch["objects"].log(json.dumps(message, separators=(",", ":")).encode())  # the bytes zenoh carries
        if self._ch["object_annotations"].has_sinks():
            self._ch["object_annotations"].log(objects_annotations(message).SerializeToString())

    def _pub_pose(self, t_us: int, pose) -> None:
        self._pose = pose
        if pose is None:
            return
        p = np.asarray(pose.p_cam_ned_m, dtype=float)
        if np.all(np.isfinite(p)):
            self._camera_trail.append(p)
            if self._ch["camera_fix"].has_sinks():
                self._ch["camera_fix"].log(_location_fix(camera_fix_fields(pose, t_us)))

    def _pub_track(self, track, payload: bytes | None) -> None:
        if self._ch["track"].has_sinks():
            self._ch["track"].log(payload if payload is not None else track_to_bytes(track))
        if track.lat_deg is not None and self._ch["target_fix"].has_sinks():
            f = location_fix_fields(
                track.lat_deg, track.lon_deg, track.alt_m, track.time_boot_us, "target", track.cov_p_ned_m2
            )
            self._ch["target_fix"].log(_location_fix(f))
        if track.p_ned_m is not None:
            self._target_trail.append(np.asarray(track.p_ned_m, dtype=float))
        if self._ch["annotations"].has_sinks():
            self._pub_annotations(track)
        if self._ch["scene"].has_sinks():
            self._pub_scene(track)
        if self._ch["tf"].has_sinks():
            self._pub_tf(track)

    def _pub_tf(self, track) -> None:
        from foxglove.messages import FrameTransform, Quaternion, Vector3

        w, x, y, z = (float(c) for c in Q_ENU_FROM_NED)
        self._ch["tf"].log(
            FrameTransform(
                timestamp=_ts_us(track.time_boot_us),
                parent_frame_id="enu",
                child_frame_id=NED_FRAME_ID,
                translation=Vector3(),
                rotation=Quaternion(w=w, x=x, y=y, z=z),
            )
        )

    def _pub_annotations(self, track) -> None:
        from foxglove.messages import (
            CircleAnnotation,
            Color,
            ImageAnnotations,
            Point2,
            PointsAnnotation,
            PointsAnnotationType,
        )

        ts = _ts_us(track.time_boot_us)
        points, circles = [], []
        if track.bbox is not None:
            x, y, w, h = track.bbox
            points.append(
                PointsAnnotation(
                    timestamp=ts,
                    type=PointsAnnotationType.LineLoop,
                    thickness=2.0,
                    outline_color=Color(**dict(zip("rgba", _STATE_RGBA.get(track.state, _GREY_RGBA)))),
                    points=[Point2(x=x, y=y), Point2(x=x + w, y=y), Point2(x=x + w, y=y + h), Point2(x=x, y=y + h)],
                )
            )
        if track.u_px is not None and track.v_px is not None:
            circles.append(
                CircleAnnotation(
                    timestamp=ts,
                    position=Point2(x=track.u_px, y=track.v_px),
                    diameter=4.0,
                    thickness=1.0,
                    outline_color=Color(r=1.0, g=0.2, b=0.2, a=1.0),
                )
            )
        self._ch["annotations"].log(ImageAnnotations(circles=circles, points=points))

    def _pub_scene(self, track) -> None:
        from foxglove.messages import (
            Color,
            LinePrimitive,
            LinePrimitiveLineType,
            Point3,
            Pose,
            Quaternion,
            SceneEntity,
            SceneUpdate,
            SpherePrimitive,
            Vector3,
        )

        ts = _ts_us(track.time_boot_us)
        s = self.settings

        def pts(a) -> list:
            return [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in a]

        def quat(q) -> Quaternion:
            return Quaternion(w=float(q[0]), x=float(q[1]), y=float(q[2]), z=float(q[3]))

        def entity(eid: str, **prims) -> SceneEntity:
            return SceneEntity(timestamp=ts, frame_id=NED_FRAME_ID, id=eid, **prims)

        ents = []
        pose, K = self._pose, self.intrinsics
        cam_lines: list[Any] = []
        if pose is not None and K is not None and np.all(np.isfinite(pose.p_cam_ned_m)):
            fr = frustum_lines_ned(
                pose.p_cam_ned_m,
                pose.q_ned_from_cam,
                K.width_px,
                K.height_px,
                K.fx_px,
                K.fy_px,
                K.cx_px,
                K.cy_px,
                FRUSTUM_DEPTH_M,
            )
            cam_lines.append(
                LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    thickness=2.0,
                    scale_invariant=True,
                    points=pts(fr),
                    color=Color(r=0.3, g=0.6, b=1.0, a=1.0),
                )
            )
        ents.append(entity("camera", lines=cam_lines))
        los_lines = []
        if track.los is not None:
            length = track.range_m if track.range_m is not None and math.isfinite(track.range_m) else s.los_length_m
            los_lines.append(
                LinePrimitive(
                    type=LinePrimitiveLineType.LineStrip,
                    thickness=1.5,
                    scale_invariant=True,
                    points=pts(los_segment_ned(track.los.p_cam_ned_m, track.los.u_ned, length)),
                    color=Color(r=1.0, g=0.9, b=0.2, a=0.9),
                )
            )
        ents.append(entity("line_of_sight", lines=los_lines))
        spheres = []
        if track.p_ned_m is not None:
            p = np.asarray(track.p_ned_m, dtype=float)
            size, q = (np.full(3, 2.0), np.array([1.0, 0.0, 0.0, 0.0]))
            if track.cov_p_ned_m2 is not None:
                size, q = ellipsoid_of_cov(track.cov_p_ned_m2)
                size = np.maximum(size, 0.5)  # visible when tiny
            color = Color(r=0.2, g=0.9, b=0.3, a=0.5) if track.observable else Color(r=1.0, g=0.5, b=0.1, a=0.35)
            spheres.append(
                SpherePrimitive(
                    pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2]), orientation=quat(q)),
                    size=Vector3(x=size[0], y=size[1], z=size[2]),
                    color=color,
                )
            )
        ents.append(entity("target", spheres=spheres))
        for eid, trail, color in (
            ("target_trail", self._target_trail, Color(r=0.2, g=0.9, b=0.3, a=0.8)),
            ("camera_trail", self._camera_trail, Color(r=0.3, g=0.6, b=1.0, a=0.8)),
        ):
            lines = (
                [
                    LinePrimitive(
                        type=LinePrimitiveLineType.LineStrip,
                        thickness=1.0,
                        scale_invariant=True,
                        points=pts(trail),
                        color=color,
                    )
                ]
                if len(trail) >= 2
                else []
            )
            ents.append(entity(eid, lines=lines))
        self._ch["scene"].log(SceneUpdate(entities=ents))


def _ts(sec: int, nsec: int):
    from foxglove.messages import Timestamp

    return Timestamp(sec=int(sec), nsec=int(nsec))


def _ts_us(t_us: int):
    return _ts(*stamp_from_us(int(t_us)))


def _location_fix(fields: dict[str, Any]):
    """The SDK's LocationFix of :func:`~onboard.io.foxglove_messages.location_fix_fields`' dict."""
    from foxglove.messages import LocationFix, LocationFixPositionCovarianceType

    f = dict(fields)
    sec, nsec = f.pop("timestamp")
    if "position_covariance_type" in f:
        f["position_covariance_type"] = LocationFixPositionCovarianceType.Known
    return LocationFix(timestamp=_ts(sec, nsec), **f)


def _json_bytes(obj) -> bytes:
    return json.dumps(obj).encode()


_STATE_RGBA = {"tracking": (0.2, 1.0, 0.3, 1.0), "coasting": (1.0, 0.8, 0.1, 1.0), "lost": (1.0, 0.2, 0.2, 1.0)}
_GREY_RGBA = (0.6, 0.6, 0.6, 1.0)
