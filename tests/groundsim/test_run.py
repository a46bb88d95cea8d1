"""``python -m groundsim run``: the loop, its CLI, its truth file; real processes on 127.0.0.1.

The end-to-end run (a 2 s P1 at --rate max as a subprocess) is shared by several tests: it is
received by a pymavlink udpin listener and a zenoh subscriber in this process, and its truth CSV
is checked against both.
"""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.app import cli
from groundsim.app.run import JitterStats, Pacer, RateSpec, RunConfig, run, run_loop
from groundsim.io.mavlink_vehicle import open_mavlink2
from groundsim.io.ports import free_tcp_port, free_udp_port
from groundsim.io.stop_signals import install_stop_signals
from groundsim.world.nav_errors import offset_geodetic
from groundsim.world.scenario import load_scenario, resolve_scenario_path, scenarios_dir
from groundsim.world.sim import BOOT_START_US, SimCore, frame_count
from groundsim.world.truth import REQUIRED_COLUMNS, TRUTH_COLUMNS, TruthRow, TruthWriter, read_truth_csv, truth_row
from onboard.core.errors import ConfigError, InputError
from onboard.core.frames import (
    Q_MOUNT_FROM_CAM,
    GeodeticOrigin,
    PinholeIntrinsics,
    quat_multiply,
    rotmat_from_quat,
    rotmat_from_rotvec,
)
from onboard.core.irframe import ENCODING_MONO8, decode_irframe
from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session
from tests.fakes import FakeClock
from tests.process_helpers import repo_env, run_module

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[2]
P1 = scenarios_dir() / "P1.yaml"
FRAME_RATE_HZ = 30.0
E2E_DURATION_S = 2.0
E2E_FRAMES = 60
MIN_DELIVERED_FRACTION = 0.9
PROCESS_TIMEOUT_S = 90.0  # a 2 s scenario at --rate max on a loaded 2-core machine ends well within this
DELIVERY_WAIT_S = 5.0  # frames still in flight after the process exits arrive within this
STAMP_TOL_US = 1  # capture stamps are rounded to whole microseconds
PIXEL_TOL_PX = 1.0  # truth pixel vs the rendered blob's centroid
LATLON_TOL_DEG = 3e-7  # #33 degE7 quantisation (0.5e-7) + time_boot_ms truncation (<= 1 ms at <= 10 m/s ~ 1e-7 deg)
ALT_TOL_M = 0.02  # #33 mm quantisation + 1 ms of climb
QUAT_F32_TOL = 1e-5  # float32 quaternion fields
SHORT_TIMEOUT_S = 60.0


def _groundsim(*args: str, timeout: float = SHORT_TIMEOUT_S) -> subprocess.CompletedProcess:
    return run_module("groundsim", *args, timeout_s=timeout)


def _assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> str:
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error:" in ln]
    assert len(errors) == 1, proc.stderr
    assert errors[0].startswith("groundsim"), errors[0]
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


def _blob_centroid_px(img: np.ndarray, near_uv=None, window: int = 7) -> tuple[float, float]:
    """Centroid (u, v) of the brightest compact blob: the frame minus its 5 x 5 median (which
    removes the sky gradient and the horizon), peak, then the weighted centroid of the window's
    pixels above 30 % of the peak, with pixel centres at (j + 0.5, i + 0.5)."""
    hp = img.astype(np.float32) - cv2.medianBlur(img, 5).astype(np.float32)
    i, j = np.unravel_index(int(np.argmax(hp)), hp.shape)
    h = window // 2
    i0, j0 = max(0, i - h), max(0, j - h)
    w = hp[i0 : i + h + 1, j0 : j + h + 1]
    w = np.where(w > 0.3 * w.max(), w, 0.0)
    ii, jj = np.mgrid[i0 : i0 + w.shape[0], j0 : j0 + w.shape[1]]
    return float((w * (jj + 0.5)).sum() / w.sum()), float((w * (ii + 0.5)).sum() / w.sum())


# --------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def e2e(tmp_path_factory):
    """One 2 s P1 run at --rate max, received over 127.0.0.1: (proc, frames, mavlink msgs, truth)."""
    out = tmp_path_factory.mktemp("run")
    truth_path = out / "truth.csv"
    zport, mport = free_tcp_port(), free_udp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    session = open_session(ZenohConfig(listen=(endpoint,)))
    payloads: list[bytes] = []
    lock = threading.Lock()

    def on_sample(sample):
        with lock:
            payloads.append(sample.payload.to_bytes())

    sub = session.declare_subscriber(frame_key("uav1"), on_sample)
    rx = open_mavlink2(f"udpin:127.0.0.1:{mport}", 255, 190)
    msgs = []
    done = threading.Event()

    def drain():  # keep the UDP buffer empty while the simulator runs
        while not done.is_set():
            m = rx.recv_match(blocking=True, timeout=0.05)
            if m is not None and m.get_type() != "BAD_DATA":
                msgs.append(m)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        proc = _groundsim(
            "run",
            "--scenario",
            str(P1),
            "--duration",
            str(E2E_DURATION_S),
            "--rate",
            "max",
            "--mavlink",
            f"udpout:127.0.0.1:{mport}",
            "--zenoh-connect",
            endpoint,
            "--truth",
            str(truth_path),
            timeout=PROCESS_TIMEOUT_S,
        )
        deadline = time.monotonic() + DELIVERY_WAIT_S
        while time.monotonic() < deadline:
            with lock:
                if len(payloads) >= E2E_FRAMES:
                    break
            time.sleep(0.05)
    finally:
        done.set()
        reader.join(PROCESS_TIMEOUT_S)  # a hang guard: it stops within one 0.05 s receive
        # the simulator has exited: every MAVLink datagram it sent to loopback is already in our
        # socket's buffer (a sendto on loopback queues at the receiver), so draining it gets them all
        while (m := rx.recv_match(blocking=False)) is not None:
            if m.get_type() != "BAD_DATA":
                msgs.append(m)
        sub.undeclare()
        session.close()
        rx.close()
    with lock:
        frames = [decode_irframe(p) for p in payloads]
    truth = read_truth_csv(truth_path) if truth_path.exists() else None
    return proc, frames, msgs, truth, truth_path


@pytest.mark.integration
def test_run_exits_cleanly_with_status_lines(e2e):
    proc, _, _, _, _ = e2e
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "done: 60/60 frames" in proc.stderr
    assert "rt x" in proc.stderr


@pytest.mark.integration
def test_frames_have_valid_headers_monotonic_seq_and_30hz_stamps(e2e):
    _, frames, _, _, _ = e2e
    # zenoh congestion control is DROP (groundsim.io.zenoh_video): at --rate max on a busy machine an
    # occasional frame may be dropped (a gap in seq, as a real link shows); nearly all must arrive
    assert len(frames) >= MIN_DELIVERED_FRACTION * E2E_FRAMES, f"{len(frames)} of {E2E_FRAMES} frames delivered"
    seqs = [f.seq for f in frames]
    assert seqs == sorted(set(seqs)) and seqs[0] < 6 and seqs[-1] < E2E_FRAMES
    for f in frames:
        assert (f.width_px, f.height_px, f.encoding) == (640, 512, ENCODING_MONO8)
        assert f.stated_zoom == 1.0  # the simulated camera's fixed lens, as calibrated (IRF1's zoom field)
        expected_us = BOOT_START_US + f.seq * 1e6 / FRAME_RATE_HZ
        assert abs(f.time_boot_us - expected_us) <= STAMP_TOL_US
    gaps_us = np.diff([f.time_boot_us for f in frames]) / np.diff(seqs)
    assert np.all(np.abs(gaps_us - 1e6 / FRAME_RATE_HZ) <= STAMP_TOL_US)


@pytest.mark.integration
def test_truth_csv_has_header_and_one_row_per_frame(e2e):
    _, frames, _, truth, truth_path = e2e
    header = truth_path.read_text().splitlines()[0].split(",")
    assert tuple(header[: len(REQUIRED_COLUMNS)]) == REQUIRED_COLUMNS
    assert tuple(header) == TRUTH_COLUMNS
    assert len(truth["seq"]) == E2E_FRAMES
    np.testing.assert_array_equal(truth["seq"], np.arange(E2E_FRAMES))
    by_seq = {f.seq: f.time_boot_us for f in frames}
    for s, t in zip(truth["seq"], truth["time_boot_us"]):
        if s in by_seq:
            assert by_seq[s] == t
    assert np.all(truth["target_visible"] == 1)  # P1's gimbal keeps the target near the centre
    # the target, 5 m/s, over 2 s: geodetic and NED columns agree on its displacement
    d_n_m = truth["target_n_m"][-1] - truth["target_n_m"][0]
    d_lat_m = (
        (truth["target_lat_deg"][-1] - truth["target_lat_deg"][0]) * math.pi / 180 * 6.3555e6
    )  # N radius at 32 deg
    assert abs(d_n_m - d_lat_m) < 0.05
    assert 7.0 < abs(d_n_m) < 9.0  # -4 m/s north for 59/30 s


@pytest.mark.integration
def test_truth_pixel_matches_rendered_blob(e2e):
    _, frames, _, truth, _ = e2e
    uv = {int(s): (u, v) for s, u, v in zip(truth["seq"], truth["target_u_px"], truth["target_v_px"])}
    errs = []
    for f in frames:
        u, v = _blob_centroid_px(np.asarray(f.pixels))
        errs.append(math.hypot(u - uv[f.seq][0], v - uv[f.seq][1]))
    assert max(errs) <= PIXEL_TOL_PX, f"max {max(errs):.2f} px"
    # and the gimbal keeps it within the reference study's ~25 px of the centre (320, 256)
    assert max(math.hypot(u - 320.0, v - 256.0) for u, v in uv.values()) < 40.0


def _interp_truth(truth, t_us, name):
    return float(np.interp(t_us, truth["time_boot_us"], truth[name]))


@pytest.mark.integration
def test_mavlink_position_and_attitude_streams(e2e):
    _, _, msgs, truth, _ = e2e
    by_type: dict[str, list] = {}
    for m in msgs:
        by_type.setdefault(m.get_type(), []).append(m)
    assert {"HEARTBEAT", "ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT", "GIMBAL_DEVICE_ATTITUDE_STATUS"} <= set(by_type)
    assert all(m.get_srcSystem() == 1 for m in msgs)
    # #31 at 50 Hz of sim time: ~100 samples in 2 s, unit quaternions, increasing stamps
    att = by_type["ATTITUDE_QUATERNION"]
    assert 90 <= len(att) <= 101
    stamps = [m.time_boot_ms for m in att]
    assert stamps == sorted(stamps) and stamps[0] == BOOT_START_US // 1000
    for m in att:
        assert abs(math.sqrt(m.q1**2 + m.q2**2 + m.q3**2 + m.q4**2) - 1.0) < QUAT_F32_TOL
    # #33 at 25 Hz: the truth observer's position moved by the navigation error the truth CSV records
    # (default RTK), checked where a sample's stamp falls on a frame (every 200 ms)
    pos = by_type["GLOBAL_POSITION_INT"]
    assert 45 <= len(pos) <= 51
    rows = {int(t): i for i, t in enumerate(truth["time_boot_us"])}
    checked = moved = 0
    for m in pos:
        i = rows.get(m.time_boot_ms * 1000)
        if i is None:
            continue
        err = [truth[f"nav_p_err_{c}_m"][i] for c in "ned"]
        lat, lon, alt = offset_geodetic(
            truth["observer_lat_deg"][i], truth["observer_lon_deg"][i], truth["observer_alt_m"][i], err
        )
        assert abs(m.lat * 1e-7 - lat) < LATLON_TOL_DEG and abs(m.lon * 1e-7 - lon) < LATLON_TOL_DEG
        assert abs(m.alt * 1e-3 - alt) < ALT_TOL_M and abs(m.relative_alt * 1e-3 - alt) < ALT_TOL_M  # origin alt 0
        moved += 0.0 < np.linalg.norm(err) < 0.2  # RTK: 2 cm white per axis
        checked += 1
    assert checked >= 9 and moved == checked


@pytest.mark.integration
def test_gimbal_status_is_the_camera_attitude_in_ned(e2e):
    """#285 (earth frame) q_ned_from_gimbal composed with the mount->camera axes is the truth's q_ned_from_cam
    turned by the navigation attitude error the truth CSV records (R_reported = Exp(phi) R_true)."""
    _, _, msgs, truth, _ = e2e
    gim = [m for m in msgs if m.get_type() == "GIMBAL_DEVICE_ATTITUDE_STATUS"]
    assert 18 <= len(gim) <= 21  # 10 Hz over 2 s
    rows = {int(t) // 1000: i for i, t in enumerate(truth["time_boot_us"])}
    matched = 0
    for m in gim:
        i = rows.get(m.time_boot_ms)
        if i is None or int(truth["time_boot_us"][i]) % 1000:
            continue  # only stamps that fall exactly on a frame
        q_nc = quat_multiply(np.array(m.q, dtype=float), Q_MOUNT_FROM_CAM)
        q_true = np.array([truth[f"q_ned_from_cam_{c}"][i] for c in "wxyz"])
        phi = np.array([truth[f"nav_att_err_{c}_rad"][i] for c in "ned"])
        assert 0 < np.linalg.norm(phi) < 0.02  # RTK: 0.1 deg bias + 0.05 deg white per axis
        np.testing.assert_allclose(
            rotmat_from_quat(q_nc), rotmat_from_rotvec(phi) @ rotmat_from_quat(q_true), atol=1e-5
        )
        matched += 1
    assert matched >= 6  # every 100 ms falls on a frame: 0, 100, ..., 1900 ms


# --------------------------------------------------------------------------- stopping


@pytest.mark.integration
@pytest.mark.parametrize("sig", [signal.SIGTERM])
def test_signal_mid_run_leaves_complete_truth_and_exit_0(tmp_path, sig):
    truth_path = tmp_path / "truth.csv"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "groundsim",
            "run",
            "--scenario",
            str(P1),
            "--rate",
            "realtime",
            "--mavlink",
            f"udpout:127.0.0.1:{free_udp_port()}",
            "--truth",
            str(truth_path),
            "--log-level",
            "warning",
        ],
        cwd=REPO,
        env=repo_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + SHORT_TIMEOUT_S
        while time.monotonic() < deadline and proc.poll() is None:
            if truth_path.exists() and truth_path.read_text().count("\n") >= 10:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()[1]
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=SHORT_TIMEOUT_S)  # a hang guard, not a measured property
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    text = truth_path.read_text()
    assert text.endswith("\n")
    lines = text.splitlines()
    assert lines[0].split(",") == list(TRUTH_COLUMNS)
    assert all(len(ln.split(",")) == len(TRUTH_COLUMNS) for ln in lines)
    truth = read_truth_csv(truth_path)
    n = len(truth["seq"])
    assert 9 <= n < 300  # stopped mid-run
    np.testing.assert_array_equal(truth["seq"], np.arange(n))


# --------------------------------------------------------------------------- bad input: one line, exit 2


@pytest.mark.integration
def test_unknown_scenario_key_is_one_line_exit_2(tmp_path):
    """As a process: exit code 2, one line, no traceback."""
    bad = tmp_path / "bad.yaml"
    bad.write_text(P1.read_text().replace("frame_rate_hz:", "frame_rate_hzz:"))
    proc = _groundsim("run", "--scenario", str(bad), "--rate", "max")
    _assert_one_line_error(proc, "frame_rate_hzz", "did you mean 'frame_rate_hz'")


def _main_err(capsys, *argv) -> tuple[int, str]:
    rc = cli.main(list(argv))
    return rc, capsys.readouterr().err


def _assert_main_one_line(capsys, argv, *needles) -> None:
    """In process (same code path as ``python -m groundsim``, which is ``sys.exit(main())``)."""
    rc, err = _main_err(capsys, *argv)
    assert rc == 2, (argv, err)
    assert err.count("\n") == 1 and "error:" in err and "Traceback" not in err, (argv, err)
    for needle in needles:
        assert needle in err, (argv, err)


def test_missing_scenario_file_is_one_line_exit_2(tmp_path, capsys):
    _assert_main_one_line(capsys, ["run", "--scenario", str(tmp_path / "nope.yaml")], "nope.yaml", "no such file")


# a 0.1 s run as fast as it goes, quiet but for errors: what the zenoh refusals below start
_SHORT_RUN = ("run", "--rate", "max", "--duration", "0.1", "--log-level", "error")


@pytest.mark.integration
def test_zenoh_listen_port_in_use_is_one_line_exit_2(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        _assert_main_one_line(
            capsys,
            [
                *_SHORT_RUN,
                "--zenoh-listen",
                f"tcp/127.0.0.1:{port}",
                "--mavlink",
                f"udpout:127.0.0.1:{free_udp_port()}",
            ],
            "port already in use",
        )


@pytest.mark.integration
def test_unreachable_zenoh_peer_is_one_line_exit_2(capsys):
    _assert_main_one_line(
        capsys,
        [
            *_SHORT_RUN,
            "--zenoh-connect",
            f"tcp/127.0.0.1:{free_tcp_port()}",
            "--zenoh-connect-timeout",
            "0.5",
            "--mavlink",
            f"udpout:127.0.0.1:{free_udp_port()}",
        ],
        "within 0.5 s: start it first (the daemon's or a router's listener), or wait longer (--zenoh-connect-timeout)",
    )


@pytest.mark.integration
def test_mavlink_port_in_use_and_bad_options_are_one_line_exit_2(capsys):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        rc, err = _main_err(
            capsys,
            "run",
            "--scenario",
            str(P1),
            "--rate",
            "max",
            "--mavlink",
            f"udpin:127.0.0.1:{s.getsockname()[1]}",
            "--log-level",
            "error",
        )
    assert rc == 2 and err.count("\n") == 1 and "already in use" in err
    for argv, needle in (
        (["run", "--rate", "fast"], "--rate"),
        (["run", "--rate", "0"], "--rate"),
        (["run", "--duration", "3601"], "--duration"),
        (["run", "--duration", "-1"], "--duration"),
        (["run", "--seed", "-3"], "--seed"),
        (["run", "--vehicle", "a/b"], "vehicle name"),
        (["run", "--mavlink", "bogus:1"], "--mavlink"),
        (["run", "--zenoh-listen", "nonsense"], "--zenoh-listen"),
        (["run", "--bogus-option"], "unrecognized arguments"),
        (["run", "--rt-priority", "0"], "--rt-priority"),
        (["run", "--rt-priority", "10", "--rate", "max"], "--rt-priority"),
        (["fly"], "invalid choice"),
    ):
        rc, err = _main_err(capsys, *argv, *(["--log-level", "error"] if argv[0] == "run" else []))
        assert rc == 2, (argv, err)
        assert err.count("\n") == 1 and "error:" in err and needle in err, (argv, err)


# --------------------------------------------------------------------------- determinism and chunking


@pytest.mark.integration
def test_same_seed_same_truth_and_chunking_does_not_change_it(tmp_path, capsys):
    """Same seed -> byte-identical truth, whether flown in 1 s chunks (--rate max) or 0.1 s chunks;
    another seed of a disturbed scenario -> another target path."""
    p1g = scenarios_dir() / "P1g.yaml"
    common = [
        "--scenario",
        str(p1g),
        "--duration",
        "1",
        "--rate",
        "max",
        "--no-render",
        "--log-level",
        "warning",
        "--mavlink",
        f"udpout:127.0.0.1:{free_udp_port()}",
    ]
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    assert cli.main(["run", *common, "--seed", "3", "--truth", str(a)]) == 0
    config = RunConfig(
        load_scenario(p1g),
        run_seed=3,
        duration_s=1.0,
        rate=RateSpec.parse("max"),
        render=False,
        mavlink=f"udpout:127.0.0.1:{free_udp_port()}",
        truth_path=b,
        flight_chunk_s=0.1,
    )
    assert run(config).frames == 30
    assert cli.main(["run", *common, "--seed", "4", "--truth", str(c)]) == 0
    assert a.read_bytes() == b.read_bytes()
    ta, tc = read_truth_csv(a), read_truth_csv(c)
    np.testing.assert_array_equal(ta["time_boot_us"], tc["time_boot_us"])
    np.testing.assert_array_equal(ta["observer_n_m"], tc["observer_n_m"])  # the observer has no disturbance
    assert np.max(np.abs(ta["target_n_m"] - tc["target_n_m"])) > 1e-4


def test_same_seed_same_pixels():
    sc = load_scenario(P1)
    frames = [SimCore(sc, seed, 0.1).frame(1).pixels for seed in (0, 0, 1)]
    np.testing.assert_array_equal(frames[0], frames[1])
    assert np.any(frames[0] != frames[2])  # the noise follows the seed


# --------------------------------------------------------------------------- the loop, in process


class FakeVehicle:
    def __init__(self, stop_after_polls=None, stop=None) -> None:
        self.states, self.polls = [], []
        self.stop_after, self.stop = stop_after_polls, stop

    def update_state(self, **state):
        self.states.append(state)

    def poll(self, now_us):
        self.polls.append(now_us)
        if self.stop_after is not None and len(self.polls) >= self.stop_after:
            self.stop.set()


class FakePublisher:
    def __init__(self) -> None:
        self.frames = []

    def publish(self, frame):
        self.frames.append(frame)


def test_loop_feeds_ticks_and_frames_in_order_on_the_boot_clock():
    sc = load_scenario(P1)
    core = SimCore(sc, 0, 0.2)
    clock, vehicle, pub = FakeClock(100.0), FakeVehicle(), FakePublisher()
    report = run_loop(core, RateSpec.parse("realtime"), mavlink=vehicle, publisher=pub, clock=clock)
    assert (core.ticks_per_frame, core.tick_rate_hz, core.frame_count) == (4, 120.0, 6)
    assert len(vehicle.polls) == 24 and len(pub.frames) == 6 and report.frames == 6 and not report.stopped
    expected_us = [BOOT_START_US + round(i * 1e6 / 120.0) for i in range(24)]
    assert vehicle.polls == expected_us
    assert [s["time_boot_us"] for s in vehicle.states] == expected_us
    assert all(s["q_gimbal"] is not None for s in vehicle.states)  # P1 is gimballed
    assert [f.seq for f in pub.frames] == list(range(6))
    assert [f.time_boot_us for f in pub.frames] == expected_us[::4]
    # a fake clock that only moves when slept: the pacer hits every deadline exactly
    assert report.jitter is not None and report.jitter.jitter_max_ms < 1e-6 and report.jitter.late_max_ms < 1e-6
    assert clock.t_s - 100.0 == pytest.approx(23 / 120.0)


def test_loop_stops_when_asked_and_reports_it():
    sc = load_scenario(P1)
    core = SimCore(sc, 0, 1.0, render=False)
    stop = threading.Event()
    vehicle = FakeVehicle(stop_after_polls=10, stop=stop)
    report = run_loop(core, RateSpec.parse("max"), mavlink=vehicle, stop=stop)
    assert len(vehicle.polls) == 10
    assert report.frames == 3 and report.stopped and report.frames_total == 30  # frames at ticks 0, 4, 8


# --------------------------------------------------------------------------- pure pieces


@pytest.mark.parametrize(
    "text, factor, paced",
    [("realtime", 1.0, True), ("max", None, False), ("2", 2.0, True), ("0.5x", 0.5, True), ("MAX", None, False)],
)
def test_rate_parse(text, factor, paced):
    r = RateSpec.parse(text)
    assert r.factor == factor and r.paced is paced


@pytest.mark.parametrize("text", ["fast", "", "0", "-1", "nan", "inf", "1e9"])
def test_rate_parse_rejects(text):
    with pytest.raises(ConfigError, match="--rate"):
        RateSpec.parse(text)


def test_pacer_waits_for_deadlines_and_reports_lateness():
    clock = FakeClock(100.0)
    p = Pacer(2.0, clock)  # twice real time
    p.start(0.0)
    assert p.wait_until(1.0) == 0.0 and clock.t_s == pytest.approx(100.5)
    clock.t_s += 0.3  # work overran the next deadline (t = 1.5 s -> wall 100.75) by 0.05 s
    assert p.wait_until(1.5) == pytest.approx(0.05)
    stop = threading.Event()
    stop.set()
    t = clock.t_s
    assert p.wait_until(100.0, stop) == 0.0 and clock.t_s == t  # stop: no sleeping
    free = Pacer(None, clock)
    free.start()
    assert free.wait_until(1e6) == 0.0 and clock.t_s == t


def test_pacer_sleeps_in_slices_so_stop_is_seen():
    clock = FakeClock(100.0)
    p = Pacer(1.0, clock)
    p.start()
    p.wait_until(1.0)
    assert max(clock.sleeps) <= 0.05 + 1e-12 and sum(clock.sleeps) == pytest.approx(1.0)


def test_jitter_stats():
    j = JitterStats(0.1)
    assert j.summary() is None
    for w, late in ((0.0, 0.0), (0.1, 0.0), (0.203, 0.003), (0.3, 0.0)):
        j.add(w, late)
    s = j.summary()
    assert s.frames == 4 and s.period_ms == pytest.approx(100.0)
    assert s.jitter_max_ms == pytest.approx(3.0) and s.late_max_ms == pytest.approx(3.0)
    assert s.jitter_p50_ms == pytest.approx(3.0)  # intervals 100, 103, 97 ms


def test_frame_count_matches_scenario():
    sc = load_scenario(P1)
    assert frame_count(sc.duration_s, sc.frame_rate_hz) == sc.frame_count == 300
    assert frame_count(0.1, 30.0) == 3 and frame_count(0.01, 30.0) == 1 and frame_count(2.0, 30.0) == 60


def test_run_config_validates():
    sc = load_scenario(P1)
    assert RunConfig(sc).duration_s == 10.0
    for kw, needle in (
        ({"duration_s": 3601.0}, "--duration"),
        ({"duration_s": 0.0}, "--duration"),
        ({"run_seed": -1}, "--seed"),
        ({"run_seed": True}, "--seed"),
    ):
        with pytest.raises(ConfigError, match=needle):
            RunConfig(sc, **kw)


@pytest.mark.parametrize("argv, frame", [([], "earth"), (["--gimbal-frame", "vehicle"], "vehicle")])
def test_gimbal_frame_option_reaches_the_simulated_vehicle(monkeypatch, argv, frame):
    """--gimbal-frame sets the frame of the vehicle's #285: earth unless asked (README, "MAVLink": why)."""
    import groundsim.io.mavlink_vehicle as mv

    made = {}

    class Opened(Exception):
        pass

    def fake_vehicle(connection, **kw):
        made.update(kw)
        raise Opened

    monkeypatch.setattr(mv, "MavlinkVehicle", fake_vehicle)
    args = cli.build_parser().parse_args(["run", "--scenario", "P1", "--no-render", *argv])
    config = cli._run_config(args)
    assert config.gimbal_frame == frame
    with pytest.raises(Opened):
        run(dataclasses.replace(config, render=False))
    assert made["gimbal_yaw_frame"] == frame and made["gimballed"]
    with pytest.raises(ConfigError, match="--gimbal-frame"):
        RunConfig(load_scenario(P1), gimbal_frame="body")


ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)
K = PinholeIntrinsics.vue_pro_640()
# camera looking north (cam z = N, cam x = E, cam y = D): q_ned_from_cam = q_ned_from_mount(identity) x mount->cam
Q_NORTH = Q_MOUNT_FROM_CAM


def test_truth_row_projection_and_visibility():
    p_cam = np.array([0.0, 0.0, -50.0])
    # 100 m north, 10 m east, 5 m below: u = cx + f * 10/100, v = cy + f * 5/100
    row = truth_row(7, 1_234_567, 0.5, ORIGIN, K, p_cam + [100.0, 10.0, 5.0], [1.0, 2.0, 3.0], p_cam, p_cam, Q_NORTH)
    assert row.target_u_px == pytest.approx(320.0 + K.fx_px * 0.1, abs=1e-9)
    assert row.target_v_px == pytest.approx(256.0 + K.fy_px * 0.05, abs=1e-9)
    assert row.target_visible == 1 and row.seq == 7 and row.time_boot_us == 1_234_567
    assert row.range_m == pytest.approx(math.sqrt(100**2 + 10**2 + 5**2))
    assert row.target_lat_deg > ORIGIN.lat_deg and row.target_alt_m == pytest.approx(45.0, abs=1e-2)
    behind = truth_row(0, 1, 0.0, ORIGIN, K, p_cam + [-100.0, 0.0, 0.0], [0, 0, 0], p_cam, p_cam, Q_NORTH)
    assert math.isnan(behind.target_u_px) and behind.target_visible == 0
    outside = truth_row(0, 1, 0.0, ORIGIN, K, p_cam + [10.0, 10.0, 0.0], [0, 0, 0], p_cam, p_cam, Q_NORTH)
    assert outside.target_u_px > 640 and outside.target_visible == 0


def test_truth_row_rejects_bad_fields():
    p = np.zeros(3)
    with pytest.raises(InputError, match="time_boot_us"):
        truth_row(0, -1, 0.0, ORIGIN, K, [100.0, 0, 0], p, p, p, Q_NORTH)
    ok = {c: 0 for c in TRUTH_COLUMNS}
    TruthRow(**ok)
    for name, value in (("target_n_m", math.inf), ("range_m", math.nan), ("target_visible", 2), ("seq", 1.5)):
        with pytest.raises(InputError, match=name):
            TruthRow(**{**ok, name: value})
    TruthRow(**{**ok, "target_u_px": math.nan, "target_v_px": math.nan})  # behind the camera: allowed


def test_truth_writer_round_trip_and_flush(tmp_path):
    path = tmp_path / "sub" / "t.csv"
    p_cam = np.array([0.0, 0.0, -50.0])
    rows = [
        truth_row(
            k,
            1_000_000 + 33_333 * k,
            k / 30,
            ORIGIN,
            K,
            p_cam + [100.0, 0.1 * k, 0.0],
            [0, 3.0, 0],
            p_cam,
            p_cam,
            Q_NORTH,
        )
        for k in range(3)
    ]
    w = TruthWriter(path)
    assert path.read_text() == ",".join(TRUTH_COLUMNS) + "\n"  # header flushed at open
    w.write(rows[0])
    assert path.read_text().count("\n") == 2  # each row flushed as written
    for r in rows[1:]:
        w.write(r)
    w.close()
    back = read_truth_csv(path)
    for name in TRUTH_COLUMNS:
        np.testing.assert_array_equal(back[name], [getattr(r, name) for r in rows])  # repr round-trips exactly
    assert back["seq"].dtype == np.int64
    with pytest.raises(InputError, match="closed"):
        w.write(rows[0])


def test_truth_writer_unwritable_path_is_config_error(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="--truth"):
        TruthWriter(tmp_path / "file" / "t.csv")


def test_read_truth_csv_names_bad_lines(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("time_boot_us,x\n1,2\n")
    with pytest.raises(InputError, match="header lacks"):
        read_truth_csv(p)
    p.write_text(",".join(TRUTH_COLUMNS) + "\n" + ",".join(["1"] * (len(TRUTH_COLUMNS) - 1)) + "\n")
    with pytest.raises(InputError, match="line 2"):
        read_truth_csv(p)


def test_scenario_name_resolves_to_shipped_file():
    assert resolve_scenario_path("P2g") == scenarios_dir() / "P2g.yaml"
    assert resolve_scenario_path("p2G") == scenarios_dir() / "P2g.yaml"  # shipped names are case-insensitive
    assert resolve_scenario_path(str(P1)) == P1


@pytest.mark.parametrize("name", ["P9", "x/y.yaml"])
def test_unknown_scenario_names_the_shipped_ones(name, capsys):
    with pytest.raises(ConfigError, match="expected an existing file or one of the shipped scenarios P1, P2, P3"):
        resolve_scenario_path(name)
    rc, err = _main_err(capsys, "run", "--scenario", name, "--log-level", "error")
    assert rc == 2 and err.count("\n") == 1 and "shipped scenarios P1, P2, P3" in err


def test_a_longer_duration_continues_the_scripted_motion():
    """--duration beyond duration_s extends the scenario: the first duration_s is the scenario's own
    flight, frame for frame; the rest continues the same models (a disturbed target included).  The
    navigation errors' white noise is drawn for the whole tick grid at once, so it is another draw."""
    sc = load_scenario(scenarios_dir() / "P1g.yaml")
    assert RunConfig(sc, duration_s=30.0).scenario.duration_s == 30.0
    short = SimCore(sc, 3, None, render=False, flight_chunk_s=1.0)
    long = SimCore(sc, 3, 30.0, render=False, flight_chunk_s=1.0)
    assert long.frame_count == 900 and long.scenario.duration_s == 30.0 and sc.duration_s == 10.0
    for k in (0, 150, short.frame_count - 1):
        a, b = dataclasses.asdict(long.frame(k).truth), dataclasses.asdict(short.frame(k).truth)
        assert {n: v for n, v in a.items() if not n.startswith("nav_")} == {
            n: v for n, v in b.items() if not n.startswith("nav_")
        }
    last = long.frame(long.frame_count - 1).truth
    planned = long.scenario.target_motion(3).state(last.t_s).p_ned_m
    flown = np.array([last.target_n_m, last.target_e_m, last.target_d_m])
    assert np.linalg.norm(flown - planned) < 5.0  # JSBSim still follows the continued path at 30 s


def test_extended_paths_that_would_collide_are_refused():
    """Two straight paths 10 m apart at the scenario's end and closing at 1 m/s meet at t = 20 s: 15 s is
    fine, 25 s is refused with the time they meet."""
    from groundsim.world.scenario import scenario_from_dict

    d = {
        "name": "closing",
        "duration_s": 10.0,
        "observer": {"motion": {"model": "uniform_linear", "p0_ned_m": [0.0, 0.0, -50.0], "v0_ned_mps": [1.0, 0, 0]}},
        "target": {"motion": {"model": "uniform_linear", "p0_ned_m": [20.0, 0.0, -50.0], "v0_ned_mps": [0.0, 0, 0]}},
    }
    sc = scenario_from_dict(d)
    assert SimCore(sc, 0, 15.0, render=False).scenario.duration_s == 15.0
    with pytest.raises(
        ConfigError,
        match=r"closing's scripted paths, continued to 25 s, come within 0 m of each other at t = 20\.000 s",
    ):
        SimCore(sc, 0, 25.0, render=False)


def test_a_motion_model_that_cannot_be_extended_is_refused_by_name():
    from groundsim.world.motion import SingerPerturbation
    from groundsim.world.scenario import VehicleSpec

    sc = load_scenario(P1)
    recorded = SingerPerturbation(sc.duration_s, (0.0, 0.0, 0.0), 1.0, np.random.default_rng(0))
    odd = dataclasses.replace(sc, observer=VehicleSpec(recorded))
    with pytest.raises(ConfigError, match="observer motion model SingerPerturbation is defined only over"):
        SimCore(odd, 0, 20.0, render=False)
    assert SimCore(odd, 0, 5.0, render=False).frame_count == 150  # within duration_s it flies as before


def test_heading_in_vehicle_state_is_body_yaw():
    sc = load_scenario(P1)
    core = SimCore(sc, 0, 0.1, render=False)
    s = core.vehicle_state(5)
    # the body's forward axis projected on the horizontal points along the heading
    fwd = rotmat_from_quat(s["q_ned_from_body"])[:, 0]
    assert math.atan2(fwd[1], fwd[0]) == pytest.approx(s["heading_rad"], abs=1e-9)
    assert abs(s["heading_rad"] - math.pi / 2) < 0.1  # P1's observer flies east, heading along its path
    assert s["alt_rel_m"] == pytest.approx(s["alt_amsl_m"] - sc.origin.alt_m)


def test_cli_defaults_match_the_adapters():
    from groundsim.io.mavlink_vehicle import DEFAULT_CONNECTION
    from onboard.io.zenoh_session import DEFAULT_VEHICLE

    assert cli.DEFAULT_MAVLINK == DEFAULT_CONNECTION == "udpout:127.0.0.1:14540"
    assert cli.DEFAULT_VEHICLE == DEFAULT_VEHICLE == "uav1"


def test_sigint_and_sigterm_set_the_stop_flag_and_handlers_are_restored():
    stop = threading.Event()
    before = signal.getsignal(signal.SIGINT)
    restore = install_stop_signals(stop)
    try:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.wait(SHORT_TIMEOUT_S)  # the handler sets the event (the timeout is a hang guard)
    finally:
        restore()
    assert signal.getsignal(signal.SIGINT) is before


class _Failing:
    """A sink whose every call fails the way a real one can (an IrtrackError)."""

    def __init__(self) -> None:
        self.calls = 0

    def _fail(self, *a, **k):
        self.calls += 1
        raise InputError("sink refused")

    update_state = poll = publish = _fail


def test_loop_survives_failing_sinks_and_unrenderable_frames(tmp_path):
    sc = load_scenario(P1)
    core = SimCore(sc, 0, 0.2)
    real_render = core.renderer().render
    calls = []

    def render(*args, **kw):  # frames 2 and 4 cannot be rendered
        calls.append(1)
        if len(calls) - 1 in (2, 4):
            raise InputError("R_ned_from_cam: not a proper rotation")
        return real_render(*args, **kw)

    core.renderer().render = render
    truth_path = tmp_path / "t.csv"
    with TruthWriter(truth_path) as w:
        report = run_loop(core, RateSpec.parse("max"), mavlink=_Failing(), publisher=_Failing(), truth=w)
    assert report.frames == 6 and not report.stopped
    assert report.errors == {"mavlink_error": 24, "publish_error": 4, "render_error": 2}
    assert len(read_truth_csv(truth_path)["seq"]) == 6  # every frame keeps its truth row


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.text(max_size=12), st.floats(allow_nan=True, allow_infinity=True).map(repr)))
def test_rate_parse_never_fails_otherwise(text):
    """Any text either parses to a valid rate or raises ConfigError naming --rate."""
    try:
        r = RateSpec.parse(text)
    except ConfigError as exc:
        assert "--rate" in str(exc)
    else:
        assert r.factor is None or 0.01 <= r.factor <= 1000.0


_finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 2**63 - 1), _finite, st.one_of(_finite, st.just(math.nan))), min_size=1, max_size=5
    )
)
def test_truth_csv_round_trips_any_values_exactly(tmp_path_factory, rows):
    path = tmp_path_factory.mktemp("rt") / "t.csv"
    written = []
    with TruthWriter(path) as w:
        for n, (t_us, x, u) in enumerate(rows):
            vals = {c: x for c in TRUTH_COLUMNS}
            vals.update(time_boot_us=t_us, seq=n, target_visible=n % 2, target_u_px=u, target_v_px=u, time_unix_us=t_us)
            row = TruthRow(**vals)
            w.write(row)
            written.append(row)
    back = read_truth_csv(path)
    for name in TRUTH_COLUMNS:
        np.testing.assert_array_equal(back[name], [getattr(r, name) for r in written])


def test_an_extended_path_faster_than_a_multirotor_is_refused_with_the_longest_duration_that_flies():
    """P3's observer flies a cubic: its speed grows as t^2, 46 m/s by 19.7 s where JSBSim's flight used to
    diverge mid-run.  Continued to 30 s it is refused up front, naming when it passes the limit."""
    from groundsim.world.sim import MAX_EXTENDED_SPEED_MPS

    sc = load_scenario(scenarios_dir() / "P3.yaml")
    with pytest.raises(
        ConfigError, match=r"P3's observer path \(Cubic\), continued to 30 s, reaches 25\.\d m/s at t = 1[45]\.\d+ s"
    ) as e:
        SimCore(sc, 0, 30.0, render=False)
    longest_s = float(str(e.value).rsplit("at most ", 1)[1].split(" s")[0])
    v_mps = np.linalg.norm(sc.observer.base_motion.state(np.array([longest_s - 0.1])).v_ned_mps)
    assert v_mps <= MAX_EXTENDED_SPEED_MPS  # the duration it names does fly
    assert SimCore(sc, 0, 12.0, render=False).scenario.duration_s == 12.0
