"""``python -m onboard.fuse``: the fusion's step logic on payloads (no sockets), its wire, and the real
process between two synthetic vehicles and a subscriber on loopback zenoh."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from groundsim.evaluation.fleet_synth import SynthTarget, SynthVehicle, measure, track_payload
from onboard.app.fuse import EVENTS, Fusion, Inbox, build_parser, drain
from onboard.app.fuse_noise import noise_models
from onboard.core.counters import RejectCounter
from onboard.core.frames import GeodeticOrigin, ned_from_geodetic
from onboard.estimation.fleet import FleetConfig
from onboard.estimation.fleet_tracker import FleetTracker
from onboard.estimation.map_estimator import NoiseModel
from onboard.io.fleet_wire import (
    CLOCK_DRIFT_PPM,
    FLEET_TRACK_SCHEMA,
    ClockConsistency,
    CommonClock,
    fleet_track_key,
    ned_transform,
    vehicle_fleet_track_key,
    vehicle_from_track_key,
)
from tests.process_helpers import terminate

REPO = Path(__file__).resolve().parents[2]
ATOL_M = 1e-6  # 1 um: frame maps
ORIGIN_1 = GeodeticOrigin(32.0, 118.8, 20.0)
ORIGIN_2 = GeodeticOrigin(32.003, 118.803, 35.0)  # ~430 m away: its tangent plane differs by ~70 urad
T0_UNIX_S = 1_800_000_000.0
UAV1 = SynthVehicle("uav1", (0.0, -120.0, -100.0), (8.0, 0.0, 0.0))
UAV2 = SynthVehicle("uav2", (0.0, 120.0, -100.0), (8.0, 0.0, 0.0))
UAV3 = SynthVehicle("uav3", (-200.0, 0.0, -120.0), (0.0, 8.0, 0.0))
TARGET = SynthTarget((900.0, 40.0, -150.0), (-6.0, 4.0, 0.0))


def payload_of(
    vehicle: SynthVehicle,
    t_s: float,
    rng,
    seq: int,
    time_unix: bool = True,
    t0_unix_s: float = T0_UNIX_S,
    clock_error_s: float = 0.0,
    published_bias_rad: float = 0.0,
) -> bytes:
    """``vehicle``'s track at ``t_s`` after ``t0_unix_s`` (truth in ORIGIN_1's frame), in its own frame (uav2,
    uav3: ORIGIN_2's), 0.3 mrad white bearing noise (its sigmas holding ``published_bias_rad`` too); its
    ``time_unix_us`` off by ``clock_error_s``."""
    los = measure(vehicle, TARGET, t_s, rng, 0.3e-3, published_bias_rad)
    origin = ORIGIN_1 if vehicle.name == "uav1" else ORIGIN_2
    R, t = ned_transform(ORIGIN_1, origin)
    los = type(los)(R @ los.p_cam_ned_m + t, R @ los.los_ned, los.sigma_az_rad, los.sigma_el_rad, los.truth_p_ned_m)
    obj = track_payload(
        vehicle.name,
        seq,
        int(1e6 + t_s * 1e6),
        los,
        origin,
        time_unix_us=int(round((t0_unix_s + t_s + clock_error_s) * 1e6)) if time_unix else None,
    )
    return json.dumps(obj).encode()


def truth_in(msg: dict, t0_unix_s: float = T0_UNIX_S) -> np.ndarray:
    """The target's true position at ``msg``'s time in ``msg``'s own frame (the fleet's origin is the first
    vehicle's heard, whichever that was)."""
    o = msg["origin"]
    R, t = ned_transform(ORIGIN_1, GeodeticOrigin(o["lat_deg"], o["lon_deg"], o["alt_m"]))
    return R @ TARGET.p_ned_m(msg["time_unix_us"] / 1e6 - t0_unix_s) + t


def new_fusion(**kw) -> Fusion:
    counter = RejectCounter()
    kw.setdefault("clock_check", ClockConsistency(judging_max_s=0.0))  # clock tests of their own: test_fuse_clock.py
    return Fusion(FleetTracker(FleetConfig(), NoiseModel(), counter), CommonClock(kw.pop("offsets", None)), **kw)


def run_pair(fusion: Fusion, seconds: float, rng, skip=()) -> list[tuple[str, dict]]:
    out = []
    for k, t in enumerate(np.arange(0.0, seconds, 1 / 30)):
        for v in (UAV1, UAV2):
            if v.name not in skip:
                fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, k), T0_UNIX_S + t + 0.005)
        out += fusion.flush()
    return out


def test_the_frame_map_between_two_origins_is_a_rigid_round_trip():
    R, t = ned_transform(ORIGIN_1, ORIGIN_2)
    Rb, tb = ned_transform(ORIGIN_2, ORIGIN_1)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    p = np.array([900.0, 40.0, -150.0])
    np.testing.assert_allclose(Rb @ (R @ p + t) + tb, p, atol=ATOL_M)
    np.testing.assert_allclose(
        t, ned_from_geodetic(ORIGIN_1.lat_deg, ORIGIN_1.lon_deg, ORIGIN_1.alt_m, ORIGIN_2), atol=ATOL_M
    )


def test_two_vehicles_in_their_own_frames_fuse_near_the_truth_and_each_gets_it_in_its_frame():
    fusion = new_fusion()
    out = run_pair(fusion, 1.0, np.random.default_rng(1))
    fleet = [p for k, p in out if k == fleet_track_key()]
    last = fleet[-1]
    assert last["schema"] == FLEET_TRACK_SCHEMA and last["observable"]
    assert sorted(c["vehicle"] for c in last["vehicles"]) == ["uav1", "uav2"]
    assert {c["time_source"] for c in last["vehicles"]} == {"vehicle"}
    truth = truth_in(last)
    e = np.asarray(last["ned_m"]) - truth
    assert float(e @ np.linalg.solve(np.asarray(last["cov_ned_m2"]), e)) < 16.3  # chi2(3) at 0.999
    assert np.linalg.norm(e) < 0.01 * np.linalg.norm(truth)
    mine = [p for k, p in out if k == vehicle_fleet_track_key("uav2")][-1]
    R, t = ned_transform(ORIGIN_1, ORIGIN_2)
    np.testing.assert_allclose(mine["ned_m"], R @ np.asarray(last["ned_m"]) + t, atol=1e-3)
    assert mine["origin"]["lat_deg"] == ORIGIN_2.lat_deg and mine["vehicle"] == "uav2"
    assert (mine["lat_deg"], mine["lon_deg"], mine["alt_m"]) == (last["lat_deg"], last["lon_deg"], last["alt_m"])
    assert fusion.counter.total == fusion.counter["target_created"] == 1


def test_without_time_unix_us_the_offset_is_configured_or_estimated_from_arrivals():
    offsets = {"uav1": T0_UNIX_S - 1.0, "uav2": T0_UNIX_S - 1.0}  # the payloads' boot clock reads 1 s at T0
    for fusion, source in ((new_fusion(offsets=offsets), "configured"), (new_fusion(), "arrival")):
        rng = np.random.default_rng(2)
        for k, t in enumerate(np.arange(0.0, 1.0, 1 / 30)):
            for v in (UAV1, UAV2):
                fusion.receive(
                    f"irtrack/{v.name}/track", payload_of(v, t, rng, k, time_unix=False), T0_UNIX_S + t + 0.004
                )
            out = fusion.flush()
        last = [p for k, p in out if k == fleet_track_key()][-1]
        assert last["observable"] and {c["time_source"] for c in last["vehicles"]} == {source}
        # the arrival estimate is the boot time plus the shortest latency (4 ms here)
        assert last["time_unix_us"] / 1e6 - T0_UNIX_S == pytest.approx(
            29 / 30 + (0.004 if source == "arrival" else 0), abs=1e-5
        )


def _good() -> dict:
    return json.loads(payload_of(UAV1, 0.0, np.random.default_rng(0), 1))


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"\xff not json", "not_json"),
        (b"[1, 2]", "bad_track"),
        (json.dumps({**_good(), "seq": "one"}).encode(), "bad_track"),
        (json.dumps({**_good(), "los_ned": [1, 0]}).encode(), "bad_track"),
        (json.dumps({**_good(), "camera_ned_m": None}).encode(), "bad_track"),
        (json.dumps({**_good(), "time_unix_us": 1.5}).encode(), "bad_time_unix_us"),
        (json.dumps({**_good(), "time_unix_us": -4}).encode(), "bad_time_unix_us"),
        (json.dumps({**_good(), "origin": None}).encode(), "no_origin"),
        (json.dumps({**_good(), "vehicle": "uav2"}).encode(), "bad_track"),
        (json.dumps({**_good(), "time_unix_us": int((T0_UNIX_S - 10) * 1e6)}).encode(), "stale"),
        (json.dumps({**_good(), "time_unix_us": int((T0_UNIX_S + 10) * 1e6)}).encode(), "future"),
    ],
)
def test_bad_input_is_counted_by_reason_and_never_becomes_a_fused_point(payload, reason):
    fusion = new_fusion()
    rng = np.random.default_rng(5)
    for k, t in enumerate(np.arange(0.0, 0.5, 1 / 30)):
        fusion.receive("irtrack/uav2/track", payload_of(UAV2, t, rng, k), T0_UNIX_S + t)
        fusion.receive("irtrack/uav1/track", payload, T0_UNIX_S + t)  # uav1 only ever sends the bad one
    assert fusion.flush() == []
    assert fusion.counter[reason] == 15
    assert fusion.tracker.targets == ()


def test_a_track_past_the_size_cap_is_refused_unparsed():
    """A good track padded with a 100 KB key was parsed and fused (extra keys are ignored); parsing is paid per byte,
    and one publisher of 5 MB tracks at 10 Hz stalled the fusion process for 6 s (no status, every vehicle silent)."""
    fusion = new_fusion()
    rng = np.random.default_rng(5)
    padded = json.dumps({**_good(), "junk": "x" * 100_000}).encode()
    for k, t in enumerate(np.arange(0.0, 0.5, 1 / 30)):
        fusion.receive("irtrack/uav2/track", payload_of(UAV2, t, rng, k), T0_UNIX_S + t)
        fusion.receive("irtrack/uav1/track", padded, T0_UNIX_S + t)
    assert fusion.flush() == []
    assert fusion.counter["track_too_large"] == 15 and fusion.tracker.targets == ()


def test_each_vehicles_refusals_are_logged_though_another_vehicle_logged_the_same_reason(caplog):
    """Stale tracks of uav1, then of uav2 within the log interval: uav2's were counted but never logged, so its
    fault stayed hidden behind uav1's (a fault-injection audit's leftover: per-vehicle log intervals)."""
    fusion = new_fusion()
    old = int((T0_UNIX_S - 10) * 1e6)
    with caplog.at_level(logging.WARNING):
        for key, who in (("irtrack/uav1/track", UAV1), ("irtrack/uav2/track", UAV2)):
            for k in range(3):
                bad = {**json.loads(payload_of(who, 0.0, np.random.default_rng(k), k)), "time_unix_us": old}
                fusion.receive(key, json.dumps(bad).encode(), T0_UNIX_S)
    assert fusion.counter["stale"] == 6
    logged = [r.getMessage() for r in caplog.records if r.getMessage().startswith("stale: ")]
    assert [m.split(":")[1].strip() for m in logged] == ["irtrack/uav1/track", "irtrack/uav2/track"], logged


def test_its_own_output_and_other_vehicles_are_not_input(caplog):
    fusion = new_fusion(vehicles=["uav1", "uva2"])  # uav2 mistyped
    fusion.receive(fleet_track_key(), b"{}", T0_UNIX_S)
    with caplog.at_level(logging.WARNING):
        fusion.receive("irtrack/uav2/track", b"{}", T0_UNIX_S)
    # not fused, but a vehicle outside --vehicles is counted and warned of, naming the close configured name (it was
    # an INFO line with no hint, and the other vehicle's rays were then warned of as unpaired)
    assert fusion.received == 0 and fusion.counter.counts == {"vehicle_not_configured": 1}
    (warned,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert "did you mean 'uva2' in --vehicles? it is 'uav2' on the wire" in warned
    assert vehicle_from_track_key("irtrack/fleet/track") is None
    assert vehicle_from_track_key("irtrack/uav1/fleet/track") is None
    assert vehicle_from_track_key("irtrack/uav1/track") == "uav1"


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--vehicles", "fleet"], "fusion's own key"),
        (["--vehicles", "uav 1"], "vehicle name"),
        (["--origin", "32,118"], "LAT,LON,ALT"),
        (["--clock-offset", "uav1"], "NAME=SECONDS"),
        (["--max-age-s", "-1"], "--max-age-s: expected a number in (0, 3600], got '-1'"),
        (["--max-age-s", "nan"], "--max-age-s: expected a number in (0, 3600], got 'nan'"),
        (["--camera-white-m", "0"], "--camera-white-m: expected a number in (0, 1000]"),
        (["--attitude-bias-deg", "-0.1"], "--attitude-bias-deg"),
        (
            ["--vehicle-noise", "uav2:camera_white_m=0"],
            "--vehicle-noise: uav2: camera_white_m: expected a number in (0, 1000]",
        ),
        (["--vehicle-noise", "uav2:attitude_bias_deg=-1"], "--vehicle-noise: uav2: attitude_bias_deg"),
        (["--vehicle-noise", "uav2:attitude_bias=0.5"], "--vehicle-noise: expected NAME:KEY=VALUE"),
        (["--vehicle-noise", "uav2"], "--vehicle-noise: expected NAME:KEY=VALUE"),
        (["--vehicle-noise", "fleet:camera_white_m=1"], "--vehicle-noise: expected NAME:KEY=VALUE"),
        (["--max-time-sigma-ms", "nan"], "--max-time-sigma-ms"),
        # zero refuses every line of sight: a window of no age or no clock uncertainty at all
        (["--max-age-s", "0"], "--max-age-s: expected a number in (0, 3600], got '0'"),
        (["--max-time-sigma-ms", "0"], "--max-time-sigma-ms: expected a number in [0.001, 10000], got '0'"),
        (["--max-time-sigma-ms", "1e-300"], "--max-time-sigma-ms: expected a number in [0.001, 10000]"),
        (
            ["--silent-after-s", "0"],
            "--silent-after-s: expected a number in (0, 3600], got '0'",
        ),  # every vehicle silent
        # values no camera has: the solve overflowed on them
        (["--attitude-bias-deg", "1e308"], "--attitude-bias-deg: expected a number in [0, 90], got '1e308'"),
        (["--camera-offset-m", "1e200"], "--camera-offset-m: expected a number in [0, 1000], got '1e200'"),
        (
            ["--vehicle-noise", "uav2:camera_offset_m=1e200"],
            "--vehicle-noise: uav2: camera_offset_m: expected a number",
        ),
        (["--origin", "0,0,1e300"], "ALT in [-1000, 100000] m"),
        (["--clock-tolerance-ms", "0"], "--clock-tolerance-ms: expected a number in (0, 10000], got '0'"),
        (["--clock-offset", "fleet=3"], "NAME=SECONDS"),
    ],
)
def test_bad_options_exit_2_on_one_line(argv, words, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--vehicles", "uav1", "uav1"], "--vehicles: uav1 given more than once"),
        (["--clock-offset", "uav1=1", "--clock-offset", "uav1=2"], "--clock-offset: uav1 given more than once"),
        (
            ["--vehicle-noise", "uav2:camera_white_m=1", "--vehicle-noise", "uav2:camera_offset_m=1"],
            "--vehicle-noise: uav2 given more than once",
        ),
        (["--vehicles", "uav1", "uav2", "--clock-offset", "uav3=1"], "--clock-offset: uav3 not one of --vehicles"),
        (
            ["--vehicles", "uav1", "--vehicle-noise", "uav02:camera_white_m=1"],
            "--vehicle-noise: uav02 not one of --vehicles uav1",
        ),
    ],
)
def test_a_vehicle_named_twice_or_outside_vehicles_is_refused(argv, words, capsys):
    from onboard.app.fuse import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1, err


def test_a_daemon_cannot_be_named_as_the_fusion():
    from onboard.app.config import build_config
    from onboard.core.schema import SchemaError

    with pytest.raises(SchemaError, match="vehicle.*other than .fleet."):
        build_config({"vehicle": "fleet"})
    assert build_config({"vehicle": "fleet2"}).vehicle == "fleet2"


# --------------------------------------------------------------------------- the real process

START_TIMEOUT_S = 30.0  # imports and the zenoh session on a busy 2-core machine
DATA_TIMEOUT_S = 15.0
STOP_TIMEOUT_S = 10.0  # SIGTERM -> exit (a hang guard: a SIGKILL after it fails the exit-code check)


class _Collector:
    """Fleet tracks and status messages as they arrive; ``wait_for`` waits on an event, not a sleep."""

    def __init__(self) -> None:
        self.fleet: list[dict] = []
        self.status: list[dict] = []
        self._cv = threading.Condition()

    def on_fleet(self, sample) -> None:
        with self._cv:
            self.fleet.append(json.loads(sample.payload.to_bytes()))
            self._cv.notify_all()

    def on_status(self, sample) -> None:
        with self._cv:
            self.status.append(json.loads(sample.payload.to_bytes()))
            self._cv.notify_all()

    def wait_for(self, predicate, timeout_s: float) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: predicate(self), timeout=timeout_s)


@pytest.mark.integration
def test_the_fuse_process_fuses_two_vehicles_degrades_to_one_honestly_and_takes_the_other_back():
    """uav2's daemon stops (its session closes) for 2.2 s and comes back: the fleet track goes on with uav1 alone
    (unobservable), the status names uav2 silent, and uav2 rejoins the same fused solution when it returns."""
    import time

    from groundsim.io.ports import free_tcp_port
    from onboard.io.zenoh_session import TRACK_ENCODING, ZenohConfig, open_session, track_key

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "onboard.fuse", "--zenoh-listen", endpoint, "--seconds", "120"]
        + ["--status-interval-s", "0.2", "--log-level", "WARNING"]
        # the synthetic bearings' published sigma is their 0.3 mrad white noise alone (no attitude bias in it, as
        # new_fusion's NoiseModel() assumes); the default 0.1 deg bias prior would take it for mostly bias and
        # fail every multi-frame solve's residual test; their camera positions are exact (1 um: it must be > 0)
        + ["--attitude-bias-deg", "0", "--camera-white-m", "1e-6"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    sessions = []
    got = _Collector()
    t_stop, t_back, t_end = 1.2, 3.4, 4.2  # uav2's daemon "dies" at t_stop and is restarted at t_back
    try:
        listen = ZenohConfig(connect=(endpoint,))
        watcher = open_session(listen)
        sessions.append(watcher)
        watcher.declare_subscriber(fleet_track_key(), got.on_fleet)
        watcher.declare_subscriber("irtrack/fleet/status", got.on_status)
        assert got.wait_for(lambda g: g.status, START_TIMEOUT_S), "no status from the fuse process"

        def publisher(name: str):
            s = open_session(listen)
            sessions.append(s)
            return s, s.declare_publisher(track_key(name), encoding=TRACK_ENCODING)

        pubs = {v.name: publisher(v.name) for v in (UAV1, UAV2)}
        rng = np.random.default_rng(7)
        t0 = time.time()  # the payloads' UTC is this machine's: nothing is stale
        for k, t in enumerate(np.arange(0.0, t_end, 1 / 30)):
            for v in (UAV1, UAV2):
                if v.name == "uav2" and t_stop <= t < t_back:
                    if v.name in pubs:
                        session, _ = pubs.pop(v.name)
                        sessions.remove(session)
                        session.close()
                    continue
                if v.name not in pubs:
                    pubs[v.name] = publisher(v.name)
                pubs[v.name][1].put(payload_of(v, t, rng, k, t0_unix_s=t0))
            time.sleep(max(0.0, t0 + t + 1 / 30 - time.time()))  # a 30 Hz camera's pace, not a wait for a result
        end_us = int((t0 + t_end - 0.1) * 1e6)
        assert got.wait_for(lambda g: any(m["time_unix_us"] >= end_us for m in g.fleet), DATA_TIMEOUT_S)
        assert got.wait_for(lambda g: g.status[-1]["events"].get("vehicle_back", 0) >= 1, DATA_TIMEOUT_S)
    finally:
        for s in sessions:
            s.close()
        terminate(proc, STOP_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr.read().decode() if proc.stderr else ""
    both = [m for m in got.fleet if len(m["vehicles"]) == 2 and m["observable"]]
    assert both, "no observable two-vehicle fleet track"
    m = both[-1]
    truth = truth_in(m, t0)
    e = np.asarray(m["ned_m"]) - truth
    assert np.linalg.norm(e) < 0.01 * np.linalg.norm(truth)
    assert float(e @ np.linalg.solve(np.asarray(m["cov_ned_m2"]), e)) < 16.3
    # within 1 s of data time after uav2 stopped, the fleet track is uav1's alone and says it is unobservable
    # (until half a frame before t_back: uav2's first frame back is stamped t0 + t_back, to float rounding)
    alone = [m for m in got.fleet if (t0 + t_stop + 1.0) * 1e6 <= m["time_unix_us"] < (t0 + t_back - 1 / 60) * 1e6]
    odd = [m for m in alone if m["observable"] or [c["vehicle"] for c in m["vehicles"]] != ["uav1"]]
    assert alone and not odd, [(m["time_unix_us"] / 1e6 - t0, m["observable"], m["vehicles"]) for m in odd][:3]
    assert any(st["silent"] == ["uav2"] for st in got.status), "uav2 never named silent"
    assert got.status[-1]["silent"] == [] and got.status[-1]["events"]["vehicle_silent"] == 1
    assert "vehicle_silent" not in got.status[-1]["rejected"]  # an event, not refused input
    # back: uav2 contributes again (after member_timeout_s it re-associated through the fleet's estimate)
    back = [m for m in got.fleet if m["time_unix_us"] >= (t0 + t_back + 0.3) * 1e6]
    assert any(len(m["vehicles"]) == 2 and m["observable"] for m in back), "uav2 did not rejoin"
    assert got.status[-1]["rejected"].get("stale", 0) == 0


def test_the_fusion_dials_no_peer_that_gossip_names_unless_told():
    """The fusion left zenoh's gossip autoconnect unset, so zenoh's default dialed every peer and router a router's
    gossip named (addresses nobody gave it); the daemon turns it off, and so does the fusion now."""
    from onboard.app.fuse import zenoh_settings
    from onboard.io.zenoh_session import build_config

    def autoconnect(*argv: str):
        settings = zenoh_settings(build_parser().parse_args(list(argv)))
        return settings.gossip_autoconnect, json.loads(build_config(settings).get_json("scouting/gossip/autoconnect"))

    assert autoconnect() == (False, [])
    assert autoconnect("--zenoh-connect", "tcp/127.0.0.1:7447", "--zenoh-listen", "tcp/127.0.0.1:0") == (False, [])
    assert autoconnect("--zenoh-config", str(REPO / "deploy" / "zenoh-router.json5")) == (False, [])
    assert autoconnect("--zenoh-gossip-autoconnect") == (True, ["router", "peer"])


def _fusion_beside_a_routers_peer(gossip: bool) -> None:
    """A router with gossip on (deploy/zenoh-router.json5's), a daemon-like peer that listens on loopback and dials
    nothing, and the fusion connected to the router as a peer, with --zenoh-gossip-autoconnect if ``gossip``: what
    the test below asserts, asserted here (each case has its own router, peers and fusion process)."""
    import time

    import zenoh

    from groundsim.io.ports import free_tcp_port
    from onboard.io.zenoh_session import TRACK_ENCODING, ZenohConfig, open_session, track_key

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps("router"))
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "true")
    sessions = [zenoh.open(cfg)]
    got = _Collector()
    control: list[bytes] = []
    proc = None
    try:
        daemon = open_session(ZenohConfig(connect=(endpoint,), listen=("tcp/127.0.0.1:0",), gossip_autoconnect=False))
        sessions.append(daemon)
        pub = daemon.declare_publisher(track_key("uav1"), encoding=TRACK_ENCODING)
        watcher = open_session(ZenohConfig(connect=(endpoint,), listen=("tcp/127.0.0.1:0",), gossip_autoconnect=True))
        sessions.append(watcher)
        watcher.declare_subscriber("irtrack/fleet/status", got.on_status)
        watcher.declare_subscriber(track_key("uav1"), lambda s: control.append(s.payload.to_bytes()))
        argv = ["--zenoh-connect", endpoint, "--zenoh-listen", "tcp/127.0.0.1:0", "--status-interval-s", "0.2"]
        proc = subprocess.Popen(
            [sys.executable, "-m", "onboard.fuse", *argv, "--seconds", "60", "--log-level", "WARNING"]
            + (["--zenoh-gossip-autoconnect"] if gossip else []),
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        assert got.wait_for(lambda g: g.status, START_TIMEOUT_S), "no status from the fuse process"
        rng, t0 = np.random.default_rng(9), time.time()
        for k in range(60):  # 2 s of a 30 Hz camera after the fusion is up
            pub.put(payload_of(UAV1, k / 30, rng, k, t0_unix_s=t0))
            time.sleep(max(0.0, t0 + (k + 1) / 30 - time.time()))
        assert len(control) >= 30, "the control peer heard nothing: the daemon-like peer is unreachable"
        seen = len(got.status)
        assert got.wait_for(lambda g: len(g.status) > seen, DATA_TIMEOUT_S)  # a status from after the last put
        assert (got.status[-1]["received"] > 0) == gossip, got.status[-1]["received"]
    finally:
        for s in reversed(sessions):
            s.close()
        if proc is not None:
            terminate(proc, STOP_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr.read().decode() if proc.stderr else ""


GOSSIP_CASES = (False, True)


@pytest.fixture(scope="module")
def gossip_cases():
    """Both cases of the test below at once, each with its own router, ports and fusion process: one after the
    other they took 4.3-5.1 s each, mostly the fusion's start and the 2 s of frames, which need little CPU (60 small
    messages a case).  Per case a future of :func:`_fusion_beside_a_routers_peer` (``result()`` raises what the
    case raised)."""
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(len(GOSSIP_CASES))
    yield {gossip: pool.submit(_fusion_beside_a_routers_peer, gossip) for gossip in GOSSIP_CASES}
    pool.shutdown(wait=True)  # each case closes its sessions and ends its process whatever happens


@pytest.mark.integration
@pytest.mark.parametrize("gossip", GOSSIP_CASES)
def test_the_fuse_process_hears_a_routers_other_peers_only_when_told_to_dial_them(gossip, gossip_cases):
    """A router with gossip on (deploy/zenoh-router.json5's), a daemon-like peer that listens on loopback and dials
    nothing, and the fusion connected to the router as a peer: by default it never dials the daemon (nothing
    arrives: a zenoh router does not relay between peers), with --zenoh-gossip-autoconnect it does.  A third peer
    that dials what gossip names is the control: the daemon's tracks reach it."""
    gossip_cases[gossip].result()


def test_the_arrival_clock_takes_the_shortest_latency_and_forgets_it_on_a_reboot():
    clock = CommonClock(window_s=10.0)
    t, src = clock.time_s("uav1", 5_000_000, None, 100.030)
    assert (t, src) == (pytest.approx(100.030), "arrival")
    t, _ = clock.time_s("uav1", 5_100_000, None, 100.110)  # 10 ms faster: the offset is 95.010 s now
    assert t == pytest.approx(100.110)
    t, _ = clock.time_s("uav1", 5_200_000, None, 100.250)  # slower: the best offset stands
    assert t == pytest.approx(100.210)
    t, _ = clock.time_s("uav1", 1_000_000, None, 101.000)  # the boot clock went back: a reboot, start over
    assert t == pytest.approx(101.000)
    assert clock.time_s("uav1", 1, 1_234_000_000, 0.0) == (pytest.approx(1234.0), "vehicle")


def test_a_restarted_daemons_unstamped_tracks_keep_the_utc_offset_its_stamped_ones_had():
    """A daemon restarted on a running autopilot publishes its first seconds without UTC (its mapping needs a few
    SYSTEM_TIME samples): its frames stay on the UTC its earlier stamps gave that boot clock, not the arrival clock;
    an autopilot reboot (the boot clock goes back) ends that memory."""
    clock = CommonClock(window_s=10.0)
    utc_minus_boot_s = 1_700_000_000.25
    assert clock.time_s("uav1", 5_000_000, int((5.0 + utc_minus_boot_s) * 1e6), 0.0)[1] == "vehicle"
    t, src = clock.time_s("uav1", 9_000_000, None, 1_700_000_100.0)  # arrival says nothing like it: ignored
    assert (t, src) == (pytest.approx(9.0 + utc_minus_boot_s, abs=1e-6), "remembered")
    # as uncertain as the boot clock may have drifted since (it was taken as exact: 18 ms after 10 min at 30 ppm)
    assert clock.remembered_sigma_s("uav1", 9_000_000) == pytest.approx(4.0 * CLOCK_DRIFT_PPM * 1e-6)
    assert clock.remembered_sigma_s("uav1", 605_000_000) == pytest.approx(0.030)
    t, src = clock.time_s("uav1", 2_000_000, None, 1_700_000_200.0)  # rebooted: back to the arrival estimate
    assert (t, src) == (pytest.approx(1_700_000_200.0), "arrival")
    assert clock.remembered_sigma_s("uav1", 2_000_000) == 0.0


# --------------------------------------------------------------------------- the fleet's clocks and silent vehicles


def run_three(fusion: Fusion, seconds: float, rng, clock_error_s: dict[str, float], t0: float = 0.0) -> list:
    """Three vehicles at 30 Hz from ``t0``; each frame arrives 5 ms + an exponential 4 ms (processing and link)
    after capture, on the fusion's clock (true UTC); a vehicle's ``time_unix_us`` is off by ``clock_error_s[name]``.
    Returns what the fusion published."""
    out = []
    first = int(round(t0 * 30))
    for k, t in enumerate(np.arange(t0, t0 + seconds, 1 / 30), start=first):
        for v in (UAV1, UAV2, UAV3):
            arrival = T0_UNIX_S + t + 0.005 + rng.exponential(0.004)
            err = clock_error_s.get(v.name, 0.0)
            fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, k, clock_error_s=err), arrival)
        out += fusion.flush()
    return out


@pytest.mark.parametrize("error_ms", [20.0, -20.0])
def test_a_vehicle_whose_clock_is_20_ms_off_is_named_and_counted_once(error_ms):
    fusion = new_fusion()
    run_three(fusion, 2.0, np.random.default_rng(11), {"uav3": error_ms / 1e3})
    st = fusion.status(T0_UNIX_S + 2.0)
    assert st["clock_inconsistent"] == ["uav3"]
    assert st["clocks"]["uav3"] == pytest.approx(-error_ms, abs=3.0)  # its floor: 20 ms short (ahead) or long
    assert abs(st["clocks"]["uav1"]) < 3.0 and abs(st["clocks"]["uav2"]) < 3.0
    fusion.status(T0_UNIX_S + 2.0)
    assert fusion.counter["clock_inconsistent"] == 1  # counted when it starts, not on every status
    assert st["silent"] == [] and st["latency_floor_ms"]["uav1"] == pytest.approx(5.0, abs=1.0)
    # and, named within the 0.1 s pairing window, its rays are fused as uncertain in time as it is off (they paired
    # at the wrong place with a 0.3 ms sigma): not refused (a slower link is named too), each ray's time sigma its
    # deviation
    seen: list = []
    tracker_add = fusion.tracker.add
    fusion.tracker.add = lambda ray: seen.append(ray) or tracker_add(ray)  # type: ignore[method-assign]
    out = run_three(fusion, 0.5, np.random.default_rng(12), {"uav3": error_ms / 1e3}, t0=2.0)
    assert fusion.counter["clock_off"] == 0
    widened = [r.time_sigma_s for r in seen if r.vehicle == "uav3"]
    assert widened and min(widened) == pytest.approx(abs(error_ms) / 1e3, abs=0.004)
    assert max(r.time_sigma_s for r in seen if r.vehicle != "uav3") < 0.001
    fleet = [p for k, p in out if k == fleet_track_key()]
    assert fleet and sorted(c["vehicle"] for c in fleet[-1]["vehicles"]) == ["uav1", "uav2", "uav3"]


def test_consistent_clocks_are_not_named_and_two_vehicles_name_the_one_off_the_fusions_clock():
    fusion = new_fusion()
    run_three(fusion, 2.0, np.random.default_rng(12), {})
    st = fusion.status(T0_UNIX_S + 2.0)
    assert st["clock_inconsistent"] == [] and "clock_inconsistent" not in fusion.counter.counts
    assert max(abs(d) for d in st["clocks"].values()) < 3.0
    for error_s in (0.020, -0.020):  # two vehicles, uav2 20 ms ahead / behind: the median is their midpoint
        check = ClockConsistency(tolerance_s=0.010, min_samples=5)
        for k in range(30):  # each frame arrives 5 ms after capture on the fusion's clock
            check.add("uav1", 100.0 + k / 30, 100.0 + k / 30 + 0.005)
            check.add("uav2", 100.0 + k / 30 + error_s, 100.0 + k / 30 + 0.005)
        devs = check.deviations_s(101.0)
        assert devs["uav1"] - devs["uav2"] == pytest.approx(error_s)
        assert check.inconsistent(101.0) == ["uav2"]  # its floor (-15 / 25 ms) is the one far from the fusion's clock
        assert check.deviations_s(112.0) == {} and check.inconsistent(112.0) == []  # the window moved past them


def test_a_vehicle_that_stops_is_named_silent_and_rejoins_when_it_returns(caplog):
    caplog.set_level(logging.WARNING)
    fusion = new_fusion(silent_after_s=1.0)
    rng = np.random.default_rng(13)
    out = run_pair(fusion, 1.0, rng)
    assert fusion.status(T0_UNIX_S + 1.0)["silent"] == []
    out = []
    for k, t in enumerate(np.arange(1.0, 3.5, 1 / 30)):  # uav2 is gone for 2.5 s: longer than member_timeout_s
        fusion.receive("irtrack/uav1/track", payload_of(UAV1, t, rng, 30 + k), T0_UNIX_S + t + 0.005)
        out += fusion.flush()
    assert fusion.status(T0_UNIX_S + 3.5)["silent"] == ["uav2"]
    assert fusion.counter["vehicle_silent"] == 1
    # it names who is still fused (it said 'fusing the others' when none was left)
    assert any("uav2: no track for" in r.getMessage() and "fusing uav1" in r.getMessage() for r in caplog.records)
    both = new_fusion(silent_after_s=1.0)  # both stop within the log interval: each is named in the log
    for v in (UAV1, UAV2):
        both.receive(f"irtrack/{v.name}/track", payload_of(v, 0.0, rng, 0), T0_UNIX_S + 0.005)
    caplog.clear()
    both.watch(T0_UNIX_S + 2.0)
    silent = [r.getMessage() for r in caplog.records if r.getMessage().startswith("vehicle_silent")]
    assert [m.split(":")[1].strip() for m in silent] == ["uav1", "uav2"]
    lone = new_fusion(silent_after_s=1.0)  # a fleet whose only vehicle stops
    lone.receive("irtrack/uav1/track", payload_of(UAV1, 0.0, rng, 0), T0_UNIX_S + 0.005)
    lone.watch(T0_UNIX_S + 2.0)
    assert any("uav1: no track" in r.getMessage() and "no vehicle left" in r.getMessage() for r in caplog.records)
    late = [p for key, p in out if key == fleet_track_key() and p["time_unix_us"] >= (T0_UNIX_S + 1.5) * 1e6]
    assert late and all([c["vehicle"] for c in p["vehicles"]] == ["uav1"] and not p["observable"] for p in late)
    out = []
    for k, t in enumerate(np.arange(3.5, 4.5, 1 / 30)):  # uav2's daemon is back
        for v in (UAV1, UAV2):
            fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, 200 + k), T0_UNIX_S + t + 0.005)
        out += fusion.flush()
    assert fusion.status(T0_UNIX_S + 4.5)["silent"] == [] and fusion.counter["vehicle_back"] == 1
    last = [p for key, p in out if key == fleet_track_key()][-1]
    assert sorted(c["vehicle"] for c in last["vehicles"]) == ["uav1", "uav2"] and last["observable"]
    e = np.asarray(last["ned_m"]) - truth_in(last)
    assert np.linalg.norm(e) < 0.01 * np.linalg.norm(truth_in(last))


# --------------------------------------------------------------------------- per-vehicle noise, refused rays


def test_vehicle_noise_overrides_the_named_keys_of_one_vehicle_and_keeps_the_global_rest():
    args = build_parser().parse_args(
        [
            "--attitude-bias-deg", "0.1", "--camera-white-m", "0.03",
            "--vehicle-noise", "uav2:attitude_bias_deg=0.5",
            "--vehicle-noise", "uav2:camera_offset_m=1.5",
        ]
    )  # fmt: skip
    noise = noise_models(args)
    assert noise["uav1"].attitude_bias_sigma_rad == pytest.approx(np.radians(0.1))
    assert noise["uav9"] == noise["uav1"] and noise["uav1"].camera_position_offset_sigma_m == 0.0
    uav2 = noise["uav2"]
    assert uav2.attitude_bias_sigma_rad == pytest.approx(np.radians(0.5))
    assert uav2.camera_position_offset_sigma_m == 1.5 and uav2.camera_position_white_sigma_m == 0.03


def _payload_dict(vehicle, t_s, rng, seq, **changes) -> dict:
    obj = json.loads(payload_of(vehicle, t_s, rng, seq))
    obj.update(changes)
    return obj


def run_pair_with(fusion: Fusion, t_range, rng, bad=lambda k, obj: None, seq0: int = 0) -> list[tuple[str, dict]]:
    """Both vehicles at 30 Hz; ``bad(k, obj)`` may change uav2's k-th payload dict in place."""
    out = []
    for k, t in enumerate(t_range):
        for v in (UAV1, UAV2):
            obj = _payload_dict(v, t, rng, seq0 + k)
            if v is UAV2:
                bad(k, obj)
            fusion.receive(f"irtrack/{v.name}/track", json.dumps(obj).encode(), T0_UNIX_S + t + 0.005)
        out += fusion.flush()
    return out


@pytest.mark.parametrize(
    "change, reason",
    [
        ({"los_sigma_az_deg": 1e-300, "los_sigma_el_deg": 1e-300}, "sigma_below_floor"),
        ({"camera_ned_m": [1e9, 0.0, -100.0]}, "camera_far"),
        ({"camera_ned_m": [0.0, 2000.0, -100.0]}, "camera_jump"),  # 2 km from the last camera in 33 ms
        ({"time_unix_sigma_us": 5_000_000}, "time_sigma"),
    ],
)
def test_an_impossible_ray_is_refused_by_reason_and_leaves_its_vehicles_object_in_the_target(change, reason):
    fusion = new_fusion()
    rng = np.random.default_rng(21)
    run_pair_with(fusion, np.arange(0.0, 1.0, 1 / 30), rng)
    (tid,) = fusion.tracker.targets
    members = fusion.tracker.members(tid)

    def bad(k, obj):
        if k == 0:
            obj.update(change)

    out = run_pair_with(fusion, np.arange(1.0, 1.5, 1 / 30), rng, bad, seq0=30)
    assert fusion.counter[reason] == 1
    assert fusion.counter["object_left"] == 0 and fusion.tracker.members(tid) == members
    fleet = [p for k, p in out if k == fleet_track_key()]
    assert fleet and all(p["ned_m"] is not None and all(x is not None for x in p["sigma_ned_m"]) for p in fleet)
    assert fleet[-1]["observable"] and len(fleet[-1]["vehicles"]) == 2
    st = fusion.status(T0_UNIX_S + 1.5)
    assert st["rejected"][reason] == 1 and st["name_clash"] == []
    assert st["events"] == {"target_created": 1} and not EVENTS & set(st["rejected"])


def test_a_vehicle_whose_published_bias_exceeds_the_prior_is_listed_in_the_status_with_the_bias_its_rays_suggest():
    """uav2 publishes (and has) a 0.3 deg attitude bias against the fusion's 0.1 deg prior: the status lists uav2 under
    ``attitude_bias_deg`` with about 0.3 deg and counts ``attitude_bias_above_prior`` under ``events``; uav1 is not
    named.  The same fleet at the prior lists nobody."""
    prior_rad = math.radians(0.1)
    for uav2_deg, named in ((0.3, True), (0.1, False)):
        fusion = Fusion(
            FleetTracker(FleetConfig(), NoiseModel(attitude_bias_sigma_rad=prior_rad), RejectCounter()),
            CommonClock(None),
        )
        uav2 = dataclasses.replace(UAV2, attitude_error_rad=tuple(np.radians([0.2, -0.25, uav2_deg])))
        rng = np.random.default_rng(5)
        for k, t in enumerate(np.arange(0.0, 1.5, 1 / 30)):
            for v, bias_rad in ((UAV1, prior_rad), (uav2, math.radians(uav2_deg))):
                payload = payload_of(v, t, rng, k, published_bias_rad=bias_rad)
                fusion.receive(f"irtrack/{v.name}/track", payload, T0_UNIX_S + t + 0.005)
            fusion.flush()
        st = fusion.status(T0_UNIX_S + 1.5)
        if named:
            assert list(st["attitude_bias_deg"]) == ["uav2"] and 0.25 < st["attitude_bias_deg"]["uav2"] < 0.35
            assert st["events"]["attitude_bias_above_prior"] > 0 and not EVENTS & set(st["rejected"])
        else:
            assert st["attitude_bias_deg"] == {} and "attitude_bias_above_prior" not in st["events"]


def test_a_time_sigma_within_the_bound_widens_the_fused_covariance():
    """The same rays with uav2's UTC known to 20 ms: accepted, and its miss v s_t across the ray (~0.1 m here)
    widens the covariance, never narrows it."""
    sig = {}
    for sigma_us in (None, 20_000):
        fusion = new_fusion()

        def stamp(k, obj, sigma_us=sigma_us):
            obj["time_unix_sigma_us"] = sigma_us

        out = run_pair_with(fusion, np.arange(0.0, 1.0, 1 / 30), np.random.default_rng(22), stamp)
        last = [p for k, p in out if k == fleet_track_key()][-1]
        assert last["observable"] and fusion.counter["time_sigma"] == 0
        sig[sigma_us] = np.asarray(last["sigma_ned_m"])
    assert np.all(sig[20_000] >= sig[None] * 0.999) and np.any(sig[20_000] > sig[None] * 1.01)


# --------------------------------------------------------------------------- two vehicles under one name


def test_two_vehicles_under_one_name_are_named_once_kept_out_and_fused_again_when_one_is_left(caplog):
    """A second drone also configured uav1, looking at another object: its tracks interleave with uav1's (seq and
    camera back and forth).  The fusion names the clash once at WARNING, keeps uav1's rays out (no confident ghost
    point: every fleet track is uav2 alone, unobservable) and fuses uav1 again once one stream is left."""
    fusion = new_fusion()
    rng = np.random.default_rng(23)
    impostor = SynthVehicle("uav1", (0.0, 0.0, -300.0), (12.0, 0.0, 0.0))
    other = SynthTarget((600.0, 300.0, -100.0))
    run_pair(fusion, 1.0, rng)
    out = []
    with caplog.at_level("WARNING"):
        for k, t in enumerate(np.arange(1.0, 4.0, 1 / 30)):
            for v in (UAV1, UAV2):
                fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, 30 + k), T0_UNIX_S + t + 0.005)
            t2 = t + 0.016
            los = measure(impostor, other, t2, rng, 0.3e-3)
            obj = track_payload("uav1", 5000 + k, int(1e6 + t2 * 1e6), los, ORIGIN_1, int((T0_UNIX_S + t2) * 1e6))
            fusion.receive("irtrack/uav1/track", json.dumps(obj).encode(), T0_UNIX_S + t2 + 0.005)
            out += fusion.flush()
    st = fusion.status(T0_UNIX_S + 4.0)
    assert st["name_clash"] == ["uav1"] and st["events"]["name_clash"] == 1
    warned = [r.getMessage() for r in caplog.records if "name_clash" in r.getMessage()]
    assert len(warned) == 1 and "'uav1'" in warned[0] and "own name" in warned[0]
    late = [p for k, p in out if k == fleet_track_key() and p["time_unix_us"] >= (T0_UNIX_S + 1.5) * 1e6]
    assert late and all([c["vehicle"] for c in p["vehicles"]] == ["uav2"] and not p["observable"] for p in late)
    assert fusion.counter["ray_name_clash"] > 100
    # the second drone lands: after clear_after_s without an anomaly uav1 is one vehicle again and fuses
    out = []
    for k, t in enumerate(np.arange(4.0, 11.0, 1 / 30)):
        for v in (UAV1, UAV2):
            fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, 200 + k), T0_UNIX_S + t + 0.005)
        out += fusion.flush()
    st = fusion.status(T0_UNIX_S + 11.0)
    assert st["name_clash"] == [] and st["events"]["name_clash_cleared"] == 1
    last = [p for k, p in out if k == fleet_track_key()][-1]
    assert sorted(c["vehicle"] for c in last["vehicles"]) == ["uav1", "uav2"] and last["observable"]
    assert np.linalg.norm(np.asarray(last["ned_m"]) - truth_in(last)) < 0.01 * np.linalg.norm(truth_in(last))


def test_a_daemon_restart_is_not_a_name_clash():
    fusion = new_fusion()
    rng = np.random.default_rng(24)
    run_pair(fusion, 1.0, rng)
    out = run_pair_with(fusion, np.arange(1.0, 2.0, 1 / 30), rng, seq0=0)  # both restart their frame counters
    assert fusion.status(T0_UNIX_S + 2.0)["name_clash"] == [] and fusion.counter["ray_name_clash"] == 0
    assert [p for k, p in out if k == fleet_track_key()][-1]["observable"]


# --------------------------------------------------------------------------- a clock ahead


@pytest.mark.parametrize("vehicles", [2, 3])
def test_a_vehicle_whose_clock_runs_ahead_is_the_one_refused(vehicles):
    """uav3 (or, with two, uav2) stamps its frames 1.5 s late, within --max-age-s: the others' rays are never
    stale, the clock check names it and its rays are refused; with three the other two fuse on."""
    fusion = new_fusion()
    rng = np.random.default_rng(25)
    fleet = []
    bad = "uav3" if vehicles == 3 else "uav2"
    for k, t in enumerate(np.arange(0.0, 4.0, 1 / 30)):
        for v in (UAV1, UAV2, UAV3)[:vehicles]:
            err = 1.5 if v.name == bad else 0.0
            arrival = T0_UNIX_S + t + 0.005 + rng.exponential(0.002)
            fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, k, clock_error_s=err), arrival)
        if t >= 1.0:  # the clock check judges a vehicle from its 20th frame in: what it sent by then is withdrawn
            fleet += [p for key, p in fusion.flush() if key == fleet_track_key()]
    st = fusion.status(T0_UNIX_S + 4.0)
    assert st["rejected"].get("ray_stale", 0) == 0
    assert st["clock_inconsistent"] == [bad] and st["rejected"]["clock_off"] > 60
    late = fleet
    assert all(bad not in [c["vehicle"] for c in p["vehicles"]] for p in late)
    # the good vehicles' rays are in the tracker, the bad one's are not (two: uav1 alone makes no fleet target)
    assert fusion.tracker.vehicles == (("uav1", "uav2") if vehicles == 3 else ("uav1",))
    if vehicles == 3:
        assert late and all(p["observable"] for p in late)
        e = np.asarray(late[-1]["ned_m"]) - truth_in(late[-1])
        assert np.linalg.norm(e) < 0.01 * np.linalg.norm(truth_in(late[-1]))


def test_a_late_camera_clock_compensated_by_the_daemon_is_fused_at_the_instant_of_its_lines_of_sight():
    """With a late camera clock compensated, a daemon's line of sight is of the stamp minus compensated_us while
    time_unix_us is the stamp's: the fusion timed the ray at the stamp, and a 100 ms late pair of cameras put the
    fused point off by the target's 0.7 m of motion at a few tens of centimetres of sigma."""
    late_s = 0.1

    def late_payload(vehicle, t, rng, k, say: bool) -> bytes:
        obj = json.loads(payload_of(vehicle, t - late_s, rng, k, t0_unix_s=T0_UNIX_S + late_s))  # stamped at t
        obj["compensated_us"] = int(late_s * 1e6) if say else 0
        return json.dumps(obj).encode()

    def nees(say: bool) -> list[float]:
        fusion, rng, out = new_fusion(), np.random.default_rng(3), []
        for k, t in enumerate(np.arange(0.2, 3.0, 1 / 30)):
            for v in (UAV1, UAV2):
                fusion.receive(f"irtrack/{v.name}/track", late_payload(v, t, rng, k, say), T0_UNIX_S + t + 0.005)
            out += [p for key, p in fusion.flush() if key == fleet_track_key() and p["observable"]]
        values = []
        for p in out[-30:]:
            e = np.asarray(p["ned_m"]) - truth_in(p)  # the truth at the time the fusion says
            values.append(float(e @ np.linalg.solve(np.asarray(p["cov_ned_m2"]), e)))
        return values

    said = nees(True)
    assert len(said) == 30 and np.mean(said) < 6.0
    assert np.mean(nees(False)) > 16.3  # the same rays timed at their stamps: confidently off


def test_a_malformed_message_is_counted_never_a_crash_and_a_refused_one_sets_no_fleet_frame():
    """bbox 5, a ragged sigma, JSON nested past the parser's depth killed the fusion process (a TypeError,
    ValueError or RecursionError where only InputError was caught); a sigma of 1e200 deg was taken; and the first
    message heard set the fleet's frame even when it was refused (a stray origin at 0, 0 made every later camera
    'far' for the life of the process)."""
    fusion = new_fusion()
    good = json.loads(payload_of(UAV1, 0.0, np.random.default_rng(0), 0))
    bad = {
        "bbox 5": {**good, "bbox": 5},
        "ragged sigma": {**good, "sigma_vel_ned_mps": [1.0, [2.0]]},
        "sigma 1e200 deg": {**good, "los_sigma_az_deg": 1e200},
    }
    for obj in bad.values():
        fusion.receive("irtrack/uav1/track", json.dumps(obj).encode(), T0_UNIX_S + 0.01)
    # past the parser's depth, within MAX_TRACK_BYTES (a bigger one is refused unparsed)
    fusion.receive("irtrack/uav1/track", b"[" * 20_000 + b"]" * 20_000, T0_UNIX_S + 0.01)
    assert fusion.counter["bad_track"] == 3 and fusion.counter["not_json"] == 1
    stray = {**good, "vehicle": "uav3", "los_sigma_az_deg": 1e-9, "los_sigma_el_deg": 1e-9}
    stray["origin"] = {"lat_deg": 0.0, "lon_deg": 0.0, "alt_m": 0.0}
    fusion.receive("irtrack/uav3/track", json.dumps(stray).encode(), T0_UNIX_S + 0.01)
    assert fusion.counter["sigma_below_floor"] == 1 and fusion.origin is None
    out = run_pair(fusion, 1.0, np.random.default_rng(1))
    assert fusion.origin == ORIGIN_1 and any(k == fleet_track_key() for k, _ in out)


def test_a_key_no_daemon_sends_or_an_origin_no_frame_holds_is_counted_and_the_fusion_goes_on():
    """A key chunk with a space (zenoh takes it) stopped the process at the next flush, which could not make that
    vehicle's output key; an origin at 1e200 m failed the frame map's SVD with a LinAlgError nobody caught."""
    fusion = new_fusion()
    good = json.loads(payload_of(UAV1, 0.0, np.random.default_rng(0), 0))
    fusion.receive("irtrack/uav 2/track", json.dumps({**good, "vehicle": "uav 2"}).encode(), T0_UNIX_S + 0.01)
    high = {**good, "origin": {**good["origin"], "alt_m": 1e200}}
    fusion.receive("irtrack/uav1/track", json.dumps(high).encode(), T0_UNIX_S + 0.01)
    assert fusion.counter["bad_vehicle_name"] == 1 and fusion.counter["bad_track"] == 1
    out = run_pair(fusion, 1.0, np.random.default_rng(1))
    assert any(k == fleet_track_key() for k, _ in out) and fusion.origin == ORIGIN_1
    assert fusion.status(T0_UNIX_S + 1.0)["silent"] == []


def test_a_message_the_checks_miss_is_counted_by_drain_and_the_next_one_fused():
    fusion = new_fusion()
    calls = []

    def receive(key, payload, arrival):
        calls.append(key)
        if len(calls) == 1:
            raise ZeroDivisionError("a bug on one message")

    fusion.receive = receive  # type: ignore[method-assign]
    inbox = Inbox()
    inbox.put(("irtrack/uav2/track", b"{}", T0_UNIX_S))
    assert drain(inbox, fusion, ("irtrack/uav1/track", b"{}", T0_UNIX_S)) == 2
    assert calls == ["irtrack/uav1/track", "irtrack/uav2/track"] and fusion.counter["receive_error"] == 1


def test_one_frame_stamped_seconds_ahead_is_refused_alone_and_does_not_shut_its_vehicle_out():
    """The clock check took the refused frame's stamp: its vehicle's latency floor became -5 s for the check's 10 s
    window, the vehicle was named off the others' clock and its good rays refused (clock_off 300, the fleet track
    unobservable for 10 s)."""
    fusion, rng = new_fusion(), np.random.default_rng(3)

    def glitch(k, obj):
        if k == 40:
            obj["time_unix_us"] += 5_000_000

    out = run_pair_with(fusion, np.arange(0.0, 8.0, 1 / 30), rng, bad=glitch)
    assert fusion.counter["future"] == 1 and "clock_off" not in fusion.counter.counts
    late = [p for k, p in out if k == fleet_track_key() and p["time_unix_us"] / 1e6 - T0_UNIX_S > 3.0]
    assert late and all(p["observable"] for p in late)


def test_a_clock_seconds_off_is_still_named_though_its_frames_are_refused():
    """The clock check skips a single stamp beyond --max-age-s (a glitch), not a clock that is off: a vehicle whose
    every stamp is 5 s ahead is still named (it was, before the glitch rule), its frames refused as future."""
    fusion, rng = new_fusion(), np.random.default_rng(8)

    def ahead(k, obj):
        obj["time_unix_us"] += 5_000_000

    run_pair_with(fusion, np.arange(0.0, 3.0, 1 / 30), rng, bad=ahead)
    status = fusion.status(T0_UNIX_S + 3.0)
    assert fusion.counter["future"] == 90 and "uav2" in status["clock_inconsistent"]


def test_only_parsed_tracks_make_a_vehicle_and_a_long_silent_one_is_forgotten():
    """5000 junk keys made 5000 'silent' vehicles in every status, kept for the life of the process."""
    from onboard.app.fuse import FORGET_AFTER_S, MAX_VEHICLES

    fusion = new_fusion()
    for i in range(500):
        fusion.receive(f"irtrack/junk{i}/track", b"x", T0_UNIX_S)
    run_pair(fusion, 0.5, np.random.default_rng(2))
    status = fusion.status(T0_UNIX_S + 5.0)
    assert fusion.counter["not_json"] == 500 and status["silent"] == ["uav1", "uav2"]
    good = json.loads(payload_of(UAV1, 0.4, np.random.default_rng(0), 99))
    for i in range(MAX_VEHICLES + 5):
        name = f"v{i}"
        fusion.receive(f"irtrack/{name}/track", json.dumps({**good, "vehicle": name}).encode(), T0_UNIX_S + 0.45)
    assert fusion.counter["too_many_vehicles"] == 7  # uav1 and uav2 hold two of the places
    later = fusion.status(T0_UNIX_S + 1.0 + FORGET_AFTER_S)
    assert later["silent"] == [] and later["vehicles"] == {} and fusion.counter["vehicle_forgotten"] == MAX_VEHICLES
    run_pair_with(fusion, np.arange(FORGET_AFTER_S + 2.0, FORGET_AFTER_S + 3.0, 1 / 30), np.random.default_rng(4))
    assert set(fusion.status(T0_UNIX_S + FORGET_AFTER_S + 3.0)["vehicles"]) == {"uav1", "uav2"}


def test_names_that_sent_once_give_their_places_to_vehicles_that_track():
    """64 one-shot names (a flood, or typos) filled every place: the real vehicles were refused for 10 minutes.
    A new name takes the place of the longest silent one; while none is silent it is refused."""
    from onboard.app.fuse import MAX_VEHICLES

    fusion = new_fusion()
    good = json.loads(payload_of(UAV1, 0.4, np.random.default_rng(0), 99))
    for i in range(MAX_VEHICLES):
        name = f"junk{i}"
        fusion.receive(f"irtrack/{name}/track", json.dumps({**good, "vehicle": name}).encode(), T0_UNIX_S + 0.4)
    fusion.receive("irtrack/late/track", json.dumps({**good, "vehicle": "late"}).encode(), T0_UNIX_S + 0.45)
    assert fusion.counter["too_many_vehicles"] == 1  # none silent yet: refused
    run_pair_with(fusion, np.arange(2.0, 3.0, 1 / 30), np.random.default_rng(4))
    assert fusion.counter["too_many_vehicles"] == 1 and fusion.counter["vehicle_forgotten"] == 2
    assert {"uav1", "uav2"} <= set(fusion.status(T0_UNIX_S + 3.0)["vehicles"])


def _stray(t, rng, k) -> bytes:
    """uav1's track as a vehicle named sim1 whose origin is 0, 0: a simulator far from the fleet."""
    obj = json.loads(payload_of(UAV1, t, rng, k))
    obj["vehicle"], obj["origin"] = "sim1", {"lat_deg": 0.0, "lon_deg": 0.0, "alt_m": 0.0}
    return json.dumps(obj).encode()


@pytest.mark.parametrize("stray_first", [True, False])
def test_a_stray_vehicle_heard_first_does_not_keep_the_fleet_frame_from_the_fleet(stray_first):
    """A well-formed track from a vehicle far from the others (a simulator on the fleet's network, a wrong position)
    set the fleet frame when it came first, and every real vehicle's camera was refused as too far from it for the
    life of the process: nothing was ever fused.  Received after the real vehicles in each period, the stray must
    not take the frame back once it was given up."""
    from onboard.app.fuse import REANCHOR_AFTER_S

    fusion, rng, out = new_fusion(), np.random.default_rng(6), []
    fusion.receive("irtrack/sim1/track", _stray(-0.01, rng, 0), T0_UNIX_S)  # the stray is heard first
    for k, t in enumerate(np.arange(0.0, 8.0, 1 / 30)):
        if stray_first:
            fusion.receive("irtrack/sim1/track", _stray(t, rng, k + 1), T0_UNIX_S + t + 0.004)
        for v in (UAV1, UAV2):
            fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, k), T0_UNIX_S + t + 0.005)
        if not stray_first:
            fusion.receive("irtrack/sim1/track", _stray(t, rng, k + 1), T0_UNIX_S + t + 0.006)
        out += fusion.flush()
    assert fusion.counter["fleet_origin_moved"] == 1 and fusion.origin in (ORIGIN_1, ORIGIN_2)
    fused = [p for k, p in out if k == fleet_track_key()]
    assert fused and min(p["time_unix_us"] / 1e6 - T0_UNIX_S for p in fused) > REANCHOR_AFTER_S
    assert {c["vehicle"] for c in fused[-1]["vehicles"]} == {"uav1", "uav2"} and fused[-1]["observable"]
    assert np.linalg.norm(np.array(fused[-1]["ned_m"]) - truth_in(fused[-1])) < 5.0


def test_with_one_real_vehicle_and_one_stray_the_frame_moves_once_not_back_and_forth():
    """Which of two vehicles 200 km apart is the stray cannot be told; the frame moved every 30 s, each move
    withdrawing the other's rays with a warning."""
    from onboard.app.fuse import REANCHOR_HOLD_S

    fusion, rng = new_fusion(), np.random.default_rng(7)
    for k, t in enumerate(np.arange(0.0, 3 * REANCHOR_HOLD_S, 1 / 10)):
        fusion.receive("irtrack/sim1/track", _stray(t, rng, k), T0_UNIX_S + t + 0.004)
        fusion.receive("irtrack/uav1/track", payload_of(UAV1, t, rng, k), T0_UNIX_S + t + 0.005)
        fusion.flush()
    assert fusion.counter["fleet_origin_moved"] == 1 and fusion.origin == ORIGIN_1


def test_a_message_heard_twice_or_replayed_is_a_duplicate_not_a_second_vehicle():
    """Each repeated seq counted against the name: one redelivered or replayed message a second had a vehicle named
    a name clash and withdrawn (63 rays kept out in the audit's run)."""
    fusion, rng, replay, out = new_fusion(), np.random.default_rng(5), {}, []
    for k, t in enumerate(np.arange(0.0, 5.0, 1 / 30)):
        for v in (UAV1, UAV2):
            payload = payload_of(v, t, rng, k)
            fusion.receive(f"irtrack/{v.name}/track", payload, T0_UNIX_S + t + 0.005)
            if v is UAV2:
                replay[k] = payload
                if k % 30 == 0:
                    fusion.receive("irtrack/uav2/track", payload, T0_UNIX_S + t + 0.006)  # delivered twice
                if k % 30 == 15 and k >= 15:
                    fusion.receive("irtrack/uav2/track", replay[k - 15], T0_UNIX_S + t + 0.006)  # 0.5 s old again
        out += fusion.flush()
    assert fusion.counter["duplicate"] == 10 and "name_clash" not in fusion.counter.counts
    last = [p for k, p in out if k == fleet_track_key()][-1]
    assert sorted(c["vehicle"] for c in last["vehicles"]) == ["uav1", "uav2"]


def test_two_daemons_of_one_name_on_the_same_counts_are_a_name_clash_not_duplicates():
    """Two daemons both named uav2, started together on one simulated boot clock: each message of the second carries
    the seq and time_boot_us of one of the first's, from a camera 424 m away.  Each was refused as a ``duplicate``
    (a redelivery), so the clash was never named (90 in 3 s in the fleet audit's run, name_clash 0); a repeat from
    another place is another vehicle's message."""
    fusion, rng = new_fusion(), np.random.default_rng(9)
    twin = SynthVehicle("uav2", (300.0, 300.0, -100.0), (0.0, -8.0, 0.0))
    for k, t in enumerate(np.arange(0.0, 3.0, 1 / 30)):
        for v in (UAV1, UAV2):
            fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, k), T0_UNIX_S + t + 0.005)
        fusion.receive("irtrack/uav2/track", payload_of(twin, t, rng, k), T0_UNIX_S + t + 0.006)
        fusion.flush()
    st = fusion.status(T0_UNIX_S + 3.0)
    assert st["name_clash"] == ["uav2"] and st["events"]["name_clash"] == 1
    assert "duplicate" not in st["rejected"]


def test_a_link_that_reorders_messages_is_not_two_vehicles_under_one_name():
    """uav2's link swaps two adjacent messages every 0.5 s: each late one stepped seq and time_boot_us back, an
    anomaly, and four in 5 s named a name clash and withdrew uav2.  A late message that slots into its stream's recent
    seq and time_boot_us order is a reorder: its ray refused as out of order, nothing counted against the name."""
    fusion, rng, out, held = new_fusion(), np.random.default_rng(6), [], None
    for k, t in enumerate(np.arange(0.0, 6.0, 1 / 30)):
        for v in (UAV1, UAV2):
            payload, arrival = payload_of(v, t, rng, k), T0_UNIX_S + t + 0.005
            if v is UAV2 and k % 15 == 0 and k > 0:
                held = payload  # delivered after the next one
                continue
            fusion.receive(f"irtrack/{v.name}/track", payload, arrival)
            if v is UAV2 and held is not None:
                fusion.receive("irtrack/uav2/track", held, arrival + 0.001)
                held = None
        out += fusion.flush()
    st = fusion.status(T0_UNIX_S + 6.0)
    assert "name_clash" not in st["events"] and st["name_clash"] == [] and fusion.counter["ray_name_clash"] == 0
    assert st["rejected"]["ray_out_of_order"] == 11
    last = [p for k, p in out if k == fleet_track_key()][-1]
    assert sorted(c["vehicle"] for c in last["vehicles"]) == ["uav1", "uav2"] and last["observable"]


def test_a_flood_is_bounded_counted_and_never_starves_the_output():
    """Above ~3000 messages a second the main loop never left its receive loop (no fleet track, no status while the
    flood lasted) and the inbox grew without bound: it holds INBOX_MAX now (the rest dropped, counted inbox_full),
    and a turn of the loop fuses a bounded number before publishing."""
    fusion, rng = new_fusion(), np.random.default_rng(9)
    inbox = Inbox(maxsize=50)
    for k in range(80):
        inbox.put(("irtrack/uav1/track", payload_of(UAV1, k / 30, rng, k), T0_UNIX_S + k / 30 + 0.005))
    first = inbox.get()
    assert drain(inbox, fusion, first, limit=20) == 20  # a bounded turn; the rest wait for the next
    assert fusion.counter["inbox_full"] == 30  # 80 offered, 50 held
    assert drain(inbox, fusion, inbox.get(), limit=100) == 30 and inbox.get() is None
    assert fusion.counter["inbox_full"] == 30  # counted once


def test_a_flickering_track_id_stays_one_fleet_target():
    """A daemon's track is of one object at a time: when both vehicles' track ids flicker (a tracker that
    re-acquires its aircraft under a new id), the aircraft stays one fleet target with both vehicles on every
    frame, not two targets taking turns while each old id waits out its silence."""
    fusion = new_fusion()
    rng = np.random.default_rng(5)
    fleet = []
    for k, t in enumerate(np.arange(0.0, 3.0, 1 / 30)):
        for v, phase in ((UAV1, 0), (UAV2, 5)):
            obj = _payload_dict(v, t, rng, k, track_id=1 + ((k + phase) // 10) % 2)
            fusion.receive(f"irtrack/{v.name}/track", json.dumps(obj).encode(), T0_UNIX_S + t + 0.005)
        fleet += [p for key, p in fusion.flush() if key == fleet_track_key()]
    assert len(fleet) == 90 and {p["target_id"] for p in fleet} == {1}
    assert all(p["observable"] and len(p["vehicles"]) == 2 for p in fleet)
    nees = [
        float(e @ np.linalg.solve(np.array(p["cov_ned_m2"]), e))
        for p in fleet
        for e in [np.array(p["ned_m"]) - truth_in(p)]
    ]
    assert np.mean(nees) < 4.0
    events = fusion.status(T0_UNIX_S + 3.0)["events"]
    assert events["target_created"] == 1 and events["object_left"] == 17  # each id change, once


def test_a_late_message_of_a_vehicles_previous_id_does_not_evict_its_current_object():
    """Retiring an object goes by the rays' times, not by arrival order: uav1's daemon moves to id 2 at 1 s and
    its last id-1 frame reaches the fusion after the first id-2 frame (a reordering link)."""
    fusion = new_fusion()
    rng = np.random.default_rng(0)
    held = None
    for k, t in enumerate(np.arange(0.0, 2.0, 1 / 30)):
        obj = _payload_dict(UAV1, t, rng, k, track_id=1 if t < 1.0 else 2)
        if k == 29:
            held = json.dumps(obj).encode()
        else:
            fusion.receive("irtrack/uav1/track", json.dumps(obj).encode(), T0_UNIX_S + t + 0.005)
        if k == 31:
            fusion.receive("irtrack/uav1/track", held, T0_UNIX_S + t + 0.006)
        obj2 = _payload_dict(UAV2, t, rng, k, track_id=7)
        fusion.receive("irtrack/uav2/track", json.dumps(obj2).encode(), T0_UNIX_S + t + 0.005)
        fusion.flush()
    (tid,) = fusion.tracker.targets
    assert sorted(fusion.tracker.members(tid)) == [("uav1", 2), ("uav2", 7)]
    assert fusion.counter["object_left"] == 1 and fusion.counter["ray_of_ended_object"] == 1


def test_ctrl_c_while_starting_is_one_line_and_130(monkeypatch, capsys):
    """Ctrl-C in the first second (imports, the estimators' warm-up) printed a traceback."""
    import onboard.app.fuse as fuse

    def interrupted(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(fuse, "warm_up", interrupted)
    assert fuse.main(["--seconds", "1"]) == 130
    assert capsys.readouterr().err == "interrupted: no fusion running yet, or its session closing\n"


@pytest.mark.parametrize("uav2_prior", [None, "uav2:attitude_bias_deg=1"], ids=["default-prior", "its-own-prior"])
def test_a_vehicle_whose_elevation_is_1_deg_off_fuses_within_its_prior_and_is_named_beyond_it(uav2_prior):
    """uav2's attitude 1 deg off about east (its elevation, looking north): with its prior configured at 1 deg both
    vehicles fuse on every frame, unobservable; with the default 0.1 deg its rays pair with none of uav1's, and the
    status says so (``ray_unpaired`` under ``events``) instead of counting nothing while nothing is fused."""
    args = build_parser().parse_args(["--vehicle-noise", uav2_prior] if uav2_prior else [])
    counter = RejectCounter()
    tracker = FleetTracker(FleetConfig(), noise_models(args), counter)
    fusion = Fusion(tracker, CommonClock(), counter=counter, clock_check=ClockConsistency(judging_max_s=0.0))
    off = SynthVehicle("uav2", UAV2.p0_ned_m, UAV2.v_ned_mps, attitude_error_rad=(0.0, np.radians(1.0), 0.0))
    rng = np.random.default_rng(2)
    fleet = []
    for k, t in enumerate(np.arange(0.0, 2.0, 1 / 30)):
        for v in (UAV1, off):
            fusion.receive(f"irtrack/{v.name}/track", payload_of(v, t, rng, k), T0_UNIX_S + t + 0.005)
        fleet += [msg for key, msg in fusion.flush() if key == fleet_track_key()]
    st = fusion.status(T0_UNIX_S + 2.0)
    if uav2_prior:
        both = [m for m in fleet if len(m["vehicles"]) == 2]
        assert len(both) >= 59 and not any(m["observable"] for m in both)
        assert "ray_unpaired" not in st["events"]
    else:
        assert fleet == [] and st["rays"] == 120
        assert st["events"]["ray_unpaired"] >= 59 and "ray_unpaired" in EVENTS


@pytest.mark.integration
def test_a_fusion_node_that_hears_nothing_says_so(monkeypatch, capsys):
    """A fusion peer that reached no daemon (it dialed a router without --zenoh-gossip-autoconnect) stayed silent
    for its whole run, its stop line's zeros the only trace (a walkthrough of docs/fleet.md); it warns once, naming
    where it listens and the gossip switch."""
    import onboard.app.fuse as fuse_app
    from groundsim.io.ports import free_tcp_port

    monkeypatch.setattr(fuse_app, "NOTHING_HEARD_S", 0.3)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    assert fuse_app.main(["--zenoh-listen", endpoint, "--seconds", "1.2"]) == 0  # it sets up its own log handler
    warned = [ln for ln in capsys.readouterr().err.splitlines() if "nothing received" in ln]
    assert len(warned) == 1 and endpoint in warned[0] and "--zenoh-gossip-autoconnect" in warned[0]


RUN_A, RUN_B = "00000000000000aa", "00000000000000bb"


def test_a_daemon_restart_stated_by_a_new_run_id_withdraws_its_objects_once_and_fuses_on():
    """uav2's daemon restarts (a new run_id) while its camera's numbering goes on: its old objects leave their targets
    at once (its object ids start again), said once, no anomaly against the name, and the fusion goes on."""
    fusion = new_fusion()
    rng = np.random.default_rng(24)
    run_pair_with(fusion, np.arange(0.0, 1.0, 1 / 30), rng, bad=lambda k, obj: obj.update(run_id=RUN_A))
    assert len(fusion.tracker.targets) == 1
    out = run_pair_with(fusion, np.arange(1.0, 2.0, 1 / 30), rng, bad=lambda k, obj: obj.update(run_id=RUN_B), seq0=30)
    st = fusion.status(T0_UNIX_S + 2.0)
    assert st["events"]["vehicle_restarted"] == 1 and st["name_clash"] == [] and fusion.counter["ray_name_clash"] == 0
    assert "run_returned" not in st["rejected"]
    last = [p for k, p in out if k == fleet_track_key()][-1]
    assert sorted(c["vehicle"] for c in last["vehicles"]) == ["uav1", "uav2"]


def test_two_daemon_runs_taking_turns_under_one_name_are_a_name_clash():
    """Two daemons named uav2 reading one camera: the same frames, two run_ids by turns.  Each message of the run
    heard before the newest is refused (run_returned) and counts against the name: a clash, named once."""
    fusion = new_fusion()
    rng = np.random.default_rng(25)
    for k, t in enumerate(np.arange(0.0, 2.0, 1 / 30)):
        fusion.receive("irtrack/uav1/track", payload_of(UAV1, t, rng, k), T0_UNIX_S + t + 0.005)
        for run in (RUN_A, RUN_B):
            obj = _payload_dict(UAV2, t, rng, k, run_id=run)
            fusion.receive("irtrack/uav2/track", json.dumps(obj).encode(), T0_UNIX_S + t + 0.006)
        fusion.flush()
    st = fusion.status(T0_UNIX_S + 2.0)
    assert st["name_clash"] == ["uav2"] and st["events"]["name_clash"] == 1
    # each refused until the clash is named (then as ray_name_clash); B's first message was taken as a restart
    assert st["rejected"]["run_returned"] == 3 and st["events"]["vehicle_restarted"] == 1
