"""The daemon: thread-safe pieces in-process, then ``python -m onboard`` end to end on 127.0.0.1.

End to end: the daemon starts first, connecting to a zenoh peer that is not there yet (the test
opens it afterwards), with a pymavlink fake autopilot on UDP and a zenoh publisher of synthetic
frames; tracks and status are read back, bad input of every kind is sent and must show up in the
status counters while tracks keep flowing; SIGTERM must end it with exit code 0 within 2 s.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav  # noqa: E402

from bench.onboard import SyntheticScene  # noqa: E402
from groundsim.io.ports import free_tcp_port, free_udp_port  # noqa: E402
from onboard.app.estimator_worker import ThreadedEstimator  # noqa: E402
from onboard.app.frame_queue import FrameQueue  # noqa: E402
from onboard.app.locked_counter import LockedCounter  # noqa: E402
from onboard.app.shared_pose import SharedPoseBuffer  # noqa: E402
from onboard.core.counters import RejectCounter  # noqa: E402
from onboard.core.errors import InputError  # noqa: E402
from onboard.core.frames import geodetic_from_ned  # noqa: E402
from onboard.core.irframe import decode_irframe  # noqa: E402
from onboard.core.pose import PoseBuffer  # noqa: E402
from onboard.core.status import STATUS_SCHEMA  # noqa: E402
from onboard.core.track import is_run_id, track_from_json  # noqa: E402
from onboard.estimation.sliding import TrackEstimate  # noqa: E402
from tests.fakes import FakeAutopilot, FakeClock, quiet_link_status  # noqa: E402
from tests.integration_helpers import loopback_daemon_command  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
WAIT_S = 5.0  # upper bound of one in-process wait
STOP_BUDGET_S = 2.0  # SIGTERM -> exit, from the issue (enforced by the daemon; the test only guards hangs)
NEVER_S = 3600.0  # a timeout that cannot pass during a test: a wait that ends was woken
CENTROID_TOL_PX = 0.15  # synthetic blob (as test_pipeline): the error measured ~0.01-0.03 px
LOG_LINE = re.compile(r'^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z level=[A-Z]+ logger=\S+ msg=".*"$')


# --------------------------------------------------------------------------- in-process pieces


@pytest.fixture(autouse=True, scope="module")
def _one_blas_thread():
    """The estimator's matrices are small: OpenBLAS threads only spin (20x slower on a loaded 2-core box)."""
    from groundsim.evaluation.parallel import limit_blas_threads

    limit_blas_threads(1)


def test_frame_queue_drops_the_oldest_and_says_so():
    q = FrameQueue(2)
    assert [q.push(i) for i in range(4)] == [0, 0, 1, 1]
    assert [q.pop(0.0), q.pop(0.0), q.pop(0.0)] == [2, 3, None]
    for bad in (0, -1, 2.0, True, None):  # a bool or a float is no length, though Python would take them for one
        with pytest.raises(InputError) as e:
            FrameQueue(bad)
        assert str(e.value) == f"FrameQueue maxlen must be a positive integer, got {bad!r}"


class _SignallingCondition(threading.Condition):
    """A Condition that says when a waiter is about to block (test instrumentation)."""

    def __init__(self, waiting: threading.Event) -> None:
        super().__init__(threading.Lock())
        self.waiting = waiting

    def wait(self, timeout=None):
        self.waiting.set()  # still holding the lock: whoever notifies comes after the wait began
        return super().wait(timeout)


def _pop_in_thread(q: FrameQueue) -> tuple[threading.Thread, list]:
    got: list = []
    th = threading.Thread(target=lambda: got.append(q.pop(NEVER_S)), daemon=True)
    th.start()
    return th, got


def test_frame_queue_pop_wakes_on_push_and_on_close():
    """A pop blocked with an hour's timeout returns the pushed item / None on close: it was woken,
    since its timeout cannot have passed (the join is a hang guard; a pop that is not woken fails it)."""
    q = FrameQueue(4)
    waiting = threading.Event()
    q._cond = _SignallingCondition(waiting)
    for wake, want in ((lambda: q.push("x"), "x"), (q.close, None)):
        waiting.clear()
        th, got = _pop_in_thread(q)
        assert waiting.wait(WAIT_S), "pop never blocked"
        wake()
        th.join(WAIT_S)
        assert not th.is_alive(), "pop was not woken"
        assert got == [want]


def test_locked_counter_counts_exactly_from_many_threads():
    c = LockedCounter(log_interval_s=3600.0)
    threads = [threading.Thread(target=lambda: [c.count("x") for _ in range(2000)]) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert c.counts == {"x": 8000}


def _shared_pose(scene: SyntheticScene):
    counter = RejectCounter()
    buf = PoseBuffer(mount=scene.mount, origin=scene.origin, counter=counter)
    return SharedPoseBuffer(buf), buf


def test_shared_pose_buffer_wait_returns_when_late_telemetry_arrives():
    scene = SyntheticScene()
    shared, buf = _shared_pose(scene)
    t_frame = scene.t_us(10)
    for t, p, v, q in scene.telemetry(t_frame - 100_000, t_frame - 10_000, 50.0):
        shared.add_attitude(t, q)
        shared.add_position_ned(t, p, v)
    assert shared.lookup(t_frame).retry  # the bracket is not there yet

    def late():
        for t, p, v, q in scene.telemetry(t_frame, t_frame + 20_000, 50.0):
            shared.add_attitude(t, q)
            shared.add_position_ned(t, p, v)

    # The telemetry arrives while wait_for waits: its clock is frozen (its hour-long timeout never
    # passes) and its second reading -- taken under the lock, just before it blocks -- starts the
    # sender, which needs that lock, so the samples come after the wait began.
    calls = []
    sender = threading.Thread(target=late, daemon=True)

    def frozen_clock() -> float:
        calls.append(1)
        if len(calls) == 2:
            sender.start()
        return 1000.0

    assert shared.wait_for(t_frame, NEVER_S, clock=frozen_clock) is True
    sender.join(WAIT_S)
    assert len(calls) >= 2, "wait_for returned before it waited: the test did not exercise the wake-up"
    assert shared.pose_at(t_frame) is not None and shared.mount is buf.mount and shared.reboots == 0


def test_shared_pose_buffer_wait_gives_up_after_its_timeout_and_at_once_on_a_gap():
    scene = SyntheticScene()
    shared, _ = _shared_pose(scene)
    t0_us = scene.t_us(0)
    for t, p, v, q in scene.telemetry(t0_us, t0_us + 40_000, 50.0):
        shared.add_attitude(t, q)
        shared.add_position_ned(t, p, v)
    # retry, but nothing comes: it gives up once its clock passes the deadline (a fake clock that
    # reads 0 s, then 1 s: past the 0.05 s timeout without any real time passing)
    readings = iter([0.0, 1.0])
    calls = []

    def stepping_clock() -> float:
        calls.append(1)
        return next(readings)

    assert shared.wait_for(t0_us + 60_000, 0.05, clock=stepping_clock) is False
    assert len(calls) == 2  # the deadline, then the one reading that found it passed
    # beyond the max gap no data can bracket the time: it gives up at once -- with a frozen clock and
    # an hour's timeout, a wait could only end by the hang guard below
    got: list = []
    th = threading.Thread(
        target=lambda: got.append(shared.wait_for(t0_us + 2_000_000, NEVER_S, clock=lambda: 0.0)), daemon=True
    )
    th.start()
    th.join(WAIT_S)
    assert not th.is_alive(), "wait_for waited for telemetry that cannot bracket the time"
    assert got == [False]


def test_shared_pose_buffer_memoises_a_lookup_until_the_next_sample():
    """A frame's wait and its pose_at ask the same question: one look-up serves both, and any new
    sample makes the next look-up fresh (the answer may have changed)."""
    scene = SyntheticScene()
    shared, buf = _shared_pose(scene)
    t0_us = scene.t_us(0)
    samples = list(scene.telemetry(t0_us, t0_us + 60_000, 50.0))
    for t, p, v, q in samples[:-1]:
        shared.add_attitude(t, q, (0.0, 0.0, 0.1))  # body rates: extrapolation allowed
        shared.add_position_ned(t, p, v)
    t_frame = samples[-2][0] + 5_000  # past the newest sample: extrapolated
    first = shared.lookup(t_frame, extrapolate=True)
    assert first.pose is not None and first.pose.extrapolated
    assert shared.lookup(t_frame, extrapolate=True) is first  # memoised
    assert shared.lookup(t_frame) is not first  # another question (interpolation only)
    before = buf.counter["pose_extrapolated"]
    pose = shared.pose_at(t_frame)
    assert pose is not None and pose.extrapolated and buf.counter["pose_extrapolated"] == before + 1  # still counted
    t, p, v, q = samples[-1]
    shared.add_attitude(t, q, (0.0, 0.0, 0.1))
    shared.add_position_ned(t, p, v)
    fresh = shared.lookup(t_frame, extrapolate=True)
    assert fresh is not first and fresh.pose is not None and not fresh.pose.extrapolated  # now bracketed


def test_the_daemons_pose_source_tells_the_pipeline_why_a_pose_is_missing():
    """The pipeline tells a GNSS outage past dead reckoning (the gnss_dropout warning) by the pose source's
    last_miss_reason; the daemon's source is the buffer behind SharedPoseBuffer and RecordingPoseSource, which
    said None whatever the buffer knew."""
    from onboard.core.frames import CameraMount, GeodeticOrigin
    from onboard.io.record import RecordingPoseSource

    buf = PoseBuffer(mount=CameraMount(), origin=GeodeticOrigin(32.0, 118.8, 50.0))
    src = RecordingPoseSource(SharedPoseBuffer(buf))
    for i in range(50):  # 0.5 s of attitude and position, then the position stops for 12 s
        t = 1_000_000 + i * 10_000
        buf.add_attitude(t, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        buf.add_position(t, 32.0, 118.8, 100.0, (1.0, 0.0, 0.0))
    for k in range(1, 1300):
        buf.add_attitude(1_490_000 + k * 10_000, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert src.pose_at(1_490_000 + 12_000_000) is None
    assert src.last_miss_reason == buf.last_miss_reason == "position_extrapolation_limit"


class _SlowEstimator:
    """add() blocks on ``gate`` after the first call; returns an estimate at t with p = (t, 0, 0)."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.gate.set()
        self.adds: list[float] = []
        self.resets = 0

    def add(self, t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        self.gate.wait(WAIT_S)
        self.adds.append(t_s)
        if t_s < 0:
            raise InputError("negative time")
        return TrackEstimate(
            t_s,
            np.array([t_s, 0.0, 0.0]),
            np.array([1.0, 0.0, 0.0]),
            np.eye(3),
            0.01 * np.eye(3),
            True,
            100.0,
            0.01,
            len(self.adds),
            "cv",
        )

    def reset(self):
        self.resets += 1


def test_threaded_estimator_returns_its_own_result_when_fast_and_propagates_when_busy():
    slow = _SlowEstimator()
    counter = LockedCounter()
    te = ThreadedEstimator(slow, counter, result_wait_s=1.0, max_extrapolation_s=2.0)
    try:
        K = SyntheticScene().intrinsics
        e1 = te.add(1.0, (1, 2), K, np.zeros(3), np.array([1.0, 0, 0, 0]))
        assert e1.t_s == 1.0 and e1.p_ned_m[0] == 1.0
        slow.gate.clear()  # the worker is now "re-selecting the model"
        te.result_wait_s = 0.02
        e2 = te.add(1.5, (1, 2), K, np.array([0.0, 0.0, 0.0]), np.array([1.0, 0, 0, 0]))
        # propagated from t = 1.0 at 1 m/s: p = 1.5, cov P + dt^2 V
        assert e2.t_s == 1.5 and e2.p_ned_m[0] == pytest.approx(1.5)
        assert e2.cov_p_ned_m2[0, 0] == pytest.approx(1.0 + 0.25 * 0.01)
        assert e2.range_m == pytest.approx(1.5)  # from the camera at the origin
        assert te.late_results == 1
        p = te.predict(1.6)
        assert p.p_ned_m[0] == pytest.approx(1.6)
        assert te.predict(5.0) is None  # beyond max_extrapolation_s
        slow.gate.set()
        deadline = time.monotonic() + WAIT_S
        while len(slow.adds) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert slow.adds == [1.0, 1.5]  # the late observation was still used
        te.result_wait_s = 1.0
        assert te.add(-1.0, (1, 2), K, np.zeros(3), np.array([1.0, 0, 0, 0])) is None  # refused, counted
        assert counter["estimator_input"] == 1
        te.reset()
        assert te.predict(1.6) is None  # nothing of the old epoch survives a reset
    finally:
        te.close()


def test_a_full_backlog_drops_observations_never_a_queued_reset():
    """A starved worker: the old track's reset, then the new track's frames beyond the backlog. Dropping the
    oldest item dropped the reset, and the new track's rows joined the old window under the new epoch."""
    slow = _SlowEstimator()
    counter = LockedCounter()
    te = ThreadedEstimator(slow, counter, result_wait_s=0.0, max_pending=5)
    try:
        K = SyntheticScene().intrinsics
        p, q = np.zeros(3), np.array([1.0, 0, 0, 0])
        slow.gate.clear()
        te.add(1.0, (1, 2), K, p, q)  # the worker takes it and blocks in it
        deadline = time.monotonic() + WAIT_S
        while te._q and time.monotonic() < deadline:
            time.sleep(0.005)
        te.reset()
        for k in range(6):  # the new track's frames, more than the backlog holds
            te.add(10.0 + k, (1, 2), K, p, q)
        assert counter["estimator_backlog"] == 2
        slow.gate.set()
        deadline = time.monotonic() + WAIT_S
        while len(slow.adds) < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert slow.resets == 1 and slow.adds == [1.0, 12.0, 13.0, 14.0, 15.0]  # the oldest new rows dropped
    finally:
        te.close()


# --------------------------------------------------------------------------- end to end


class Daemon:
    def __init__(self, args: list[str], env: dict) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "onboard", *args],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: list[str] = []
        self.started = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))
            if "onboard service started" in line:
                self.started.set()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(5)


@pytest.fixture
def daemon_env(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("IRTRACK_")}
    env.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return env


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_daemon_end_to_end(tmp_path, daemon_env):
    import zenoh

    from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session, status_key, track_key

    scene = SyntheticScene()
    mport, zport, gport, uport = free_udp_port(), free_tcp_port(), free_udp_port(), free_udp_port()
    alive = tmp_path / "alive"
    from pymavlink import mavutil

    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gport}")  # a ground station listening, as QGC on 14550
    gcs_got: list = []
    # two copies of QGC (the same ids) dialling the camera's udpin endpoint: two links, as MAVLink counts them
    qgcs = [
        mavutil.mavlink_connection(f"udpout:127.0.0.1:{uport}", source_system=255, source_component=190) for _ in "ab"
    ]
    qgc_got: list[list] = [[], []]  # (arrival time, message) per copy
    d = Daemon(
        [
            "--mavlink",
            f"udpin:127.0.0.1:{mport}",
            "--zenoh-connect",
            f"tcp/127.0.0.1:{zport}",
            "--gcs",
            f"udpout:127.0.0.1:{gport}",
            "--gcs",
            f"udpin:127.0.0.1:{uport}",
            "--set",
            f"output.health_file={alive}",
            "--set",
            "output.status_interval_s=0.5",
            "--set",
            "logging.reject_log_interval_s=60",
            "--set",
            "output.unobservable_positions=true",
        ],
        daemon_env,
    )
    session = None
    try:
        assert d.started.wait(45), "daemon did not start:\n" + "\n".join(d.lines)
        # the zenoh peer appears only now: the daemon must have started without it and connect later
        session = open_session(ZenohConfig(listen=(f"tcp/127.0.0.1:{zport}",)))
        tracks: queue.Queue = queue.Queue()
        statuses: queue.Queue = queue.Queue()
        subs = [
            session.declare_subscriber(track_key(), lambda s: tracks.put(s.payload.to_bytes())),
            session.declare_subscriber(status_key(), lambda s: statuses.put(s.payload.to_bytes())),
        ]
        pub = session.declare_publisher(frame_key(), congestion_control=zenoh.CongestionControl.BLOCK)
        ap = FakeAutopilot(mport, scene=scene)

        got_tracks: list = []
        got_status: list = []
        state = {
            "k": 0,
            "next_frame": time.monotonic(),
            "next_tel": time.monotonic(),
            "next_hb": 0.0,
            "tel_n": 0,
            "last_payload": None,
        }

        def drain():
            while not tracks.empty():
                got_tracks.append(track_from_json(tracks.get()))
            while not statuses.empty():
                got_status.append(json.loads(statuses.get()))

        def tick():
            """One 5 ms turn of the fake world: MAVLink pump, heartbeat, telemetry at 50/25 Hz, frames at 30 Hz."""
            now = time.monotonic()
            ap.pump()
            while (m := gcs.recv_match(blocking=False)) is not None:
                gcs_got.append(m)
            for q, got in zip(qgcs, qgc_got):
                while (m := q.recv_match(blocking=False)) is not None:
                    got.append((time.monotonic(), m))
            if now >= state["next_hb"]:
                ap.heartbeat()
                for q in qgcs:  # QGC's own heartbeat, 1 Hz: the udpin endpoint keeps each copy as a peer
                    q.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 4)
                state["next_hb"] = now + 1.0
            if now >= state["next_tel"]:
                t = ap.boot_us()
                ap.attitude(t)
                if state["tel_n"] % 2 == 0:
                    ap.position(t)
                state["tel_n"] += 1
                state["next_tel"] += 0.02
            if now >= state["next_frame"]:
                k = state["k"]
                # the camera sees the scene at its stamp, however late this loop gets round to the frame (under
                # load by tens of ms, while the target crosses the image at ~20 px/s)
                t_us = ap.boot_us()
                payload = scene.payload(k, time_boot_us=t_us, content_us=t_us)
                pub.put(payload)
                state["last_payload"] = payload
                state["k"] += 1
                state["next_frame"] += 1 / 30
            drain()
            time.sleep(0.005)

        def run_until(pred, timeout_s: float, what: str):
            deadline = time.monotonic() + timeout_s
            while not pred():
                assert time.monotonic() < deadline, f"timed out waiting for {what}; daemon log:\n" + "\n".join(
                    d.lines[-30:]
                )
                assert d.proc.poll() is None, "daemon died:\n" + "\n".join(d.lines[-30:])
                tick()

        # 1. tracks flow, with the pose at capture time from the fake autopilot
        # (the objects chain confirms the target over its first 11 frames: "searching" until then, then "tracking")
        run_until(
            lambda: sum(t.pose_valid and t.state == "tracking" for t in got_tracks) >= 20, 30, "20 tracks with a pose"
        )
        good = [t for t in got_tracks if t.pose_valid]
        states = [t.state for t in good]
        first = states.index("tracking")
        assert first <= 11 and all(s == "searching" for s in states[:first]) and set(states[first:]) == {"tracking"}
        good = [t for t in good if t.state == "tracking"]
        assert all(t.vehicle == "uav1" and t.track_id == 1 for t in good)
        for t in good:
            truth = scene.uv((t.time_boot_us - scene.boot_us0) / 1e6)
            assert math.hypot(t.u_px - truth[0], t.v_px - truth[1]) < CENTROID_TOL_PX, (t.seq, t.u_px, t.v_px, truth)
        assert good[-1].origin is not None and abs(good[-1].origin.lat_deg - 32.0) < 0.01

        # 2. bad input of every kind, each survived
        ap.junk()
        t = ap.boot_us()
        ap.send(
            mav.MAVLink_attitude_quaternion_message((t + 1) // 1000, math.nan, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, [0.0] * 4)
        )  # refused by the typed encoder: sent raw
        ap.attitude(t + 2, q=(0.0, 0.0, 0.0, 0.0))
        ap.position(t + 3, 0.0, 0.0, 100.0)  # GNSS dropout

        def put_bad(payload: bytes) -> None:
            """One bad frame, then a turn of the fake world: the camera streams on meanwhile, as a real one would
            (sent all at once, the bad input can hold the good frames back by more than
            input.time_reset_threshold_s on a loaded machine: a clock step, which restarts the estimator)."""
            pub.put(payload)
            tick()

        last = state["last_payload"]
        put_bad(last)  # duplicate
        put_bad(scene.payload(0, seq=1, time_boot_us=scene.boot_us0 + 1))  # out of order (long ago, seq back)
        odd_seq = decode_irframe(last).seq + 100_000  # numbering moving on, stamps wrong: one frame each
        put_bad(scene.payload(0, seq=odd_seq, time_boot_us=decode_irframe(last).time_boot_us + 3_600_000_000))
        put_bad(scene.payload(0, seq=odd_seq + 1, time_boot_us=1000))  # 1 ms after boot
        for _ in range(20):  # repeated: counted 20 times, logged once
            put_bad(np.random.default_rng(5).integers(0, 256, 4000, dtype=np.uint8).tobytes())
        put_bad(last[:-640])  # wrong size
        # too large for input.max_frame_bytes (16 MiB default) but within zenoh's own limit (that + 4 KiB):
        # counted by the daemon; far larger payloads never reach it (zenoh drops them, test_zenoh_limits)
        put_bad(last + bytes(16 * 1024 * 1024 + 1 - len(last)))

        want = {
            "mavlink_bad_data": 1,
            "attitude_not_finite": 1,
            "attitude_zero": 1,
            "position_zero": 1,
            "frame_duplicate": 1,
            "frame_out_of_order": 1,
            "frame_time_ahead": 1,
            "frame_time_behind": 1,
            "frame_magic": 20,
            "frame_size": 1,
            "frame_too_large": 1,
        }

        def counted():
            return got_status and all(got_status[-1]["rejected"].get(k, 0) >= n for k, n in want.items())

        run_until(counted, 20, "the bad input in the status counters")
        n_before = len(got_tracks)
        run_until(lambda: len(got_tracks) >= n_before + 10, 10, "tracks after the bad input")
        assert got_tracks[-1].state == "tracking" and got_tracks[-1].pose_valid
        restarts = {"frame_time_reset", "frame_stream_restart", "frame_sequence_reset"}
        assert not restarts & set(got_status[-1]["rejected"])  # no odd frame restarted the stream or the estimator

        # 3. status document and MAVLink tracking status
        st = got_status[-1]
        assert st["schema"] == STATUS_SCHEMA and st["vehicle"] == "uav1"
        assert st["rejected"]["frame_magic"] == 20 and st["rejected"]["frame_too_large"] == 1
        assert st["frames"]["rejected"] >= 24 and st["frames"]["processed"] >= 20
        assert st["frames"]["in"] >= st["frames"]["processed"] + st["frames"]["rejected"]
        assert st["link"]["state"] == "connected" and st["link"]["autopilot_sysid"] == 1
        # one run: every track and status states its id (a restarted daemon draws another)
        assert is_run_id(st["run_id"]) and {t.run_id for t in got_tracks} == {st["run_id"]}
        # the session as configured, and the one peer it has: this test's session (no router on this loopback)
        assert st["zenoh"]["connect"] == [f"tcp/127.0.0.1:{zport}"] and st["zenoh"]["config_file"] is None
        assert (st["zenoh"]["routers"], st["zenoh"]["peers"]) == (0, 1)
        assert st["processing_ms"]["n"] > 0 and st["processing_ms"]["p50"] > 0
        assert st["latency_ms"]["p50"] is not None and st["cpu"]["share"] is not None
        # what the daemon got (/proc/self/stat + its worker) from the second status on
        assert {"gets_share", "throttled_share", "needs_share", "quota_cores"} <= set(st["cpu"])
        assert st["cpu"]["gets_share"] is None or st["cpu"]["gets_share"] >= 0
        run_until(lambda: got_status[-1]["capture_to_track_ms"] is not None, 10, "TIMESYNC-based capture latency")
        assert 0 < got_status[-1]["capture_to_track_ms"]["p50"] < 1000

        def on_gcs(mtype):
            return [m for m in gcs_got if m.get_type() == mtype]

        run_until(lambda: len(on_gcs("CAMERA_TRACKING_IMAGE_STATUS")) >= 3, 10, "CAMERA_TRACKING_IMAGE_STATUS")
        img = on_gcs("CAMERA_TRACKING_IMAGE_STATUS")[-1]
        assert img.get_srcComponent() == 100 and img.get_srcSystem() == 1  # the camera component of the vehicle
        assert img.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
        assert img.tracking_mode == mav.CAMERA_TRACKING_MODE_RECTANGLE and math.isnan(img.point_x)  # auto: the box
        u_last = got_tracks[-1].u_px / 640
        assert abs((img.rec_top_x + img.rec_bottom_x) / 2 - u_last) < 0.05  # the image moves slowly
        assert any(m.get_type() == "HEARTBEAT" and m.type == mav.MAV_TYPE_CAMERA for m in gcs_got)

        # 3b. per-link rates (mavlink.io message_rates: an interval applies to the link it was set on): copy a stops
        # #275 as QGC does on every stop; copy b, on the same port with the same ids, keeps the default 10 Hz
        def qgc_of(i, mtype, since=0.0):
            return [(t, m) for t, m in qgc_got[i] if m.get_type() == mtype and t >= since]

        run_until(lambda: all(qgc_of(i, "CAMERA_TRACKING_IMAGE_STATUS") for i in (0, 1)), 10, "#275 on both copies")
        t_set = time.monotonic()
        qgcs[0].mav.command_long_send(1, 100, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 275, -1, 0, 0, 0, 0, 0)
        run_until(lambda: qgc_of(0, "COMMAND_ACK", t_set), 5, "SET_MESSAGE_INTERVAL's ACK")
        t_acked = qgc_of(0, "COMMAND_ACK", t_set)[0][0]
        run_until(lambda: time.monotonic() >= t_acked + 1.0, 3, "a second of #275")
        after = [len(qgc_of(i, "CAMERA_TRACKING_IMAGE_STATUS", t_acked)) for i in (0, 1)]
        assert qgc_of(0, "COMMAND_ACK", t_set)[0][1].result == mav.MAV_RESULT_ACCEPTED
        assert after[0] == 0 and after[1] >= 5, f"#275 in the second after a's -1: a {after[0]}, b {after[1]}"
        for i, want_us in ((0, -1), (1, 100_000)):  # GET_MESSAGE_INTERVAL: each copy its own link's
            t_get = time.monotonic()
            qgcs[i].mav.command_long_send(1, 100, mav.MAV_CMD_GET_MESSAGE_INTERVAL, 0, 275, 0, 0, 0, 0, 0, 0)
            run_until(lambda i=i, t=t_get: qgc_of(i, "MESSAGE_INTERVAL", t), 5, "MESSAGE_INTERVAL")
            assert qgc_of(i, "MESSAGE_INTERVAL", t_get)[0][1].interval_us == want_us
        run_until(lambda: got_status[-1]["camera"]["link_intervals"], 5, "the status's link_intervals")
        (own,) = got_status[-1]["camera"]["link_intervals"]
        assert (
            own["link"].startswith(f"udpin:127.0.0.1:{uport} from 127.0.0.1:")
            and own["image_status_interval_s"] is None
        )
        assert got_status[-1]["camera"]["default_image_status_interval_s"] == pytest.approx(0.1)
        assert not ap.got("CAMERA_TRACKING_IMAGE_STATUS")  # the autopilot link carries only what the autopilot needs
        # 4. a 3-D estimate (observable or not: unobservable_positions is on) and its #276
        run_until(lambda: any(t.has_position for t in got_tracks[-5:]), 20, "a track with a 3-D position")
        withpos = [t for t in got_tracks if t.has_position][-1]
        assert withpos.window_frames >= 30 and withpos.origin is not None
        lat, lon, _ = geodetic_from_ned(withpos.p_ned_m, withpos.origin)
        assert abs(float(lat) - withpos.lat_deg) < 1e-9 and abs(float(lon) - withpos.lon_deg) < 1e-9
        run_until(lambda: len(on_gcs("CAMERA_TRACKING_GEO_STATUS")) >= 1, 10, "CAMERA_TRACKING_GEO_STATUS")
        geo = on_gcs("CAMERA_TRACKING_GEO_STATUS")[-1]
        assert abs(geo.lat * 1e-7 - 32.0) < 0.01 and abs(geo.lon * 1e-7 - 118.8) < 0.01
        assert geo.h_acc > 0 and geo.v_acc > 0 and math.isfinite(geo.vel_acc) and geo.dist > 0
        assert alive.exists()
        flood = [ln for ln in d.lines if "frame_magic" in ln]
        assert len(flood) == 1, flood  # no log flood on repeated bad input
        for s in subs:
            s.undeclare()
        pub.undeclare()
    finally:
        if d.proc.poll() is None:
            d.proc.send_signal(signal.SIGTERM)
            try:
                rc = d.proc.wait(STOP_BUDGET_S + 3)  # a hang guard; the budget itself is the daemon's
            except subprocess.TimeoutExpired:
                rc = None
        else:
            rc = d.proc.returncode  # it had exited (crashed) before the SIGTERM: rc says how
        d.stop()
        gcs.close()
        for q in qgcs:
            q.close()
        if session is not None:
            session.close()
    # the 2 s budget is enforced by the daemon itself (onboard.app.main.SHUTDOWN_BUDGET_S): over it,
    # it logs "shutdown took longer" and exits 1 -- so exit 0 without that line is the budget kept
    assert rc == 0, "\n".join(d.lines[-20:])
    assert not any("shutdown took longer" in ln for ln in d.lines), "\n".join(d.lines[-20:])
    assert not alive.exists()  # removed on clean shutdown
    d._reader.join(2)
    assert not any("Traceback" in ln for ln in d.lines), "\n".join(d.lines)
    bad_lines = [ln for ln in d.lines if not LOG_LINE.match(ln)]
    assert not bad_lines, bad_lines  # structured: one line per event
    assert any("signal SIGTERM" in ln for ln in d.lines) and any("onboard service stopped" in ln for ln in d.lines)


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_daemon_exits_2_when_its_zenoh_port_is_taken(daemon_env):
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        proc = subprocess.run(
            loopback_daemon_command(port, "null"),
            cwd=REPO,
            env=daemon_env,
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last == f"zenoh: cannot listen on tcp/127.0.0.1:{port}: port already in use"


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_two_daemons_of_one_vehicle_name_each_warn_name_clash_once_in_log_and_status(daemon_env):
    """Two daemons started as uav1 (a config copied to a second vehicle, a daemon started twice): their tracks and
    statuses interleave on the same keys.  Each says so once, and its status lists it; neither crashes."""
    from onboard.io.zenoh_session import ZenohConfig, open_session, status_key

    zport = free_tcp_port()
    common = ["--set", "output.health_file=null", "--set", "output.status_interval_s=0.5"]
    first = Daemon(
        ["--mavlink", f"udpin:127.0.0.1:{free_udp_port()}", "--zenoh-listen", f"tcp/127.0.0.1:{zport}", *common],
        daemon_env,
    )
    second = None
    session = None
    try:
        assert first.started.wait(45), "first daemon did not start:\n" + "\n".join(first.lines)
        statuses: queue.Queue = queue.Queue()
        session = open_session(ZenohConfig(connect=(f"tcp/127.0.0.1:{zport}",)))
        sub = session.declare_subscriber(status_key(), lambda s: statuses.put(json.loads(s.payload.to_bytes())))
        # alone, its own statuses are not another daemon's
        alone_until = time.monotonic() + 2.0
        while time.monotonic() < alone_until:
            with contextlib.suppress(queue.Empty):
                codes = [w["code"] for w in statuses.get(timeout=0.5)["warnings"]]
                assert "name_clash" not in codes
        second = Daemon(
            [
                "--mavlink",
                f"udpin:127.0.0.1:{free_udp_port()}",
                "--zenoh-connect",
                f"tcp/127.0.0.1:{zport}",
                "--zenoh-listen",
                "tcp/127.0.0.1:0",
                *common,
            ],
            daemon_env,
        )
        assert second.started.wait(45), "second daemon did not start:\n" + "\n".join(second.lines)
        listed = None
        deadline = time.monotonic() + 20.0
        while listed is None and time.monotonic() < deadline:
            with contextlib.suppress(queue.Empty):
                st = statuses.get(timeout=0.5)
                listed = next((w for w in st["warnings"] if w["code"] == "name_clash"), None)
        assert listed is not None, "no status listed name_clash:\n" + "\n".join(first.lines + second.lines)
        assert "irtrack/uav1/status" in listed["message"] and "its status says up" in listed["message"]
        warned_by = lambda d: sum("name_clash: another daemon publishes as this vehicle" in ln for ln in d.lines)  # noqa: E731
        clash_deadline = time.monotonic() + 10.0
        while not (warned_by(first) and warned_by(second)) and time.monotonic() < clash_deadline:
            time.sleep(0.2)
        time.sleep(2.0)  # statuses go on arriving: still one WARNING each
        assert (warned_by(first), warned_by(second)) == (1, 1), "\n".join(first.lines + second.lines)
        assert first.proc.poll() is None and second.proc.poll() is None
        sub.undeclare()
    finally:
        if session is not None:
            session.close()
        first.stop()
        if second is not None:
            second.stop()


CTRL_C_WHILE_STARTING_S = 0.8  # after the launch: importing, or starting the estimator process and its fork server


@pytest.mark.integration
@pytest.mark.timeout(60)
@pytest.mark.parametrize("when", ["starting", "serving"])
def test_ctrl_c_stops_the_daemon_cleanly_whenever_it_comes(daemon_env, when):
    """A terminal's Ctrl-C is SIGINT to the whole process group (the daemon, its fork server, its estimator
    process): exit 0, one line saying what happened, no traceback from any of them."""
    proc = subprocess.Popen(
        loopback_daemon_command(free_tcp_port(), "null"),
        cwd=REPO,
        env=daemon_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as in a terminal
    )
    try:
        if when == "starting":
            time.sleep(CTRL_C_WHILE_STARTING_S)
        else:
            assert proc.stderr is not None
            for line in proc.stderr:
                if "onboard service started" in line:
                    break
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=STOP_BUDGET_S + 10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "signal SIGINT while starting: stopped before serving" in err or "signal SIGINT: shutting down" in err, err


def _group_members(pgid: int, word: str) -> set[int]:
    """The live (not zombie) processes of process group ``pgid`` whose command line holds ``word``."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
            cmdline = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z" and word in cmdline:
            found.add(int(stat.parent.name))
    return found


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_sigterm_as_the_daemon_starts_serving_leaves_no_process_behind(daemon_env):
    """The estimator's first worker is spawned while the daemon starts, its fork server still importing when the daemon
    serves: a SIGTERM then stops the daemon cleanly, within its budget, and nothing of the daemon's runs on.  (A fork
    server that serves takes 0.6-0.9 s of interpreter teardown after the daemon's exit, as it did before; one still
    importing hears neither that exit nor a Ctrl-C until its imports are done: the daemon SIGKILLs it, which
    tests/onboard/test_worker_restart.py checks where it would otherwise run on.)"""
    proc = subprocess.Popen(
        loopback_daemon_command(free_tcp_port(), "null"),
        cwd=REPO,
        env=daemon_env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: what it leaves is found there
    )
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            if "onboard service started" in line:
                break
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(STOP_BUDGET_S + 5) == 0
        t_end = time.monotonic() + STOP_BUDGET_S
        while _group_members(proc.pid, "") and time.monotonic() < t_end:
            time.sleep(0.05)
        assert _group_members(proc.pid, "") == set()
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        for pid in _group_members(proc.pid, ""):
            os.kill(pid, signal.SIGKILL)
    assert "Traceback" not in err, err


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_a_daemon_whose_estimator_process_cannot_start_exits_1_in_one_line(tmp_path, daemon_env):
    """An estimator worker process that cannot be started (here its fork server exits as it starts) ends the daemon
    with exit code 1 and one line that says so, not a traceback: the worker is spawned while the daemon starts, and
    its failure is found by the main loop (it raised from the service's constructor, unhandled, before)."""
    (tmp_path / "sitecustomize.py").write_text(
        "import os\n"
        "with open('/proc/self/cmdline', 'rb') as f:\n"
        "    if b'multiprocessing.forkserver import main' in f.read():\n"
        "        os._exit(3)  # the fork server, as it starts\n"
    )
    env = {**daemon_env, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO), daemon_env.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        loopback_daemon_command(free_tcp_port(), "null"), cwd=REPO, env=env, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    said = [line for line in proc.stderr.splitlines() if "estimator process could not be started" in line]
    assert len(said) == 1 and "level=ERROR" in said[0], proc.stderr


def test_the_main_loop_ends_on_an_estimator_that_could_not_be_started():
    """OnboardService._check_estimator_start, each watchdog turn of the main loop: the estimator's start_error, once
    set, becomes EstimatorStartError naming it; none while the first worker is there or still starting."""
    import types

    from onboard.app.estimator_worker import EstimatorStartError
    from onboard.app.service import OnboardService

    service = types.SimpleNamespace(estimator=types.SimpleNamespace(start_error=None))
    OnboardService._check_estimator_start(service)  # type: ignore[arg-type]
    service.estimator.start_error = ConnectionRefusedError("fork server gone")
    with pytest.raises(EstimatorStartError, match="could not be started: ConnectionRefusedError: fork server gone"):
        OnboardService._check_estimator_start(service)  # type: ignore[arg-type]


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_process_estimator_gives_the_inline_estimates_when_it_keeps_up():
    """Same observations, same answers: the child process runs the same deterministic estimator."""
    from onboard.app.config import OnboardConfig
    from onboard.app.estimator_worker import ProcessEstimator
    from onboard.pipeline.frame_pipeline import make_estimator

    scene = SyntheticScene()
    N_FRAMES = 120  # 4 s: the window keeps a row per 0.06 s, min_frames 30 of them before the first estimate
    cfg = OnboardConfig()
    inline = make_estimator(cfg)
    counter = LockedCounter()
    pe = ProcessEstimator(cfg, counter, result_wait_s=30.0)  # wait as long as it takes: no propagation
    try:
        K = scene.intrinsics
        n_same = 0
        for k in range(N_FRAMES):
            ts = k / 30.0
            p_cam, q = scene.camera(ts)
            uv = scene.uv(ts) + 0.2 * np.sin(np.array([k, 2.0 * k]))
            t_s = scene.t_us(k) / 1e6
            a = inline.add(t_s, uv, K, p_cam, q)
            b = pe.add(t_s, uv, K, p_cam, q)
            assert (a is None) == (b is None)
            if a is not None:
                assert np.array_equal(a.p_ned_m, b.p_ned_m) and np.array_equal(a.cov_p_ned_m2, b.cov_p_ned_m2)
                n_same += 1
        assert n_same >= 10 and pe.late_results == 0 and counter.total == 0
        assert pe.worker_cpu_s > 0
        p = pe.predict(scene.t_us(N_FRAMES - 1) / 1e6 + 0.1)
        assert p is not None and p.p_ned_m[0] == pytest.approx(b.p_ned_m[0] + 0.1 * b.v_ned_mps[0])
        pe.reset()
        assert pe.predict(scene.t_us(N_FRAMES - 1) / 1e6) is None
        assert pe.add(1.0, (1.0, 2.0), K, np.zeros(3), np.array([1.0, 0, 0, 0])) is None  # a fresh window
        pe._proc.kill()  # a dead worker is noticed, counted and restarted
        pe._proc.join(5)
        assert pe.add(2.0, (1.0, 2.0), K, np.zeros(3), np.array([1.0, 0, 0, 0])) is None
        assert counter["estimator_restart"] == 1 and counter["estimator_error"] == 0 and pe.restarts == 1
    finally:
        pe.close()


# --------------------------------------------------------------------------- warnings and #276 policy (no sockets)


class _FakeLink:
    autopilot_sysid = 1
    open_error = None  # MavlinkLink.open_error: the connection is open

    def __init__(self) -> None:
        self.rx = 0
        self.geo: list[dict] = []

    def status(self):
        return quiet_link_status("connected" if self.rx else "waiting", autopilot_sysid=1, messages_rx=self.rx)

    def send_tracking_image_status(self, **kw) -> None:
        pass

    def send_tracking_geo_status(self, **kw) -> None:
        self.geo.append(kw)


def _quiet_service(overrides=None):
    from onboard.app.config import build_config
    from onboard.app.service import OnboardService

    cfg = build_config(
        {
            "estimator": {"enabled": False},
            "output": {"health_file": None},
            "zenoh": {"connect": ["tcp/10.1.2.3:7447"]},
            "mavlink": {"connection": "udpin:0.0.0.0:14999"},
            **(overrides or {}),
        }
    )
    clock = FakeClock()
    svc = OnboardService(cfg, clock=clock, clock_ns=clock.ns)
    svc.link = _FakeLink()
    return svc, clock


def test_a_daemon_stopping_while_guidance_commands_the_vehicle_sends_zero_velocity_before_the_link_closes():
    """SIGTERM while sending setpoints left the last one flying (ArduCopter: for its 3 s timeout)."""
    import types

    svc, clock = _quiet_service({"guidance": {"enabled": True}, "estimator": {"enabled": True, "worker": "inline"}})
    tap = next(t for t in svc.taps if hasattr(t, "halt"))
    sent: list = []
    order: list = []
    svc.link.state, svc.link.autopilot_mode, svc.link.home_alt_amsl_m = "connected", (3, 129, 4), 0.0
    svc.link.send_setpoint = lambda v: sent.append(np.asarray(v)) or order.append("setpoint") or True
    svc.link.close = types.MethodType(lambda self: order.append("close"), svc.link)
    tap.gate.state = "sending"  # commanding the vehicle as the daemon is told to stop
    svc.close(timeout_s=0.5)
    assert len(sent) == 1 and not sent[0].any() and order[:2] == ["setpoint", "close"]
    assert tap.status()["setpoints"]["state"] == "stopped" and tap.gate.why.startswith("shutdown")


def test_the_main_loop_wakes_for_the_next_guidance_setpoint(monkeypatch):
    """The loop's idle wait counted follow's next time, not guidance's: each setpoint could be up to
    MAIN_LOOP_MAX_IDLE_S late (PX4 at 2.1 Hz: 3 of 33 gaps over the 0.5 s it takes as the stream lost)."""
    import socket
    import types

    import onboard.app.service as service_module

    svc, clock = _quiet_service({"guidance": {"enabled": True}, "estimator": {"enabled": True, "worker": "inline"}})
    timeouts: list = []
    select_stub = types.SimpleNamespace(select=lambda r, w, x, timeout: timeouts.append(timeout) or ([], [], []))
    monkeypatch.setattr(service_module, "select", select_stub)
    quiet, other = socket.socketpair()
    try:
        svc.link.fileno = quiet.fileno
        svc.link.seconds_to_next_due = lambda: 10.0
        tap = next(t for t in svc.taps if t.name == "guidance")
        tap._next_setpoint_s = clock() + 0.02
        svc._idle(clock(), 0.005, clock() + 10.0)
        assert timeouts == [pytest.approx(0.02)]
    finally:
        quiet.close()
        other.close()


def test_a_liveness_file_that_cannot_be_touched_is_a_warning_in_the_status(tmp_path):
    svc, clock = _quiet_service()
    svc._health_path = str(tmp_path / "gone" / "alive")  # its folder removed under the daemon
    svc._touch_health()
    svc._watch(clock())
    codes = [w["code"] for w in svc.status(clock())["warnings"]]
    assert "health_file" in codes and svc.health_error.endswith("No such file or directory")
    (tmp_path / "gone").mkdir()
    svc._touch_health()
    svc._watch(clock())
    assert "health_file" not in [w["code"] for w in svc.status(clock())["warnings"]]


def test_an_autopilot_reboot_reaches_the_status_warnings():
    """The pose buffer's reboot (the attitude's boot clock back, confirmed by three samples) is in the status."""
    svc, clock = _quiet_service()
    for k in range(20):  # 10 s of boot time, then the clock back near its start
        assert svc.pose.add_attitude(10_000_000 + 20_000 * k, [1.0, 0.0, 0.0, 0.0])
    svc._watch(clock())
    assert "autopilot_rebooted" not in [w["code"] for w in svc.status(clock())["warnings"]]
    for k in range(3):
        svc.pose.add_attitude(300_000 + 20_000 * k, [1.0, 0.0, 0.0, 0.0])
    assert svc.pose.reboots == 1
    svc._watch(clock())
    assert "autopilot_rebooted" in [w["code"] for w in svc.status(clock())["warnings"]]


def test_a_gimbal_under_a_fixed_mount_withholds_the_very_next_frames_direction():
    """The watchdog warns gimbal_mismatch at its 2 Hz turn; a frame processed before it must not carry a line of
    sight made without the gimbal (a newcomer's fixed-mount daemon against a gimballed simulator published two)."""
    from onboard.core.irframe import IrFrame

    svc, clock = _quiet_service()
    assert not svc.mount.gimballed and svc.pipeline.withheld_because == ()
    frame = IrFrame(seq=0, time_boot_us=1000, pixels=np.zeros((512, 640), np.uint8))
    svc._process(frame, clock.ns())
    assert svc.pipeline.withheld_because == ()  # no gimbal reported: nothing withheld
    svc.link.gimbal_reports = 1
    svc._process(IrFrame(seq=1, time_boot_us=34_333, pixels=frame.pixels), clock.ns())
    assert svc.pipeline.withheld_because == ("gimbal_mismatch",)
    assert [w.code for w in svc.watchdog.active] == []  # before the watchdog's own turn
    svc._watch(clock())
    assert "gimbal_mismatch" in [w.code for w in svc.watchdog.active]


def test_a_camera_clock_offset_not_compensated_withholds_direction_and_position_while_its_warning_holds():
    """A constant -300 ms (beyond time_offset.max_offset_ms, never compensated) was warned, and its 3-D positions went
    out 270 m off at a Mahalanobis d^2 up to 4495 against their own covariance.  Withheld while warned and not
    compensated; a compensation that covers it, or the warning's clearing, publishes again."""
    from onboard.core.irframe import IrFrame
    from onboard.estimation.time_offset import TimeOffsetEstimate, TimeOffsetEstimator

    svc, clock = _quiet_service()
    svc.pipeline.time_offset = offset = TimeOffsetEstimator()
    pixels = np.zeros((512, 640), np.uint8)
    seq = 0

    def frame_with(estimate_ms: float, sigma_ms: float, compensated_ms: float) -> tuple[str, ...]:
        nonlocal seq
        offset.estimate = TimeOffsetEstimate(estimate_ms, sigma_ms, "confident", compensated_ms, 3, 240, 0, 5.0)
        clock.t_s += 1 / 30
        svc._process(IrFrame(seq=seq, time_boot_us=1000 + 33_333 * seq, pixels=pixels), clock.ns())
        seq += 1
        return svc.pipeline.withheld_because

    assert frame_with(-300.0, 10.0, 0.0) == ()  # the warning is raised after this frame
    assert "camera_time_offset" in [w.code for w in svc.watchdog.active]
    assert frame_with(-300.0, 10.0, 0.0) == ("camera_time_offset",)
    assert svc.status(clock())["geometry"]["withheld_because"] == ["camera_time_offset"]
    assert "withheld" in next(w.message for w in svc.watchdog.active if w.code == "camera_time_offset")
    assert frame_with(-300.0, 10.0, -295.0) == ()  # compensated (the warning still says so): published
    assert "withheld" not in next(w.message for w in svc.watchdog.active if w.code == "camera_time_offset")
    assert frame_with(-250.0, 10.0, -295.0) == ("camera_time_offset",)  # the offset moved off the compensation
    # hysteresis: withheld until at most half the threshold (20 ms) is left, not released at 19 and taken at 21 again
    assert frame_with(-280.0, 10.0, -295.0) == ("camera_time_offset",)  # 15 ms left: still withheld
    assert frame_with(-286.0, 10.0, -295.0) == ()  # 9 ms left: published
    assert frame_with(-280.0, 10.0, -295.0) == ()  # 15 ms again: not withheld until 20 are left
    assert frame_with(5.0, 2.0, 0.0) == () and svc.watchdog.active == ()  # back: nothing off, the warning cleared


def test_two_senders_on_the_frame_key_withhold_direction_and_position_while_warned():
    """Two numberings interleaving on the key (a second camera, or another vehicle's publishing under this one's name):
    frame_sources is warned, and no line of sight goes out while it holds -- none of the frames is known to come
    from the configured camera, its mount and intrinsics.  One numbering again: published after the warning clears."""
    from onboard.core.irframe import IrFrame

    svc, clock = _quiet_service()
    pixels = np.zeros((512, 640), np.uint8)
    svc._watch(clock())  # the watchdog's turn, every 0.5 s in the daemon
    for k in range(12):  # the configured camera at 100.., another at 5000.., alternating
        svc.arrival_gaps.see(100 + k)
        svc.arrival_gaps.see(5000 + k)
        clock.t_s += 1 / 15
        if k % 4 == 3:
            svc._watch(clock())
    assert "frame_sources" in [w.code for w in svc.watchdog.active]
    svc._process(IrFrame(seq=112, time_boot_us=1000, pixels=pixels), clock.ns())
    assert svc.pipeline.withheld_because == ("frame_sources",)
    assert "withheld" in next(w.message for w in svc.watchdog.active if w.code == "frame_sources")
    for k in range(13, 200):  # the other sender gone: one numbering, past the warning's clearing time
        svc.arrival_gaps.see(100 + k)
        clock.t_s += 1 / 30
        if k % 15 == 0:
            svc._watch(clock())
    svc._watch(clock())
    svc._process(IrFrame(seq=300, time_boot_us=2_000_000, pixels=pixels), clock.ns())
    assert "frame_sources" not in [w.code for w in svc.watchdog.active] and svc.pipeline.withheld_because == ()


def test_frames_stating_a_2x_zoom_withhold_direction_and_position_from_the_first_and_the_status_says_so(caplog):
    """IRF1's zoom field through the daemon's own frame path (decode, _process, watchdog, status): a P1-like
    sequence whose frames state 2x from frame 10 to 19 and 1.0 again after."""
    import dataclasses

    from onboard.core.irframe import encode_irframe
    from tests.onboard.test_pipeline import FakeEstimator

    scene = SyntheticScene()
    o = scene.origin
    origin = {"lat_deg": o.lat_deg, "lon_deg": o.lon_deg, "alt_m": o.alt_m}
    svc, clock = _quiet_service({"imaging": {"chain": "single"}, "pose": {"wait_ms": 0, "origin": origin}})
    svc.pipeline.estimator = FakeEstimator(scene, ready_after=3)  # the true target: positions from frame 3
    fed_us = scene.t_us(0) - 100_000
    tracks, statuses = [], []
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for k in range(30):
            t_hi = scene.t_us(k) + 45_000
            for t, p, v, q in scene.telemetry(fed_us + 1, t_hi, 50.0):
                svc.pose.add_attitude(t, q)
                svc.pose.add_position_ned(t, p, v)
            fed_us = t_hi
            clock.t_s += 1 / 30
            payload = encode_irframe(dataclasses.replace(scene.frame(k), zoom=2.0 if 10 <= k < 20 else 1.0))
            tracks.append(svc._process(decode_irframe(payload), clock.ns()))
            statuses.append(svc.status(clock())["geometry"])
    assert all(tr.los is not None for tr in tracks[:10]) and tracks[9].has_position
    assert all(tr.los is None and not tr.has_position and tr.u_px is not None for tr in tracks[10:20])
    assert all(tr.los is not None for tr in tracks[20:]) and tracks[-1].has_position
    assert statuses[9] == {"output": "published", "withheld_because": [], "zoom": 1.0, "frames_withheld_zoom": 0}
    assert statuses[10] == {
        "output": "withheld",
        "withheld_because": ["zoom_mismatch"],
        "zoom": 2.0,
        "frames_withheld_zoom": 1,
    }
    assert statuses[-1] == {"output": "published", "withheld_because": [], "zoom": 1.0, "frames_withheld_zoom": 10}
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name.endswith("watchdog")]
    assert len(warned) == 1 and warned[0].startswith("zoom_mismatch: IR frames state a zoom of 2x")
    assert svc.status(clock())["warnings"] == []  # cleared by the frames back at 1.0


def test_service_warns_once_about_no_frames_and_no_mavlink_naming_what_to_check(caplog):
    svc, clock = _quiet_service()
    svc.watchdog.restart(clock())
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for _ in range(200):  # 20 s of the main loop's checks
            clock.t_s += 0.1
            svc._watch(clock())
    warned = [
        r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == "onboard.app.watchdog"
    ]
    assert len(warned) == 2
    assert any("irtrack/uav1/ir/frame" in m and "tcp/10.1.2.3:7447" in m for m in warned)
    assert any("udpin:0.0.0.0:14999" in m for m in warned)
    codes = [w["code"] for w in svc.status(clock())["warnings"]]
    assert sorted(codes) == ["no_frames", "no_mavlink"]
    svc.link.rx = 5
    with svc._stats_lock:
        svc.frames_in = 1
    svc._watch(clock())
    assert svc.status(clock())["warnings"] == []


def test_service_frame_of_another_size_is_warned_with_both_sizes(caplog):
    from onboard.core.irframe import IrFrame

    svc, clock = _quiet_service()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for k in range(4):  # input.queue_length
            svc.queue.push((IrFrame(seq=k, time_boot_us=1000 + k, pixels=np.zeros((256, 320), np.uint8)), clock.ns()))
        t = threading.Thread(target=svc._pipeline_loop)  # the service's own frame loop
        t.start()
        deadline = time.monotonic() + 10.0
        while svc.counter["frame_dims_mismatch"] < 4 and time.monotonic() < deadline:
            svc._pipe_stop.wait(0.01)
        svc._pipe_stop.set()
        svc.queue.close()
        t.join(10)
    warned = [
        r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == "onboard.app.watchdog"
    ]
    assert len(warned) == 1 and "320 x 256" in warned[0] and "640 x 512" in warned[0]
    assert svc.counter["frame_dims_mismatch"] == 4
    assert [w["code"] for w in svc.status(clock())["warnings"]] == ["frame_size"]


# #276 only for observable positions: tests/onboard/test_selection.py (through the camera component)


class _TapRecorder:
    """A FrameObserver that remembers what the service handed it."""

    name = "test_tap"

    def __init__(self) -> None:
        self.received: list[int] = []
        self.frames: list[tuple[int, bool]] = []  # (seq, with a track)
        self.status_payloads: list[bytes] = []

    def start(self) -> None:
        pass

    def on_received(self, frame, received_ns: int) -> None:
        self.received.append(frame.seq)

    def on_frame(self, frame, result) -> None:
        self.frames.append((frame.seq, result.track is not None))

    def on_status(self, data: bytes) -> None:
        self.status_payloads.append(data)

    def status(self):
        return {"frames": len(self.frames)}

    def close(self, timeout_s: float) -> None:
        pass


def test_every_output_tap_sees_each_frame_once_taken_or_refused():
    """One observer interface for the recorder, the live view and the video: each frame the pipeline takes is
    handed to every tap once, with what became of it (a refused frame too, without a track), and the tap's
    section is in the status JSON."""
    from onboard.core.irframe import IrFrame

    svc, clock = _quiet_service()
    tap = _TapRecorder()
    svc.taps.append(tap)
    svc.observers.append(tap)
    right, wrong = np.zeros((512, 640), np.uint8), np.zeros((256, 320), np.uint8)
    for k, pixels in enumerate([right, wrong, right]):
        svc.queue.push((IrFrame(seq=k, time_boot_us=1000 + 40_000 * k, pixels=pixels), clock.ns()))
    t = threading.Thread(target=svc._pipeline_loop)
    t.start()
    deadline = time.monotonic() + 10.0
    while len(tap.frames) < 3 and time.monotonic() < deadline:
        svc._pipe_stop.wait(0.01)
    svc._pipe_stop.set()
    svc.queue.close()
    t.join(10)
    assert tap.frames == [(0, True), (1, False), (2, True)]
    assert svc.newest.value is not None and svc.newest.value[0].seq == 2
    assert svc.status(clock())["test_tap"] == {"frames": 3}


class _FakeGcs:
    """The camera component's sockets: hands out the commands it is given, keeps what is sent."""

    def __init__(self, commands) -> None:
        self.commands, self.sent = list(commands), []

    def set_system_id(self, sysid: int) -> None:
        pass

    def poll(self):
        out, self.commands = self.commands, []
        return out

    def send(self, msg) -> int:
        self.sent.append(msg)
        return 1

    def links(self) -> list:
        return [None]  # one link, every endpoint


def test_commands_the_camera_refuses_are_in_the_status_rejected_counts():
    from onboard.io.camera_protocol import CameraCommand

    svc, clock = _quiet_service({"gcs": {"endpoints": ["udpout:127.0.0.1:9"]}})
    unsupported = CameraCommand(mav.MAV_CMD_IMAGE_START_CAPTURE, (0.0,) * 7, 255, 190)
    denied = CameraCommand(mav.MAV_CMD_REQUEST_MESSAGE, (33.0,) + (0.0,) * 6, 255, 190)
    svc.gcs = _FakeGcs([unsupported, unsupported, denied])
    svc.camera_step(clock())
    acks = [m.fields["result"] for m in svc.gcs.sent if m.msg == "command_ack"]
    assert acks == [mav.MAV_RESULT_UNSUPPORTED, mav.MAV_RESULT_UNSUPPORTED, mav.MAV_RESULT_DENIED]
    rejected = svc.status(clock())["rejected"]
    assert rejected["gcs_command_unsupported"] == 2 and rejected["gcs_command_denied"] == 1
    assert svc.status(clock())["camera"]["counters"]["cmd_unsupported"] == 2


def test_a_camera_off_video_fps_is_warned_with_the_bit_rate_it_gets():
    """The video tap's streamer measures the camera from the frames it is handed; the main loop's checks warn."""
    from onboard.app.observers import VideoTap

    svc, clock = _quiet_service({"video": {"destination": "127.0.0.1:9", "fps": 30.0}})
    (video,) = [t for t in svc.taps if isinstance(t, VideoTap)]
    video.start()
    try:
        img = np.zeros((512, 640), np.uint8)
        for k in range(30):  # a 10 Hz camera
            video.streamer.submit(img, capture_time_us=1_000_000 + 100_000 * k)
        svc._watch(clock())
        (w,) = [w for w in svc.watchdog.active if w.code == "video_rate"]
        assert "10.0 frames/s but video.fps is 30" in w.message
        assert svc.status(clock())["video"]["camera_rate_hz"] == 10.0
        assert "video_rate" in {w["code"] for w in svc.status(clock())["warnings"]}
    finally:
        video.close(1.0)


class _Put:
    def __init__(self) -> None:
        self.payloads: list[dict] = []

    def put(self, data) -> None:
        self.payloads.append(json.loads(data))


def test_tracks_and_objects_carry_utc_once_system_time_maps_the_boot_clock():
    """Before SYSTEM_TIME: ``time_unix_us`` is null in the track and the objects message (never a made-up time);
    after three samples: both carry the frame's UTC with its sigma, and the status says where it came from."""
    from onboard.core.irframe import IrFrame

    svc, clock = _quiet_service({"imaging": {"chain": "objects"}})
    svc._track_pub, svc._objects_pub = _Put(), _Put()
    assert svc.status(clock())["utc"]["state"] == "none"
    unix0_us = 1_800_000_000_000_000
    pixels = np.zeros((512, 640), np.uint8)
    svc.queue.push((IrFrame(seq=0, time_boot_us=3_200_000, pixels=pixels), clock.ns()))
    t = threading.Thread(target=svc._pipeline_loop)
    t.start()
    try:
        deadline = time.monotonic() + 10.0
        while len(svc._objects_pub.payloads) < 1 and time.monotonic() < deadline:
            svc._pipe_stop.wait(0.01)
        for k in (1, 2, 3):  # the MAVLink thread's SYSTEM_TIME, whole ms of boot time
            assert svc.utc.add_system_time(k * 1_000_000, unix0_us + k * 1_000_000)
        svc.queue.push((IrFrame(seq=1, time_boot_us=3_233_333, pixels=pixels), clock.ns()))
        while len(svc._objects_pub.payloads) < 2 and time.monotonic() < deadline:
            svc._pipe_stop.wait(0.01)
    finally:
        svc._pipe_stop.set()
        svc.queue.close()
        t.join(10)
    tracks, objects = svc._track_pub.payloads, svc._objects_pub.payloads
    assert [m["time_boot_us"] for m in tracks] == [m["time_boot_us"] for m in objects] == [3_200_000, 3_233_333]
    assert tracks[0]["time_unix_us"] is None and objects[0]["time_unix_us"] is None
    sigma = tracks[1]["time_unix_sigma_us"]
    assert 289 <= sigma < 1000 and objects[1]["time_unix_sigma_us"] == sigma
    assert abs(tracks[1]["time_unix_us"] - (unix0_us + 3_233_333)) <= 2 * sigma
    assert objects[1]["time_unix_us"] == tracks[1]["time_unix_us"]
    utc = svc.status(clock())["utc"]
    assert utc["state"] == "ok" and utc["source"] == "SYSTEM_TIME" and utc["samples"] == 3
    assert abs(utc["offset_us"] - unix0_us) <= 2 * utc["sigma_us"]


def test_the_status_says_how_old_its_latest_track_is():
    """After the frames stop, the status keeps the last track's state ('tracking'); its age says it is old."""
    from onboard.core.track import Track

    svc, clock = _quiet_service()
    assert svc.status(clock())["track"] is None
    svc.newest.value = (Track("uav1", 3, 1_100_000, "tracking", track_id=1), clock())
    clock.t_s += 4.0
    track = svc.status(clock())["track"]
    assert track["state"] == "tracking" and track["age_s"] == pytest.approx(4.0)


def test_the_daemon_publishes_its_counts_once_more_as_it_stops():
    """Whoever watches the status key (a ground station, a demo stopping the daemon) gets the counts the run ended
    with, not the last periodic status up to an interval before: here the clock never reaches the first one."""
    svc, clock = _quiet_service()
    tap = _TapRecorder()
    svc.taps.append(tap)
    t = threading.Thread(target=svc.run)
    t.start()
    time.sleep(0.2)  # a few turns of the loop, the status interval never reached (the clock stands still)
    assert tap.status_payloads == []
    svc._stop.set()
    t.join(10)
    assert not t.is_alive()
    (last,) = tap.status_payloads
    assert json.loads(last)["schema"] == "irtrack.status/1"


# REQUEST_MESSAGE(CAMERA_INFORMATION) to the camera (system 1, component 100), unsigned, from QGC's ids
UNSIGNED_CAMERA_INFORMATION_REQUEST = bytes(
    mav.MAVLink_command_long_message(
        1, 100, mav.MAV_CMD_REQUEST_MESSAGE, 0, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION, 0, 0, 0, 0, 0, 0
    ).pack(mav.MAVLink(None, srcSystem=255, srcComponent=190))
)


def _camera_messages(gcs, parser, mtype: str | None = None, signed: bool = False, component: int | None = 100) -> list:
    """(message, sender) of ``component`` (None: any) waiting on the ground station's socket, parsed by ``parser``
    (of type ``mtype``, verified by the parser's key with ``signed``)."""
    out = []
    while True:
        try:
            data, addr = gcs.recvfrom(65535)
        except BlockingIOError:
            return out
        for m in parser.parse_buffer(data) or []:
            if m.get_type() == "BAD_DATA" or (mtype and m.get_type() != mtype):
                continue
            if component is not None and m.get_srcComponent() != component:
                continue
            if not signed or m._signed:
                out.append((m, addr))


def _serve_until(d: Daemon, ap, done, what: str, timeout_s: float = 30.0) -> None:
    """Play the autopilot (heartbeat, its link's traffic) every 0.1 s until ``done()``; the daemon must live."""
    deadline = time.monotonic() + timeout_s
    while not done():
        assert time.monotonic() < deadline, f"{what}:\n" + "\n".join(d.lines[-30:])
        assert d.proc.poll() is None, "daemon died:\n" + "\n".join(d.lines[-30:])
        ap.heartbeat()
        ap.pump()
        time.sleep(0.1)


SIGNING_KEY = bytes(range(32))


def _signed_daemon(tmp_path, daemon_env, *sets: str):
    """A daemon with ``mavlink.signing_key_file`` (``SIGNING_KEY``), its camera on a ground station's UDP socket of
    ours, and ``sets`` (``--set`` values): ``(daemon, that socket, mavlink port, zenoh port)``."""
    import socket

    key_file = tmp_path / "mavlink.key"
    key_file.write_text(SIGNING_KEY.hex())
    mport, zport, gport = free_udp_port(), free_tcp_port(), free_udp_port()
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", gport))
    gcs.setblocking(False)
    # no frame reaches these daemons: the estimator on a thread spares each the estimator process's fork server
    # (1.4 s of CPU beside its start), which nothing here checks
    options = [arg for value in ("estimator.worker=thread", *sets) for arg in ("--set", value)]
    d = Daemon(
        ["--mavlink", f"udpin:127.0.0.1:{mport}", "--zenoh-listen", f"tcp/127.0.0.1:{zport}", "--gcs",
         f"udpout:127.0.0.1:{gport}", "--set", f"mavlink.signing_key_file={key_file}", *options],
        daemon_env,
    )  # fmt: skip
    return d, gcs, mport, zport


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_with_a_signing_key_the_daemons_camera_signs_and_takes_only_signed_commands(tmp_path, daemon_env):
    """mavlink.signing_key_file signs the camera component's link too: its heartbeat reaches a ground station signed
    with the key, and an unsigned command (which could move the tracked target) is refused and counted."""
    from onboard.io.zenoh_session import ZenohConfig as _ZenohConfig
    from onboard.io.zenoh_session import open_session, status_key

    key = SIGNING_KEY
    d, gcs, mport, zport = _signed_daemon(tmp_path, daemon_env, "output.status_interval_s=0.5")
    session = None
    try:
        assert d.started.wait(45), "daemon did not start:\n" + "\n".join(d.lines)
        statuses: queue.Queue = queue.Queue()
        session = open_session(_ZenohConfig(connect=(f"tcp/127.0.0.1:{zport}",)))
        session.declare_subscriber(status_key(), lambda s: statuses.put(json.loads(s.payload.to_bytes())))
        ap = FakeAutopilot(mport)
        ap.conn.setup_signing(key, sign_outgoing=True, link_id=1)
        verified = mav.MAVLink(None)
        verified.robust_parsing = True
        verified.signing.secret_key = key
        camera: list = []  # (heartbeat, sender) of component 100, verified with the key

        def heard() -> bool:
            camera.extend(_camera_messages(gcs, verified, "HEARTBEAT", signed=True))
            return bool(camera)

        _serve_until(d, ap, heard, "no signed camera heartbeat")
        # an unsigned REQUEST_MESSAGE back to the camera: refused, counted in the status, never answered
        gcs.sendto(UNSIGNED_CAMERA_INFORMATION_REQUEST, camera[0][1])
        refused = []

        def counted() -> bool:
            try:
                refused.append(statuses.get(timeout=0.5).get("rejected", {}).get("gcs_unsigned", 0))
            except queue.Empty:
                pass
            return bool(refused) and refused[-1] > 0

        _serve_until(d, ap, counted, "the unsigned command was not counted", timeout_s=20.0)
        assert refused[-1] == 1
        answers = [m.get_type() for m, _ in _camera_messages(gcs, verified, component=None)]
        assert "COMMAND_ACK" not in answers and "CAMERA_INFORMATION" not in answers
    finally:
        if session is not None:
            session.close()
        d.stop()
        gcs.close()


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_no_zenoh_peer_in_time_names_the_daemons_setting_not_an_option_it_lacks(daemon_env):
    """The daemon has no --zenoh-connect-timeout (groundsim run has): its message names zenoh.connect_timeout_s."""
    proc = subprocess.run(
        [sys.executable, "-m", "onboard", "--mavlink", f"udpin:127.0.0.1:{free_udp_port()}", "--zenoh-connect",
         f"tcp/127.0.0.1:{free_tcp_port()}", "--set", "zenoh.connect_timeout_s=0.5", "--set", "output.health_file=null"],
        cwd=REPO, env=daemon_env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("zenoh: no peer reachable at tcp/127.0.0.1:") and last.endswith(
        "or wait longer (zenoh.connect_timeout_s)"
    ), last


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_gcs_signed_false_leaves_the_camera_unsigned_beside_a_signed_autopilot_link(tmp_path, daemon_env):
    """gcs.signed: false, for a ground station on a link left unsigned: the autopilot link stays signed, the camera's
    heartbeat goes out unsigned and an unsigned command is answered."""
    key = SIGNING_KEY
    d, gcs, mport, _ = _signed_daemon(tmp_path, daemon_env, "gcs.signed=false")
    try:
        assert d.started.wait(45), "daemon did not start:\n" + "\n".join(d.lines)
        ap = FakeAutopilot(mport)
        ap.conn.setup_signing(key, sign_outgoing=True, link_id=1)  # the autopilot link: signed as before
        plain = mav.MAVLink(None)
        plain.robust_parsing = True
        got: list = []

        def answered() -> bool:
            new = _camera_messages(gcs, plain)
            if new and not got:  # the camera is there: ask it, unsigned
                gcs.sendto(UNSIGNED_CAMERA_INFORMATION_REQUEST, new[0][1])
            got.extend(m for m, _ in new)
            return any(m.get_type() == "COMMAND_ACK" for m in got)

        _serve_until(d, ap, answered, "no answer from the camera")
        assert got and not any(getattr(m, "_signed", False) for m in got)
        (ack,) = [m for m in got if m.get_type() == "COMMAND_ACK"]
        assert ack.result == mav.MAV_RESULT_ACCEPTED
    finally:
        d.stop()
        gcs.close()


def test_a_frame_a_pipeline_error_stops_is_in_the_status_frame_counts():
    """A frame taken from the queue whose processing raised was counted pipeline_error but in none of the frames
    counts: in 5, processed 4, dropped 0, rejected 0 (an audit of the overload path). It is a rejected frame now,
    so every frame received is in one count."""
    import numpy as np

    from onboard.core.irframe import IrFrame

    svc, clock = _quiet_service()
    px = np.zeros((512, 640), np.uint8)

    def feed(k: int) -> None:
        svc.frames_in += 1
        svc.queue.push((IrFrame(seq=k, time_boot_us=1000 + 33_333 * k, pixels=px), clock.ns()))
        svc._process(*svc.queue.pop(0.0))

    for k in range(3):
        feed(k)
    track = svc.pipeline._track
    svc.pipeline._track = lambda *a, **kw: (_ for _ in ()).throw(RuntimeError("boom"))
    feed(3)
    svc.pipeline._track = track
    feed(4)
    st = svc.status(clock())
    f = st["frames"]
    assert st["rejected"]["pipeline_error"] == 1 and f["processed"] == 4 and f["rejected"] == 1
    assert f["in"] == f["processed"] + f["dropped"] + f["rejected"] + f["queue_length"]


@pytest.mark.parametrize("period_ns, bunched", [(0, 6), (33_333_333, 0)])
def test_frames_dropped_from_a_burst_are_told_from_a_pipeline_behind(period_ns, bunched):
    """Ten frames captured 33 ms apart arriving at once (a link holding and releasing them) overflow the 4-frame
    queue: those drops were counted 'pipeline behind' and warned as the CPU's (a frame-stream audit). Frames that
    arrive at the camera's pace and still overflow it are the pipeline's."""
    import numpy as np

    from onboard.core.irframe import IrFrame, encode_irframe

    svc, clock = _quiet_service()
    px = np.zeros((512, 640), np.uint8)
    for k in range(10):
        payload = encode_irframe(IrFrame(seq=k, time_boot_us=1_000_000 + 33_333 * k, pixels=px))
        svc._on_frame(_Sample(payload))
        clock.t_s += period_ns / 1e9
    assert svc.frames_dropped == 6 and svc.frames_dropped_bunched == bunched


def test_a_frame_cut_short_on_the_way_is_refused_not_counted_missing():
    """Frames 3-5 truncated: counted frame_size (refused) and, the seq being read only after a decode that
    succeeded, also frames.missing, as if lost on the way; in = processed + dropped + rejected + queued, and
    in + missing is what the camera sent, so they were counted twice."""
    import numpy as np

    from onboard.core.irframe import IrFrame, encode_irframe

    svc, _ = _quiet_service({"input": {"queue_length": 100}})
    px = np.zeros((512, 640), np.uint8)
    for k in range(10):
        payload = encode_irframe(IrFrame(seq=k, time_boot_us=1_000_000 + 33_333 * k, pixels=px))
        svc._on_frame(_Sample(payload[:-1000] if 3 <= k <= 5 else payload))
    assert svc.counter["frame_size"] == 3 and len(svc.queue) == 7
    assert svc.arrival_gaps.missing == 0


class _Sample:
    """A zenoh sample as the frame callback reads it: untyped, its payload's length and bytes."""

    def __init__(self, payload: bytes) -> None:
        self.encoding = None
        self.payload = self
        self._bytes = payload

    def __len__(self) -> int:
        return len(self._bytes)

    def to_bytes(self) -> bytes:
        return self._bytes


@pytest.mark.parametrize("worker, counted", [("thread", 0.0), ("inline", 0.0), ("process", 5.0)])
def test_the_cpu_status_adds_the_estimators_cpu_only_from_a_worker_process(worker, counted):
    """/proc/self/stat holds a thread worker's CPU already; adding the worker's own count too put gets_share above the
    process's share by 0.01-0.07 of a core in every status (an audit). Only a live worker process is not in it."""
    import types

    svc, _ = _quiet_service({"estimator": {"enabled": False, "worker": worker}})
    svc.estimator = types.SimpleNamespace(worker_cpu_s=5.0)
    assert svc._worker_process_cpu() == counted


def test_a_warning_flapping_with_every_frame_does_not_silence_the_periodic_status(monkeypatch):
    """Each warning change publishes a status at once; it also pushed the periodic schedule an interval further,
    so a warning raised and cleared by every frame (two cameras on the key, one stating a 2x zoom: zoom_mismatch,
    50 changes a second) left the status key silent for minutes after they stopped."""
    from onboard.app.service import WARNING_STATUS_MIN_S

    svc, clock = _quiet_service()
    published: list[float] = []
    monkeypatch.setattr(svc, "_publish_status", lambda now, last_cpu: published.append(now) or last_cpu)
    flap_until_s = clock() + 6.0
    turns = {"n": 0}

    def idle(turn_s, period_s, next_own_s):  # one 20 ms turn of fake time; a frame of either camera in each
        turns["n"] += 1
        if clock() < flap_until_s:
            flapping = bool(turns["n"] % 2)
            svc.watchdog.zoom(clock(), 2.0 if flapping else 1.0, flapping)
        clock.t_s += 0.02

    monkeypatch.setattr(svc, "_idle", idle)
    svc.run(max_duration_s=10.0)
    interval_s = svc.config.output.status_interval_s
    quiet = [t for t in published if t > flap_until_s + 0.1]  # the camera that flapped is gone: periodic only
    flapping = [t for t in published if t <= flap_until_s]
    # each change at once, but at most one status each WARNING_STATUS_MIN_S (one a 20 ms turn before: ~300 in 6 s)
    assert len(flapping) <= 6.0 / WARNING_STATUS_MIN_S + 6.0 / interval_s + 2, len(flapping)
    assert len(quiet) >= int(3.9 / interval_s) - 1, (len(published), quiet[:5])
    assert all(b - a <= interval_s + 0.05 for a, b in zip(quiet, quiet[1:]))


def test_another_daemons_statuses_are_read_at_most_once_a_second_however_fast_they_come(monkeypatch):
    """Any peer may publish on the vehicle's status key: a flood costs a time stamp per message, not a JSON parse."""
    import types

    import onboard.app.service as service_module

    svc, clock = _quiet_service()
    parsed: list[bytes] = []
    monkeypatch.setattr(service_module, "twin_words", lambda b: parsed.append(b) or f"words {len(parsed)}")
    sample = types.SimpleNamespace(payload=types.SimpleNamespace(to_bytes=lambda: b"{}"))
    for _ in range(50):  # 50 in 0.49 s
        svc._on_twin_status(sample)
        clock.t_s += 0.01
    assert len(parsed) == 1 and svc._twin_heard[:2] == (clock() - 0.01, "words 1")
    clock.t_s += 0.6
    svc._on_twin_status(sample)  # a second after the one read: read again
    assert len(parsed) == 2 and svc._twin_heard[1] == "words 2"
    svc.watchdog.name_clash(clock(), svc._twin_heard[:2], "irtrack/uav1/status")
    assert [w.code for w in svc.watchdog.active] == ["name_clash"]
