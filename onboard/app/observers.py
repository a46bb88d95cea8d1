"""The daemon's output taps behind one interface, :class:`FrameObserver`: the flight recorder
(``record.path``), the Foxglove live view (``live_view.port``), the H.264 video (``video.destination``) and the
observer guidance (``guidance.advise``; :mod:`onboard.app.guidance_tap`).

:class:`NewestTrack` is one more: it hands the newest track to the main thread (the GCS camera component,
FOLLOW_TARGET).

The service calls every observer at the same few points, whichever taps are configured: ``on_received``
(the zenoh thread, each frame that passed its header checks), ``on_frame`` (the pipeline thread, once per
frame it took, after the track was published), ``on_status`` (the main thread, each status JSON),
``status`` (the observer's section of the status JSON) and ``start`` / ``close``.  None of them blocks
the caller: each tap queues for a thread of its own and drops (and counts) when that thread is behind.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from onboard.app.config import OnboardConfig
from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics
from onboard.core.irframe import IrFrame
from onboard.core.track import Track
from onboard.io.record import NOT_LOOKED_UP

__all__ = [
    "FrameResult",
    "FrameObserver",
    "RecorderTap",
    "LiveViewTap",
    "VideoTap",
    "NewestTrack",
    "make_observers",
    "recording_metadata",
    "frame_objects",
]


@dataclass(frozen=True)
class FrameResult:
    """What became of one frame the pipeline took.

    ``pose_looked_up``: the pipeline asked for the frame's pose (False: refused before the look-up);
    ``pose``: the answer (a :class:`~onboard.core.pose.PoseAt` or None); ``track``: None when the frame was
    refused or failed; ``payload``: the track JSON as published (None when not published); ``objects``: every
    object of the frame as published on ``irtrack/<vehicle>/objects`` (the ``irtrack.objects/1`` dict of
    :func:`frame_objects`; None without the objects image chain or without a track); ``imaging_pose``: the pose
    the image chain got before the telemetry wait, when it asked for one (else
    :data:`~onboard.io.record.NOT_LOOKED_UP`; :meth:`onboard.io.record.RecordingPoseSource.take_lookups`);
    ``withheld_because``: the codes that withheld the frame's line of sight and 3-D position
    (:attr:`~onboard.pipeline.frame_pipeline.FramePipeline.last_withheld`)."""

    received_ns: int
    pose_looked_up: bool
    pose: Any
    track: Track | None
    payload: bytes | None
    objects: dict[str, Any] | None = None
    imaging_pose: Any = NOT_LOOKED_UP
    withheld_because: tuple[str, ...] = ()


def frame_objects(pipeline: Any, track: Track | None) -> dict[str, Any] | None:
    """The ``irtrack.objects/1`` message of the frame ``pipeline``'s image chain just took and ``track`` came of
    (:func:`onboard.imaging.objects.objects_message`, stamped with the frame's capture time and compensation);
    None when the chain tracks one object only (no ``last_objects``) or the frame got no track (refused).  Its lines
    of sight are null where the track's would be for want of a pose or where the pipeline withheld the frame's geometry
    (``last_withheld``): the chain's rotation is then its last one, or one the daemon calls wrong."""
    upd = getattr(pipeline.tracker, "last_objects", None)
    if upd is None or track is None:
        return None
    from onboard.imaging.objects import objects_message

    rays = track.pose_valid and not getattr(pipeline, "last_withheld", ())
    return objects_message(
        upd,
        track.time_boot_us,
        track.time_unix_us,
        track.time_unix_sigma_us,
        track.compensated_us,
        rays,
        getattr(pipeline, "attitude_sigma_rad", 0.0),
        track.run_id,
    )


class FrameObserver(Protocol):
    """An output tap of the frame loop (module docstring)."""

    #: the key of :meth:`status`'s section in the status JSON
    name: str

    def start(self) -> None:
        """Open what the tap writes to; a resource that cannot be had raises :class:`InputError`, one line."""

    def on_received(self, frame: IrFrame, received_ns: int) -> None:
        """A frame as received (zenoh thread)."""

    def on_frame(self, frame: IrFrame, result: FrameResult) -> None:
        """A frame the pipeline took, and what became of it (pipeline thread)."""

    def on_status(self, data: bytes) -> None:
        """The status JSON as published (main thread)."""

    def status(self) -> dict[str, Any] | None:
        """The tap's own counters, for the status JSON (None: no section)."""

    def close(self, timeout_s: float) -> None:
        """Stop, flushing what is queued (after the pipeline thread stopped)."""


class RecorderTap:
    """The flight recorder (:class:`onboard.io.record.FlightRecorder`): frames, pipeline inputs, tracks, status."""

    name = "record"

    def __init__(self, recorder: Any, path: str) -> None:
        self.recorder = recorder
        self._path = path

    def start(self) -> None:
        try:
            self.recorder.start()
        except OSError as exc:
            from onboard.io.record_files import record_path_problem

            # a file where the folder should be, or a folder at the path itself, fails as EEXIST: "File exists"
            # named neither; --check's own words do
            problem = record_path_problem(self._path)
            if problem is not None:
                raise InputError(f"record.path: cannot write {self._path}: {problem}") from None
            raise InputError(f"record.path: cannot write {exc.filename or self._path}: {exc.strerror or exc}") from None

    def on_received(self, frame: IrFrame, received_ns: int) -> None:
        self.recorder.on_frame(frame, received_ns)

    def on_frame(self, frame: IrFrame, result: FrameResult) -> None:
        self.recorder.on_frame_input(
            frame, result.received_ns, result.pose_looked_up, result.pose, result.imaging_pose, result.withheld_because
        )
        if result.track is not None:
            self.recorder.on_track(result.track, result.payload)
        if result.objects is not None:
            self.recorder.on_objects(result.objects, frame.seq)

    def on_status(self, data: bytes) -> None:
        self.recorder.on_status(data)

    def status(self) -> dict[str, Any]:
        return self.recorder.stats()

    def close(self, timeout_s: float) -> None:
        # within the time given: the recorder drops (and counts) what it cannot write by then and finishes the
        # file, rather than outliving the daemon's shutdown budget with a file left without its summary
        self.recorder.close(timeout_s)


class LiveViewTap:
    """The Foxglove WebSocket live view (:class:`onboard.io.live_view.LiveView`)."""

    name = "live_view"

    def __init__(self, live_view: Any) -> None:
        self.live_view = live_view

    def start(self) -> None:
        self.live_view.start()  # a port in use raises InputError, one line

    def on_received(self, frame: IrFrame, received_ns: int) -> None:
        self.live_view.on_frame(frame)

    def on_frame(self, frame: IrFrame, result: FrameResult) -> None:
        self.live_view.on_pose(frame, result.pose)
        if result.track is not None:
            self.live_view.on_track(result.track, result.payload)
        if result.objects is not None:
            self.live_view.on_objects(result.objects)

    def on_status(self, data: bytes) -> None:
        self.live_view.on_status(data)

    def status(self) -> dict[str, Any]:
        return self.live_view.stats()

    def close(self, timeout_s: float) -> None:
        self.live_view.close(timeout_s)


class VideoTap:
    """The IR video with the track and every object overlaid (:class:`onboard.io.video.VideoStreamer`), opened at
    :meth:`start`."""

    name = "video"

    def __init__(self, config: OnboardConfig, intrinsics: PinholeIntrinsics) -> None:
        self._config = config.video
        self._intrinsics = intrinsics
        self.streamer: Any = None

    def start(self) -> None:
        from onboard.io.video import VideoStreamer

        # make_observers adds the tap only for a configured destination (the streamer refuses none)
        self.streamer = VideoStreamer(self._config, self._intrinsics.width_px, self._intrinsics.height_px)

    def on_received(self, frame: IrFrame, received_ns: int) -> None:
        pass

    def on_frame(self, frame: IrFrame, result: FrameResult) -> None:
        if self.streamer is not None and result.track is not None:
            # drops its oldest when behind
            self.streamer.submit(frame.pixels, result.track, frame.time_boot_us, result.objects)

    def on_status(self, data: bytes) -> None:
        pass

    def status(self) -> dict[str, Any] | None:
        return None if self.streamer is None else self.streamer.status()

    def close(self, timeout_s: float) -> None:
        if self.streamer is not None:
            self.streamer.close(timeout_s / 2)


class NewestTrack:
    """The newest track and when it came (on the service's clock), handed to the main thread: the GCS
    camera component's tracking status (#275 / #276), FOLLOW_TARGET and the status JSON's last track
    read it on their own timers.  One reference, replaced whole: no lock needed."""

    name = "newest_track"

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.value: tuple[Track, float] | None = None  # (track, clock() when it came)

    def current(self, now: float, stale_s: float) -> Track | None:
        """The newest track unless older than ``stale_s`` at ``now``."""
        value = self.value
        if value is None or now - value[1] > stale_s:
            return None
        return value[0]

    def start(self) -> None:
        pass

    def on_received(self, frame: IrFrame, received_ns: int) -> None:
        pass

    def on_frame(self, frame: IrFrame, result: FrameResult) -> None:
        if result.track is not None:
            self.value = (result.track, self._clock())

    def on_status(self, data: bytes) -> None:
        pass

    def status(self) -> dict[str, Any] | None:
        return None

    def close(self, timeout_s: float) -> None:
        pass


def recording_metadata(config: OnboardConfig) -> dict[str, str]:
    """The recording's ``irtrack`` metadata: the effective configuration (replay's default), as YAML."""
    import yaml

    from onboard.app.config import config_to_dict

    return {"config_yaml": yaml.safe_dump(config_to_dict(config), sort_keys=False), "vehicle": config.vehicle}


def make_observers(
    config: OnboardConfig, intrinsics: PinholeIntrinsics, clock_ns: Any, clock: Any = None
) -> list[FrameObserver]:
    """The taps ``config`` asks for, in the order their sections appear in the status JSON (video, record,
    live view, guidance) and in which they are started and closed."""
    taps: list[FrameObserver] = []
    if config.video.destination:
        taps.append(VideoTap(config, intrinsics))
    if config.record.path:
        from onboard.io.record import FlightRecorder

        recorder = FlightRecorder(
            config.record,
            vehicle=config.vehicle,
            metadata=recording_metadata(config),
            clock_ns=clock_ns,
        )
        taps.append(RecorderTap(recorder, config.record.path))
    if config.live_view.port is not None:
        from onboard.io.live_view import LiveView

        live = LiveView(config.live_view, vehicle=config.vehicle, intrinsics=intrinsics)
        taps.append(LiveViewTap(live))
    if config.guidance.advise:
        from onboard.app.guidance_tap import make_guidance_tap

        guidance = (
            make_guidance_tap(config, clock_ns=clock_ns)
            if clock is None
            else make_guidance_tap(config, clock, clock_ns)
        )
        if guidance is not None:
            taps.append(guidance)
    return taps
