"""Scenarios of several observers (``observers:``): the parser, the per-observer views (own streams, boot
clocks, one shared world and UTC), the run options that name the vehicles, and clear errors naming the file
and the field for bad input."""

from __future__ import annotations

import copy
import datetime
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.app.run import (
    DEFAULT_FLEET_MAVLINK_PORT,
    RateSpec,
    RunConfig,
    VehicleLeg,
    fleet_truth_path,
    mavlink_endpoints,
    parse_start_time,
    run_fleet_loop,
    split_mavlink_option,
)
from groundsim.world.scenario import (
    DEFAULT_START_TIME_UTC,
    FLEET_BOOT_MIN_US,
    FLEET_BOOT_SPAN_MS,
    ScenarioError,
    load_scenario,
    parse_utc_us,
    scenario_from_dict,
    scenarios_dir,
)
from groundsim.world.sim import BOOT_START_US, SimCore
from onboard.core.errors import ConfigError

F1 = scenarios_dir() / "F1.yaml"
P1 = scenarios_dir() / "P1.yaml"
F1_START_UNIX_US = 1_780_304_400_000_000  # 2026-06-01T09:00:00Z, F1's start_time_utc
ATOL_M = 1e-9


def fleet_dict() -> dict:
    """F1 as a mapping, shortened to 1 s (the parser checks every frame's separation)."""
    d = yaml.safe_load(F1.read_text())
    d["duration_s"] = 1.0
    return d


def _error(d: dict, source="F.yaml") -> str:
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict(d, source)
    msg = str(ei.value)
    assert "\n" not in msg
    return msg


# --------------------------------------------------------------------------- the parser


def test_f1_has_two_named_observers_with_the_shared_camera_and_errors():
    sc = load_scenario(F1)
    assert sc.is_fleet
    assert [o.name for o in sc.observers] == ["uav1", "uav2"]
    assert sc.start_time_utc_us == F1_START_UNIX_US
    for o in sc.observers:
        assert o.camera == sc.camera and o.camera.gimbal is not None
        assert o.nav_noise == "RTK"
    # the first observer is what code that knows one observer sees
    assert sc.observer == sc.observers[0].vehicle
    t = sc.frame_times_s()
    p1, p2 = (o.vehicle.motion.state(t).p_ned_m for o in sc.observers)
    baseline_m = np.linalg.norm(p2 - p1, axis=-1)
    assert 150.0 <= baseline_m.min() and baseline_m.max() <= 300.0
    tgt = sc.target.motion.state(t).p_ned_m
    for p in (p1, p2):
        r = np.linalg.norm(tgt - p, axis=-1)
        assert 600.0 <= r.min() and r.max() <= 1000.0
        # straight and level: no manoeuvre, so one vehicle alone cannot range the target
        v = np.diff(p, axis=0) * sc.frame_rate_hz
        np.testing.assert_allclose(v, np.broadcast_to(v[0], v.shape), atol=1e-6)
        assert v[0][2] == 0.0
    assert sc.duration_s == 30.0


def test_each_view_is_one_observer_in_the_shared_world():
    sc = scenario_from_dict(fleet_dict())
    v1, v2 = sc.observer_views()
    assert (v1.observer_name, v2.observer_name) == ("uav1", "uav2")
    assert not v1.is_fleet and v1.observer_views() == (v1,)
    assert v1.observer == sc.observers[0].vehicle and v2.observer == sc.observers[1].vehicle
    assert v1.target == v2.target == sc.target  # one shared target
    # the observer's own streams differ between vehicles; the world's stay shared
    a, b = v1.rng("nav.errors").normal(size=4), v2.rng("nav.errors").normal(size=4)
    assert not np.allclose(a, b)
    np.testing.assert_array_equal(
        v1.rng("target.disturbance").normal(size=4), v2.rng("target.disturbance").normal(size=4)
    )
    np.testing.assert_array_equal(v1.rng("render.scene").normal(size=4), sc.rng("render.scene").normal(size=4))
    # a single-observer scenario is its own only view, its streams unchanged
    p1 = load_scenario(P1)
    assert p1.observer_views() == (p1,) and p1.observer_name is None and p1.boot_start_us is None


def test_boot_clocks_differ_per_vehicle_are_whole_ms_and_come_from_seed_and_name():
    d = fleet_dict()
    sc = scenario_from_dict(d)
    boots = [o.boot_start_us for o in sc.observers]
    assert boots[0] != boots[1]
    for b in boots:
        assert FLEET_BOOT_MIN_US <= b < FLEET_BOOT_MIN_US + 1000 * FLEET_BOOT_SPAN_MS and b % 1000 == 0
    assert [o.boot_start_us for o in scenario_from_dict(copy.deepcopy(d)).observers] == boots  # deterministic
    d2 = copy.deepcopy(d)
    d2["seed"] += 1
    assert [o.boot_start_us for o in scenario_from_dict(d2).observers] != boots
    d3 = copy.deepcopy(d)
    d3["observers"][1]["boot_time_s"] = 12.5
    assert scenario_from_dict(d3).observers[1].boot_start_us == 12_500_000
    assert scenario_from_dict(d3).observers[0].boot_start_us == boots[0]


def test_an_observer_may_have_its_own_camera_and_navigation_errors():
    d = fleet_dict()
    d["observers"][1]["nav_noise"] = "GNSS"
    d["observers"][1]["camera"] = {"gimbal": None, "mount": {"yaw_deg": 20.0}}
    sc = scenario_from_dict(d)
    v1, v2 = sc.observer_views()
    assert (v1.nav_noise, v2.nav_noise) == ("RTK", "GNSS")
    assert v1.camera.gimbal is not None and v2.camera.gimbal is None


def test_start_time_defaults_to_a_fixed_epoch_and_reads_iso_texts():
    d = fleet_dict()
    del d["start_time_utc"]
    assert scenario_from_dict(d).start_time_utc_us == parse_utc_us(DEFAULT_START_TIME_UTC)
    assert load_scenario(P1).start_time_utc_us == parse_utc_us(DEFAULT_START_TIME_UTC)
    d["start_time_utc"] = datetime.datetime(2026, 6, 1, 9, 0, tzinfo=datetime.UTC)  # YAML's unquoted timestamp
    assert scenario_from_dict(d).start_time_utc_us == F1_START_UNIX_US
    assert parse_utc_us("2026-06-01T11:00:00+02:00") == F1_START_UNIX_US


@settings(max_examples=50, deadline=None)
@given(st.datetimes(min_value=datetime.datetime(1971, 1, 1), max_value=datetime.datetime(2200, 1, 1)))
def test_utc_texts_round_trip_to_exact_microseconds(t):
    t = t.replace(tzinfo=datetime.UTC)
    want = round((t - datetime.datetime(1970, 1, 1, tzinfo=datetime.UTC)) / datetime.timedelta(microseconds=1))
    assert parse_utc_us(t.isoformat()) == want
    assert parse_utc_us(t.isoformat().replace("+00:00", "Z")) == want


def _dup(d):
    d["observers"][1]["name"] = "uav1"


def _no_name(d):
    del d["observers"][0]["name"]


def _unknown(d):
    d["observers"][1]["colour"] = "red"


def _both(d):
    d["observer"] = {"motion": d["observers"][0]["motion"]}


def _neither(d):
    del d["observers"]


def _bad_nav(d):
    d["observers"][1]["nav_noise"] = "RTX"


def _bad_name(d):
    d["observers"][1]["name"] = "uav 2"


def _collide(d):
    d["observers"][1]["motion"] = dict(d["observers"][0]["motion"], p0_ned_m=[0.0, -144.5, -100.0])


def _empty(d):
    d["observers"] = []


@pytest.mark.parametrize(
    "mutate, head, text",
    [
        (_dup, "F.yaml: observers[1].name: ", "a name not used by an earlier observer, got 'uav1'"),
        (_no_name, "F.yaml: observers[0].name: ", "expected a value (required)"),
        (_unknown, "F.yaml: observers[1].colour: ", "unknown key 'colour'"),
        (_both, "F.yaml: observers: ", "either observer or observers, not both"),
        (_neither, "F.yaml: observer: ", "expected a value (required)"),
        (_empty, "F.yaml: observer: ", "expected a value (required)"),
        (_bad_nav, "F.yaml: observers[1].nav_noise: ", "did you mean 'RTK'?"),
        (_bad_name, "F.yaml: observers[1].name: ", "got 'uav 2'"),
        (_collide, "F.yaml: observers[1].motion: ", "at least 1 m from observers[0] (uav1)"),
    ],
    ids=["duplicate", "missing-name", "unknown-field", "both", "neither", "empty", "nav-noise", "bad-name", "collide"],
)
def test_bad_fleets_are_one_line_naming_file_and_field(mutate, head, text):
    d = fleet_dict()
    mutate(d)
    msg = _error(d)
    assert msg.startswith(head), msg
    assert text in msg, msg


@pytest.mark.parametrize("text", ["yesterday", "2026-01-01T00:00:00", 20260101, "1969-12-31T23:59:59Z"])
def test_bad_start_time_is_one_line(text):
    d = fleet_dict()
    d["start_time_utc"] = text
    msg = _error(d)
    assert msg.startswith("F.yaml: start_time_utc: expected an ISO 8601 UTC time"), msg


def test_a_bad_fleet_file_names_the_file(tmp_path):
    d = fleet_dict()
    _dup(d)
    p = tmp_path / "fleet.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(ScenarioError, match=rf"^{p}: observers\[1\]\.name: "):
        load_scenario(p)


# --------------------------------------------------------------------------- the simulation core


def test_views_fly_one_world_on_their_own_boot_clocks_and_one_utc():
    sc = scenario_from_dict(fleet_dict())
    cores = [SimCore(v, 0, 0.2, render=False) for v in sc.observer_views()]
    rows = [[c.frame(k).truth for k in range(c.frame_count)] for c in cores]
    boots = [o.boot_start_us for o in sc.observers]
    for c, b, rs in zip(cores, boots, rows):
        assert c.boot_start_us == b
        assert c.unix_time_at_boot_us == F1_START_UNIX_US - b
        for r in rs:
            assert r.time_boot_us == b + round(r.t_s * 1e6)
            assert r.time_unix_us == F1_START_UNIX_US + round(r.t_s * 1e6)
    for a, b in zip(*rows):
        assert a.time_unix_us == b.time_unix_us and a.time_boot_us != b.time_boot_us
        # the shared target flies the same path for both vehicles; the observers are 290 m apart
        np.testing.assert_allclose(
            [a.target_n_m, a.target_e_m, a.target_d_m], [b.target_n_m, b.target_e_m, b.target_d_m], atol=ATOL_M
        )
        assert b.observer_e_m - a.observer_e_m == pytest.approx(290.0, abs=1.0)
    # each vehicle has its own navigation errors
    assert cores[0].nav_error(3).att_err_ned_rad.tolist() != cores[1].nav_error(3).att_err_ned_rad.tolist()
    # SimCore given the fleet itself simulates its first observer, as the fleet run does
    whole = SimCore(sc, 0, 0.2, render=False)
    assert whole.boot_start_us == boots[0] and whole.frame(2).truth == rows[0][2]


def test_a_single_observer_keeps_its_boot_clock_and_gains_the_scenario_utc():
    sc = load_scenario(P1)
    core = SimCore(sc, 0, 0.1, render=False)
    start = parse_utc_us(DEFAULT_START_TIME_UTC)
    assert core.boot_start_us == BOOT_START_US
    assert core.unix_time_at_boot_us == start - BOOT_START_US
    row = core.frame(1).truth
    assert row.time_boot_us == BOOT_START_US + round(row.t_s * 1e6)
    assert row.time_unix_us == start + round(row.t_s * 1e6)
    moved = SimCore(sc, 0, 0.1, render=False, start_time_unix_us=F1_START_UNIX_US)
    assert moved.frame(1).truth.time_unix_us == F1_START_UNIX_US + round(row.t_s * 1e6)


# --------------------------------------------------------------------------- run options


def test_mavlink_options_name_each_observer_and_default_the_others():
    sc = load_scenario(F1)
    assert split_mavlink_option("uav1=udpout:127.0.0.1:1") == ("uav1", "udpout:127.0.0.1:1")
    assert split_mavlink_option("udpout:127.0.0.1:14540") == (None, "udpout:127.0.0.1:14540")
    assert mavlink_endpoints(sc, ["uav2=udpout:127.0.0.1:9"], "uav1") == (
        ("uav1", f"udpout:127.0.0.1:{DEFAULT_FLEET_MAVLINK_PORT}"),
        ("uav2", "udpout:127.0.0.1:9"),
    )
    p1 = load_scenario(P1)
    assert mavlink_endpoints(p1, [], "uav1") == (("uav1", "udpout:127.0.0.1:14540"),)
    assert mavlink_endpoints(p1, ["tcp:127.0.0.1:5760"], "uav1") == (("uav1", "tcp:127.0.0.1:5760"),)
    assert mavlink_endpoints(p1, ["uav7=tcp:127.0.0.1:5760"], "uav7") == (("uav7", "tcp:127.0.0.1:5760"),)


@pytest.mark.parametrize(
    "scenario, values, text",
    [
        (F1, ["udpout:127.0.0.1:9"], "several observers (uav1, uav2): expected NAME=ENDPOINT"),
        (F1, ["uav3=udpout:127.0.0.1:9"], "expected an observer of F1 (uav1, uav2), got 'uav3'"),
        (F1, ["uav1=udpout:127.0.0.1:9", "uav1=udpout:127.0.0.1:8"], "observer 'uav1' given twice"),
        (F1, ["uav1=udpout:127.0.0.1:9", "uav2=udpout:127.0.0.1:9"], "share endpoint"),
        (P1, ["udpout:127.0.0.1:9", "udpout:127.0.0.1:8"], "has one observer"),
        (P1, ["uav2=udpout:127.0.0.1:9"], "expected CONN or uav1=CONN"),
    ],
)
def test_bad_mavlink_options_are_config_errors_naming_the_option(scenario, values, text):
    with pytest.raises(ConfigError, match="^--mavlink: ") as ei:
        mavlink_endpoints(load_scenario(scenario), values, "uav1")
    assert text in str(ei.value)


def test_truth_paths_start_times_and_fleet_run_configs():
    assert fleet_truth_path(Path("out/truth.csv"), "uav2") == Path("out/truth.uav2.csv")
    assert fleet_truth_path(Path("t"), "a") == Path("t.a.csv")
    assert parse_start_time(None) is None
    assert parse_start_time("2026-06-01T09:00:00Z") == F1_START_UNIX_US
    assert parse_start_time("now") > F1_START_UNIX_US - 10**15  # the wall clock, in us
    with pytest.raises(ConfigError, match="^--start-time-utc: "):
        parse_start_time("soon")
    # before the UNIX epoch: said as the option's, not as an internal field's (SYSTEM_TIME's time is unsigned)
    with pytest.raises(ConfigError, match="^--start-time-utc: expected a time from 1970-01-01T00:00:00Z on"):
        parse_start_time("1960-01-01T00:00:00Z")
    assert parse_start_time("1970-01-01T00:00:00Z") == 0
    sc = load_scenario(F1)
    cfg = RunConfig(sc, duration_s=1.0, mavlink_by_vehicle=(("uav2", "udpout:127.0.0.1:9"),))
    assert cfg.mavlink_by_vehicle == (("uav1", "udpout:127.0.0.1:14540"), ("uav2", "udpout:127.0.0.1:9"))
    with pytest.raises(ConfigError, match="^--record: not supported"):
        RunConfig(sc, duration_s=1.0, record_path=Path("x.mcap"))
    with pytest.raises(ConfigError, match="mavlink_by_vehicle"):
        RunConfig(load_scenario(P1), mavlink_by_vehicle=(("uav1", "udpout:127.0.0.1:9"),))


# --------------------------------------------------------------------------- the loop, in process


class _Vehicle:
    def __init__(self) -> None:
        self.polls: list[int] = []
        self.counters = {"tx": 0}

    def update_state(self, **state):
        pass

    def poll(self, now_us):
        self.polls.append(now_us)
        self.counters["tx"] += 1


class _Truth:
    def __init__(self) -> None:
        self.rows = []

    def write(self, row, labels=()):
        self.rows.append(row)


def test_the_fleet_loop_steps_every_vehicle_on_its_own_boot_clock_in_lockstep():
    sc = scenario_from_dict(fleet_dict())
    legs = [
        VehicleLeg(SimCore(v, 0, 0.1, render=False), _Vehicle(), None, _Truth(), v.observer_name)
        for v in sc.observer_views()
    ]
    report = run_fleet_loop(legs, RateSpec.parse("max"))
    assert report.frames == 3 and not report.stopped
    assert report.mavlink_counters == {"uav1.tx": 12, "uav2.tx": 12}
    for leg, o in zip(legs, sc.observers):
        assert leg.mavlink.polls == [o.boot_start_us + round(i * 1e6 / 120.0) for i in range(12)]
        assert [r.time_boot_us for r in leg.truth.rows] == leg.mavlink.polls[::4]
    assert [r.time_unix_us for r in legs[0].truth.rows] == [r.time_unix_us for r in legs[1].truth.rows]


def test_cli_refuses_a_plain_mavlink_or_a_vehicle_for_a_fleet(capsys):
    from groundsim.app import cli

    for extra, text in (
        (
            ["--mavlink", "udpout:127.0.0.1:9"],
            "--mavlink: F1 has several observers (uav1, uav2): expected NAME=ENDPOINT",
        ),
        (["--vehicle", "uav9"], "--vehicle: F1 has several observers"),
        (["--start-time-utc", "soon"], "--start-time-utc: expected now or an ISO 8601 UTC time"),
        (["--utc-error-ms", "uav9=20"], "--utc-error-ms: expected NAME=MS with NAME one of uav1, uav2"),
        (["--utc-error-ms", "uav2=soon"], "--utc-error-ms: expected NAME=MS"),
        (["--utc-error-ms", "uav2=20", "--utc-error-ms", "uav2=5"], "--utc-error-ms: expected NAME=MS"),
    ):
        assert cli.main(["run", "--scenario", "F1", "--rate", "max", "--no-render", *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("groundsim run: error: ") and text in err[0], err


def test_utc_error_options_name_vehicles_and_become_microseconds():
    from groundsim.app.run import utc_errors

    sc = scenario_from_dict(fleet_dict())
    assert utc_errors(sc, ["uav2=20", "uav1=-0.5"], "uav1") == (("uav2", 20_000), ("uav1", -500))
    assert utc_errors(sc, [], "uav1") == ()
