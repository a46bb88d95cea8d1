"""The onboard daemon's wiring and event loop (``python -m onboard``).

Threads (nothing else runs concurrently):

* **zenoh subscriber callback** (zenoh's thread) on ``irtrack/<vehicle>/ir/frame``: counts the
  payload, refuses it on its length alone (:func:`onboard.core.irframe.check_payload_size`: a frame
  100x too large is never copied), copies it out once and checks its header and size
  (:func:`onboard.core.irframe.decode_irframe`: microseconds, the pixels stay a view), counting each
  refusal as ``frame_<reason>``, and pushes ``(IrFrame, received_mono_ns)`` into a bounded
  :class:`FrameQueue`; when full the *oldest* frame is dropped and counted (``dropped_queue``; also
  ``frames_dropped_bunched`` when the queued frames arrived much faster than they were captured, a burst,
  which the ``overload`` warning names instead of the CPU).
  It never blocks.  The output taps (:mod:`onboard.app.observers`) see each frame as received.  Zenoh's thread also
  notes a status on ``irtrack/<vehicle>/status`` from another session (another daemon of this name: the watchdog's
  ``name_clash``), one tuple assigned.
* **pipeline thread**: pops frames, runs :meth:`FramePipeline.process` (admission,
  imaging -- the objects chain first waits up to ``imaging.pose_wait_ms`` (40 ms) for the attitude sample after
  the frame, to register it with an interpolated rotation --, pose at capture time -- waiting up to
  ``pose.wait_ms`` (a few ms) for telemetry that
  brackets it, on a condition signalled by every new pose sample, then extrapolating the newest
  samples over a bounded horizon (:mod:`onboard.core.pose`) -- and the estimator), publishes the track JSON on
  ``irtrack/<vehicle>/track`` and hands each frame's outcome to the output taps, one call each
  (:class:`~onboard.app.observers.FrameObserver`: recorder, live view, video, and the newest track
  for the main thread).  It touches the liveness file (:func:`onboard.app.health.mark_alive`) at least
  every ``output.health_interval_s``, busy or idle.
* **estimator worker** (``estimator.worker``, :mod:`onboard.app.estimator_worker`): ``process``
  (default) runs the sliding-window estimator in a child process, ``thread`` in a thread, ``inline``
  in the pipeline thread.  A frame waits up to ``estimator.result_wait_ms`` for its own estimate, past
  that it gets the newest estimate propagated to its time; a worker process that dies is replaced.  The first
  worker process is spawned while the daemon starts (its fork server imports for a second or more), not before it
  serves; one that cannot be started ends the daemon (:meth:`OnboardService.run` raises
  :class:`~onboard.app.estimator_worker.EstimatorStartError`).
* **main thread**: woken by MAVLink input and by its own timers (at most ``mavlink.poll_rate_hz`` turns a
  second, :meth:`OnboardService._idle`): :meth:`MavlinkLink.poll` /
  :meth:`MavlinkLink.tick` (the autopilot link, component 191: heartbeat, rate requests, TIMESYNC);
  the camera component (:meth:`OnboardService.camera_step`, with ``gcs.endpoints``): commands from
  ground stations through :class:`~onboard.io.gcs_link.GcsLink` into
  :class:`~onboard.io.camera_protocol.CameraProtocol`, tracking requests queued to the pipeline
  (:meth:`FramePipeline.request_selection`, decided on its next frame and ACKed here), heartbeat,
  CAMERA_TRACKING_IMAGE_STATUS / GEO_STATUS of the newest track while tracking at the rates asked
  (defaults ``output.tracking_*_status_hz``; #276 only for observable positions unless
  ``output.geo_status_unobservable``), the status JSON on ``irtrack/<vehicle>/status`` every
  ``output.status_interval_s``, and the :class:`~onboard.app.watchdog.Watchdog`'s input checks (no frames
  / no MAVLink for 5 s; frame size and residual checks are fed by the pipeline thread): each
  condition is logged once at WARNING and listed in the status JSON's ``warnings`` while it holds.  It
  owns the pymavlink connection alone; pose samples go into the shared
  :class:`~onboard.app.shared_pose.SharedPoseBuffer` under a lock held for one ``add`` or one lookup (microseconds),
  so a pose lookup never blocks MAVLink.

Shutdown: :meth:`OnboardService.request_stop` (the SIGTERM/SIGINT handler of ``__main__``) ends the
main loop; :meth:`OnboardService.close` stops the threads, undeclares the zenoh entities, closes
the session and the MAVLink connection, and removes the liveness file.
"""

from __future__ import annotations

import collections
import functools
import json
import logging
import math
import select
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from onboard.app.components import make_camera_protocol, zenoh_unreachable_hint, zenoh_where
from onboard.app.config import OnboardConfig
from onboard.app.cpu_load import CpuLoad
from onboard.app.estimator_worker import (
    EstimatorStartError,
    ProcessEstimator,
    ThreadedEstimator,
    make_estimator_worker,
)
from onboard.app.frame_queue import FrameQueue, arrived_bunched
from onboard.app.locked_counter import LockedCounter
from onboard.app.observers import (
    FrameObserver,
    FrameResult,
    NewestTrack,
    RecorderTap,
    VideoTap,
    frame_objects,
    make_observers,
)
from onboard.app.os_thread import name_os_thread
from onboard.app.shared_pose import SharedPoseBuffer
from onboard.app.status_sections import camera_section, estimator_label, time_offset_section, twin_words
from onboard.app.watchdog import OVERLOAD_CLEAR_S, STALL_NAMED_S, Watchdog
from onboard.core.errors import InputError
from onboard.core.irframe import IrFrame, IrFrameError, check_payload_size, decode_irframe
from onboard.core.pose import PoseBuffer
from onboard.core.status import RollingStats, build_status
from onboard.core.track import Track, new_run_id, track_to_bytes
from onboard.core.utc_clock import UtcClock, with_utc
from onboard.io.record import NOT_LOOKED_UP
from onboard.io.zenoh_session import FRAME_SCHEMA, foreign_schema, frame_key, status_key
from onboard.pipeline.admission import ArrivalGaps
from onboard.pipeline.frame_pipeline import (
    ACCEPTED_FRAME_EVENTS,
    TRACKER_REFUSALS,
    FramePipeline,
    FrameRejected,
    make_tracker,
)
from onboard.pipeline.withholding import CLOCK_OFFSET, clock_offset_withholds

if TYPE_CHECKING:
    from onboard.io.gcs_link import GcsLink
    from onboard.io.mavlink_link import MavlinkLink

__all__ = ["OnboardService"]

log = logging.getLogger(__name__)

WATCH_PERIOD_S = 0.5  # the watchdog's input checks in the main loop
WARNING_STATUS_MIN_S = 0.2  # a warning's change is published at once, but at most this often (the loop in run)
#: an output tap's close gets at least this long past a shutdown deadline: enough to finish a file's summary
MIN_TAP_CLOSE_S = 0.1
MAIN_LOOP_MAX_IDLE_S = 0.05  # the main loop's longest sleep without input (stop requests, timers it cannot see)
#: the watchdog's warnings the pipeline withholds the geometry for (zoom_mismatch is not one: the pipeline decides
#: it from each frame's own zoom, not a frame late from the watchdog's); camera_time_offset withholds it too, while the
#: offset is not compensated (:func:`onboard.pipeline.withholding.clock_offset_withholds`); frame_sources: with two
#: senders on the key no frame is known to come from the configured camera, its mount and intrinsics
MISMATCH_WARNINGS = frozenset({"gimbal_mismatch", "camera_mismatch", "frame_sources"})


class OnboardService:
    """The daemon: build with a validated :class:`OnboardConfig`, then :meth:`start`, :meth:`run`, :meth:`close`.

    ``clock`` (s) and ``clock_ns`` are monotonic clocks (fakeable); ``clock_ns`` stamps frame
    receipt and TIMESYNC, so the two are on one clock.
    """

    def __init__(
        self,
        config: OnboardConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if not isinstance(config, OnboardConfig):
            raise InputError(f"OnboardService needs an OnboardConfig, got {type(config).__name__}")
        self.config = config
        self._clock = clock
        self._clock_ns = clock_ns
        self._stall: tuple[float, float] = (-math.inf, 0.0)  # (when, how long) the main loop last stood still
        self.counter = LockedCounter(
            log_interval_s=config.logging.reject_log_interval_s,
            clock=clock,
            logger=logging.getLogger("onboard.rejects"),
        )
        self.mount = config.camera.camera_mount()
        self._first_telemetry_s: float | None = None  # when the first attitude/position arrived (watchdog)
        self._next_follow_s = -math.inf  # FOLLOW_TARGET pacing (follow_step)
        buffer = PoseBuffer(
            mount=self.mount,
            config=config.pose,
            origin=config.pose.geodetic_origin(),
            counter=self.counter,
            bearing_white_sigma_rad=config.bearing_white_sigma_rad(),
        )
        self.pose = SharedPoseBuffer(buffer)
        self.queue = FrameQueue(config.input.queue_length)
        est = make_estimator_worker(config, self.counter)
        self.estimator_kind = "disabled" if est is None else f"sliding window ({config.estimator.worker})"
        self.estimator = est
        wait_s, chain_wait_s = config.pose.wait_ms / 1000.0, config.imaging.pose_wait_ms / 1000.0
        self._frame_schema = FRAME_SCHEMA  # frames typed with another schema are refused (frame_schema)
        self._frame_encoding: Any = None  # zenoh's Encoding of FRAME_ENCODING, made by start()
        pose_source: Any = self.pose
        self._pose_memo = None  # remembers each frame's pose for the recorder, the live view's 3-D scene and guidance
        if config.record.path or config.live_view.port is not None or config.guidance.advise:  # guidance: the pose
            from onboard.io.record import RecordingPoseSource

            pose_source = self._pose_memo = RecordingPoseSource(self.pose)
        self.pipeline = FramePipeline(
            config,
            pose_source,
            make_tracker(config),
            est,
            config.pose.geodetic_origin(),
            counter=self.counter,
            # the pipeline waits for telemetry that brackets a frame (pose.wait_ms at most); the objects chain
            # for the bracket even where the newest samples could be extrapolated (imaging.pose_wait_ms)
            pose_wait=functools.partial(self.pose.wait_for, timeout_s=wait_s, clock=clock) if wait_s > 0 else None,
            chain_pose_wait=functools.partial(self.pose.wait_for, timeout_s=chain_wait_s, clock=clock, bracket=True)
            if config.imaging.chain == "objects" and chain_wait_s > 0
            else None,
            clock_ns=clock_ns,
        )
        # this run's id on every track and status: a consumer tells a restarted daemon (ids and origin anew) by it
        self.run_id = self.pipeline.run_id = new_run_id()
        # the output taps, and the newest track for the main thread (the GCS camera, FOLLOW_TARGET, status)
        self.newest = NewestTrack(clock)
        self.taps: list[FrameObserver] = make_observers(config, self.pipeline.intrinsics, clock_ns, clock)
        # the taps that act in the loop (guidance: setpoints to the autopilot, on a schedule the loop wakes for)
        self._setpoint_taps: list[Any] = [tap for tap in self.taps if hasattr(tap, "setpoint_step")]
        self.observers: list[FrameObserver] = [*self.taps, self.newest]
        self.recorder = next((t.recorder for t in self.taps if isinstance(t, RecorderTap)), None)
        self.link: MavlinkLink | None = None  # the autopilot link, opened by start()
        self.utc = UtcClock(counter=self.counter)  # boot clock -> UTC from the link's SYSTEM_TIME (read lock-free)
        self.gcs: GcsLink | None = None  # the camera component's sockets (gcs.endpoints), opened by start()
        self.camera = (
            make_camera_protocol(config, self.pipeline.intrinsics, self.counter) if config.gcs.endpoints else None
        )
        self._selection_results: collections.deque = collections.deque()  # TrackResults from the pipeline thread
        self.session: Any = None
        # the session's routers and peers at the last watch (None: not known), for the status's zenoh section
        self._zenoh_linked: tuple[int | None, int | None] = (None, None)
        self._sub = None
        self._twin_sub = None  # another daemon's status under this vehicle's name (name_clash)
        #: when the newest status of another daemon of this name arrived (self._clock), what the last one read said in
        #: words, and when that one was read
        self._twin_heard: tuple[float, str, float] | None = None
        self._track_pub = None
        self._objects_pub = None
        self._status_pub = None
        self._stop = threading.Event()
        self._pipe_thread: threading.Thread | None = None
        self._pipe_stop = threading.Event()
        self._stats_lock = threading.Lock()
        self.frames_in = 0
        self.arrival_gaps = ArrivalGaps()  # frames numbered by the camera that never reached the daemon
        self.frames_dropped = 0
        self.frames_dropped_bunched = 0  # of those, dropped as frames arrived bunched (a link's burst, not the CPU)
        self.tracks_published = 0
        self.frames_failed = 0  # frames taken that a pipeline error stopped before they were processed
        self.latency_ms = RollingStats(1000)
        self.queue_wait_ms = RollingStats(1000)
        self.publish_ms = RollingStats(1000)
        self.capture_to_track_ms = RollingStats(1000)
        self._done: collections.deque = collections.deque(maxlen=1000)  # (time_boot_us, published_mono_ns)
        self._pipeline_cpu_s = 0.0
        self._health_path = config.output.health_file
        self._health_failed = False
        #: why the liveness file could not be touched the last time (None: it was, or there is none)
        self.health_error: str | None = None
        self._started_s = clock()
        self.status_count = 0
        self._warnings_published = 0  # the watchdog's change count at the last status
        self._withheld_at = -1  # the watchdog's change count when the pipeline's withheld_because was set
        self._warned_codes: tuple[str, ...] = ()  # the watchdog's warnings at that change count
        self._offset_withholds = False  # camera_time_offset withholds the geometry, its offset not compensated
        self.watchdog = Watchdog(
            started_s=self._started_s,
            frame_key=frame_key(config.vehicle),
            zenoh_where=zenoh_where(config),
            mavlink_connection=config.mavlink.connection,
            camera_size_px=(self.pipeline.intrinsics.width_px, self.pipeline.intrinsics.height_px),
        )
        self.cpu_load = CpuLoad()
        self._name_frames_thread = True  # zenoh's thread for _on_frame, named in the OS on its first frame

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Open MAVLink and zenoh, declare the subscriber/publishers, start the pipeline thread.

        Raises the zenoh adapter's typed errors (port in use ...); a missing peer is not an error.
        """
        import zenoh

        from onboard.estimation.guidance import GUIDANCE_SCHEMA
        from onboard.io.mavlink_link import MavlinkLink
        from onboard.io.zenoh_session import (
            DAEMON_CONFIG_FILE_FIELD,
            DAEMON_CONNECT_TIMEOUT_FIELD,
            FRAME_ENCODING,
            GUIDANCE_ENCODING,
            OBJECTS_ENCODING,
            STATUS_ENCODING,
            TRACK_ENCODING,
            guidance_key,
            objects_key,
            open_session,
            track_key,
        )

        cfg = self.config
        if self._health_path:
            from onboard.app.health import claim_health_file

            claim_health_file(self._health_path)  # a real file named by mistake: refused, never touched or deleted
        for tap in self.observers:
            tap.start()  # a file that cannot be written, a port in use: fails the start, in one line (InputError)
        self.link = MavlinkLink(
            cfg.mavlink,
            self.pose,
            self.counter,
            gimballed=self.mount.gimballed,
            clock=self._clock,
            clock_ns=self._clock_ns,
            utc_clock=self.utc,
        )
        if self.recorder is not None:
            self.link.raw_tap = self.recorder.on_mavlink
        if self.camera is not None:
            from onboard.io.gcs_link import GcsLink

            # the camera signs and checks as the autopilot link does: unsigned, a click could move the tracked target
            self.gcs = GcsLink(
                cfg.gcs.endpoints,
                cfg.gcs.component_id,
                counter=self.counter,
                signing_key=cfg.mavlink.signing_key() if cfg.gcs.signed else None,
            )
            self.camera.link_name = self.gcs.link_name  # the status names the links that set their own rates
        hint = zenoh_unreachable_hint(cfg)
        if hint is not None:
            log.warning("%s", hint)
        self.session = open_session(
            cfg.zenoh,
            max_payload_bytes=cfg.input.max_frame_bytes,
            file_option=DAEMON_CONFIG_FILE_FIELD,
            timeout_option=DAEMON_CONNECT_TIMEOUT_FIELD,
        )
        self._track_pub = self.session.declare_publisher(
            track_key(cfg.vehicle),
            encoding=zenoh.Encoding(TRACK_ENCODING),
            congestion_control=zenoh.CongestionControl.DROP,
        )
        self._status_pub = self.session.declare_publisher(
            status_key(cfg.vehicle), encoding=zenoh.Encoding(STATUS_ENCODING)
        )
        if hasattr(self.pipeline.tracker, "last_objects"):  # the objects image chain
            self._objects_pub = self.session.declare_publisher(
                objects_key(cfg.vehicle),
                encoding=zenoh.Encoding(OBJECTS_ENCODING),
                congestion_control=zenoh.CongestionControl.DROP,
            )
        self._frame_encoding = zenoh.Encoding(FRAME_ENCODING)
        self._sub = self.session.declare_subscriber(frame_key(cfg.vehicle), self._on_frame)
        # zenoh does not deliver this session's own statuses back (REMOTE): any status on the key is another daemon's
        # under this name, whose tracks interleave with ours for every consumer (the watchdog's name_clash)
        self._twin_sub = self.session.declare_subscriber(
            status_key(cfg.vehicle), self._on_twin_status, allowed_origin=zenoh.Locality.REMOTE
        )
        guidance = next((t for t in self.taps if t.name == "guidance"), None)
        if guidance is not None:  # advised manoeuvres on irtrack/<vehicle>/guidance (onboard.app.guidance_tap)
            key = guidance_key(cfg.vehicle)
            pub = self.session.declare_publisher(key, encoding=zenoh.Encoding(GUIDANCE_ENCODING))
            recorder = self.recorder
            if recorder is None:
                guidance.attach(pub.put)  # type: ignore[attr-defined]
            else:  # what the operator and the autopilot were advised belongs in the flight's record

                def publish(payload: bytes) -> None:
                    pub.put(payload)
                    recorder.on_json(key, GUIDANCE_SCHEMA, payload)

                guidance.attach(publish)  # type: ignore[attr-defined]
        self._pipe_thread = threading.Thread(target=self._pipeline_loop, name="irtrack-pipeline", daemon=True)
        self._pipe_thread.start()
        self._started_s = self._clock()
        self.watchdog.restart(self._started_s)  # the 5 s of the input checks run from here
        log.info(
            "onboard service started: vehicle=%s mavlink=%s frames=%s estimator=%s",
            cfg.vehicle,
            cfg.mavlink.connection,
            frame_key(cfg.vehicle),
            self.estimator_kind,
        )

    def request_stop(self) -> None:
        """Ask :meth:`run` to return (signal-handler safe)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def close(self, timeout_s: float = 1.0, deadline_s: float | None = None) -> None:
        """Stop threads and close everything; bounded by about ``timeout_s`` plus zenoh's close.  ``deadline_s``
        (``time.monotonic()``): when everything must be closed by (the daemon's shutdown budget); the output
        taps, closed last, then get what is left of it (at least :data:`MIN_TAP_CLOSE_S`) instead of
        ``timeout_s``: the recorder writes its backlog for that long and finishes its file within it."""
        self._stop.set()
        # guidance commanding the vehicle: zero velocity first, not its last setpoint flown on
        if self.link is not None:
            for halt in (getattr(tap, "halt", None) for tap in self.taps):
                if halt is not None:
                    halt(self.link)
        self._pipe_stop.set()
        self.queue.close()
        if self._pipe_thread is not None:
            self._pipe_thread.join(timeout_s)
            if self._pipe_thread.is_alive():
                log.warning("pipeline thread did not stop within %.1f s", timeout_s)
        if isinstance(self.estimator, (ThreadedEstimator, ProcessEstimator)):
            self.estimator.close(timeout_s / 2)
        for ent in (self._sub, self._twin_sub, self._track_pub, self._status_pub, self._objects_pub):
            if ent is not None:
                try:
                    ent.undeclare()
                except Exception as exc:  # noqa: BLE001 - already gone with the session
                    log.debug("zenoh undeclare failed: %s", exc)
        self._sub = self._twin_sub = self._track_pub = self._status_pub = self._objects_pub = None
        if self.session is not None:
            try:
                self.session.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("zenoh session close failed: %s", exc)
            self.session = None
        if self.link is not None:
            self.link.close()
        if self.gcs is not None:
            self.gcs.close()
            self.gcs = None
        for tap in self.observers:
            left = timeout_s if deadline_s is None else max(deadline_s - time.monotonic(), MIN_TAP_CLOSE_S)
            tap.close(left)  # after the pipeline: the recorder's last frames are in the file
        if self._health_path:
            from onboard.app.health import release_health_file

            release_health_file(self._health_path)
        if self._pipe_thread is not None:
            log.info(
                "onboard service stopped: %d frames in, %d missing on the way, %d tracks published",
                self.frames_in,
                self.arrival_gaps.missing,
                self.tracks_published,
            )

    # ------------------------------------------------------------------ another daemon of this name (zenoh thread)

    def _on_twin_status(self, sample) -> None:
        """A status on this vehicle's status key from another zenoh session: another daemon publishes as this
        vehicle.  Noted with what it says (any peer may publish there: whatever it sent, the clash is noted, and
        nothing of it is used but the words).  Read at most once a second: a peer flooding the key costs a time
        stamp per message, not a JSON parse."""
        now, heard = self._clock(), self._twin_heard
        if heard is not None and 0.0 <= now - heard[2] < 1.0:
            self._twin_heard = (now, heard[1], heard[2])
            return
        self._twin_heard = (now, twin_words(sample.payload.to_bytes()), now)

    # ------------------------------------------------------------------ frames in (zenoh thread)

    def _on_frame(self, sample) -> None:
        received = self._clock_ns()
        if self._name_frames_thread:  # for top -H and /proc (bench.onboard's CPU by thread)
            self._name_frames_thread = False
            name_os_thread("irtrack-frames")
        with self._stats_lock:
            self.frames_in += 1
        try:
            enc = getattr(sample, "encoding", None)
            if (named := foreign_schema(enc, self._frame_schema, self._frame_encoding)) is not None:
                self.counter.count("frame_schema", f"frame encoding {enc} names {named}, not {self._frame_schema}")
                return
            payload = sample.payload
            max_bytes = self.config.input.max_frame_bytes
            check_payload_size(len(payload), max_bytes)  # before any copy: a 100x frame costs nothing
            frame = decode_irframe(payload.to_bytes(), max_bytes)  # header checks; pixels stay a view
            with self._stats_lock:
                self.arrival_gaps.see(frame.seq)
            for tap in self.taps:
                tap.on_received(frame, received)  # never blocks: queued, or dropped and counted when behind
        except IrFrameError as exc:
            with self._stats_lock:  # it arrived, broken (counted below): not a frame lost on the way
                if exc.seq is not None:
                    self.arrival_gaps.see(exc.seq)
                else:  # refused before its number was read (on its length, or not an IRF1 header): its gap knows it
                    self.arrival_gaps.unnumbered()
            self.counter.count(f"frame_{exc.reason}", str(exc))
            return
        except Exception as exc:  # noqa: BLE001 - a callback must never raise into zenoh
            self.counter.count("frame_receive_error", f"{type(exc).__name__}: {exc}")
            return
        dropped = self.queue.push((frame, received))
        if dropped:
            oldest = self.queue.oldest()
            bunched = oldest is not None and arrived_bunched(
                oldest[1], oldest[0].time_boot_us, received, frame.time_boot_us
            )
            with self._stats_lock:
                self.frames_dropped += dropped
                if bunched:
                    self.frames_dropped_bunched += dropped
            queue_of = f"queue of {self.config.input.queue_length}"
            if bunched:  # the pipeline may keep up: the link delivered frames together (see arrived_bunched)
                arrived_ms = (received - oldest[1]) / 1e6
                captured_ms = (frame.time_boot_us - oldest[0].time_boot_us) / 1e3
                why = (
                    f"frames arrived in a burst (the queued ones within {arrived_ms:.1f} ms, captured "
                    f"{captured_ms:.0f} ms apart): oldest frame dropped ({queue_of})"
                )
            else:
                why = f"pipeline behind: oldest frame dropped ({queue_of})"
            self.counter.count("dropped_queue", why, dropped)

    # ------------------------------------------------------------------ pipeline thread

    def _pipeline_loop(self) -> None:
        name_os_thread("irtrack-pipe")
        health_every_s = self.config.output.health_interval_s
        next_health = -math.inf
        publish = self.config.output.publish_track
        while not self._pipe_stop.is_set():
            now = self._clock()
            if now >= next_health:
                self._touch_health()
                next_health = now + health_every_s
            item = self.queue.pop(min(health_every_s, 0.5))
            if item is None:
                continue
            frame, received_ns = item
            self.queue_wait_ms.add((self._clock_ns() - received_ns) / 1e6)
            track = self._process(frame, received_ns)
            payload = self._publish_track(track) if track is not None and publish else None
            objects = frame_objects(self.pipeline, track)  # the objects chain's, for zenoh and the taps
            if objects is not None and publish and self._objects_pub is not None:
                self._publish_objects(objects)
            looked_up, pose, imaging_pose = (
                self._pose_memo.take_lookups() if self._pose_memo is not None else (False, None, NOT_LOOKED_UP)
            )
            withheld = self.pipeline.last_withheld
            result = FrameResult(received_ns, looked_up, pose, track, payload, objects, imaging_pose, withheld)
            for tap in self.observers:
                tap.on_frame(frame, result)
            if track is None:
                continue
            done = self._clock_ns()
            self.latency_ms.add((done - received_ns) / 1e6)
            self._done.append((track.time_boot_us, done))

    def _process(self, frame: IrFrame, received_ns: int) -> Track | None:
        """One frame through the pipeline, with the watchdog's frame checks; None when it was refused or failed."""
        c0 = time.thread_time()
        # fail-safe: while the configured camera disagrees with the vehicle, no direction or position goes out
        # (looked up again when the watchdog's conditions changed: its change count is read before them)
        changes = self.watchdog.changes
        moved = changes != self._withheld_at
        if moved:
            self._withheld_at = changes
            self._warned_codes = tuple(w.code for w in self.watchdog.active)
        # a camera clock offset withholds while its warning holds and it is not compensated, which moves with the
        # estimate (a block every 3 s), not with the warning: checked each frame
        offset_withholds = CLOCK_OFFSET in self._warned_codes and clock_offset_withholds(
            self.pipeline.time_offset_estimate, self.config.time_offset.warn_threshold_ms, self._offset_withholds
        )
        if moved or offset_withholds != self._offset_withholds:
            self._offset_withholds = offset_withholds
            self.pipeline.withheld_because = tuple(
                c for c in self._warned_codes if c in MISMATCH_WARNINGS or (c == CLOCK_OFFSET and offset_withholds)
            )
        withheld = self.pipeline.withheld_because
        if not self.mount.gimballed and "gimbal_mismatch" not in withheld and self.link is not None:
            # a gimbal reporting under a fixed mount: the watchdog names it at its next turn (2 Hz), but no frame
            # in between may carry a direction made without the gimbal
            if getattr(self.link, "gimbal_reports", 0) > 0:
                self.pipeline.withheld_because = (*withheld, "gimbal_mismatch")
        processed = self.pipeline.frames_processed
        try:
            track = with_utc(self.pipeline.process(frame, received_ns), self.utc.mapping)  # its UTC, once known
            now_s = self._clock()
            self.watchdog.frame_size(now_s, frame.width_px, frame.height_px)
            self.watchdog.zoom(now_s, self.pipeline.last_zoom, self.pipeline.zoom_withheld)
            self.watchdog.residual(now_s, track.residual_rms_norm)
            self.watchdog.navigation(now_s, self.pipeline.last_position_age_s, rejected=self.counter.counts)
            self.watchdog.camera_clock(now_s, self.pipeline.clock_apart_s)
            stamp_s = None  # how far the stamp stood from the telemetry: only a frame without a pose needs it
            if not track.pose_valid and (newest_us := self.pose.newest_rotation_time_boot_us()) is not None:
                stamp_s = (frame.time_boot_us - newest_us) / 1e6
            self.watchdog.frame_pose(now_s, track.pose_valid, stamp_s)
            self.watchdog.camera_time_offset(
                now_s,
                self.pipeline.time_offset_estimate,
                self.config.time_offset.warn_threshold_ms,
                withheld=self._offset_withholds,
            )
            return track
        except FrameRejected as exc:
            if exc.reason == "dims_mismatch":
                self.watchdog.frame_size(self._clock(), frame.width_px, frame.height_px)
            return None
        except Exception as exc:  # noqa: BLE001 - never let one frame kill the loop
            self.counter.count("pipeline_error", f"{type(exc).__name__}: {exc}")
            if self.pipeline.frames_processed == processed:
                # taken and not processed: a refused frame in the status's frame counts, which else lost it
                # (in = processed + dropped + rejected + queued)
                self.frames_failed += 1
            if self.counter["pipeline_error"] == 1:  # the first one with its traceback, on one line
                log.exception("pipeline error (frame skipped)")
            return None
        finally:
            self._pipeline_cpu_s += time.thread_time() - c0

    def _publish_objects(self, objects: dict) -> None:
        """Every confirmed object of the frame just processed on ``irtrack/<vehicle>/objects``."""
        if self._objects_pub is None:
            return
        try:
            self._objects_pub.put(json.dumps(objects, separators=(",", ":")).encode())
        except Exception as exc:  # noqa: BLE001 - a failed publication must not stop the frame loop
            self.counter.count("objects_publish_error", f"{type(exc).__name__}: {exc}")

    def _publish_track(self, track: Track) -> bytes | None:
        """The track JSON on ``irtrack/<vehicle>/track``; the payload, None when not published."""
        if self._track_pub is None:
            return None
        try:
            p0 = self._clock_ns()
            payload = track_to_bytes(track)
            self._track_pub.put(payload)
            self.publish_ms.add((self._clock_ns() - p0) / 1e6)
            with self._stats_lock:
                self.tracks_published += 1
            return payload
        except Exception as exc:  # noqa: BLE001
            self.counter.count("track_publish_error", f"{type(exc).__name__}: {exc}")
            return None

    def _touch_health(self) -> None:
        if not self._health_path:
            return
        try:
            from onboard.app.health import mark_alive

            mark_alive(self._health_path)
            self._health_failed = False
            self.health_error = None
        except OSError as exc:
            if not self._health_failed:
                log.warning("cannot touch liveness file %s: %s", self._health_path, exc)
            self._health_failed = True
            self.health_error = f"{self._health_path}: {exc.strerror or exc}"

    # ------------------------------------------------------------------ main thread

    def run(self, max_duration_s: float | None = None) -> None:
        """The main loop: MAVLink poll/tick, tracking status out, status JSON; returns when stopped."""
        cfg = self.config
        period = 1.0 / cfg.mavlink.poll_rate_hz
        now = self._clock()
        end = math.inf if max_duration_s is None else now + max_duration_s
        next_status = now + cfg.output.status_interval_s
        last_status_s = -math.inf  # the last status published (warning changes: at most each WARNING_STATUS_MIN_S)
        last_cpu = (now, time.process_time(), self._pipeline_cpu_s + self._worker_cpu())
        next_watch = now
        turn_s = now
        previous_turn_s = now
        while not self._stop.is_set() and now < end:
            # the loop turns every 50 ms at most; one a second late is the process standing still (SIGSTOP, a paused
            # or swapping computer: a CPU quota holds it back for a period, 100 ms), which overload names.  The
            # process CPU time cannot tell it apart: the threads resume at once on the frames and telemetry queued
            # meanwhile, before this thread looks
            top_s = self._clock()
            gap_s, previous_turn_s = top_s - previous_turn_s, top_s
            if gap_s >= STALL_NAMED_S:
                self._stall = (top_s, gap_s)
            try:
                if self.link is not None:  # None until start()
                    self.link.poll()
                    self.link.tick()
            except Exception as exc:  # noqa: BLE001 - the link adapter should not raise; be sure
                self.counter.count("mavlink_loop_error", f"{type(exc).__name__}: {exc}")
            now = self._clock()
            try:
                self.camera_step(now)
            except Exception as exc:  # noqa: BLE001 - the camera component must not stop the loop
                self.counter.count("camera_loop_error", f"{type(exc).__name__}: {exc}")
            if now >= next_watch:  # 5 s timeouts: 2 Hz is plenty, the loop itself turns at poll_rate_hz
                self._check_estimator_start()
                self._watch(now)
                next_watch = now + WATCH_PERIOD_S
            try:
                self.follow_step(now)
            except Exception as exc:  # noqa: BLE001 - the follow output must not stop the loop
                self.counter.count("follow_loop_error", f"{type(exc).__name__}: {exc}")
            for tap in self._setpoint_taps:
                tap.setpoint_step(now, self.link)  # never raises
            due = now >= next_status
            changed = self.watchdog.changes != self._warnings_published
            if due or (changed and now - last_status_s >= WARNING_STATUS_MIN_S):
                # a warning raised or cleared goes out at once, not up to a status interval later, but at most once
                # each WARNING_STATUS_MIN_S (a warning flapping with every loop turn made a status a turn); only the
                # periodic status moves the schedule on: a warning that comes and goes with every frame (two cameras
                # on the key) would otherwise push it an interval further at each change, minutes ahead in seconds
                self._warnings_published = self.watchdog.changes
                last_cpu = self._publish_status(now, last_cpu)
                last_status_s = now
                if due:
                    next_status = max(next_status + cfg.output.status_interval_s, now)
            wake_s = min(next_watch, next_status)
            if self.watchdog.changes != self._warnings_published:
                wake_s = min(wake_s, last_status_s + WARNING_STATUS_MIN_S)  # the held change, as soon as it may go
            self._idle(turn_s, period, wake_s)
            turn_s = now = self._clock()
        # the counts as the run ends, on the status key: whoever watches it (a ground station, a demo stopping the
        # daemon) sees how the run ended, not the last periodic status up to an interval before it
        self._publish_status(self._clock(), last_cpu)

    def _check_estimator_start(self) -> None:
        """Raise :class:`EstimatorStartError` when the estimator's first worker process could not be started: it is
        spawned while the daemon starts, not before (:class:`ProcessEstimator`), and a daemon whose estimator never ran
        ends as it did when it waited for that worker, with exit code 1, rather than serve frames without 3-D."""
        error = getattr(self.estimator, "start_error", None)
        if error is not None:
            raise EstimatorStartError(f"estimator process could not be started: {type(error).__name__}: {error}")

    def _idle(self, turn_s: float, period_s: float, next_own_s: float) -> None:
        """Sleep until MAVLink input arrives (the autopilot link, the camera component's endpoints) or the next
        timer is due (heartbeats, TIMESYNC, the camera's messages, FOLLOW_TARGET, guidance setpoints, the watchdog, the
        status), at most ``MAIN_LOOP_MAX_IDLE_S``, turning at most ``mavlink.poll_rate_hz`` times a second (a flood
        costs no more): a fixed-rate loop woke 200 times a second for nothing, ~0.02 CPU s per s on a companion-class
        core.  Without a descriptor to wait on (a link being reopened, a test double) the loop turns at
        ``poll_rate_hz``."""
        link = self.link
        link_fd = getattr(link, "fileno", lambda: None)()
        fds: list[int] = [] if link_fd is None else [link_fd]
        if self.gcs is not None:
            fds += self.gcs.filenos()
        now = self._clock()
        if not fds:
            self._stop.wait(max(turn_s + period_s - now, 0.0))
            return
        to_next_due = getattr(link, "seconds_to_next_due", None)
        due_s = min(next_own_s, now + (0.0 if to_next_due is None else to_next_due()))
        if self.camera is not None:
            due_s = min(due_s, self.camera.next_due_s())
        if self.config.follow.enabled:
            due_s = min(due_s, self._next_follow_s)
        for tap in self._setpoint_taps:  # a setpoint late by an idle turn is a gap PX4's OFFBOARD may count as lost
            due_s = min(due_s, tap.next_setpoint_s)
        timeout = min(max(due_s - now, 0.0), MAIN_LOOP_MAX_IDLE_S)
        try:
            ready, _, _ = select.select(fds, [], [], timeout)
        except (OSError, ValueError):  # a descriptor closed under us: the next turn reopens or counts it
            ready = []
            timeout = 0.0
        if ready or timeout == 0.0:  # the rate cap, for input that was waiting (a flood) or a busy timer
            rest = turn_s + period_s - self._clock()
            if rest > 0:
                time.sleep(rest)

    def _watch(self, now: float) -> None:
        with self._stats_lock:
            frames_in, returns = self.frames_in, self.arrival_gaps.returns
        self.watchdog.frame_sources(now, returns)
        rx = refused = None
        open_error = None
        if self.link is not None:
            open_error = self.link.open_error
            try:
                st = self.link.status()
                # the messages signing refused say nothing of the autopilot: a sender with another key is no link
                refused = int(st.messages_refused)
                rx = int(st.messages_rx) - refused
            except Exception as exc:  # noqa: BLE001 - a status snapshot must not stop the loop
                self.counter.count("mavlink_loop_error", f"status: {type(exc).__name__}: {exc}")
        self.watchdog.step(
            now,
            frames_in=frames_in,
            mavlink_rx=rx,
            mavlink_refused=refused,
            mavlink_open_error=open_error,
            rejected=self.counter.counts,
            rotation=(self.pose.newest_rotation_time_boot_us(), self.mount.gimballed),
        )
        self.watchdog.autopilot_reboots(now, self.pose.reboots)
        if self.session is not None:
            try:  # (two calls into zenoh every WATCH_PERIOD_S)
                self._zenoh_linked = (
                    len(list(self.session.info.routers_zid())),
                    len(list(self.session.info.peers_zid())),
                )
            except Exception:  # noqa: BLE001 - informational: not known is no warning
                self._zenoh_linked = (None, None)
            if self.config.zenoh.connect:
                routers, peers = self._zenoh_linked
                linked = None if routers is None or peers is None else routers + peers
                self.watchdog.zenoh_links(now, tuple(self.config.zenoh.connect), linked)
        self.watchdog.components(
            now,
            estimator_restarts=int(getattr(self.estimator, "restarts", 0)),
            record=None if self.recorder is None else self.recorder.stats(),
            health_error=self.health_error,
        )
        self.watchdog.load(
            now,
            frames_dropped=self.frames_dropped,
            frames_dropped_bunched=self.frames_dropped_bunched,
            estimates_stale=self.counter.counts.get("estimate_stale", 0),
            cpu_words=self.cpu_load.words(),
            estimator_silent_s=float(getattr(self.estimator, "silent_s", 0.0)),
            quota_bound=self.cpu_load.quota_bound(),
            stalled_s=self._stall[1] if now - self._stall[0] < OVERLOAD_CLEAR_S else 0.0,
        )
        if self.link is not None:
            if self._first_telemetry_s is None and self.pose.newest_time_boot_us() is not None:
                self._first_telemetry_s = now
            self.watchdog.gimbal(
                now,
                gimballed=self.mount.gimballed,
                gimbal_reports=int(getattr(self.link, "gimbal_reports", 0)),
                telemetry_since_s=self._first_telemetry_s,
            )
            self.watchdog.gnss(now, getattr(self.link, "gnss", None))
            slow_streams = getattr(self.link, "slow_streams", None)
            if slow_streams is not None:
                self.watchdog.stream_rates(now, slow_streams())
            duplicate_senders = getattr(self.link, "duplicate_senders", None)
            if duplicate_senders is not None:
                self.watchdog.autopilot_duplicate(now, duplicate_senders())
            self.watchdog.utc(now, self.utc.mapping)
        heard = self._twin_heard
        self.watchdog.name_clash(now, None if heard is None else heard[:2], status_key(self.config.vehicle))
        video = next((t for t in self.taps if isinstance(t, VideoTap)), None)
        if video is not None and video.streamer is not None:
            vc = self.config.video
            self.watchdog.video_rate(now, video.streamer.camera_rate_hz, vc.fps, vc.bitrate_bps)

    def _worker_cpu(self) -> float:
        return getattr(self.estimator, "worker_cpu_s", 0.0)

    def _worker_process_cpu(self) -> float:
        """The estimator's CPU seconds where /proc/self/stat does not hold them: a worker process's (a live child is
        not in it until reaped); a thread worker's are this process's already, and were counted twice."""
        return self._worker_cpu() if self.config.estimator.worker == "process" else 0.0

    def _current_track(self, now: float) -> Track | None:
        return self.newest.current(now, self.config.output.track_stale_s)

    def follow_step(self, now: float) -> bool:
        """FOLLOW_TARGET (#144) to the autopilot when ``follow.enabled``: the newest track's position at
        most every 1 / ``follow.rate_hz`` s, only when it is observable and not stale (an autopilot
        chasing an unobservable range would chase a guess).  Returns True when one was sent."""
        fc = self.config.follow
        if not fc.enabled or self.link is None or now < self._next_follow_s:
            return False
        from onboard.io.follow import follow_target

        target = follow_target(self._current_track(now))
        if target is None:
            return False
        self._next_follow_s = now + 1.0 / fc.rate_hz
        return bool(self.link.send_follow_target(target))

    def camera_step(self, now: float) -> int:
        """The camera component's turn in the main loop: commands in (tracking requests queued to the
        pipeline), the pipeline's decisions ACKed, heartbeat and #275/#276 out, with the autopilot's
        system id (the link's, else ``mavlink.autopilot_sysid``; a ground station ties the camera to
        that vehicle); silent while neither is known (commands read then are dropped, counted
        ``gcs_command_before_system_id``).  Returns
        the number of messages sent."""
        cam, gcs = self.camera, self.gcs
        if cam is None or gcs is None:
            return 0
        sysid = getattr(self.link, "autopilot_sysid", None) or self.config.mavlink.autopilot_sysid
        if sysid is None:
            # read and dropped, not left in the socket: without a system id nothing can be answered, and a command
            # left waiting would be carried out when the autopilot appears, long after its sender gave up on it (a
            # click 10 s old selected where the target no longer is); only broadcast ones reach here (GcsLink.poll)
            for cmd in gcs.poll():
                self.counter.count(
                    "gcs_command_before_system_id",
                    f"command {cmd.command} from {cmd.src_system}/{cmd.src_component} dropped: the autopilot's "
                    "system id is not known yet (mavlink.autopilot_sysid unset, no autopilot locked)",
                    level=logging.INFO,
                )
            return 0
        gcs.set_system_id(sysid)
        # CAMERA_INFORMATION names the gimbal the camera is on: the one the link follows (0: none, or not heard yet)
        cam.gimbal_device_id = (getattr(self.link, "gimbal_device_id", None) or 0) if self.mount.gimballed else 0
        boot_ms = int((now - self._started_s) * 1000)
        track = self._current_track(now)
        sent = 0
        for cmd in gcs.poll():
            out, request = cam.handle(cmd, now, boot_ms, track)
            for msg in out:
                sent += gcs.send(msg) > 0
            if request is not None:
                self.pipeline.request_selection(request, self._selection_results.append)
        while self._selection_results:
            for msg in cam.complete(self._selection_results.popleft()):
                sent += gcs.send(msg) > 0
        for msg in cam.tick(now, track, gcs.links()):  # #275 / #276 on each link's own schedule
            sent += gcs.send(msg) > 0
        return sent

    def status(
        self, now: float | None = None, cpu_share: float | None = None, pipeline_share: float | None = None
    ) -> dict[str, Any]:
        """The ``irtrack.status/1`` dict now (see :func:`onboard.core.track.build_status`)."""
        now = self._clock() if now is None else now
        self._drain_capture_latency()
        counts = self.counter.counts
        link = None
        if self.link is not None:
            st = self.link.status()
            link = {k: getattr(st, k) for k in st.__dataclass_fields__}
        latest = self.newest.value
        with self._stats_lock:
            frames_in, dropped, published = self.frames_in, self.frames_dropped, self.tracks_published
            missing = self.arrival_gaps.missing
        warnings: list[Mapping[str, str]] = list(self.watchdog.active_dicts())
        status = build_status(
            vehicle=self.config.vehicle,
            run_id=self.run_id,
            uptime_s=now - self._started_s,
            frames_in=frames_in,
            frames_processed=self.pipeline.frames_processed,
            frames_dropped=dropped,
            frames_missing=missing,
            frames_rejected=sum(
                v
                for k, v in counts.items()
                if (k.startswith("frame_") and k not in ACCEPTED_FRAME_EVENTS) or k in TRACKER_REFUSALS
            )
            + self.frames_failed,
            tracks_published=published,
            processing_ms=self.pipeline.processing_ms.summary(),
            latency_ms=self.latency_ms.summary(),
            pose_wait_ms=self.pipeline.pose_wait_ms.summary(),
            capture_to_track_ms=self.capture_to_track_ms.summary() if len(self.capture_to_track_ms) else None,
            rejected=counts,
            link=link,
            cpu_share=cpu_share,
            pipeline_cpu_share=pipeline_share,
            last_track=None if latest is None else latest[0],
            last_track_age_s=None if latest is None else max(now - latest[1], 0.0),
            estimator=estimator_label(self.estimator_kind, self.estimator),
            queue_length=len(self.queue),
            queue_wait_ms=self.queue_wait_ms.summary(),
            publish_ms=self.publish_ms.summary(),
            stages_ms={
                "imaging": self.pipeline.imaging_ms.summary(),
                "estimator": self.pipeline.estimator_ms.summary(),
            },
            warnings=warnings,
            withheld_because=self.pipeline.withheld_because,
            zoom=self.pipeline.last_zoom,
            frames_withheld_zoom=self.pipeline.frames_withheld_zoom,
            camera_time_offset=time_offset_section(self.pipeline, self.config),
        )
        status["utc"] = self.utc.status()  # boot clock -> UTC (onboard.core.utc_clock)
        if self.session is not None:
            routers, peers = self._zenoh_linked
            status["zenoh"] = {
                "connect": list(self.config.zenoh.connect),
                "listen": list(self.config.zenoh.listen),
                "config_file": self.config.zenoh.config_file,
                "routers": routers,
                "peers": peers,
            }
        if self.camera is not None:
            status["camera"] = camera_section(self.camera, self.config, self.pipeline)
        for tap in self.taps:
            section = tap.status()
            if section is not None:
                status[tap.name] = section
        return status

    def _drain_capture_latency(self) -> None:
        sync = getattr(self.link, "clock_sync", None)
        while self._done:
            t_boot_us, done_ns = self._done.popleft()
            if sync is None or not sync.synced:
                continue
            boot_us = sync.to_boot_us(done_ns)
            if boot_us is not None:
                self.capture_to_track_ms.add((boot_us - t_boot_us) / 1000.0)

    def _publish_status(self, now: float, last_cpu: tuple[float, float, float]) -> tuple[float, float, float]:
        t0, p0, w0 = last_cpu
        p1, w1 = time.process_time(), self._pipeline_cpu_s + self._worker_cpu()
        wall = max(now - t0, 1e-9)
        status = self.status(now, (p1 - p0) / wall, (w1 - w0) / wall)
        status["cpu"].update(self.cpu_load.sample(now, self._worker_process_cpu()))
        try:
            data = json.dumps(status, separators=(",", ":"), allow_nan=False).encode()
        except (TypeError, ValueError) as exc:
            self.counter.count("status_publish_error", f"{type(exc).__name__}: {exc}")
            return now, p1, w1
        for tap in self.taps:
            tap.on_status(data)
        if self._status_pub is not None:
            try:
                self._status_pub.put(data)
                self.status_count += 1
            except Exception as exc:  # noqa: BLE001
                self.counter.count("status_publish_error", f"{type(exc).__name__}: {exc}")
        return now, p1, w1
