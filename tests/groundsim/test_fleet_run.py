"""End to end: ``groundsim run --scenario F1`` flies two observers, each vehicle's MAVLink on its own
endpoint (``--mavlink NAME=ENDPOINT``), its frames on ``irtrack/<NAME>/ir/frame`` and its own truth file;
every vehicle has its own boot clock and sends SYSTEM_TIME mapping it to the one simulated UTC."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from groundsim.io.mavlink_vehicle import open_mavlink2
from groundsim.io.ports import free_tcp_port, free_udp_port
from groundsim.world.scenario import load_scenario, scenarios_dir
from groundsim.world.truth import read_truth_csv
from onboard.core.irframe import decode_irframe
from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session
from tests.process_helpers import run_module

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

F1 = scenarios_dir() / "F1.yaml"
NAMES = ("uav1", "uav2")
DURATION_S = 1.0
FRAMES = 30
F1_START_UNIX_US = 1_780_304_400_000_000  # F1's start_time_utc, 2026-06-01T09:00:00Z
UTC_ERROR_US = {"uav1": 0, "uav2": 20_000}  # --utc-error-ms uav2=20: its SYSTEM_TIME's UTC 20 ms late
PROCESS_TIMEOUT_S = 150.0  # two vehicles, 1 s at --rate max, on a loaded 2-core machine
DELIVERY_WAIT_S = 5.0
BOOT_MS_TOL_US = 1000  # SYSTEM_TIME carries the boot time in whole ms, UTC in us
LON_GAP_DEG = 2e-3  # uav2 flies 290 m east of uav1: 0.003 deg of longitude at 32 N


class _Listener:
    """A plain pymavlink udpin socket, drained by a thread while the simulator runs."""

    def __init__(self, port: int) -> None:
        self.conn = open_mavlink2(f"udpin:127.0.0.1:{port}", 255, 190)
        self.msgs: list = []
        self.arrivals_unix_s: list[float] = []  # each message's receipt on this machine's clock, while running
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        while not self._done.is_set():
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is not None and m.get_type() != "BAD_DATA":
                self.msgs.append(m)
                self.arrivals_unix_s.append(time.time())

    def close(self) -> None:
        self._done.set()
        self._thread.join(PROCESS_TIMEOUT_S)
        # the simulator has exited: what it sent to loopback is already queued at our socket
        while (m := self.conn.recv_match(blocking=False)) is not None:
            if m.get_type() != "BAD_DATA":
                self.msgs.append(m)
        self.conn.close()

    def of(self, mtype: str) -> list:
        return [m for m in self.msgs if m.get_type() == mtype]


@pytest.fixture(scope="module")
def fleet_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet")
    ports = {n: free_udp_port() for n in NAMES}
    zport = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    session = open_session(ZenohConfig(listen=(endpoint,)))
    payloads: dict[str, list[bytes]] = {n: [] for n in NAMES}
    lock = threading.Lock()
    subs = []
    for n in NAMES:

        def on_sample(sample, n=n):
            with lock:
                payloads[n].append(sample.payload.to_bytes())

        subs.append(session.declare_subscriber(frame_key(n), on_sample))
    listeners = {n: _Listener(p) for n, p in ports.items()}
    try:
        argv = ["run", "--scenario", "F1", "--rate", "max", "--duration", str(DURATION_S), "--log-level", "warning"]
        argv += ["--zenoh-connect", endpoint, "--truth", str(out / "truth.csv"), "--utc-error-ms", "uav2=20"]
        for n in NAMES:
            argv += ["--mavlink", f"{n}=udpout:127.0.0.1:{ports[n]}"]
        proc = run_module("groundsim", *argv, timeout_s=PROCESS_TIMEOUT_S)
        deadline = time.monotonic() + DELIVERY_WAIT_S
        while time.monotonic() < deadline:
            with lock:
                if all(len(p) >= FRAMES for p in payloads.values()):
                    break
            time.sleep(0.05)
    finally:
        for lst in listeners.values():
            lst.close()
        for s in subs:
            s.undeclare()
        session.close()
    with lock:
        frames = {n: [decode_irframe(p) for p in ps] for n, ps in payloads.items()}
    return proc, listeners, frames, out


def test_the_run_writes_one_truth_file_per_observer(fleet_run):
    proc, _, _, out = fleet_run
    assert proc.returncode == 0, proc.stderr
    assert not (out / "truth.csv").exists()
    t1, t2 = (read_truth_csv(out / f"truth.{n}.csv") for n in NAMES)
    assert len(t1["seq"]) == len(t2["seq"]) == FRAMES
    # one UTC for both, the scenario's start + t; each its own boot clock
    np.testing.assert_array_equal(t1["time_unix_us"], t2["time_unix_us"])
    np.testing.assert_array_equal(t1["time_unix_us"], F1_START_UNIX_US + np.round(t1["t_s"] * 1e6).astype(np.int64))
    assert len(set(t1["time_boot_us"] - t2["time_boot_us"])) == 1 and t1["time_boot_us"][0] != t2["time_boot_us"][0]
    # one shared target, two observers 290 m apart
    for c in ("target_n_m", "target_e_m", "target_d_m"):
        np.testing.assert_allclose(t1[c], t2[c], atol=1e-9)
    np.testing.assert_allclose(t2["observer_e_m"] - t1["observer_e_m"], 290.0, atol=1.0)
    assert t1["target_visible"].all() and t2["target_visible"].all()


def test_each_endpoint_gets_its_own_vehicle_with_its_boot_clock_and_a_consistent_utc(fleet_run):
    proc, listeners, _, out = fleet_run
    assert proc.returncode == 0, proc.stderr
    sc = load_scenario(F1)
    boots = {o.name: o.boot_start_us for o in sc.observers}
    lon = {}
    for n, lst in listeners.items():
        for mtype in ("HEARTBEAT", "ATTITUDE", "ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT", "SYSTEM_TIME"):
            assert lst.of(mtype), f"{n}: no {mtype}"
        truth = read_truth_csv(out / f"truth.{n}.csv")
        boot0, boot1 = int(truth["time_boot_us"][0]), int(truth["time_boot_us"][-1])
        assert boot0 == boots[n]
        for m in lst.of("ATTITUDE") + lst.of("GLOBAL_POSITION_INT"):  # stamped on this vehicle's boot clock
            assert boot0 - 1000 <= m.time_boot_ms * 1000 <= boot1 + 1000, (n, m)
        for st in lst.of("SYSTEM_TIME"):
            unix_at_boot_us = st.time_unix_usec - st.time_boot_ms * 1000
            # UTC at boot + boot time = the one simulated UTC (plus the injected error), to the ms the boot
            # time is rounded to
            err = UTC_ERROR_US[n]
            assert 0 <= unix_at_boot_us - (F1_START_UNIX_US + err - boots[n]) < BOOT_MS_TOL_US, (n, st)
        first = lst.of("SYSTEM_TIME")[0]
        # its instant up to 1 ms after the first poll, the boot time truncated to ms
        at_us = first.time_unix_usec - (F1_START_UNIX_US + UTC_ERROR_US[n])
        assert 0 <= at_us < 1000 and first.time_boot_ms * 1000 == boots[n], (n, first)
        lon[n] = np.mean([m.lon for m in lst.of("GLOBAL_POSITION_INT")]) * 1e-7
    assert lon["uav2"] - lon["uav1"] > LON_GAP_DEG  # each endpoint has its own vehicle, not a copy
    assert listeners["uav1"].of("SYSTEM_TIME")[0].time_boot_ms != listeners["uav2"].of("SYSTEM_TIME")[0].time_boot_ms


def test_each_observers_frames_are_on_its_own_key_stamped_on_its_boot_clock(fleet_run):
    proc, _, frames, out = fleet_run
    assert proc.returncode == 0, proc.stderr
    for n in NAMES:
        truth = read_truth_csv(out / f"truth.{n}.csv")
        got = {f.seq: f.time_boot_us for f in frames[n]}
        assert len(got) >= FRAMES * 0.9, (n, len(got))
        for seq, stamp in got.items():
            assert stamp == truth["time_boot_us"][seq]


def test_a_paced_fleet_run_puts_utc_on_the_wall_clock_when_its_loop_starts():
    """``--rate realtime`` starts UTC at the machine's clock (``--start-time-utc now`` by default) when the loop
    starts, not when the process did: each SYSTEM_TIME's UTC is its receipt time on loopback, within a few
    ms (start-up put it ~0.5 s behind before); the injected ``--utc-error-ms`` shows on its vehicle only."""
    ports = {n: free_udp_port() for n in NAMES}
    listeners = {n: _Listener(p) for n, p in ports.items()}
    try:
        argv = ["run", "--scenario", "F1", "--rate", "realtime", "--duration", "2", "--no-render"]
        argv += ["--log-level", "warning", "--utc-error-ms", "uav2=20"]
        for n in NAMES:
            argv += ["--mavlink", f"{n}=udpout:127.0.0.1:{ports[n]}"]
        proc = run_module("groundsim", *argv, timeout_s=PROCESS_TIMEOUT_S)
    finally:
        for lst in listeners.values():
            lst.close()
    assert proc.returncode == 0, proc.stderr
    lag_s = {}
    for n, lst in listeners.items():
        lags = [
            t - m.time_unix_usec / 1e6 for m, t in zip(lst.msgs, lst.arrivals_unix_s) if m.get_type() == "SYSTEM_TIME"
        ]
        assert len(lags) >= 2, n
        lag_s[n] = float(np.min(lags))  # the fastest delivery: the clock offset, not the queueing
    assert abs(lag_s["uav1"]) < 0.05, lag_s
    assert lag_s["uav1"] - lag_s["uav2"] == pytest.approx(0.020, abs=0.010), lag_s
