"""``python -m onboard.replay``: a recorded flight (:mod:`onboard.io.record`) fed again through the pipeline.

    python -m onboard.replay FILE.mcap [FILE.1.mcap ...] [--rate max|realtime] [--jobs 1|2] [--config FILE]
                             [--set FIELD=VALUE]... [--out tracks.jsonl] [--objects-out objects.jsonl] [--compare]
                             [--live-view PORT]

The recording's ``irtrack.frame_input/1`` messages say which frames the daemon's pipeline took, in
which order, and the pose it interpolated for each; the frames themselves are the
``foxglove.RawImage`` messages.  Replay builds a new :class:`~onboard.pipeline.frame_pipeline.FramePipeline` with the
recording's configuration (its ``irtrack`` metadata; ``--config`` replaces it, ``--set`` overrides
fields), the estimator **inline** (lockstep: no worker, no waiting), and feeds it exactly those frames
with exactly those poses.  With the recording's configuration and a daemon that ran the inline
estimator (``estimator.worker: inline``), the tracks come out equal, field for field, to the recorded
ones.  A daemon with a worker (``process``, the default, or ``thread``) used the newest estimate
propagated to a frame's time whenever the worker was late, so its tracks depend on timing and no replay
gives them again: ``--compare`` then says so and also counts the 3-D positions that differ by more than
``SIGMA_GATE`` sigmas of the two estimates' covariances together (:mod:`onboard.app.replay_compare`).  A changed estimator or
tracker shows as differences: ``--compare`` prints them per frame (a regression check on yesterday's
flights).

With the objects image chain (``imaging.chain: objects``) the recording also holds every object of every frame
(``irtrack.objects/1`` on ``irtrack/<vehicle>/objects``): replay makes them again (``--objects-out``), shows them
in the live view (the JSON and the boxes over the frame, as the daemon's live view does) and ``--compare``
compares them frame by frame.  That chain associates objects with each frame's camera rotation, so its tracker
runs in this process (``--jobs 2`` falls back to one: the imaging process has no poses).

The daemon's withholding of a frame's line of sight and 3-D position for its watchdog's warnings (a camera or
gimbal unlike the configuration, two senders on the frame key, a camera clock offset left uncompensated: decided
from its links and clocks) is taken from the frame's ``irtrack.frame_input/1`` (``withheld_because``), so the replay
withholds the same frames and restarts its estimate where the flight's did; a recording from before that field is
replayed as if nothing had been withheld for them.

Not replayed: operator selections (MAVLink camera TRACK_POINT/RECTANGLE/STOP are not recorded as
such), and the pose buffer is not rebuilt from the raw MAVLink (the recorded poses are used).  The UTC stamps
(``time_unix_us``, ``time_unix_sigma_us``: the boot clock mapped through the autopilot's SYSTEM_TIME, not the
pipeline's work) are the recorded track's of the same frame, whatever the replay's configuration; a frame with no
recorded track has none.

Not replayed either: the frames whose ``irtrack.frame_input/1`` the recorder dropped (its backlog full): the file
shows no trace of them, so replay prints the drops the last recorded status counts (:func:`recorder_drops`).

**A rotated recording** (``FILE.mcap``, ``FILE.1.mcap``, ...: ``record.max_file_mb``, ``record.max_file_s``) is one
flight when its files are given in order, ``python -m onboard.replay FILE.mcap FILE.1.mcap FILE.2.mcap``: one pipeline
is fed across them, as the daemon's was, so the tracks go on over the files' boundaries and the outputs and
``--compare`` are the whole flight's (:func:`load_flight`).  The files must be one recording's (its ``recording_id``;
an older recorder's files without one are checked on what they have: :mod:`onboard.app.flight_parts`), each once,
in order, without a gap: else a refusal (exit 2) names the file and what is wrong.  A flight that starts at a later
file (file 0 deleted by ``record.max_files``, or not given) is replayed from a fresh pipeline at that file, while the
daemon's went on from the files before it: its tracks and objects need not be the recorded ones, and replay says so
(:func:`rotated_part_note`).  Giving only ``FILE.mcap`` replays that file only, as asked (quick; file 0's
``--compare`` holds alone): the files after it are not picked up by themselves, but a note names them and the command
line that replays the whole flight (:func:`more_files_note`; a shell's ``FILE.*.mcap`` sorts ``FILE.10`` before
``FILE.2``, which the order check refuses).

``--rate realtime`` paces frames at their recorded receive times; ``max`` (default) runs as fast as
the pipeline goes and prints the speed against real time.  The flight report (plots of a recording) is
the ground side's: ``python -m groundsim report FILE.mcap``.

``--compare`` is a check: it exits 3 when the replay is not the recording's.  With a recording of the inline
estimator that is any frame whose track differs in any field (floats bit for bit), any frame in one of the two only, and any frame of objects that differs or is in one only.  With a
worker's recording, whose estimates no replay gives bit for bit, it is any frame in one only, any frame whose
track follows another object (``track_id``: an operator's selection, which is not replayed, shows so), any 3-D position
beyond ``SIGMA_GATE`` sigmas of the two covariances together and any frame of objects that differs or is in one only
(the image chain does not depend on the estimator's timing).

Exit codes: 0 done (with ``--compare``: the replay is the recording's); 2 a file that is not a readable MCAP
recording, a damaged message in one, a recording without frame inputs, an output file that cannot be written, or
a bad option (one line; the outputs are checked before the replay, so one that cannot be written costs no replay
and nothing is written); 3 ``--compare`` found a difference; 130 interrupted (Ctrl-C or SIGTERM: one line saying
how many frames were replayed and what was written).

A file cut short (a killed daemon) is read up to its last complete chunk (the summary says so); one cut before its
first message is refused, and so is one whose structure is damaged (a record where the MCAP layout has none, a chunk
its message indexes disagree with, a summary that counts other messages or chunks than the file holds:
:mod:`onboard.io.mcap_read`), naming the byte.  A message that does not decode (JSON that does not parse or lacks a
field replay reads, a RawImage that is not one) is refused in one line naming the file, the topic, the message's
index on that topic (from 0) and its log time: a replay that skipped it would not be the flight's (a frame left out
changes every track after it), and the flight report (:func:`load_recording`) refuses it alike.
"""

from __future__ import annotations

from onboard.core.blas import single_thread_blas_env

single_thread_blas_env()  # the replayed pipeline is single-threaded like the daemon's: before numpy is imported

import argparse  # noqa: E402
import collections  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator, Sequence  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from typing import Any  # noqa: E402

from onboard.app.cli_args import (  # noqa: E402
    OneLineParser,
    add_config_option,
    add_live_view_option,
    add_set_option,
    config_overrides,
    help_summary,
    sigterm_as_interrupt,
)
from onboard.app.output_files import same_file_clash  # noqa: E402
from onboard.app.recorded_messages import (  # noqa: E402
    damage_text,
    frame_input_row,
    json_object,
    track_row,
    truth_objects_row,
    truth_row,
    unread_version,
)
from onboard.app.recording import (  # noqa: E402
    Recording,
    more_files_note,
    no_frames_text,
    recorder_drops,
    recorder_drops_note,
    rotated_part_note,
    stopped_note,
)
from onboard.app.replay_compare import (  # noqa: E402
    beyond_a_workers_sigma,
    compare_objects,
    compare_tracks,
    compare_within_sigma,
    print_compare,
)
from onboard.core.errors import InputError, IrtrackError  # noqa: E402
from onboard.core.status import STATUS_SCHEMA  # noqa: E402
from onboard.io.foxglove_messages import OBJECTS_SCHEMA, irframe_from_rawimage  # noqa: E402
from onboard.io.mcap_read import FrameRef, read_recording  # noqa: E402
from onboard.io.pose_json import pose_from_json  # noqa: E402
from onboard.io.record import (  # noqa: E402
    FRAME_INPUT_TOPIC,
    IMAGING_POSE_TOPIC,
    STOPPED_METADATA,
    TRUTH_OBJECTS_TOPIC,
    TRUTH_TOPIC,
)

__all__ = [
    "Recording",
    "load_recording",
    "load_flight",
    "ReplayResult",
    "replay",
    "ReplayProgress",
    "recorded_worker",
    "no_frames_text",
    "recorder_drops",
    "recorder_drops_note",
    "stopped_note",
    "rotated_part_note",
    "more_files_note",
    "main",
]

log = logging.getLogger(__name__)

EXIT_OK, EXIT_ERROR, EXIT_CONFIG, EXIT_INTERRUPTED = 0, 1, 2, 130
PROGRESS_EVERY_S = 5.0  # a progress line on stderr this often: a long replay is never silent, a short one is
#: ``--compare`` found a difference; distinct from 1, which an unexpected error (a traceback) also gives
EXIT_DIFFERENT = 3


def load_recording(path: str) -> Recording:
    """The :class:`Recording` of the MCAP file ``path``.  Every message that replay and the flight report read is
    decoded and checked here, once, for the fields they read: a damaged one raises :class:`InputError` naming the
    file, the topic, the message's index on that topic and its log time.  Damage is refused rather than skipped:
    a replay without the message would not be the flight's.  A file cut short before its first message is refused
    too (nothing to read)."""
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from google.protobuf.message import DecodeError

    meta: dict[str, str] = {}
    frames: dict = {}
    inputs, tracks, truth, objects, truth_objects = [], [], [], [], []
    imaging_poses: dict = {}
    statuses: list = []
    input_log_ns: list = []
    counts: dict[str, int] = {}
    first = last = None
    truncated = None
    stopped = None
    for m in read_recording(path):
        if isinstance(m, dict):
            if "truncated" in m:
                truncated = m["truncated"]
            elif m.get("metadata") == "irtrack" and not meta:
                meta = {k: v for k, v in m.items() if k != "metadata"}
            elif m.get("metadata") == STOPPED_METADATA:
                stopped = {k: v for k, v in m.items() if k != "metadata"}
            continue
        index = counts.get(m.topic, 0)
        counts[m.topic] = index + 1
        first = m.log_time_ns if first is None else first
        last = m.log_time_ns
        unread = unread_version(m.topic, m.schema)
        if unread:
            raise InputError(f"{path}: message {index} on {m.topic} (log time {m.log_time_ns} ns) is of {unread}")
        try:
            if m.schema == "foxglove.RawImage":
                img = RawImage()
                img.ParseFromString(m.data)
                t_us = int(img.timestamp.seconds) * 1_000_000 + int(img.timestamp.nanos) // 1000
                ref = FrameRef(path, m.data_offset, len(m.data), None if m.data_offset is not None else m.data)
                frames.setdefault((m.sequence, t_us), []).append((ref, m.publish_time_ns))
            elif m.topic == FRAME_INPUT_TOPIC:
                inputs.append(frame_input_row(m.data))
                input_log_ns.append(m.log_time_ns)
            elif m.schema == STATUS_SCHEMA:
                json_object(m.data, ())  # shown in a live view as recorded: a JSON object, or damage named here
                statuses.append((m.log_time_ns, bytes(m.data)))
            elif m.schema.startswith("irtrack.track/"):
                tracks.append(track_row(m.data))
            elif m.topic == TRUTH_TOPIC:
                truth.append(truth_row(m.data))
            elif m.topic == TRUTH_OBJECTS_TOPIC:
                truth_objects.append(truth_objects_row(m.data))
            elif m.schema == OBJECTS_SCHEMA:
                objects.append(json_object(m.data, ("time_boot_us", "frame_index")))
            elif m.topic == IMAGING_POSE_TOPIC:
                obj = json_object(m.data, ("seq", "time_boot_us"), pose=True)
                imaging_poses.setdefault((obj["seq"], obj["time_boot_us"]), []).append(obj)
        except (ValueError, DecodeError, KeyError, TypeError, RecursionError, InputError) as exc:
            raise InputError(
                f"{path}: message {index} on {m.topic} (log time {m.log_time_ns} ns) is damaged: {damage_text(exc)}"
            ) from None
    if truncated is not None and not counts:
        raise InputError(f"{path}: file cut short before its first message ({truncated})")
    return Recording(
        path,
        meta,
        frames,
        inputs,
        tracks,
        truth,
        first,
        last,
        truncated,
        counts,
        objects,
        imaging_poses,
        statuses,
        input_log_ns,
        stopped=stopped,
        truth_objects=truth_objects,
    )


def load_flight(paths: str | Sequence[str]) -> Recording:
    """The :class:`Recording` of one flight recorded in the files ``paths`` (a rotated recording's ``FILE.mcap``,
    ``FILE.1.mcap``, ... in that order; one path: :func:`load_recording`'s): every file read as
    :func:`load_recording` reads it, then joined in order -- a frame whose image went into one file and whose
    frame input into the next is found.  InputError naming the file when they are not one recording's files, each
    once, in order, without a gap (:func:`onboard.app.flight_parts.parts_problem`); the first may be a later file
    than file 0 (:func:`rotated_part_note` says so)."""
    from onboard.app.flight_parts import FilePart, parts_problem

    recs = [load_recording(p) for p in ([paths] if isinstance(paths, str) else paths)]
    if len(recs) == 1:
        return recs[0]
    problem = parts_problem(
        [
            FilePart(
                r.path,
                r.metadata,
                int(r.inputs[0]["time_boot_us"]) if r.inputs else None,
                int(r.inputs[-1]["time_boot_us"]) if r.inputs else None,
            )
            for r in recs
        ]
    )
    if problem is not None:
        raise InputError(problem)
    frames: dict = {}
    imaging_poses: dict = {}
    counts: collections.Counter = collections.Counter()
    for r in recs:
        for key, copies in r.frames.items():
            frames.setdefault(key, []).extend(copies)
        for key, poses in r.imaging_poses.items():
            imaging_poses.setdefault(key, []).extend(poses)
        counts.update(r.counts)
    cut = [f"{r.path}: {r.truncated}" for r in recs if r.truncated is not None]
    first_log = [r.first_log_ns for r in recs if r.first_log_ns is not None]
    last_log = [r.last_log_ns for r in recs if r.last_log_ns is not None]
    return Recording(
        recs[0].path,
        recs[0].metadata,
        frames,
        [i for r in recs for i in r.inputs],
        [t for r in recs for t in r.tracks],
        [t for r in recs for t in r.truth],
        first_log[0] if first_log else None,
        last_log[-1] if last_log else None,
        "; ".join(cut) if cut else None,
        dict(counts),
        [o for r in recs for o in r.objects],
        imaging_poses,
        [s for r in recs for s in r.statuses],
        [t for r in recs for t in r.input_log_ns],
        [r.path for r in recs],
        # (a stop ends the recording: only its last file can say one)
        stopped=next((r.stopped for r in reversed(recs) if r.stopped is not None), None),
        truth_objects=[t for r in recs for t in r.truth_objects],
    )


def config_of(rec: Recording, config_path: str | None = None, overrides: dict | None = None):
    """The replay's :class:`OnboardConfig`: ``config_path``, else the recording's metadata; ``overrides``
    (``{path: (value, source)}``) on top; the estimator inline and no recording, whatever they said."""
    import yaml

    from onboard.app.config import build_config, load_config

    ov = dict(overrides or {})
    ov["estimator.worker"] = ("inline", "replay")
    ov["record.path"] = (None, "replay")
    if config_path is not None:
        return load_config(config_path, ov, environ={})
    text = rec.metadata.get("config_yaml")
    if text is None:
        raise InputError(f"{rec.path}: no configuration in its metadata (not a daemon recording?); give --config")
    where = f"{rec.path} (metadata config_yaml)"
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(f"{where}: not YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(raw, dict):
        raise InputError(f"{where}: expected a mapping of configuration sections, got {type(raw).__name__}")
    imaging = raw.get("imaging")
    if isinstance(imaging, dict) and "chain" not in imaging:
        # the effective configuration names every field: one without imaging.chain was recorded before the
        # field existed, by the single chain, which is what replays it (the default has changed since)
        imaging["chain"] = "single"
    for p, (value, _src) in ov.items():
        node = raw
        keys = p.split(".")
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    # an override's error names its option (--set), the rest the recording's metadata
    return build_config(raw, where, {p: src for p, (_v, src) in ov.items()})


def recorded_worker(rec: Recording) -> str | None:
    """Where the recording daemon ran its estimator (``estimator.worker`` of its metadata: ``inline``,
    ``thread`` or ``process``); None when the recording does not say."""
    import yaml

    text = rec.metadata.get("config_yaml")
    if text is None:
        return None
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    estimator = raw.get("estimator") if isinstance(raw, dict) else None
    worker = estimator.get("worker") if isinstance(estimator, dict) else None
    return str(worker) if worker is not None else None


class _RecordedPose:
    """A pose source answering with the pose recorded for the frame being replayed: the image chain's first
    (``irtrack.imaging_pose/1``, when recorded for the frame), then the frame's."""

    def __init__(self, counter: Any) -> None:
        self.pose: Any = None  # the PoseAt recorded for the frame being replayed
        self.counter = counter
        self.origin = None
        self._first: list = []  # the image chain's pose of the frame, answered once

    def set_frame(self, pose: Any, imaging_pose: list | None = None) -> None:
        """The frame's pose and (a one-element list, when recorded) the image chain's."""
        self.pose = pose
        self._first = imaging_pose or []

    def pose_at(self, time_boot_us: int, *args, **kwargs):
        if self._first:
            return self._first.pop()
        return self.pose


@dataclass
class ReplayResult:
    tracks: list  # track dicts (irtrack.track/2) in processing order
    frames_fed: int
    frames_missing: int  # frame_input entries whose frame is not in the file (the recorder dropped it)
    frames_refused: int
    wall_s: float
    flight_s: float
    counts: dict = field(default_factory=dict)
    interrupted: bool = False  # Ctrl-C: the tracks of the frames fed so far
    objects: list = field(default_factory=list)  # irtrack.objects/1 dicts in processing order (objects chain)

    @property
    def speed_x(self) -> float:
        return self.flight_s / self.wall_s if self.wall_s > 0 else math.inf


def _frames_taken(rec: Recording) -> Iterator[tuple[int, dict, Any]]:
    """``(index, frame_input, IrFrame)`` of every frame the recorded pipeline took that is in the file, in order
    (a frame_input whose frame the recorder dropped yields ``(index, frame_input, None)``)."""
    used: dict = {}
    for i, inp in enumerate(rec.inputs):
        key = (int(inp["seq"]), int(inp["time_boot_us"]))
        cands = rec.frames.get(key, [])
        k = used.get(key, 0)
        if k >= len(cands):
            yield i, inp, None
            continue
        used[key] = k + 1
        ref, _rx_ns = cands[k]
        frame = irframe_from_rawimage(key[0], ref.raw_image(), f"{ref.path}: frame seq {key[0]}")
        zoom = inp.get("zoom")  # the RawImage cannot carry IRF1's zoom: frame_input does (absent: not stated)
        yield i, inp, frame if zoom is None else dataclasses.replace(frame, zoom=float(zoom))


class _TappedTracker:
    """The imaging process's tracker: what each ``update`` returned (or the InputError it raised) goes to the pipe."""

    BATCH = 16

    def __init__(self, tracker, conn) -> None:
        self._tracker, self._conn = tracker, conn
        self._batch: list[tuple[str, Any]] = []

    def update(self, pixels):
        try:
            upd = self._tracker.update(pixels)
        except InputError as exc:
            self._put(("error", str(exc)))
            raise
        self._put(("ok", upd))
        return upd

    def _put(self, item) -> None:
        self._batch.append(item)
        if len(self._batch) >= self.BATCH:
            self.flush()

    def flush(self) -> None:
        if self._batch:
            self._conn.send(self._batch)
            self._batch = []


class _PipedTracker:
    """The lockstep process's tracker: answers each ``update`` with the imaging process's result for that frame."""

    def __init__(self, conn) -> None:
        self._conn = conn
        self._pending: collections.deque = collections.deque()

    def update(self, pixels):
        if not self._pending:
            try:
                self._pending.extend(self._conn.recv())
            except EOFError:
                raise IrtrackError("replay: the imaging process ended early (see its error above)") from None
        kind, value = self._pending.popleft()
        if kind == "error":
            raise InputError(value)
        return value


def _imaging_child(rec: Recording, config, conn) -> None:
    """Runs in the forked imaging process: the same admission and tracker over the same frames, no pose, no estimator.
    A Ctrl-C, or a SIGTERM to the group (``timeout``, a job's limit), reaches it with the parent: the parent stops
    it by closing the pipe (the parent's SIGTERM-as-Ctrl-C handler, inherited by the fork, is the parent's alone)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from onboard.core.counters import RejectCounter
    from onboard.pipeline.frame_pipeline import FramePipeline, FrameRejected, make_tracker

    tapped = _TappedTracker(make_tracker(config), conn)
    pipe = FramePipeline(
        config, None, tapped, None, config.pose.geodetic_origin(), counter=RejectCounter(log_interval_s=3600.0)
    )
    frames = _frames_taken(rec)
    try:
        while True:
            try:
                taken = next(frames, None)
            except InputError:
                # a frame that cannot be read from the file: the parent reads the same frame and reports it in
                # its own words; this process sends what it has and stops (no traceback of its own)
                break
            if taken is None:
                break
            _i, inp, frame = taken
            if frame is None:
                continue
            try:
                pipe.process(frame, int(inp["received_ns"]))
            except FrameRejected:
                pass
        tapped.flush()
    except (BrokenPipeError, EOFError, OSError):
        pass  # the parent stopped reading (interrupted, or an error it reports itself)
    finally:
        conn.close()


def _start_imaging_process(rec: Recording, config):
    """Fork the imaging process (the recording is inherited, not copied); None where fork is unsafe or missing:
    other threads running (a live view), or no fork on this platform."""
    import multiprocessing
    import threading

    if threading.active_count() > 1 or "fork" not in multiprocessing.get_all_start_methods():
        return None, None
    ctx = multiprocessing.get_context("fork")
    recv_conn, send_conn = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_imaging_child, args=(rec, config, send_conn), name="irtrack-replay-imaging", daemon=True)
    proc.start()
    send_conn.close()
    return proc, recv_conn


def replay(
    rec: Recording, config, *, rate: str = "max", on_track=None, live=None, jobs: int = 1, on_input=None
) -> ReplayResult:
    """Feed ``rec``'s pipeline inputs through a new FramePipeline (inline estimator); see the module docstring.
    ``live``: an :class:`onboard.io.live_view.LiveView` shown each frame, its pose and track (never waited for).
    ``on_input(n)``: called with the number of the recording's frame inputs taken so far, each one (progress).
    ``jobs=2``: the tracker runs ahead in a forked process (the same admission, the same frames, so the same
    updates; each frame's estimate is still made before the next frame's, in this process): the estimator and the
    imaging overlap on two cores, the tracks are the same (falls back to one process where fork is unsafe, and for
    the objects image chain, which needs each frame's pose)."""
    from onboard.app.observers import frame_objects
    from onboard.core.counters import RejectCounter
    from onboard.core.track import is_run_id, track_to_json
    from onboard.pipeline.frame_pipeline import FramePipeline, FrameRejected, make_estimator, make_tracker

    if jobs not in (1, 2):
        raise InputError(f"replay jobs: expected 1 or 2, got {jobs!r}")
    counter = RejectCounter(log_interval_s=3600.0)
    poses = _RecordedPose(counter)
    wall0 = time.perf_counter()
    proc = conn = None
    if jobs == 2 and config.imaging.chain == "objects":
        log.warning("--jobs 2: the objects image chain needs each frame's pose, so it replays in one process")
    elif jobs == 2 and live is None:
        proc, conn = _start_imaging_process(rec, config)
    tracker = make_tracker(config) if conn is None else _PipedTracker(conn)
    utc_of = _recorded_utc(rec.tracks)
    pipe = FramePipeline(config, poses, tracker, make_estimator(config), config.pose.geodetic_origin(), counter=counter)
    # the recorded run's id: a replay reproduces that run's tracks (a recording is one daemon run; none: older files)
    pipe.run_id = next((t["run_id"] for t in rec.tracks if is_run_id(t.get("run_id"))), None)
    out: list = []
    out_objects: list = []
    chain_used: dict = {}  # (seq, time_boot_us) -> the image chain's poses of that frame used so far
    missing = refused = fed = 0
    rx0 = None
    interrupted = False
    shown_statuses = 0  # the recorded statuses put on the live view so far

    def show_statuses(until_ns: float) -> None:  # the recorded status messages logged before until_ns
        nonlocal shown_statuses
        while shown_statuses < len(rec.statuses) and rec.statuses[shown_statuses][0] <= until_ns:
            if live is not None:
                live.on_status(rec.statuses[shown_statuses][1])
            shown_statuses += 1

    try:
        for i, inp, frame in _frames_taken(rec):
            if on_input is not None:
                on_input(i + 1)
            if live is not None and i < len(rec.input_log_ns):
                show_statuses(rec.input_log_ns[i])
            if frame is None:
                missing += 1
                continue
            where = f"{rec.path}: frame_input {i} pose"
            key = (int(inp["seq"]), int(inp["time_boot_us"]))
            chain_poses, n = rec.imaging_poses.get(key, ()), chain_used.get(key, 0)
            chain_used[key] = n + 1
            chain_pose = [pose_from_json(chain_poses[n]["pose"], where)] if n < len(chain_poses) else None
            poses.set_frame(pose_from_json(inp.get("pose"), where), chain_pose)
            if rate == "realtime":
                rx = int(inp["received_ns"])
                rx0 = rx if rx0 is None else rx0
                ahead = (rx - rx0) / 1e9 - (time.perf_counter() - wall0)
                if ahead > 0:
                    time.sleep(ahead)
            fed += 1
            if live is not None:
                live.on_frame(frame)
            if (codes := inp.get("withheld_because")) is not None:
                # the daemon's watchdog decided these from its links and clocks, which a replay does not have: the
                # frame's geometry is withheld as the flight's was (its own zoom the pipeline decides again)
                pipe.withheld_because = tuple(codes)
            try:
                track = pipe.process(frame, int(inp["received_ns"]))
            except FrameRejected:
                refused += 1
                continue
            finally:
                if live is not None:
                    live.on_pose(frame, poses.pose)
            track = _with_recorded_utc(track, utc_of)
            objects = frame_objects(pipe, track)
            if live is not None:
                live.on_track(track)
                if objects is not None:
                    live.on_objects(objects)
            if objects is not None:
                out_objects.append(json.loads(json.dumps(objects, allow_nan=False)))
            obj = json.loads(json.dumps(track_to_json(track), allow_nan=False))
            out.append(obj)
            if on_track is not None:
                on_track(obj)
        if live is not None:
            show_statuses(math.inf)  # the last ones (the daemon's status as it stopped)
    except KeyboardInterrupt:  # Ctrl-C: what was replayed so far is the result
        interrupted = True
    finally:
        if conn is not None:
            conn.close()
        if proc is not None:
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
                proc.join(5.0)
    wall = time.perf_counter() - wall0
    flight_s = 0.0
    if rec.inputs:
        flight_s = (int(rec.inputs[-1]["received_ns"]) - int(rec.inputs[0]["received_ns"])) / 1e9
    return ReplayResult(out, fed, missing, refused, wall, flight_s, counter.counts, interrupted, out_objects)


def _recorded_utc(tracks: list) -> dict:
    """(seq, time_boot_us) -> the recorded tracks' ``(time_unix_us, time_unix_sigma_us)`` of that frame, in file
    order (a duplicated frame's in turn); frames the daemon had no UTC for are left out."""
    out: dict = {}
    for t in tracks:
        if t.get("time_unix_us") is not None:
            out.setdefault((int(t["seq"]), int(t["time_boot_us"])), collections.deque()).append(
                (int(t["time_unix_us"]), t.get("time_unix_sigma_us"))
            )
    return out


def _with_recorded_utc(track, utc_of: dict):
    """``track`` with the UTC stamp the daemon gave its frame: the boot clock's mapping to UTC comes from the
    autopilot link's SYSTEM_TIME, not from the pipeline, so a replay takes the flight's, whatever its configuration
    (a frame with no recorded track, or none with a stamp, has none)."""
    got = utc_of.get((track.seq, track.time_boot_us))
    if not got:
        return track
    unix_us, sigma_us = got.popleft()
    return track.with_time_unix(unix_us, sigma_us)


# --------------------------------------------------------------------------- entry point


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m onboard.replay",
        description=help_summary(__doc__),
        epilog=f"Exit 0 done (with --compare: no difference); {EXIT_CONFIG} an unreadable or damaged recording, an "
        f"output that cannot be written (checked before the replay) or a bad option; {EXIT_DIFFERENT} --compare found "
        f"a difference; {EXIT_INTERRUPTED} Ctrl-C or SIGTERM.",
    )
    p.add_argument(
        "mcap",
        metavar="FILE.mcap",
        nargs="+",
        help="a recording of python -m onboard --record; several: the files of one rotated recording, replayed as "
        "one flight in the order given (FILE.mcap FILE.1.mcap FILE.2.mcap ...)",
    )
    p.add_argument("--rate", choices=("max", "realtime"), default="max", help="pacing (default: %(default)s)")
    p.add_argument(
        "--jobs",
        type=int,
        choices=(1, 2),
        default=1,
        help="2: the tracker runs ahead in a second process, overlapping the estimator (same tracks; "
        "needs fork, no --live-view and imaging.chain single; default: %(default)s)",
    )
    add_config_option(p, "configuration to replay with (default: the recording's)")
    add_set_option(p, "override a config field; repeatable")
    p.add_argument("--out", metavar="tracks.jsonl", help="write the replayed tracks here, one JSON per line")
    p.add_argument(
        "--objects-out",
        metavar="objects.jsonl",
        help="write every frame's objects (imaging.chain objects: irtrack.objects/1) here, one JSON per line",
    )
    p.add_argument(
        "--compare",
        action="store_true",
        help=f"print the per-frame difference to the recorded tracks (and objects); exit {EXIT_DIFFERENT} when the "
        "replay differs (a worker estimator's recording: positions beyond its sigma; see the module docstring)",
    )
    add_live_view_option(
        p,
        "serve the replay over the Foxglove WebSocket protocol on 127.0.0.1:PORT (onboard/io/live_view.py; "
        "with --rate realtime to watch it as flown)",
    )
    # the flight report moved to the ground side (python -m groundsim report): the old options say where
    p.add_argument("--report", metavar="DIR", help=argparse.SUPPRESS)
    p.add_argument("--truth", metavar="SIM.mcap", help=argparse.SUPPRESS)
    return p


class ReplayProgress:
    """A line on stderr every ``PROGRESS_EVERY_S`` while the replay runs (an hour's flight replays for minutes):
    the frames taken so far (refused and missing ones included) of the recording's, and the rate."""

    def __init__(self, total: int) -> None:
        self.total, self.done = total, 0
        self.t0_s = self.last_s = time.monotonic()

    def __call__(self, done: int) -> None:
        self.done = done
        now_s = time.monotonic()
        if now_s - self.last_s >= PROGRESS_EVERY_S:
            self.last_s = now_s
            share = f" ({100.0 * done / self.total:.0f} %)" if self.total else ""
            rate = done / max(now_s - self.t0_s, 1e-9)
            print(f"replay: {done}/{self.total} frames{share}, {rate:.0f} frames/s", file=sys.stderr, flush=True)


@dataclass
class _Progress:
    """How far a run got, for the line a Ctrl-C prints."""

    frames: int = 0
    written: str = "nothing written"


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.report is not None or args.truth is not None:
        print(
            f"python -m onboard.replay: the flight report moved: python -m groundsim report {' '.join(args.mcap)}",
            file=sys.stderr,
        )
        return EXIT_CONFIG
    progress = _Progress()
    try:
        with sigterm_as_interrupt():  # SIGTERM (timeout, a job's limit) ends it as Ctrl-C does
            return _run(args, progress)
    except KeyboardInterrupt:  # outside the replay loop (which stops by itself): reading the file, writing, comparing
        print(f"interrupted: {progress.frames} frames replayed; {progress.written}", file=sys.stderr)
        return EXIT_INTERRUPTED


def _run(args: argparse.Namespace, progress: _Progress) -> int:
    from onboard.app.config import OnboardConfigError

    try:
        clash = same_file_clash(
            [("--out", args.out), ("--objects-out", args.objects_out)], [("MCAP", path) for path in args.mcap]
        )
        if clash is not None:
            raise InputError(clash)
        for path in (args.out, args.objects_out):
            if path:
                _check_writable(path)
        overrides = config_overrides(args.set)
        rec = load_flight(args.mcap)
        if not rec.inputs:  # nothing to replay; without a cut, the flight report's words (it refuses the file too)
            raise InputError(
                f"{rec.name}: file cut short ({rec.truncated}) before its first irtrack.frame_input message"
                if rec.truncated
                else no_frames_text(rec)
            )
        if not rec.frames:  # the pipeline's inputs without their pixels: a replay would feed nothing and say zeros
            raise InputError(
                f"{rec.name}: {len(rec.inputs)} frames taken by the pipeline and none of their images recorded "
                "(record.frames: false, or every frame dropped by the recorder): nothing to replay"
            )
        config = config_of(rec, args.config, overrides)
    except (OnboardConfigError, IrtrackError) as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    if len(rec.files) > 1:
        print(f"one flight in {len(rec.files)} files of a rotated recording: {', '.join(rec.files)}")
    print(
        f"{rec.name}: {sum(rec.counts.values())} messages, {len(rec.inputs)} frames taken by the pipeline, "
        f"{len(rec.tracks)} recorded tracks"
        + (f", {len(rec.objects)} frames of objects" if rec.objects else "")
        + (f"; file cut short ({rec.truncated}): read to its last chunk" if rec.truncated else "")
    )
    for note in (
        rotated_part_note(rec),
        more_files_note(rec, "python -m onboard.replay"),
        recorder_drops_note(rec),
        stopped_note(rec),
    ):
        if note is not None:
            print(note)
    live = None
    try:
        if args.live_view is not None:
            from onboard.io.live_view import LiveView

            live = LiveView(
                config.live_view,
                port=args.live_view,
                vehicle=config.vehicle,
                intrinsics=config.camera.pinhole(),
            )
            live.start()
            print(f"live view: ws://{live.settings.host}:{live.port}", flush=True)
        res = replay(rec, config, rate=args.rate, live=live, jobs=args.jobs, on_input=ReplayProgress(len(rec.inputs)))
    except IrtrackError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    finally:
        if live is not None:
            live.close()
    progress.frames = res.frames_fed
    if res.interrupted:
        if args.out:
            try:
                _write_tracks(args.out, res.tracks, progress)
                progress.written = f"{args.out}: the {len(res.tracks)} tracks of those frames"
            except InputError as exc:  # still the interruption's one line
                progress.written = str(exc)
        print(f"interrupted: {progress.frames} frames replayed; {progress.written}", file=sys.stderr)
        return EXIT_INTERRUPTED
    try:
        print(
            f"replayed {res.frames_fed} frames ({res.frames_refused} refused, {res.frames_missing} missing from the "
            f"file) -> {len(res.tracks)} tracks in {res.wall_s:.2f} s: "
            f"{res.frames_fed / max(res.wall_s, 1e-9):.0f} frames/s, x{res.speed_x:.1f} real time"
        )
        if args.out:
            _write_tracks(args.out, res.tracks, progress)
            print(f"tracks: {args.out}")
        if args.objects_out:
            _write_tracks(args.objects_out, res.objects, _Progress())
            note = "" if res.objects else "; the objects chain makes them: --set imaging.chain=objects"
            print(f"objects: {args.objects_out} ({len(res.objects)} frames{note})")
    except InputError as exc:  # an output that could be opened before the replay but not written now (disk full)
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    if args.compare:
        return _compare(rec, res)
    return EXIT_OK


def _compare(rec: Recording, res: ReplayResult) -> int:
    """``--compare``: print the differences of the replay to the recording; EXIT_DIFFERENT when it is not the
    recording's (the module docstring says when), else EXIT_OK."""
    diffs, matched, unmatched = compare_tracks(rec.tracks, res.tracks)
    worker = recorded_worker(rec)
    timed = worker is not None and worker != "inline"
    within = compare_within_sigma(rec.tracks, res.tracks) if timed or any(d.d_pos_m for d in diffs) else None
    objects_differ = False
    if rec.objects or res.objects:  # before the tracks' lines, whose summary stays the last line
        n, same, left = compare_objects(rec.objects, res.objects)
        print(f"compare: objects: {same}/{n} frames identical, {n - same} differ, {left} unmatched")
        objects_differ = same < n or left > 0
    print_compare(diffs, matched, unmatched, within, worker)
    if timed:  # its estimates depend on the worker's timing: only positions well beyond the recorded sigma count
        differs = unmatched > 0 or (within is not None and beyond_a_workers_sigma(within))
    else:
        differs = unmatched > 0 or bool(diffs)
    return EXIT_DIFFERENT if differs or objects_differ else EXIT_OK


def _check_writable(path: str) -> None:
    """InputError unless ``path`` opens for writing; the file system is left as it was (a file made to find out
    is removed, an existing one is not truncated), so a replay refused after this check has written nothing."""
    existed = os.path.lexists(path)
    try:
        with open(path, "a", encoding="utf-8"):
            pass
        if not existed:
            os.remove(path)
    except OSError as exc:
        raise InputError(f"{path}: cannot write: {exc.strerror or exc}") from None


def _write_tracks(path: str, tracks: list, progress: _Progress) -> None:
    """The tracks (or objects) as JSON lines (``--out``, ``--objects-out``); InputError when the file cannot be
    written."""
    progress.written = f"{path}: written in part"
    try:
        with open(path, "w", encoding="utf-8") as f:
            for t in tracks:
                f.write(json.dumps(t, separators=(",", ":")) + "\n")
    except OSError as exc:
        raise InputError(f"{path}: cannot write: {exc.strerror or exc}") from None
    progress.written = f"{path}: all {len(tracks)} tracks"


if __name__ == "__main__":
    sys.exit(main())
