"""Recording, end to end: a closed-loop run (daemon + simulator on 127.0.0.1, 10 s) recorded by both
(``python -m onboard --record``, ``groundsim run --record``), read with the `mcap` package's reader: channels,
schemas, and message counts match what was sent and received; a SIGKILLed recording daemon leaves a readable file.

The recorded run is the suite's one recorded P1 flight (session fixture ``recorded_p1_flight``, tests/conftest.py),
which the replay tests read too."""

from __future__ import annotations

import base64
import json
import os
import re
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
ONBOARD_CONFIG = REPO / "config" / "onboard_sim.yaml"
READY_TIMEOUT_S = 40.0
SIM_ALLOWANCE_S = 30.0
DURATION_S = 10.0
FRAME_RATE_HZ = 30  # the simulator's camera in P1
DRAIN_TIMEOUT_S = 8.0


@dataclass
class RecordedRun:
    out: Path
    daemon_mcap: Path
    sim_mcap: Path
    tracks: list  # the track dicts received over zenoh, in arrival order
    status: dict | None
    daemon_rc: int | None
    sim_rc: int | None
    config_path: Path
    encodings: set  # zenoh encodings the track and status samples came with


def _start(cmd, log_path: Path, env) -> subprocess.Popen:
    with open(log_path, "wb") as f:
        return subprocess.Popen(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)


def _kill(proc: subprocess.Popen | None, sig=signal.SIGTERM, wait_s: float = 10.0) -> int | None:
    if proc is None:
        return None
    if proc.poll() is None:
        try:
            os.kill(proc.pid, sig)
            proc.wait(wait_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(wait_s)
        except ProcessLookupError:
            pass
    return proc.returncode


def record_pair(
    out: Path,
    *,
    duration_s: float = DURATION_S,
    kill_daemon_when: Callable[[Path], bool] | None = None,
    extra_daemon_args: tuple = (),
) -> RecordedRun:
    """Daemon (worker inline, --record) then simulator (--record, real time) on loopback; returns what they wrote.

    ``kill_daemon_when(daemon_mcap)``: polled while the simulator runs; once true the daemon is SIGKILLed. The
    simulator ending first, or its time allowance passing, fails the calling test: the condition never held."""
    from groundsim.evaluation.demo import (
        TrackStore,
        child_env,
        close_zenoh,
        daemon_command,
        log_tail,
        plan_demo,
        sim_command,
    )
    from onboard.io.zenoh_session import ZenohConfig, open_session, status_key, track_key

    out.mkdir(parents=True, exist_ok=True)
    plan = plan_demo("P1", duration_s, 0, out, str(ONBOARD_CONFIG))
    env = child_env()
    d_mcap, s_mcap = out / "daemon.mcap", out / "sim.mcap"
    dcmd = daemon_command(plan) + ["--record", str(d_mcap), "--set", "estimator.worker=inline", *extra_daemon_args]
    scmd = sim_command(plan) + ["--record", str(s_mcap)]
    store = TrackStore()
    daemon = sim = session = None
    subs: list = []
    daemon_rc = sim_rc = None
    try:
        daemon = _start(dcmd, out / "onboard.log", env)
        session = open_session(ZenohConfig(connect=(plan.zenoh_endpoint,)))
        encodings: set = set()
        subs.append(
            session.declare_subscriber(
                track_key(plan.vehicle),
                lambda s: (encodings.add(str(s.encoding)), store.on_track(s.payload.to_bytes())),
            )
        )
        subs.append(
            session.declare_subscriber(
                status_key(plan.vehicle),
                lambda s: (encodings.add(str(s.encoding)), store.on_status(s.payload.to_bytes())),
            )
        )
        t_ready = time.monotonic() + READY_TIMEOUT_S
        while not store.ready.wait(0.1):
            assert daemon.poll() is None, f"daemon exited {daemon.returncode}:\n{log_tail(out / 'onboard.log')}"
            assert time.monotonic() < t_ready, (
                f"no daemon status within {READY_TIMEOUT_S} s:\n{log_tail(out / 'onboard.log')}"
            )
        sim = _start(scmd, out / "sim.log", env)
        t0 = time.monotonic()
        deadline = t0 + duration_s + SIM_ALLOWANCE_S
        while sim.poll() is None:
            assert daemon.poll() is None, f"daemon crashed {daemon.returncode}:\n{log_tail(out / 'onboard.log')}"
            assert time.monotonic() < deadline, f"simulator stuck:\n{log_tail(out / 'sim.log')}"
            if kill_daemon_when is not None and kill_daemon_when(d_mcap):
                daemon_rc = _kill(daemon, signal.SIGKILL)
                break
            time.sleep(0.05)
        if kill_daemon_when is not None:
            assert daemon_rc is not None, (
                f"never {kill_daemon_when!r} while the simulator ran (rc {sim.returncode}):\n"
                f"{log_tail(out / 'onboard.log')}"
            )
        else:
            assert sim.returncode == 0, f"simulator exited {sim.returncode}:\n{log_tail(out / 'sim.log')}"
            # The daemon drains its queue, and has received every frame sent (its status, once a second, says
            # so): stopped earlier, the last frame may still be on its way to it under the suite's load.
            n_sent = int(duration_s * FRAME_RATE_HZ)
            last = len(store.tracks)
            t_end = time.monotonic() + DRAIN_TIMEOUT_S
            while time.monotonic() < t_end:
                time.sleep(0.3)
                status = store.snapshot()[1] or {}
                frames = status.get("frames", {})
                # a frame lost on the way (zenoh drops a camera's frames rather than delay them) is counted missing
                if len(store.tracks) == last and frames.get("in", 0) + frames.get("missing", 0) >= n_sent:
                    break
                last = len(store.tracks)
    finally:
        close_zenoh(subs, session)
        sim_rc = _kill(sim)
        if daemon_rc is None:
            daemon_rc = _kill(daemon)
    tracks, status = store.snapshot()
    return RecordedRun(out, d_mcap, s_mcap, tracks, status, daemon_rc, sim_rc, plan.onboard_config_path, encodings)


def _messages(path: Path) -> list:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return list(make_reader(f).iter_messages())


def test_closed_loop_recording_has_every_channel_with_its_schema_and_counts(recorded_p1_flight):
    r = recorded_p1_flight
    assert r.daemon_rc == 0 and r.sim_rc == 0
    # typed payloads, as a generic zenoh recorder sees them
    assert r.encodings == {"application/json;irtrack.track/2", "application/json;irtrack.status/1"}
    msgs = _messages(r.daemon_mcap)
    by: dict = {}
    for s, c, m in msgs:
        by.setdefault(c.topic, []).append((s, c, m))
    schemas = {t: (v[0][0].name, v[0][0].encoding, v[0][1].message_encoding) for t, v in by.items()}
    assert schemas == {
        "/mavlink/autopilot": ("irtrack.mavlink_raw/1", "jsonschema", "json"),
        "irtrack/uav1/ir/frame": ("foxglove.RawImage", "protobuf", "protobuf"),
        "/onboard/frame_input": ("irtrack.frame_input/1", "jsonschema", "json"),
        "/onboard/camera_fix": ("foxglove.LocationFix", "protobuf", "protobuf"),
        "irtrack/uav1/track": ("irtrack.track/2", "jsonschema", "json"),
        "/onboard/target_fix": ("foxglove.LocationFix", "protobuf", "protobuf"),
        "irtrack/uav1/status": ("irtrack.status/1", "jsonschema", "json"),
        # the manoeuvres advised while the range was unobservable (guidance.advise), as published
        "irtrack/uav1/guidance": ("irtrack.guidance/1", "jsonschema", "json"),
        # the default (objects) image chain's: every object, the pose it associated with, their overlay
        "irtrack/uav1/objects": ("irtrack.objects/1", "jsonschema", "json"),
        "/onboard/imaging_pose": ("irtrack.imaging_pose/1", "jsonschema", "json"),
        "/onboard/object_annotations": ("foxglove.ImageAnnotations", "protobuf", "protobuf"),
    }
    sim = _messages(r.sim_mcap)
    sim_by: dict = {}
    for _s, c, m in sim:
        sim_by.setdefault(c.topic, []).append(m)
    n_sent = len(sim_by["irtrack/uav1/ir/frame"])
    assert n_sent == int(DURATION_S * 30) and len(sim_by["/groundsim/truth"]) == n_sent
    status = r.status
    frames_in = status["frames_in"] if "frames_in" in status else status["frames"]["in"]
    # the daemon recorded every frame it received (its last words say how many), and one track per track it
    # published (seen by us over zenoh); a frame lost on the way under the suite's load is counted missing
    stopped = re.search(r"stopped: (\d+) frames in, (\d+) missing on the way", (r.out / "onboard.log").read_text())
    assert stopped, (r.out / "onboard.log").read_text()[-3000:]
    received, missing = int(stopped[1]), int(stopped[2])
    assert len(by["irtrack/uav1/ir/frame"]) == received and received + missing <= n_sent
    assert received >= 0.9 * n_sent, (received, missing, n_sent)
    # (the inline estimator's model selections stall the pipeline: the queue drops frames, the recording says which)
    assert len(by["irtrack/uav1/track"]) == len(r.tracks) >= n_sent // 2
    assert [json.loads(m.data) for _, _, m in by["irtrack/uav1/track"]] == r.tracks
    assert len(by["/onboard/frame_input"]) >= len(r.tracks)
    print(f"frames sent {n_sent}, taken by the pipeline {len(by['/onboard/frame_input'])}, tracks {len(r.tracks)}")
    assert frames_in <= n_sent
    # the frames are the ones the simulator sent, byte for byte
    sent = {m.sequence: m.data for m in sim_by["irtrack/uav1/ir/frame"]}
    for _, _, m in by["irtrack/uav1/ir/frame"][::37]:
        assert m.data == sent[m.sequence]
    # MAVLink: the daemon read what the vehicle sent (datagram for datagram, minus any still in flight at the end)
    vehicle = [json.loads(m.data) for m in sim_by["/mavlink/vehicle"]]
    autopilot = [json.loads(m.data) for _, _, m in by["/mavlink/autopilot"]]
    tx = [m["data"] for m in vehicle if m["direction"] == "tx"]
    rx = [m["data"] for m in autopilot if m["direction"] == "rx"]
    # and what the daemon wrote to the autopilot (heartbeats, rate requests, TIMESYNC) is what the vehicle read
    # (the daemon's first heartbeats went out before the simulator started, its last after it stopped)
    ours = [m["data"] for m in autopilot if m["direction"] == "tx"]
    theirs = [m["data"] for m in vehicle if m["direction"] == "rx"]
    assert set(theirs) <= set(ours) and len(theirs) >= DURATION_S
    from onboard.io.mavlink_wire import mavlink2

    parser = mavlink2.MAVLink(None)
    kinds = {parser.decode(bytearray(base64.b64decode(d))).get_type() for d in ours}
    assert {"HEARTBEAT", "COMMAND_LONG", "TIMESYNC"} <= kinds, kinds
    assert set(rx) <= set(tx) and len(rx) >= 0.95 * len(tx)
    rec = json.loads(by["irtrack/uav1/status"][-1][2].data)["record"]
    assert rec["dropped"] == 0 and rec["write_errors"] == 0
    size_mb = r.daemon_mcap.stat().st_size / 1e6
    print(
        f"daemon recording: {len(msgs)} messages, {size_mb:.1f} MB for {DURATION_S:g} s "
        f"({size_mb * 60 / DURATION_S:.0f} MB/min); simulator recording {r.sim_mcap.stat().st_size / 1e6:.1f} MB"
    )


def _readable_frames(path: Path) -> tuple[dict[int, bytes], Exception | None]:
    """The frames (sequence -> RawImage bytes) the independent `mcap` reader reads from the start of ``path``,
    and the error that ended the reading (None: the file ended with its footer)."""
    from mcap.stream_reader import StreamReader

    topics, frames = {}, {}
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f).records:
                name = type(rec).__name__
                if name == "Channel":
                    topics[rec.id] = rec.topic
                elif name == "Message" and topics[rec.channel_id] == "irtrack/uav1/ir/frame":
                    frames[rec.sequence] = rec.data
        except Exception as exc:  # noqa: BLE001 - the end of an unfinished file: whichever error the reader gives
            return frames, exc
    return frames, None


class FramesOnDisk:
    """Kill condition: the file on disk holds at least ``floor`` frames in finished chunks, as the `mcap` reader
    reads them while the daemon still writes (the file is re-read only when it has grown)."""

    def __init__(self, floor: int) -> None:
        self.floor = floor
        self.size = 0
        self.frames_before_kill = 0

    def __call__(self, path: Path) -> bool:
        size = path.stat().st_size if path.exists() else 0
        if size == self.size:
            return False
        self.size = size
        self.frames_before_kill = len(_readable_frames(path)[0])
        return self.frames_before_kill >= self.floor

    def __repr__(self) -> str:
        return f"{self.floor} frames on disk (last read {self.frames_before_kill} in {self.size} bytes)"


def test_sigkilled_recording_daemon_leaves_a_file_readable_up_to_its_last_chunk(tmp_path):
    # The guarantee: finished chunks reach the file while the daemon runs (each ``record.chunk_kb`` or
    # ``record.flush_interval_s``), and a SIGKILL loses only the unfinished one. The kill waits for > 1 s of frames
    # (30 Hz) in finished chunks on disk, not for a wall-clock time: a loaded machine starts the simulator late.
    on_disk = FramesOnDisk(floor=30)
    r = record_pair(tmp_path, duration_s=8.0, kill_daemon_when=on_disk)
    assert r.daemon_rc == -signal.SIGKILL
    frames, ended = _readable_frames(r.daemon_mcap)
    assert ended is not None, "a killed recording has no footer"
    # what was readable before the kill still is (the kill may have let the writer finish one more chunk)
    assert len(frames) >= on_disk.frames_before_kill >= on_disk.floor, (len(frames), on_disk.frames_before_kill)
    # the frames are the ones the simulator sent, byte for byte
    from mcap.reader import make_reader

    with open(r.sim_mcap, "rb") as f:
        sent = {m.sequence: m.data for _s, _c, m in make_reader(f).iter_messages(topics=["irtrack/uav1/ir/frame"])}
    assert frames.keys() <= sent.keys()
    assert all(frames[seq] == sent[seq] for seq in frames)
    print(
        f"SIGKILL once {on_disk.frames_before_kill} frames were on disk: {len(frames)} frames readable, "
        f"ended by {type(ended).__name__}"
    )


def test_every_json_message_conforms_to_the_schema_embedded_in_its_recording(recorded_p1_flight):
    # every key a message has is declared, every required key present, every value of its declared type: the
    # schemas a viewer reads from the file describe the messages beside them (daemon: track, status, frame input,
    # MAVLink; simulator: truth, MAVLink)
    from tests.json_schema_check import check

    seen = set()
    for path in (recorded_p1_flight.daemon_mcap, recorded_p1_flight.sim_mcap):
        for s, c, m in _messages(path):
            if c.message_encoding != "json":
                continue
            assert s.encoding == "jsonschema"
            errors = check(json.loads(m.data), json.loads(s.data))
            assert not errors, (c.topic, errors[:5])
            seen.add(s.name)
    assert seen == {
        "irtrack.track/2",
        "irtrack.status/1",
        "irtrack.guidance/1",
        "irtrack.frame_input/1",
        "irtrack.mavlink_raw/1",
        "irtrack.truth/1",
        # the default (objects) image chain's
        "irtrack.objects/1",
        "irtrack.imaging_pose/1",
    }


def test_log_times_are_the_events_and_sequences_number_every_channel(recorded_p1_flight):
    msgs = _messages(recorded_p1_flight.daemon_mcap)
    by: dict = {}
    for _s, c, m in msgs:
        by.setdefault(c.topic, []).append(m)
    # a frame's input is handed to the recorder before its track (the same thread, in that order): its log time
    # is no later, whenever the writer thread wrote either
    inputs = {m.sequence: m.log_time for m in by["/onboard/frame_input"]}
    tracks = by["irtrack/uav1/track"]
    assert tracks and all(inputs[m.sequence] <= m.log_time for m in tracks)
    # a received frame is logged at its receipt, before the pipeline took it
    received = {m.sequence: m.log_time for m in by["irtrack/uav1/ir/frame"]}
    assert all(received[seq] <= t for seq, t in inputs.items())
    # publish time: the log time (MCAP's rule when the publisher's is not known), on the wall clock
    assert all(m.publish_time == m.log_time for ms in by.values() for m in ms)
    # sequences: the frame's on the frame channels (a fix: its frame's), a count on the others
    for topic in ("/onboard/frame_input", "/onboard/camera_fix", "irtrack/uav1/track"):
        assert [m.sequence for m in by[topic]] == sorted(m.sequence for m in by[topic]), topic
    assert {m.sequence for m in by["/onboard/camera_fix"]} <= set(inputs)
    assert {m.sequence for m in by["/onboard/target_fix"]} <= {m.sequence for m in tracks}
    for topic in ("irtrack/uav1/status", "/mavlink/autopilot"):
        assert [m.sequence for m in by[topic]] == list(range(len(by[topic]))), topic  # nothing dropped
    sim: dict = {}
    for _s, c, m in _messages(recorded_p1_flight.sim_mcap):
        sim.setdefault(c.topic, []).append(m)
    truth = sim["/groundsim/truth"]
    assert [m.sequence for m in truth] == [json.loads(m.data)["seq"] for m in truth] == list(range(len(truth)))
