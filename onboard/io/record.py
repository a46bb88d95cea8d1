"""Flight recording: the daemon's inputs and outputs as an MCAP file, written as they happen (adapter).

``python -m onboard ... --record FILE.mcap`` (or config ``record.path``) and ``groundsim run --record
FILE.mcap`` write one.  MCAP (https://mcap.dev) is the container rosbag2 and Foxglove use; every
channel below has a schema a generic viewer understands, and the file is chunked.  A file closed by
:meth:`FlightRecorder.close` (the daemon's SIGTERM, SIGINT or SIGHUP) ends with its summary and footer: complete
and indexed, whatever reader opens it.  A daemon killed with SIGKILL (or a power cut) leaves a file without them:
its finished chunks are whole (at most ``record.chunk_kb`` or ``record.flush_interval_s`` of data lost), but only
a streaming reader reads it (``mcap.stream_reader.StreamReader``; :mod:`onboard.app.replay` does), not the
indexed one (``mcap.reader.make_reader``, which reads the footer first);
``python -m onboard.record_recover CUT.mcap WHOLE.mcap`` (:mod:`onboard.app.record_recover`) writes its whole
records into a complete, indexed file.

Channels (topic: schema name, schema encoding / message encoding):

================================  =============================  =================  ============================
topic                             schema                         encoding           one message per
================================  =============================  =================  ============================
``/mavlink/<link>``               ``irtrack.mavlink_raw/1``      jsonschema / json  datagram (or read) in or out
``irtrack/<v>/ir/frame``          ``foxglove.RawImage``          protobuf           frame as received
``/onboard/frame_input``          ``irtrack.frame_input/1``      jsonschema / json  frame the pipeline took
``/onboard/imaging_pose``         ``irtrack.imaging_pose/1``     jsonschema / json  frame (image chain objects)
``irtrack/<v>/track``             ``irtrack.track/2``            jsonschema / json  track (bytes as published)
``irtrack/<v>/status``            ``irtrack.status/1``           jsonschema / json  status (bytes as published)
``irtrack/<v>/guidance``          ``irtrack.guidance/1``         jsonschema / json  advice (bytes as published)
``/onboard/target_fix``           ``foxglove.LocationFix``       protobuf           track with a position
``/onboard/camera_fix``           ``foxglove.LocationFix``       protobuf           frame with a pose
``irtrack/<v>/objects``           ``irtrack.objects/1``          jsonschema / json  frame (image chain objects)
``/onboard/object_annotations``   ``foxglove.ImageAnnotations``  protobuf           frame (image chain objects)
``/groundsim/truth``              ``irtrack.truth/1``            jsonschema / json  simulator frame (groundsim)
``/groundsim/truth/objects``      ``irtrack.truth_objects/1``    jsonschema / json  simulator frame with a scene
``/groundsim/truth/annotations``  ``foxglove.ImageAnnotations``  protobuf           simulator frame with a scene
================================  =============================  =================  ============================

* ``irtrack.mavlink_raw/1``: ``{"link": "autopilot", "direction": "rx" | "tx", "receive_time_ns":
  int (monotonic clock of the recorder's process, the clock frames are stamped with), "source": "host:port"
  or null, "data": base64 of the bytes exactly as read (a UDP datagram, or a serial/TCP read) or written
  (``tx``: one message as packed, its time the hand-over)}``.
* ``foxglove.RawImage``: ``timestamp`` = capture time on the vehicle's boot clock (``time_boot_us``,
  so it reads as 1970 plus the autopilot's uptime), ``frame_id`` ``ir_camera``, ``encoding`` ``mono8``
  or ``mono16`` (little-endian), ``step`` = width x bytes per pixel; the MCAP message's ``sequence`` is
  the frame's ``seq``.
* ``irtrack.frame_input/1``: ``{"seq", "time_boot_us", "received_ns", "pose_looked_up": bool,
  "pose": null | PoseAt, "zoom": number | null, "withheld_because": [string]}``: a frame the pipeline thread took
  from its queue (in that order), the zoom its IRF1 header stated (the RawImage has no field for it; 0 not stated,
  null a value JSON cannot hold, which the daemon read as not stated too; absent in recordings made before the
  field), the codes that withheld its line of sight and 3-D position (the status's ``geometry.withheld_because``
  as this frame was processed: the daemon's watchdog warnings, which a replay cannot decide again, and the frame's
  own ``zoom_mismatch``; absent before the field), and the interpolated pose it got (:func:`~onboard.io.pose_json.pose_to_json`; floats printed by ``repr``, so they read
  back bit for bit).  A frame received but never taken was dropped by the queue.  :mod:`onboard.app.replay` feeds
  these frames with these poses through a new :class:`~onboard.pipeline.frame_pipeline.FramePipeline`.
* ``irtrack.objects/1``: the message published on ``irtrack/<v>/objects`` (:func:`onboard.imaging.objects.objects_message`:
  every confirmed or coasting object of the frame with its id, state, centre, box, line of sight and score,
  and the primary target's id); the MCAP message's ``sequence`` is the frame's ``seq``.
  ``/onboard/object_annotations`` draws the same objects over the frame in Foxglove's Image panel (a box and
  the id of each, the primary target green; :func:`onboard.io.foxglove_messages.objects_annotations`;
  ``timestamp`` = the frame's capture time, as the RawImage's).
* ``irtrack.truth_objects/1`` (groundsim): ``{"seq", "time_boot_us", "t_s", "objects": [{"id", "cls", "u_px",
  "v_px", "box_px": [x, y, w, h] or null, "visibility", "contrast_netd", "warm", "range_m", "p_ned_m"}]}``, the
  rows of ``<truth>.objects.csv`` of that frame (:mod:`groundsim.world.truth`), drawn by ``/groundsim/truth/annotations``.
* ``irtrack.imaging_pose/1``: ``{"seq", "time_boot_us", "pose": null | PoseAt}``: the pose an image chain that
  associates with the camera's rotation (``imaging.chain: objects``) got for the frame before the pipeline
  waited for its telemetry (the frame's own pose, in ``frame_input``, is looked up after that wait, so the two can
  differ); replay gives the chain this one.
* Log times are the recorder's wall clock at the event (``time.time_ns`` at start, advanced by the
  monotonic clock, so they never go back): a frame's is its receive time (the ``received_ns`` its caller
  gives), a MAVLink read's its ``receive_ns`` when given, every other message's the moment it is handed to the
  recorder (its ``on_*`` call), stamped under the queue's lock so that the file's order is that order.  The
  writer thread writes later and never restamps.  (A frame stamped at receipt may come after messages stamped
  later: MCAP allows any log-time order within a chunk, a chunk's index records its earliest and latest, and
  readers sort.)  ``publish_time`` is the log time on every channel (MCAP: the log time when the publish time
  is not known).
* ``sequence``: the publisher's number where the message carries one -- the frame's ``seq`` on the frame,
  ``frame_input``, ``imaging_pose``, ``camera_fix``, track (its ``seq``), ``target_fix``, objects and object
  annotations channels, the simulator frame's ``seq`` on the truth channels -- else the recorder's count of
  the channel's messages handed to it, from 0 over the whole recording (rotation continues it): status and
  ``/mavlink/<link>``.  A message dropped at the queue keeps its number, so a gap in a counted channel is a drop.
  Numbers are wrapped to the record's 32 bits.

Metadata record ``irtrack``: ``config_yaml`` (the effective configuration, what replay uses by
default), ``vehicle``, ``started_utc`` (when this file was opened), ``recorder`` (``onboard`` or ``groundsim``),
``file_index`` (0, 1, ... of a rotated recording) and ``recording_id`` (random, the same in every file of one
recording: what tells a replay of several files that they are one flight's; the other fields do not -- a daemon
restarted with the same configuration records another flight with the same ones).  Metadata record
``irtrack.stopped`` (:data:`STOPPED_METADATA`), in the last file of a recording that stopped before the flight ended
(a disk short of ``record.min_free_mb``, a write the disk refused, the file deleted): ``reason`` (the status's
``record.stopped``) and ``stopped_utc``; a replay says it.

**Never stalls the caller**: every ``on_*`` method timestamps, numbers, appends to a deque and returns
(microseconds); a writer thread encodes (protobuf, JSON) and writes.  When the backlog passes
``record.queue_mb`` new messages are dropped and counted (``dropped``, per topic in
``dropped_by_topic``; the daemon's status JSON shows :meth:`FlightRecorder.stats` under ``record``), the first drop
logged once and the total at close (the status that counted them ends with the daemon).
**Bounded**: a file is closed (with its summary) and the next one opened (``FILE.1.mcap``,
``FILE.2.mcap``, ...) past ``record.max_file_mb`` or ``record.max_file_s``; with
``record.max_files`` > 0 the oldest files beyond that many are deleted.  Every ``record.sync_mb`` written the
file is synced to disk and its pages dropped from the page cache (:meth:`FlightRecorder._maybe_sync`).
**Never fills the disk, never leaves a torn record**: with less than ``record.min_free_mb`` free where it records
(checked at start, every ``record.flush_interval_s`` and at each rotation) the recorder finishes its file and stops;
a write the disk refuses (ENOSPC, EIO) is cut back to the last whole record and stops it too, the file finished
without the refused chunk.  Either way the flight goes on, later messages are dropped and counted, and the status's
``record.stopped`` says why (None while recording).
**A file deleted or moved away under it** (its link count 0, or its name gone; checked once a second) is finished
through its descriptor, said once, and the recording goes on in the next file (``FILE.N.mcap``): a moved file is
complete where it went; a deleted one's messages are lost (``record.lost_files``), the later ones not.
**Finished within its close's time**: :meth:`FlightRecorder.close` writes the backlog until a little before its
timeout, drops and counts what is left then (``dropped_at_close``), and finishes the file (last chunk, summary,
footer) in the writer thread: a shutdown bounded in time still leaves a complete file.

**Cheap per frame** (``python -m bench.record`` prints the callers' and the writer's CPU per frame): chunks are
written by :class:`onboard.io.mcap_chunks.ChunkWriter` (the mcap package's layout byte for byte, one ``writev`` per
chunk from where the data lies: a frame's pixels are not copied in user space); the writer thread is woken per
chunk's worth of messages or at its flush deadline, not per message (a wake-up per message costs both threads GIL
hand-offs and the callers latency); chunks are uncompressed by default (``record.compression: none``: lz4 and zstd
cost milliseconds of CPU per noisy frame) and carry no CRCs (a CRC of 0 means "not computed" in MCAP); the raw
MAVLink JSON is assembled from cached constant parts; the camera fix's geodesy runs on floats
(:func:`onboard.core.frames.geodetic_from_ned1`).  The message encodings are :mod:`onboard.io.foxglove_messages`'s,
shared with the live view.
"""

from __future__ import annotations

import base64
import collections
import datetime
import errno
import json
import logging
import math
import os
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from onboard.core.errors import InputError
from onboard.core.status import STATUS_SCHEMA
from onboard.core.track import TRACK_SCHEMA, track_to_bytes
from onboard.io.foxglove_messages import (
    FRAME_INPUT_SCHEMA,
    IMAGING_POSE_SCHEMA,
    JSON_SCHEMAS,
    MAVLINK_RAW_SCHEMA,
    OBJECTS_SCHEMA,
    TRUTH_OBJECTS_SCHEMA,
    camera_fix_fields,
    file_descriptor_set,
    location_fix_fields,
    objects_annotations,
    rawimage_pieces,
    truth_objects_annotations,
)
from onboard.io.pose_json import pose_to_json
from onboard.io.record_config import MB, RecordConfig
from onboard.io.record_files import free_disk_bytes, free_recording_path, rotated_path
from onboard.io.worker_queue import stop_and_join

if TYPE_CHECKING:
    from io import FileIO

    from onboard.io.mcap_chunks import ChunkWriter

__all__ = [
    "FRAME_INPUT_TOPIC",
    "TARGET_FIX_TOPIC",
    "CAMERA_FIX_TOPIC",
    "TRUTH_TOPIC",
    "OBJECT_ANNOTATIONS_TOPIC",
    "IMAGING_POSE_TOPIC",
    "NOT_LOOKED_UP",
    "STOPPED_METADATA",
    "TRUTH_OBJECTS_TOPIC",
    "TRUTH_ANNOTATIONS_TOPIC",
    "RecordConfig",
    "FlightRecorder",
    "RecordingPoseSource",
    "mavlink_topic",
]

log = logging.getLogger(__name__)

FRAME_INPUT_TOPIC = "/onboard/frame_input"
TARGET_FIX_TOPIC = "/onboard/target_fix"
CAMERA_FIX_TOPIC = "/onboard/camera_fix"
TRUTH_TOPIC = "/groundsim/truth"
OBJECT_ANNOTATIONS_TOPIC = "/onboard/object_annotations"
TRUTH_OBJECTS_TOPIC = "/groundsim/truth/objects"
TRUTH_ANNOTATIONS_TOPIC = "/groundsim/truth/annotations"
#: the metadata record that says, in the file itself, why the recording stopped before the flight ended
STOPPED_METADATA = "irtrack.stopped"
#: of a close's time, what the writer keeps for finishing the file (the last chunk, the summary, the footer: a few
#: small writes) after it stops writing the backlog
FINISH_RESERVE_S = 0.2
IMAGING_POSE_TOPIC = "/onboard/imaging_pose"
#: no pose was looked up for the image chain (as distinct from a look-up that answered None)
NOT_LOOKED_UP: Any = type("NotLookedUp", (), {"__repr__": lambda self: "NOT_LOOKED_UP"})()


def mavlink_topic(link: str) -> str:
    return f"/mavlink/{link}"


def _os_error_text(exc: OSError) -> str:
    """The system's words for ``exc``, after the file it names if any (the next file a rotation could not make: a
    read-only folder, a name taken); a write to the open descriptor names none."""
    what = exc.strerror or str(exc)
    return f"{exc.filename}: {what}" if exc.filename else what


# --------------------------------------------------------------------------- pure encoders


_COMPACT_JSON = json.JSONEncoder(separators=(",", ":"))  # json.dumps(obj, separators=(",", ":")), the encoder made once
_json_str = json.encoder.encode_basestring_ascii  # how json.dumps writes a str (ensure_ascii)


class RecordingPoseSource:
    """A pose source that remembers the ``pose_at`` answers of a frame (for the ``frame_input`` and
    ``imaging_pose`` channels).

    The pipeline calls ``pose_at`` from its one thread: once per frame, or twice with an image chain that
    associates with the camera's rotation (before imaging, without waiting for telemetry; then the frame's pose,
    after the wait).  :meth:`take` returns ``(looked_up, pose)`` -- the last answer -- for the frame just
    processed and forgets it; :meth:`take_lookups` also the first answer when there were two (else
    :data:`NOT_LOOKED_UP`).  Other attributes read through."""

    def __init__(self, source) -> None:
        self._source = source
        self._answers: list[Any] = []

    def pose_at(self, time_boot_us: int, *args, **kwargs):
        pose = self._source.pose_at(time_boot_us, *args, **kwargs)
        self._answers.append(pose)
        return pose

    def take(self) -> tuple[bool, Any]:
        looked_up, pose, _ = self.take_lookups()
        return looked_up, pose

    def take_lookups(self) -> tuple[bool, Any, Any]:
        """``(looked_up, pose, imaging_pose)``: the frame's pose (its last answer) and, when the frame was looked
        up twice, the first answer (the image chain's, which may be None); else :data:`NOT_LOOKED_UP`."""
        answers, self._answers = self._answers, []
        if not answers:
            return False, None, NOT_LOOKED_UP
        return True, answers[-1], answers[0] if len(answers) > 1 else NOT_LOOKED_UP

    def __getattr__(self, name: str):
        return getattr(self._source, name)


# --------------------------------------------------------------------------- the recorder


class FlightRecorder:
    """An MCAP writer thread fed by non-blocking ``on_*`` calls from any thread (module docstring).

    ``metadata``: string fields of the ``irtrack`` metadata record (``config_yaml`` ...).
    ``vehicle``: names the zenoh-like topics.  ``clock_ns``: the monotonic clock the caller stamps
    receive times with; ``wall_ns``: the wall clock for log times (read once).  ``json_schemas``: JSON Schemas
    by name beyond :data:`JSON_SCHEMAS`, for :meth:`on_json` (the simulator's ``irtrack.truth/1``).
    """

    def __init__(
        self,
        settings: RecordConfig,
        *,
        vehicle: str = "uav1",
        metadata: Mapping[str, str] | None = None,
        recorder: str = "onboard",
        clock_ns: Callable[[], int] = time.monotonic_ns,
        wall_ns: Callable[[], int] = time.time_ns,
        json_schemas: Mapping[str, Mapping[str, Any]] | None = None,
    ) -> None:
        if not isinstance(settings, RecordConfig):
            raise InputError(f"FlightRecorder needs a RecordConfig, got {type(settings).__name__}")
        if settings.path is None:
            raise InputError("record.path: expected a file name ending in .mcap, got null")
        self.settings = settings
        self.path: str = settings.path
        self.vehicle = vehicle
        self._meta = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._meta.setdefault("vehicle", vehicle)
        self._meta.setdefault("recorder", recorder)
        self._meta.setdefault("recording_id", uuid.uuid4().hex)
        self._clock_ns = clock_ns
        self._mono0 = clock_ns()
        self._wall0 = wall_ns()
        self._q: collections.deque = collections.deque()
        self._cond = threading.Condition(threading.Lock())
        self._queued_bytes = 0
        # the writer is woken when a chunk's worth is queued or at its flush deadline, not per message: a wake-up
        # per message (6 a frame) costs the writer and the callers GIL hand-offs
        self._wake_bytes = min(settings.chunk_bytes, settings.queue_bytes // 4)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frame_topic = f"irtrack/{vehicle}/ir/frame"
        self.track_topic = f"irtrack/{vehicle}/track"
        self.status_topic = f"irtrack/{vehicle}/status"
        self.objects_topic = f"irtrack/{vehicle}/objects"
        # counters (written by the writer thread or under the lock; read without it: ints)
        self.messages_written = 0
        self.bytes_written = 0  # bytes of closed files + the open one's position
        self.dropped = 0
        self.dropped_by_topic: collections.Counter = collections.Counter()
        self.write_errors = 0
        self.writer_cpu_s = 0.0  # CPU time of the writer thread (encoding, compression, writing)
        self.syncs = 0  # fdatasync + page-cache drops (sync_bytes)
        self._synced = 0
        self.files: list[str] = []
        self.max_queue_bytes = 0
        self._writer: ChunkWriter | None = None
        self._file: FileIO | None = None
        self._index = 0
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._file_started_s = 0.0
        self._closed_bytes = 0
        self._pb: dict[str, Any] | None = None
        self._mav_parts: dict = {}  # (link, direction, source) -> the constant parts of its mavlink_raw JSON
        self._json_schemas: dict[str, Mapping[str, Any]] = {**JSON_SCHEMAS, **(json_schemas or {})}
        self._counts: dict[str, int] = {}  # topic -> messages handed over (the sequence of counted channels)
        self.dropped_at_close = 0  # backlog not written by close's deadline (also in dropped)
        #: why the recording stopped before close (free space under ``min_free_mb``, a write the disk refused); None
        #: while it records.  Messages handed over after it are dropped and counted.
        self.stopped: str | None = None
        #: files deleted or replaced under the recorder while it wrote them (their messages are lost)
        self.lost_files: list[str] = []
        self.files_deleted = 0  # the oldest files removed under record.max_files
        self._next_lost_check_s = 0.0
        self._finish_ok = True  # the last file finished had its summary written
        self._write_until = math.inf  # time.monotonic() past which a closing writer drops the rest
        self._said_full = False  # the first message dropped for a full backlog was logged

    # ------------------------------------------------------------------ producers (any thread)

    def log_time_ns(self, mono_ns: int | None = None) -> int:
        return self._wall0 + ((self._clock_ns() if mono_ns is None else mono_ns) - self._mono0)

    def _put(
        self, kind: str, topic: str, nbytes: int, item: tuple, t_ns: int | None = None, seq: int | None = None
    ) -> bool:
        """Queue ``item`` for the writer, stamped ``t_ns`` (the recorder's clock; None: now, the hand-over) and
        numbered ``seq`` (None: the channel's count); False when dropped (counted) or closed."""
        with self._cond:
            if self._stop.is_set():
                return False
            if t_ns is None:
                t_ns = self._clock_ns()  # under the lock: the queue's order is the stamps' order
            if seq is None:
                seq = self._counts.get(topic, 0)
                self._counts[topic] = seq + 1  # a dropped message keeps its number: the gap shows the drop
            full = self.stopped is None and self._queued_bytes + nbytes > self.settings.queue_bytes
            if self.stopped is None and not full:
                self._queued_bytes += nbytes
                if self._queued_bytes > self.max_queue_bytes:
                    self.max_queue_bytes = self._queued_bytes
                self._q.append((kind, topic, nbytes, item, t_ns, seq & 0xFFFFFFFF))
                if self._queued_bytes >= self._wake_bytes:
                    self._cond.notify()  # a chunk's worth: the writer turns (else at its flush deadline)
                return True
            self.dropped += 1  # (stopped: nothing is written any more, and the stop was said)
            self.dropped_by_topic[topic] += 1
            say = full and not self._said_full
            self._said_full = self._said_full or full
        if say:  # outside the lock: a log handler's I/O never holds up the other callers
            log.warning(
                "recorder: backlog past record.queue_mb (%g MB): messages dropped from the recording, the first on %s"
                " (counted per topic, the status's record.dropped_by_topic; said once, the total at close)",
                self.settings.queue_mb,
                topic,
            )
        return False

    def on_mavlink(
        self, data: bytes, link: str = "autopilot", source=None, direction: str = "rx", receive_ns: int | None = None
    ) -> bool:
        """Raw MAVLink bytes read from (or written to) ``link``; ``source`` the peer (host, port) if known."""
        return self._put(
            "mavlink", mavlink_topic(link), len(data) + 100, (bytes(data), link, source, direction), receive_ns
        )

    def on_frame(self, frame, received_ns: int) -> bool:
        """An :class:`~onboard.core.irframe.IrFrame` as received (its pixels must not change afterwards)."""
        if not self.settings.frames:
            return False
        return self._put(
            "frame", self.frame_topic, int(frame.pixels.nbytes) + 100, (frame,), int(received_ns), int(frame.seq)
        )

    def on_frame_input(
        self,
        frame,
        received_ns: int,
        pose_looked_up: bool,
        pose,
        imaging_pose=NOT_LOOKED_UP,
        withheld_because: tuple[str, ...] = (),
    ) -> bool:
        """A frame the pipeline took, with the pose it got (``pose_looked_up`` False: refused before the lookup);
        ``imaging_pose``: the pose its image chain got before the telemetry wait, when it asked for one
        (:meth:`RecordingPoseSource.take_lookups`; on ``/onboard/imaging_pose``); ``withheld_because``: the codes
        that withheld its line of sight and 3-D position."""
        seq = int(frame.seq)
        t_us = int(frame.time_boot_us)
        taken = (t_us, int(received_ns), bool(pose_looked_up), pose, float(frame.zoom), tuple(withheld_because))
        ok = self._put("frame_input", FRAME_INPUT_TOPIC, 700, taken, seq=seq)
        if imaging_pose is not NOT_LOOKED_UP:
            ok = self._put("imaging_pose", IMAGING_POSE_TOPIC, 700, (t_us, imaging_pose), seq=seq) and ok
        return ok

    def on_track(self, track, payload: bytes | None = None) -> bool:
        """A :class:`~onboard.core.track.Track` (``payload``: its published bytes, made here when None)."""
        return self._put("track", self.track_topic, 1500, (track, payload), seq=int(track.seq))

    def on_objects(self, message: Mapping[str, Any], seq: int) -> bool:
        """The ``irtrack.objects/1`` message of frame ``seq`` (a dict, not changed afterwards): its JSON and its
        foxglove.ImageAnnotations."""
        nbytes = 200 + 400 * len(message.get("objects", ()))
        return self._put("objects", self.objects_topic, nbytes, (message,), seq=int(seq))

    def on_truth_objects(self, message: Mapping[str, Any]) -> bool:
        """The simulator's ``irtrack.truth_objects/1`` message of one frame: its JSON and its annotations."""
        nbytes = 200 + 400 * len(message.get("objects", ()))
        return self._put("truth_objects", TRUTH_OBJECTS_TOPIC, nbytes, (message,), seq=int(message.get("seq", 0)))

    def on_status(self, payload: bytes) -> bool:
        return self._put("json", self.status_topic, len(payload) + 100, (STATUS_SCHEMA, bytes(payload)))

    def on_json(self, topic: str, schema: str, obj: Mapping[str, Any] | bytes, sequence: int | None = None) -> bool:
        """Any JSON message with one of :data:`JSON_SCHEMAS` or the constructor's ``json_schemas`` (the truth
        channel); ``sequence``: the publisher's number for it (None: the channel's count)."""
        data = obj if isinstance(obj, (bytes, bytearray)) else _COMPACT_JSON.encode(obj).encode()
        if schema not in self._json_schemas:
            raise InputError(f"recorder: no JSON Schema named {schema!r} for {topic}")
        return self._put("json", topic, len(data) + 100, (schema, bytes(data)), seq=sequence)

    def stats(self) -> dict[str, Any]:
        """For the status JSON: written/dropped messages, bytes, files, queue."""
        with self._cond:
            queued, dropped, by_topic = self._queued_bytes, self.dropped, dict(self.dropped_by_topic)
        return {
            "path": self.settings.path,
            "files": len(self.files),
            "current_file": self.files[-1] if self.files else None,
            "messages_written": self.messages_written,
            "bytes_written": self.bytes_written,
            "dropped": dropped,
            "dropped_by_topic": by_topic,
            "dropped_at_close": self.dropped_at_close,
            "queue_bytes": queued,
            "max_queue_bytes": self.max_queue_bytes,
            "write_errors": self.write_errors,
            "writer_cpu_s": round(self.writer_cpu_s, 3),
            "syncs": self.syncs,
            "stopped": self.stopped,
            "lost_files": list(self.lost_files),
            "files_deleted": self.files_deleted,
        }

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Open the first file (errors here are the caller's: a bad directory fails at start, a full disk does not)
        and the thread; a ``path`` an earlier recording holds is kept, this one goes beside it
        (:func:`free_recording_path`)."""
        free = free_recording_path(self.path)
        if free != self.path:
            log.warning("record.path: %s holds an earlier recording, kept; this one is %s", self.path, free)
            self.path = free
        try:
            self._open(0)  # first: a path that cannot be written is the caller's error, as ever
        except OSError as exc:
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            # a disk with no room at all is the min_free_mb case, not a wrong path: the daemon that exited 2 here
            # tracked nothing, while one with a few MB free flew unrecorded
            self._abandon_file(0)
            self.stopped = f"no room to start it ({_os_error_text(exc)})"
            log.warning("recorder: not recording to %s: %s", self.path, self.stopped)
            return
        reason = self._short_of_space()
        if reason is not None:  # the flight goes on unrecorded: tracking is not held hostage by a full disk
            self.stopped = reason
            self._note_stopped(reason)
            self._finish()  # a few kB: the configuration, no messages
            log.warning("recorder: not recording to %s: %s", self.path, reason)
            return
        self._thread = threading.Thread(target=self._run, name="irtrack-recorder", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued until :data:`FINISH_RESERVE_S` (at most a quarter of ``timeout_s``) before
        ``timeout_s`` is up, drop and count the rest (``dropped_at_close``), finish the file (last chunk, summary,
        footer) and stop the thread: the writer thread does it all, and this waits for it up to ``timeout_s``.
        Only a write the disk does not complete in that time leaves the file without its summary (logged)."""
        self._write_until = time.monotonic() + max(timeout_s - min(FINISH_RESERVE_S, timeout_s / 4), 0.0)
        if self._thread is None:  # never started: no file open, nothing queued is written
            stop_and_join(self._cond, self._stop, None, timeout_s)
            self._finish()
        elif not stop_and_join(self._cond, self._stop, self._thread, timeout_s):
            log.warning(
                "recorder: %s not finished within %.1f s (a write did not return); it ends at its last chunk:"
                " python -m onboard.record_recover reads it whole",
                self.files[-1] if self.files else self.path,
                timeout_s,
            )
        with self._cond:
            dropped, by_topic = self.dropped, sorted(self.dropped_by_topic.items())
        if dropped:  # the status that counted them ends with the daemon: the log keeps the recording's holes
            log.warning(
                "recorder: %d messages dropped from the recording in all (%s)",
                dropped,
                ", ".join(f"{n} on {topic}" for topic, n in by_topic),
            )

    # ------------------------------------------------------------------ writer thread

    def _run(self) -> None:
        s = self.settings
        next_flush = time.monotonic() + s.flush_interval_s
        while True:
            with self._cond:
                while self._queued_bytes < self._wake_bytes and not self._stop.is_set():
                    left = next_flush - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
                batch = list(self._q)
                self._q.clear()
                self._queued_bytes = 0
                stop = self._stop.is_set()
            c0 = time.thread_time()
            for i, (kind, topic, _n, item, t_ns, seq) in enumerate(batch):
                if self._stop.is_set() and time.monotonic() >= self._write_until:
                    self._drop_at_close(batch[i:])
                    break
                try:
                    self._write(kind, topic, item, t_ns, seq)
                except OSError as exc:  # the disk refused a write: nothing after it can be trusted to land
                    self.write_errors += 1
                    self._halt(f"a write failed ({_os_error_text(exc)})", batch[i + 1 :], refused=True)
                    break
                except Exception as exc:  # noqa: BLE001 - the recorder must not die on one message
                    self.write_errors += 1
                    if self.write_errors == 1:
                        log.exception(
                            "recorder: cannot write a %s message (%s: %s); counted", kind, type(exc).__name__, exc
                        )
            if stop:  # closing: the file is finished here, by the thread that wrote it
                self._finish()
                self.writer_cpu_s += time.thread_time() - c0
                return
            if self._stop.is_set():  # closing began during this batch: no sync or rotation, take the rest now
                self.writer_cpu_s += time.thread_time() - c0
                continue
            now = time.monotonic()
            step = "flush"
            try:
                if now >= next_flush:
                    next_flush = now + s.flush_interval_s
                    if self._writer is not None:
                        self._writer.flush()
                        reason = self._short_of_space()
                        if reason is not None:
                            self._halt(reason, [], refused=False)
                step = "sync"
                self._maybe_sync()
                step = "rotate"
                self._maybe_rotate()
            except OSError as exc:
                self.write_errors += 1
                # a refused write leaves its chunk unwritten (cut back: discarded); a failed sync or rotation refused
                # no chunk, and the one in progress is finished with the file if the disk takes it
                self._halt(f"a {'write' if step == 'flush' else step} failed ({_os_error_text(exc)})", [],
                           refused=step == "flush")  # fmt: skip
            except Exception as exc:  # noqa: BLE001
                self.write_errors += 1
                log.warning("recorder: flush/rotate failed: %s: %s", type(exc).__name__, exc)
            self.writer_cpu_s += time.thread_time() - c0

    def _short_of_space(self) -> str | None:
        """Why not to write on (free space under ``record.min_free_mb`` where the recording goes), or None."""
        floor = self.settings.min_free_bytes
        if floor <= 0:
            return None
        free = free_disk_bytes(self.files[-1] if self.files else self.path)
        if free is None or free >= floor:
            return None
        return f"{free / MB:.0f} MB free, under record.min_free_mb ({self.settings.min_free_mb:g})"

    def _halt(self, reason: str, rest: list, refused: bool) -> None:
        """Stop recording for good (writer thread): the queued messages and ``rest`` (the batch after the one being
        written) are dropped and counted, the file is finished -- without the chunk in progress when the disk
        ``refused`` it -- and every later message is dropped and counted (:meth:`_put`).  Said once."""
        with self._cond:
            if self.stopped is not None:
                return
            self.stopped = reason
            rest = rest + list(self._q)
            self._q.clear()
            self._queued_bytes = 0
            self._count_dropped(rest)
        w = self._writer
        if refused and w is not None:
            topics = {cid: topic for topic, cid in self._channels.items()}
            lost = w.discard_chunk()
            with self._cond:
                for cid, n in lost.items():
                    self.messages_written -= n
                    self.dropped += n
                    self.dropped_by_topic[topics.get(cid, "?")] += n
        # no file left: the one being written was deleted and the next could not be made (its folder gone with it)
        path = self.files[-1] if self.files else None
        self._note_stopped(reason)
        self._finish()
        log.warning(
            "recorder: stopped recording: %s; %s (the flight goes on; later messages are dropped and"
            " counted, the status's record.stopped says why)%s",
            reason,
            f"{path} ends there" if path else "no file of the recording is left (record.lost_files)",
            "" if self._finish_ok else "; it has no summary: python -m onboard.record_recover reads it whole",
        )

    def _count_dropped(self, items: list) -> None:
        """Count queued items that will not be written, per topic (the caller holds the lock)."""
        self.dropped += len(items)
        for _kind, topic, *_ in items:
            self.dropped_by_topic[topic] += 1

    def _drop_at_close(self, rest: list) -> None:
        """The backlog left at close's deadline: dropped, counted, said once."""
        with self._cond:
            self._count_dropped(rest)
        self.dropped_at_close += len(rest)
        log.warning("recorder: %d queued messages not written by the shutdown's deadline: dropped (counted)", len(rest))

    def _open(self, index: int) -> None:
        from onboard.io.mcap_chunks import ChunkWriter

        s = self.settings
        path = rotated_path(self.path, index)
        d = os.path.dirname(os.path.abspath(path))
        os.makedirs(d, exist_ok=True)
        # exclusive: never over a file (start chose a free name); unbuffered: the chunk writer writes whole records
        f = self._file = open(path, "xb", buffering=0)
        # the mcap package's layout, the frames' pixels written from where they lie (onboard.io.mcap_chunks); no CRCs:
        # a CRC reads every frame's pixels once more (MCAP: a CRC of 0 means "not computed")
        w = self._writer = ChunkWriter(
            f.fileno(), chunk_size=s.chunk_bytes, compression=s.compression, enable_crcs=False
        )
        w.start(profile="", library="irtrack onboard.io.record")
        meta = dict(self._meta)
        meta["file_index"] = str(index)
        meta["started_utc"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")
        w.add_metadata("irtrack", meta)
        w.flush()  # the header and metadata are on disk before the first message
        self._channels, self._schemas = {}, {}
        self._synced = 0
        self._file_started_s = time.monotonic()
        self._index = index
        self.files.append(path)
        if s.max_files > 0:
            while len(self.files) > s.max_files:
                old = self.files.pop(0)
                try:
                    os.unlink(old)
                    self.files_deleted += 1
                    # said: the flight's beginning is gone, and record.files counts only the files kept
                    log.info("recorder: deleted the oldest file %s (record.max_files %d)", old, s.max_files)
                except OSError as exc:
                    log.warning("recorder: cannot delete %s: %s", old, exc)
        log.info("recording to %s", path)

    def _abandon_file(self, index: int) -> None:
        """Close and remove file ``index`` when its header did not fit (made here, exclusively: no one else's), so that
        no torn file is left for a reader, a replay of the rotated files, or the next start's
        :func:`free_recording_path` to step around."""
        f, self._file, self._writer = self._file, None, None
        if f is None:  # the open itself was refused: nothing made
            return
        try:
            f.close()
        except OSError:
            pass  # the data it could not write is what is being thrown away
        try:
            os.unlink(rotated_path(self.path, index))
        except OSError as exc:
            log.warning("recorder: cannot remove the torn %s: %s", rotated_path(self.path, index), exc)

    def _note_stopped(self, reason: str) -> None:
        """Write the :data:`STOPPED_METADATA` record into the file being finished, so that the file itself says why
        the recording ends before the flight did (the log and the live status are gone by the time it is read).  Best
        effort: a disk that refuses it refuses the summary after it too, which :meth:`_finish` says."""
        w = self._writer
        if w is None:
            return
        try:
            w.add_metadata(
                STOPPED_METADATA,
                {
                    "reason": reason,
                    "stopped_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds"),
                },
            )
        except Exception as exc:  # noqa: BLE001 - the file is finished (or not) the same way after it
            log.debug("recorder: cannot note the stop in %s: %s", self.files[-1] if self.files else "?", exc)

    def _finish(self) -> None:
        w, f = self._writer, self._file
        if w is None or f is None:
            return
        self._finish_ok = False
        try:
            w.finish()
            self._finish_ok = True
        except Exception as exc:  # noqa: BLE001
            self.write_errors += 1
            log.warning("recorder: cannot finish %s: %s", self.files[-1] if self.files else "?", exc)
        finally:
            self._closed_bytes += w.position
            try:
                f.close()
            except OSError as exc:
                log.warning("recorder: cannot close %s: %s", self.files[-1] if self.files else "?", exc)
        self._writer = self._file = None
        self.bytes_written = self._closed_bytes

    def _maybe_sync(self) -> None:
        """Past ``sync_bytes`` written since the last sync: the file's data to disk (``fdatasync``, the GIL
        released) and its pages out of the page cache (``POSIX_FADV_DONTNEED``).  The flight computer's page
        cache does not fill with the flight, a power cut loses at most that much, and the writer's next
        pages are recycled ones, which the kernel fills at a fraction of the CPU that fresh page-cache pages cost
        (``python -m bench.record`` prints both)."""
        s, w, f = self.settings, self._writer, self._file
        if w is None or f is None or s.sync_bytes <= 0:
            return
        pos = w.position
        if pos - self._synced < s.sync_bytes:
            return
        fd = f.fileno()
        os.fdatasync(fd)
        if hasattr(os, "posix_fadvise"):
            os.posix_fadvise(fd, 0, pos, os.POSIX_FADV_DONTNEED)
        self._synced = pos
        self.syncs += 1

    def _file_gone(self) -> str | None:
        """``"deleted"`` when the file being written has no name left (its messages are lost), ``"moved"`` when its
        name is gone but the file has another (finished through its descriptor, it is complete where it went), else
        None; checked at most once a second (an fstat and a stat).  Inode numbers are not compared: an overlay file
        system on older kernels gives different ones through the two calls."""
        now = time.monotonic()
        if self._file is None or now < self._next_lost_check_s:
            return None
        self._next_lost_check_s = now + 1.0
        try:
            if os.fstat(self._file.fileno()).st_nlink == 0:
                return "deleted"
            return None if os.path.exists(self.files[-1]) else "moved"
        except OSError:  # another error (a permission changed): the writes will tell
            return None

    def _maybe_rotate(self) -> None:
        if self._writer is None:
            return
        gone = self._file_gone()
        if gone is not None:
            name = self.files[-1]
            # finished through its descriptor: a moved file is complete where it went, a deleted one is lost
            try:
                opened = self._next_file(give_up=True)
            finally:  # once the next file is open (or could not be): the status names where the recording goes on
                if gone == "deleted":
                    self.lost_files.append(name)
            if opened:
                log.warning(
                    "recorder: %s was %s while recording%s; recording goes on in %s",
                    name,
                    gone,
                    ": the messages written to it are lost (the status's record.lost_files)"
                    if gone == "deleted"
                    else " (finished where it went, whole)",
                    self.files[-1],
                )
            return
        s = self.settings
        size = self._writer.position
        self.bytes_written = self._closed_bytes + size
        if size >= s.max_file_bytes or time.monotonic() - self._file_started_s >= s.max_file_s:
            self._next_file()

    def _next_file(self, give_up: bool = False) -> bool:
        """Finish the file being written and open the next (``FILE.N.mcap``), unless free space is short (the
        recording stops there); ``give_up``: the finished file leaves :attr:`files` (deleted or moved away under the
        recorder).  True when the next file is open."""
        index = self._index + 1
        self._finish()
        if give_up:
            self.files.pop()
        reason = self._short_of_space()
        if reason is not None:
            self._halt(reason, [], refused=False)
            return False
        try:
            self._open(index)
        except OSError:
            # the next file's header did not fit (or it could not be made): none of it is left torn and unlisted;
            # the writer loop stops the recording, the file before it finished whole
            self._abandon_file(index)
            raise
        return True

    # encoding ---------------------------------------------------------

    def _protobuf(self) -> dict[str, Any]:
        if self._pb is None:
            from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
            from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
            from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

            self._pb = {
                "foxglove.RawImage": RawImage,
                "foxglove.LocationFix": LocationFix,
                "foxglove.ImageAnnotations": ImageAnnotations,
            }
        return self._pb

    def _channel(self, w: ChunkWriter, topic: str, schema: str) -> int:
        cid = self._channels.get(topic)
        if cid is not None:
            return cid
        sid = self._schemas.get(schema)
        if schema.startswith("foxglove."):
            msg_enc = "protobuf"
            if sid is None:
                sid = w.register_schema(schema, "protobuf", file_descriptor_set(self._protobuf()[schema]))
        else:
            msg_enc = "json"
            if sid is None:
                sid = w.register_schema(schema, "jsonschema", json.dumps(self._json_schemas[schema]).encode())
        self._schemas[schema] = sid
        cid = w.register_channel(topic, msg_enc, sid, {})
        self._channels[topic] = cid
        return cid

    def _add(self, topic: str, schema: str, data, mono_ns: int, sequence: int) -> None:
        """One message stamped ``mono_ns`` (the recorder's clock; its log time and publish time) and numbered
        ``sequence`` (32 bits)."""
        w = self._writer
        if w is None:
            return
        t = self.log_time_ns(mono_ns)
        try:
            w.add_message(self._channel(w, topic, schema), t, data, t, sequence)
        except OSError:  # taken into its chunk, whose write failed: counted as the chunk's others (_halt)
            self.messages_written += 1
            raise
        self.messages_written += 1

    def _add_json(self, topic: str, schema: str, obj: Any, mono_ns: int, seq: int) -> None:
        """``obj`` as the bytes ``json.dumps(obj, separators=(",", ":"))`` gives."""
        self._add(topic, schema, _COMPACT_JSON.encode(obj).encode(), mono_ns, seq)

    def _pb_bytes(self, schema: str, fields: dict[str, Any]) -> bytes:
        cls = self._protobuf()[schema]
        ts = fields.pop("timestamp")
        msg = cls(**fields)
        msg.timestamp.seconds, msg.timestamp.nanos = ts
        return msg.SerializeToString()

    def _mavlink_json(self, data: bytes, link: str, source, direction: str, now: int) -> bytes:
        """The ``irtrack.mavlink_raw/1`` JSON of one read: the bytes ``json.dumps(obj, separators=(",", ":"))`` gives
        for ``{"link", "direction", "receive_time_ns", "source", "data"}``, its constant parts made once per
        (link, direction, source) -- a link reads 100-200 datagrams a second."""
        try:
            parts = self._mav_parts.get((link, direction, source))
        except TypeError:  # an unhashable source
            parts = None
        if parts is None:
            src = (
                None
                if source is None
                else (f"{source[0]}:{source[1]}" if isinstance(source, tuple) and len(source) >= 2 else str(source))
            )
            parts = (
                f'{{"link":{_json_str(link)},"direction":{_json_str(direction)},"receive_time_ns":'.encode(),
                f',"source":{"null" if src is None else _json_str(src)},"data":"'.encode(),
            )
            try:
                if len(self._mav_parts) < 256:
                    self._mav_parts[(link, direction, source)] = parts
            except TypeError:
                pass
        return b"".join((parts[0], str(int(now)).encode(), parts[1], base64.b64encode(data), b'"}'))

    def _write(self, kind: str, topic: str, item: tuple, now: int, seq: int) -> None:
        """One queued item's messages, stamped ``now`` (its hand-over, or the receipt it was given) and numbered
        ``seq``; a channel derived from it (a fix, annotations) takes the same stamp and number."""
        if self._writer is None:
            return
        if kind == "frame":
            (frame,) = item
            self._add(
                topic, "foxglove.RawImage", rawimage_pieces(frame, self._protobuf()["foxglove.RawImage"]), now, seq
            )
        elif kind == "frame_input":
            t_us, received_ns, looked_up, pose, zoom, withheld = item
            obj = {
                "seq": seq,  # the frame's, which is the message's sequence
                "time_boot_us": t_us,
                "received_ns": received_ns,
                "pose_looked_up": looked_up,
                "pose": pose_to_json(pose),
                "zoom": zoom if math.isfinite(zoom) else None,  # NaN and inf: JSON has none
                "withheld_because": list(withheld),
            }
            self._add_json(topic, FRAME_INPUT_SCHEMA, obj, now, seq)
            if pose is not None:
                self._add(
                    CAMERA_FIX_TOPIC,
                    "foxglove.LocationFix",
                    self._pb_bytes("foxglove.LocationFix", camera_fix_fields(pose, t_us)),
                    now,
                    seq,
                )
        elif kind == "track":
            track, payload = item
            if payload is None:
                payload = track_to_bytes(track)
            self._add(topic, TRACK_SCHEMA, payload, now, seq)
            if track.lat_deg is not None:
                self._add(
                    TARGET_FIX_TOPIC,
                    "foxglove.LocationFix",
                    self._pb_bytes(
                        "foxglove.LocationFix",
                        location_fix_fields(
                            track.lat_deg, track.lon_deg, track.alt_m, track.time_boot_us, "target", track.cov_p_ned_m2
                        ),
                    ),
                    now,
                    seq,
                )
        elif kind == "imaging_pose":
            t_us, pose = item
            obj = {"seq": seq, "time_boot_us": t_us, "pose": pose_to_json(pose)}
            self._add_json(topic, IMAGING_POSE_SCHEMA, obj, now, seq)
        elif kind == "objects":
            (message,) = item
            self._add_json(topic, OBJECTS_SCHEMA, message, now, seq)
            ann = objects_annotations(message, self._protobuf()["foxglove.ImageAnnotations"])
            self._add(OBJECT_ANNOTATIONS_TOPIC, "foxglove.ImageAnnotations", ann.SerializeToString(), now, seq)
        elif kind == "truth_objects":
            (message,) = item
            self._add_json(topic, TRUTH_OBJECTS_SCHEMA, message, now, seq)
            ann = truth_objects_annotations(message, self._protobuf()["foxglove.ImageAnnotations"])
            self._add(TRUTH_ANNOTATIONS_TOPIC, "foxglove.ImageAnnotations", ann.SerializeToString(), now, seq)
        elif kind == "mavlink":
            data, link, source, direction = item
            self._add(topic, MAVLINK_RAW_SCHEMA, self._mavlink_json(data, link, source, direction, now), now, seq)
        elif kind == "json":
            schema, data = item
            self._add(topic, schema, data, now, seq)
        else:  # pragma: no cover - programming error
            raise InputError(f"unknown record kind {kind!r}")
