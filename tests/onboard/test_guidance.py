"""Observer guidance (onboard.estimation.guidance): the advice keeps its limits, asks for a manoeuvre only when it
helps, and the prediction agrees with the geometry (a straight observer gains nothing, a manoeuvre does)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from onboard.core.errors import InputError
from onboard.core.schema import SchemaError, build
from onboard.estimation.guidance import (
    BRAKE_S,
    GuidanceConfig,
    GuidancePlanner,
    ObserverState,
    TargetPosterior,
    candidate_path,
)
from onboard.estimation.map_estimator import NoiseModel

ATOL_M = 1e-9  # 1 nm: closed-form integration
SLACK_MPS = 1e-9  # the limits are kept exactly, not within a tolerance
F_PX = (764.7, 764.7)
RTK = NoiseModel(
    pixel_sigma_px=0.3,
    attitude_white_sigma_rad=math.radians(0.05),
    attitude_bias_sigma_rad=math.radians(0.1),
    camera_position_white_sigma_m=0.02,
)


@pytest.fixture(scope="module")
def planner() -> GuidancePlanner:
    return GuidancePlanner.for_noise(GuidanceConfig(), RTK, F_PX)


def unobservable(observer: ObserverState, p_ned_m, v_ned_mps, ratio: float = 0.5) -> TargetPosterior:
    """A track whose range sigma is ``ratio`` of the range (what an unobservable window reports)."""
    p = np.asarray(p_ned_m, float)
    u = (p - observer.p_ned_m) / np.linalg.norm(p - observer.p_ned_m)
    r = float(np.linalg.norm(p - observer.p_ned_m))
    cov = 4.0 * np.eye(3) + (ratio * r) ** 2 * np.outer(u, u)
    return TargetPosterior.from_track(
        observer.t_s, p, v_ned_mps, cov, (1.0, 1.0, 0.5), observer.p_ned_m, observer.v_ned_mps
    )


def test_candidate_path_slews_at_the_acceleration_then_holds():
    dt = np.linspace(0.0, 6.0, 61)
    p, v = candidate_path(np.zeros(3), np.array([8.0, 0, 0]), np.array([0.0, 8.0, 0]), 2.0, dt)
    T = math.hypot(8.0, 8.0) / 2.0
    acc = np.linalg.norm(np.diff(v, axis=0), axis=1) / np.diff(dt)
    assert np.all(acc <= 2.0 + 1e-9)
    np.testing.assert_allclose(v[dt >= T], [[0.0, 8.0, 0.0]] * int(np.sum(dt >= T)), atol=ATOL_M)
    # the position is the velocity's integral (trapezoid exact for a piecewise-linear velocity on the knots)
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:, 0] + v[:-1, 0]) * np.diff(dt))])
    assert np.max(np.abs(p[:, 0] - integral)) < 0.05  # the kink at T falls between samples
    assert np.all(np.linalg.norm(v, axis=1) <= 8.0 + 1e-9)  # convexity: never faster than the ends


def test_straight_observer_is_advised_to_manoeuvre_and_it_pays(planner):
    obs = ObserverState(5.0, [0.0, 40.0, -60.0], [0.0, 8.0, 0.0])
    tgt = unobservable(obs, [135.0, 50.0, -80.0], [-3.0, -2.0, 0.0])
    advice = planner.advise(obs, tgt)
    assert advice.status == "advise" and advice.recommended
    assert advice.manoeuvre != "hold"
    # holding a straight line against a constant-velocity target leaves range where it was (unobservable) ...
    assert advice.sigma_range_without_m > 0.8 * advice.sigma_range_now_m
    # ... the manoeuvre ranges it (a few percent of the range within the horizon)
    assert advice.sigma_range_with_m < 0.2 * advice.sigma_range_without_m
    assert advice.valid_until_s == pytest.approx(obs.t_s + planner.config.valid_for_s)


def test_nothing_advised_while_observable_with_margin(planner):
    obs = ObserverState(5.0, [0.0, 40.0, -60.0], [0.0, 8.0, 0.0])
    tgt = unobservable(obs, [135.0, 50.0, -80.0], [-3.0, -2.0, 0.0], ratio=0.01)
    advice = planner.advise(obs, tgt)
    assert advice.status == "observable" and not advice.recommended and advice.v_ned_mps is None


def test_observer_outside_its_limits_gets_no_advice(planner):
    low = ObserverState(5.0, [0.0, 0.0, -5.0], [0.0, 8.0, 0.0])  # 5 m up, the band starts at 20 m
    advice = planner.advise(low, unobservable(low, [135.0, 50.0, -80.0], [-3.0, -2.0, 0.0]))
    assert advice.status == "outside_limits" and advice.v_ned_mps is None


def test_field_of_view_limit_discards_candidates():
    cfg = build(GuidanceConfig, {"max_los_off_heading_deg": 30.0})
    pl = GuidancePlanner.for_noise(cfg, RTK, F_PX)
    obs = ObserverState(5.0, [0.0, 0.0, -60.0], [8.0, 0.0, 0.0])
    advice = pl.advise(obs, unobservable(obs, [150.0, 0.0, -80.0], [0.0, 0.0, 0.0]))
    crossing = [c for c in advice.candidates if c.name.startswith("cross_")]
    assert crossing and all(not c.feasible and c.why == "field_of_view" for c in crossing)


@pytest.mark.parametrize(
    "field, value",
    [
        ("min_altitude_m", 200.0),
        ("cruise_speed_mps", 50.0),
        ("los_elevation_min_deg", 60.0),
        ("heading_changes_deg", [200.0]),
    ],
)
def test_config_refuses_inconsistent_limits(field, value):
    with pytest.raises(SchemaError, match=field):
        build(GuidanceConfig, {field: value})


@pytest.mark.parametrize(
    "autopilot, mode, ok",
    [
        (12, 393216, True),  # PX4 OFFBOARD: main mode 6 << 16
        (12, 4, False),  # ArduCopter's GUIDED number under PX4: PX4 never reports it
        (12, 0, False),  # no main mode
        (12, 393216 + 1, False),  # PX4's low 16 bits are reserved (0)
        (3, 4, True),  # ArduCopter GUIDED
        (3, 393216, False),  # PX4's encoding under ArduPilot
    ],
)
def test_a_custom_mode_the_autopilot_never_reports_is_refused(autopilot, mode, ok):
    """The gate would wait in not_accepting for good, saying nothing: refused at load, naming the field."""
    settings = {"accept_autopilot": autopilot, "accept_custom_mode": mode}
    if ok:
        assert build(GuidanceConfig, settings).accept_custom_mode == mode
    else:
        with pytest.raises(SchemaError, match="accept_custom_mode"):
            build(GuidanceConfig, settings)


def test_bad_posterior_is_refused():
    with pytest.raises(InputError, match="cov_pv"):
        TargetPosterior(0.0, [1.0, 0, 0], [0.0, 0, 0], np.zeros((6, 6)))


_finite = dict(allow_nan=False, allow_infinity=False)
#: the statuses an observer within its limits may get (``outside_limits`` is not one of them)
WITHIN_LIMITS_STATUSES = {"advise", "observable", "no_gain", "no_feasible"}


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    # the observer inside the default altitude band (20 to 150 m) and, below, its speed and climb limits; the target
    # 20 to 400 m away. Drawn from boxes around them, most cases were an observer outside its limits (at 0 m, or
    # faster than max_speed) or a target at the camera (hypothesis favours 0.0): no advice, so no limit was checked
    alt_m=st.floats(20.0, 150.0, **_finite),
    speed_frac=st.floats(0.0, 1.0, **_finite),
    heading=st.floats(-math.pi, math.pi, **_finite),
    climb_frac=st.floats(-1.0, 1.0, **_finite),
    range_m=st.floats(20.0, 400.0, **_finite),
    los_az=st.floats(-math.pi, math.pi, **_finite),
    los_el=st.floats(-math.radians(80.0), math.radians(40.0), **_finite),
    v_tgt=st.tuples(*[st.floats(-10.0, 10.0, **_finite)] * 3),
    # over quiet_below_sigma_range_ratio (0.03): test_nothing_advised_while_observable_with_margin has those
    ratio=st.floats(0.05, 2.0, **_finite),
    max_speed=st.floats(3.0, 15.0, **_finite),
    climb=st.floats(0.0, 3.0, **_finite),
    off_heading=st.sampled_from([60.0, 120.0, 180.0]),
)
# one that is advised (the geometry of test_straight_observer_is_advised_to_manoeuvre_and_it_pays): the limit checks
# below run whatever hypothesis draws
@example(
    alt_m=60.0,
    speed_frac=8.0 / 12.0,
    heading=math.pi / 2,
    climb_frac=0.0,
    range_m=math.sqrt(135.0**2 + 10.0**2 + 20.0**2),
    los_az=math.atan2(10.0, 135.0),
    los_el=math.atan2(20.0, math.hypot(135.0, 10.0)),
    v_tgt=(-3.0, -2.0, 0.0),
    ratio=0.5,
    max_speed=12.0,
    climb=2.0,
    off_heading=180.0,
)
def test_advice_never_leaves_the_limits(
    planner,
    alt_m,
    speed_frac,
    heading,
    climb_frac,
    range_m,
    los_az,
    los_el,
    v_tgt,
    ratio,
    max_speed,
    climb,
    off_heading,
):
    cfg = build(
        GuidanceConfig,
        {
            "max_speed_mps": max_speed,
            "cruise_speed_mps": min(6.0, max_speed),
            "max_climb_rate_mps": climb,
            "max_los_off_heading_deg": off_heading,
            "horizon_s": 4.0,
        },
    )
    pl = GuidancePlanner(cfg, planner.estimator, F_PX)
    speed = speed_frac * max_speed
    v_obs = (speed * math.cos(heading), speed * math.sin(heading), climb_frac * climb)
    obs = ObserverState(3.0, [0.0, 0.0, -alt_m], v_obs)
    rel = range_m * np.array(
        [math.cos(los_el) * math.cos(los_az), math.cos(los_el) * math.sin(los_az), -math.sin(los_el)]
    )
    p_tgt = obs.p_ned_m + rel
    advice = pl.advise(obs, unobservable(obs, p_tgt, v_tgt, ratio))
    assert advice.status in WITHIN_LIMITS_STATUSES, (advice.status, advice.why)
    if not advice.recommended:
        assert advice.v_ned_mps is None
        return
    v = advice.v_ned_mps
    assert v is not None
    assert cfg.min_speed_mps - SLACK_MPS <= math.hypot(v[0], v[1]) <= cfg.max_speed_mps + SLACK_MPS
    assert abs(v[2]) <= cfg.max_climb_rate_mps + SLACK_MPS
    # the path it predicts keeps the altitude band and the target in view, at the configured acceleration
    p, vp = candidate_path(obs.p_ned_m, obs.v_ned_mps, v, cfg.max_accel_mps2, pl.dt_s)
    assert cfg.altitude_ok(p)
    los = p_tgt + np.asarray(v_tgt) * pl.dt_s[:, None] - p
    el = np.degrees(np.arctan2(-los[:, 2], np.hypot(los[:, 0], los[:, 1])))
    assert np.all((el >= cfg.los_elevation_min_deg) & (el <= cfg.los_elevation_max_deg))
    assert advice.sigma_range_with_m < cfg.min_gain_ratio * advice.sigma_range_without_m
    assert advice.valid_until_s > advice.t_s


def _track(t_us: int, p_ned_m, v_ned_mps, cov, **kw):
    from onboard.core.frames import GeodeticOrigin
    from onboard.core.track import Track

    return Track(
        vehicle="uav1",
        seq=1,
        time_boot_us=t_us,
        state="tracking",
        origin=GeodeticOrigin(32.0, 118.8, 0.0),
        lat_deg=32.0,
        lon_deg=118.8,
        alt_m=80.0,
        p_ned_m=tuple(p_ned_m),
        v_ned_mps=tuple(v_ned_mps),
        cov_p_ned_m2=cov,
        range_m=float(np.linalg.norm(p_ned_m)),
        **kw,
    )


def test_tap_publishes_advice_json_once_per_interval_and_counts_what_it_skips():
    from types import SimpleNamespace

    from onboard.app.config import OnboardConfig
    from onboard.app.guidance_tap import make_guidance_tap
    from onboard.estimation.guidance import GUIDANCE_SCHEMA
    from onboard.io.zenoh_session import GUIDANCE_ENCODING, guidance_key

    tap = make_guidance_tap(OnboardConfig())
    assert tap is not None and guidance_key("uav1") == "irtrack/uav1/guidance"
    assert GUIDANCE_ENCODING.endswith(GUIDANCE_SCHEMA)
    sent: list[bytes] = []
    tap.attach(sent.append)
    cam = np.array([0.0, 40.0, -60.0])
    p = np.array([135.0, 50.0, -80.0])
    u = (p - cam) / np.linalg.norm(p - cam)
    cov = 4.0 * np.eye(3) + (0.5 * np.linalg.norm(p - cam)) ** 2 * np.outer(u, u)
    pose = SimpleNamespace(p_cam_ned_m=cam, body=SimpleNamespace(v_ned_mps=np.array([0.0, 8.0, 0.0])))
    # the band is above home: nothing planned until the autopilot has said where home is
    assert tap.step(_track(4_000_000, p, (-3.0, -2.0, 0.0), cov), pose) is None and not sent
    tap.home_alt_amsl_m = 0.0  # home at the (origin-less) pose's origin, as the link sets it from #33
    payload = tap.step(_track(5_000_000, p, (-3.0, -2.0, 0.0), cov), pose)
    assert payload is not None and sent == [payload]
    import json

    msg = json.loads(payload)
    assert msg["schema"] == GUIDANCE_SCHEMA and msg["status"] == "advise" and msg["in_loop"] is False
    assert msg["valid_until_boot_us"] == 5_000_000 + 3_000_000
    assert msg["sigma_range_with_m"] < msg["sigma_range_without_m"]
    # not due again until update_interval_s of capture time has passed
    assert tap.step(_track(5_500_000, p, (-3.0, -2.0, 0.0), cov), pose) is None and len(sent) == 1
    # an autopilot that sends no velocity: skipped and counted
    blind = SimpleNamespace(p_cam_ned_m=cam, body=SimpleNamespace(v_ned_mps=np.full(3, np.nan)))
    assert tap.step(_track(6_100_000, p, (-3.0, -2.0, 0.0), cov), blind) is None
    assert tap.status()["skipped"] == {"no_home": 1, "no_velocity": 1} and tap.status()["published"] == 1
    # observable with margin: nothing published
    small = 4.0 * np.eye(3)
    assert tap.step(_track(7_200_000, p, (-3.0, -2.0, 0.0), small), pose) is None
    assert tap.status()["last_status"] == "observable" and len(sent) == 1


def test_setpoint_message_round_trips_velocity_only():
    from onboard.io.mavlink_wire import SETPOINT_VELOCITY_ONLY_MASK, SetPositionTargetLocalNed, wire_roundtrip

    sp = SetPositionTargetLocalNed(12_345_000, 1, 1, (1.5, -2.25, 0.5))
    msg = wire_roundtrip(sp.to_message())
    assert msg.type_mask == SETPOINT_VELOCITY_ONLY_MASK and msg.coordinate_frame == 1
    assert SetPositionTargetLocalNed.from_message(msg) == sp
    msg.type_mask = 0  # a position setpoint: not what this type carries
    with pytest.raises(InputError, match="only velocity"):
        SetPositionTargetLocalNed.from_message(msg)


GUIDED = (3, 128 | 1, 4)  # ArduPilot, armed + custom mode, GUIDED
LOITER = (3, 128 | 1, 5)


def test_setpoint_gate_sends_only_in_the_accepting_mode_and_latches_a_stop_until_the_pilot_takes_over():
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True, "geofence_north_m": [-100.0, 100.0]}))
    inside = (0.0, np.array([0.0, 0.0, -60.0]), np.array([0.0, 5.0, 0.0]))
    advice = (10.0, np.array([3.0, 4.0, 0.0]))

    def step(now, mode=GUIDED, pose=inside, adv=advice, link=True):
        return gate.step(now, link_connected=link, mode=mode, pose=(now, *pose[1:]) if pose else None, advice=adv)

    assert step(0.0, mode=LOITER).state == "not_accepting"
    d = step(0.1)
    assert d.send and d.state == "sending" and np.allclose(d.v_ned_mps, [3.0, 4.0, 0.0])
    d = step(10.5)
    # the advice lapsed: zero velocity for BRAKE_S (not the last setpoint flown on until the autopilot's timeout)
    assert d.send and d.state == "waiting" and not d.v_ned_mps.any() and d.why == "no advice in force: braking"
    assert not step(11.6).send and gate.why == "no advice in force"  # then nothing
    assert step(1.0).send
    out = (0.0, np.array([150.0, 0.0, -60.0]), np.array([0.0, 5.0, 0.0]))
    d = step(1.2, pose=out)
    # stopped, latched: for BRAKE_S zero velocity (the vehicle holds instead of flying the last setpoint on until the
    # autopilot's own timeout), then nothing
    assert d.send and d.state == "stopped" and d.why.startswith("geofence") and not d.v_ned_mps.any()
    d = step(1.4)
    assert d.send and not d.v_ned_mps.any() and gate.state == "stopped"  # latched, back inside or not
    assert not step(2.3).send and gate.state == "stopped"
    assert step(2.4, mode=LOITER).state == "not_accepting"  # the pilot took over: re-armed
    assert step(2.6).send
    d = step(2.8, link=False)
    # zero velocity too: without heartbeats the mode is unknown, and any other mode ignores the setpoint
    assert d.send and not d.v_ned_mps.any() and d.state == "stopped" and d.why.startswith("link_lost")
    assert gate.stops == {"geofence": 1, "link_lost": 1}
    off = SetpointGate(GuidanceConfig())
    assert off.step(0.0, link_connected=True, mode=GUIDED, pose=inside, advice=advice).state == "off"


def test_the_gate_says_the_pilot_left_the_mode_for_as_long_as_the_vehicle_stays_out_of_it():
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True, "geofence_north_m": [-100.0, 100.0]}))
    inside = (0.0, np.array([0.0, 0.0, -60.0]), np.array([0.0, 5.0, 0.0]))
    advice = (100.0, np.array([3.0, 4.0, 0.0]))

    def step(now, mode=GUIDED):
        return gate.step(now, link_connected=True, mode=mode, pose=(now, *inside[1:]), advice=advice)

    assert step(0.0, mode=LOITER).why == "the autopilot is not in the accepting mode"  # never handed over
    assert step(0.25).send
    # the pilot switched to LOITER mid-manoeuvre: the status (1 Hz) must still say so at the setpoint steps after
    # the first (4 Hz), not read as if the vehicle had never been handed over
    for t in (0.5, 0.75, 1.0, 5.0):
        d = step(t, mode=LOITER)
        assert not d.send and d.state == "not_accepting" and d.why == "the autopilot left the accepting mode"
    assert step(5.25).send and gate.why == ""  # back in the mode: the pilot's hand-over again
    step(5.5, mode=(3, 128 | 1, 9))  # then another mode: left again
    assert step(5.75, mode=LOITER).why == "the autopilot left the accepting mode"


def test_setpoint_gate_refuses_a_disarmed_or_foreign_autopilot_and_an_old_pose():
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    pose = (0.0, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    advice = (10.0, np.array([3.0, 0.0, 0.0]))
    assert gate.step(0.0, link_connected=True, mode=(3, 1, 4), pose=pose, advice=advice).state == "not_accepting"
    assert gate.step(0.0, link_connected=True, mode=(12, 129, 4), pose=pose, advice=advice).state == "not_accepting"
    assert gate.step(5.0, link_connected=True, mode=GUIDED, pose=pose, advice=advice).state == "waiting"


def test_tap_sends_the_advice_in_force_to_the_autopilot_only_through_the_gate():
    from types import SimpleNamespace

    from onboard.app.config import OnboardConfig
    from onboard.app.guidance_tap import make_guidance_tap
    from onboard.app.observers import FrameResult
    from onboard.core.schema import build as build_cfg

    now = [100.0]
    cfg = build_cfg(OnboardConfig, {"guidance": {"enabled": True}})
    tap = make_guidance_tap(cfg, clock=lambda: now[0], clock_ns=lambda: 0)  # frames handled as they arrive (0 ns)
    assert tap is not None and tap.in_loop
    sent: list = []
    link = SimpleNamespace(
        state="connected",
        autopilot_mode=LOITER,
        send_setpoint=lambda v: sent.append(v) or True,
        home_alt_amsl_m=0.0,
        heartbeat_age_s=lambda: 0.0,
    )
    tap.setpoint_step(now[0] - 10.0, link)  # the link has told where home is (#33), before the first frame
    cam = np.array([0.0, 40.0, -60.0])
    body = SimpleNamespace(p_ned_m=cam, v_ned_mps=np.array([0.0, 8.0, 0.0]))
    pose = SimpleNamespace(p_cam_ned_m=cam, body=body, origin=None, pos_extrapolated_us=0)
    p = np.array([135.0, 50.0, -80.0])
    u = (p - cam) / np.linalg.norm(p - cam)
    cov = 4.0 * np.eye(3) + (0.5 * np.linalg.norm(p - cam)) ** 2 * np.outer(u, u)
    track = _track(5_000_000, p, (-3.0, -2.0, 0.0), cov)
    tap.on_frame(None, FrameResult(0, True, pose, track, None))  # the pose the gate checks
    assert tap.step(track, pose) is not None  # an advice in force for valid_for_s
    assert not tap.setpoint_step(now[0], link) and tap.status()["setpoints"]["state"] == "not_accepting"
    assert tap.status()["setpoints"]["resumes"] is None
    link.autopilot_mode = GUIDED
    now[0] += 1.0
    assert tap.setpoint_step(now[0], link) and len(sent) == 1
    assert not tap.setpoint_step(now[0] + 0.01, link)  # paced at setpoint_rate_hz
    now[0] += 5.0  # the advice (3 s) and the pose (1 s) are old now
    tap.on_frame(None, FrameResult(0, True, pose, None, None))
    assert tap.setpoint_step(now[0], link) and not sent[-1].any()  # the advice ended: braking
    now[0] += 1.1
    tap.on_frame(None, FrameResult(0, True, pose, None, None))
    assert not tap.setpoint_step(now[0], link) and tap.status()["setpoints"]["why"] == "no advice in force"
    link.send_setpoint = None  # a broken link object: counted, never raised into the main loop
    tap._advice = (now[0] + 3.0, np.array([1.0, 0.0, 0.0]), None)
    assert not tap.setpoint_step(now[0] + 1.0, link) and tap.status()["setpoints"]["errors"] == 1


def test_setpoints_are_paced_on_a_schedule_so_a_late_turn_does_not_stretch_the_next_gap():
    """Each setpoint was paced 1/rate from when the main loop came round, so every late turn added to the gap (PX4 at
    2.1 Hz: gaps up to 0.516 s).  On a schedule a late one is followed by one on time; after a stall no burst."""
    now = [100.0]
    tap, link, sent = _in_loop_tap(now)  # 4 Hz
    tap._pose = (now[0] + 100.0, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    tap._advice = (now[0] + 100.0, np.array([1.0, 0.0, 0.0]), None)
    link.autopilot_mode = GUIDED
    start = tap.next_setpoint_s  # the schedule's step after the first (LOITER) one
    t = [start + 0.04, start + 0.25, start + 0.51, start + 0.75, start + 5.0, start + 5.01, start + 5.25]
    fired = [tap.setpoint_step(x, link) for x in t]
    # late by 40 ms, then on time at +0.25 (was: not before +0.29); a stall of 4 s: one now, the next a period on
    assert fired == [True, True, True, True, True, False, True]
    assert tap.next_setpoint_s == pytest.approx(start + 5.5)
    tap.in_loop = False
    assert tap.next_setpoint_s == math.inf  # advice only: nothing for the main loop to wake for


def _warned_at_start(config, caplog, words: str) -> list[str]:
    """The WARNING lines holding ``words`` that a guidance tap of ``config`` logs when it starts (then closed)."""
    import logging

    from onboard.app.guidance_tap import make_guidance_tap

    tap = make_guidance_tap(config)
    with caplog.at_level(logging.WARNING, logger="onboard.app.guidance_tap"):
        tap.start()
    tap.close(1.0)
    return [r.getMessage() for r in caplog.records if words in r.getMessage()]


def test_guidance_in_the_loop_with_a_fixed_pod_and_no_heading_limit_is_warned_at_start(caplog):
    """config/onboard.yaml ships a fixed pod and max_los_off_heading_deg 180 (no limit): an autopilot that yaws along
    the commanded velocity can turn the pod away from the target in a cross-track manoeuvre.  Warned once at start,
    naming the keys, unless the limit keeps the target within half the horizontal field of view (22.7 deg here)."""
    from onboard.app.config import OnboardConfig
    from onboard.app.guidance_tap import fixed_pod_heading_warning
    from onboard.core.schema import build as build_cfg

    def cfg(guidance, gimballed=False):
        return build_cfg(OnboardConfig, {"guidance": guidance, "camera": {"mount": {"gimballed": gimballed}}})

    why = fixed_pod_heading_warning(cfg({"enabled": True}))
    assert why is not None and "guidance.max_los_off_heading_deg 180" in why and "camera.mount.gimballed" in why
    assert "<= 22.7" in why
    assert fixed_pod_heading_warning(cfg({"enabled": True, "max_los_off_heading_deg": 22.0})) is None
    assert fixed_pod_heading_warning(cfg({"enabled": True}, gimballed=True)) is None  # the pod looks where it likes
    assert fixed_pod_heading_warning(cfg({"enabled": False})) is None  # advice only: nothing is commanded
    assert _warned_at_start(cfg({"enabled": True}), caplog, "max_los_off_heading_deg") == [why]


def test_guidance_in_the_loop_without_a_fixed_origin_warns_that_the_geofence_moves_with_the_first_fix(caplog):
    """With pose.origin null (the shipped default) the geofence box is centred on each run's first fix: said once at
    start, naming the keys, when setpoints go out; nothing with an origin or without the loop."""

    from onboard.app.config import OnboardConfig
    from onboard.app.guidance_tap import moving_geofence_warning
    from onboard.core.schema import build as build_cfg

    origin = {"lat_deg": 32.0, "lon_deg": 118.8, "alt_m": 0.0}

    def cfg(guidance, pose=None):
        return build_cfg(OnboardConfig, {"guidance": guidance, "pose": pose or {}})

    why = moving_geofence_warning(cfg({"enabled": True}))
    assert why is not None and "pose.origin" in why and "guidance.geofence_north_m" in why
    assert moving_geofence_warning(cfg({"enabled": True}, {"origin": origin})) is None
    assert moving_geofence_warning(cfg({"enabled": False})) is None  # advice only: nothing is commanded
    assert _warned_at_start(cfg({"enabled": True}), caplog, "pose.origin") == [why]


def test_the_altitude_band_is_above_home_by_default_so_it_holds_at_any_site_elevation():
    """A site 488 m above sea level: a vehicle 60 m above home is inside the default 20-150 m band (it would be
    far above it AMSL); until the autopilot has said where home is, there is no reference and no advice."""
    from types import SimpleNamespace

    from onboard.app.guidance_tap import reference_alt_m
    from onboard.core.frames import GeodeticOrigin

    assert GuidanceConfig().altitude_reference == "home"
    pose = SimpleNamespace(origin=GeodeticOrigin(47.4, 8.5, 548.0))  # the first fix, 60 m above home
    assert reference_alt_m(pose, "home", 488.0) == pytest.approx(60.0)
    assert reference_alt_m(pose, "amsl", 488.0) == pytest.approx(548.0)
    assert reference_alt_m(pose, "home", None) is None
    c = GuidanceConfig()
    assert c.altitude_ok(np.array([0.0, 0.0, -reference_alt_m(pose, "home", 488.0)]))
    assert not c.altitude_ok(np.array([0.0, 0.0, -reference_alt_m(pose, "amsl", 488.0)]))


def test_a_gate_that_first_sees_the_accepting_mode_waits_for_the_pilot_to_hand_over():
    """A daemon restarted in flight (a crash, the container's restart policy) found the autopilot still in GUIDED and
    sent again 13.6 s later, with nobody's consent: its stop latch lived in the old process.  The hand-over is the
    autopilot entering the mode while this daemon watches."""
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    pose = (0.0, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    advice = (10.0, np.array([3.0, 0.0, 0.0]))

    def step(now, mode):
        return gate.step(now, link_connected=True, mode=mode, pose=(now, *pose[1:]), advice=advice)

    assert gate.step(0.0, link_connected=False, mode=None, pose=pose, advice=advice).state == "waiting"
    d = step(0.1, GUIDED)
    assert not d.send and d.state == "stopped" and d.why.startswith("handover")
    assert not step(0.5, GUIDED).send  # no brake either: this daemon never sent
    assert step(0.6, LOITER).state == "not_accepting"
    assert step(0.7, GUIDED).send
    assert gate.stops == {"handover": 1}


def test_arming_in_the_accepting_mode_is_the_hand_over():
    """With require_armed (the default) the accepting state is the mode and armed: a pilot who arms on the ground in
    GUIDED hands over as one who switches to GUIDED armed does (deploy/README.md says so); a daemon that first sees the
    vehicle armed in GUIDED still waits."""
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    pose = (np.array([0.0, 0.0, -60.0]), np.zeros(3))
    advice = (10.0, np.array([3.0, 0.0, 0.0]))
    guided_disarmed = (GUIDED[0], GUIDED[1] & ~128, GUIDED[2])

    def step(now, mode):
        return gate.step(now, link_connected=True, mode=mode, pose=(now, *pose), advice=advice)

    d = step(0.1, guided_disarmed)
    assert not d.send and d.state == "not_accepting"
    assert step(0.2, GUIDED).send  # armed in the mode: handed over
    assert gate.stops == {}


def test_a_link_that_comes_back_in_the_accepting_mode_waits_for_the_pilot_to_hand_over():
    """LOITER, the link lost for 7 s, back in GUIDED: the gate's "mode seen" lived for the whole process, so it sent
    an advice of -8 m/s 76 ms after the first GUIDED heartbeat, a switch it never saw; a fresh daemon waited.  The
    link's return is a fresh start; a gate that was commanding when it was lost stays stopped under link_lost."""
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    pose = (0.0, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    advice = (100.0, np.array([-8.0, 0.0, 0.0]))

    def step(now, mode, link=True):
        return gate.step(now, link_connected=link, mode=mode, pose=(now, *pose[1:]), advice=advice)

    assert step(0.0, LOITER).state == "not_accepting"
    assert not step(1.0, None, link=False).send
    d = step(8.0, GUIDED)
    assert not d.send and d.state == "stopped"
    assert d.why == "handover: the autopilot was in the accepting mode when its link came back"
    assert step(8.5, LOITER).state == "not_accepting"
    assert step(9.0, GUIDED).send  # the switch seen: handed over
    d = step(9.25, None, link=False)  # lost while commanding: braking, latched
    assert d.send and not d.v_ned_mps.any() and d.why.startswith("link_lost")
    # back in the mode: zero velocity again for BRAKE_S (the brake went into the dead link), still latched
    d = step(16.0, GUIDED)
    assert d.send and not d.v_ned_mps.any() and gate.state == "stopped" and gate.why.startswith("link_lost")
    assert not step(16.0 + BRAKE_S, GUIDED).send and gate.state == "stopped"
    assert step(16.5 + BRAKE_S, LOITER).state == "not_accepting"
    assert step(17.0 + BRAKE_S, GUIDED).send
    assert gate.stops == {"handover": 1, "link_lost": 1}


def test_setpoints_stop_once_the_autopilots_heartbeat_is_older_than_the_guidance_timeout():
    """The gate took the link as up until mavlink.heartbeat_timeout_s (5 s): setpoints went on for 5 s after the
    autopilot's heartbeats stopped.  guidance.heartbeat_timeout_s brakes and stops sooner, as a lost link does."""
    from onboard.estimation.guidance import SetpointGate

    with pytest.raises(SchemaError, match="heartbeat_timeout_s"):
        build(GuidanceConfig, {"heartbeat_timeout_s": 1.0})  # a 1 Hz heartbeat a little late would stop it
    assert GuidanceConfig().heartbeat_timeout_s == 2.5
    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    pose = (0.0, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    advice = (100.0, np.array([3.0, 0.0, 0.0]))

    def step(now, mode, age):
        return gate.step(now, link_connected=True, mode=mode, pose=(now, *pose[1:]), advice=advice, heartbeat_age_s=age)

    assert step(0.0, LOITER, 0.3).state == "not_accepting"
    assert step(0.5, GUIDED, 0.2).send
    assert step(2.75, GUIDED, 2.45).send  # the heartbeats stopped at 0.3 s
    d = step(3.0, GUIDED, 2.7)  # the link is still "connected" (it waits 5 s): the gate does not
    assert d.send and not d.v_ned_mps.any() and d.state == "stopped"
    assert d.why == "link_lost: no autopilot heartbeat for guidance.heartbeat_timeout_s"
    assert step(3.75, GUIDED, 3.45).send  # the brake: zero velocity for BRAKE_S
    assert not step(4.25, GUIDED, 3.95).send
    # heard again, still in the mode: zero velocity for BRAKE_S more (the first brake went into the dead link),
    # then nothing, latched until the hand-over
    d = step(4.5, GUIDED, 0.0)
    assert d.send and not d.v_ned_mps.any() and gate.state == "stopped"
    assert step(4.5 + BRAKE_S - 0.1, GUIDED, 0.1).send and not step(4.5 + BRAKE_S, GUIDED, 0.1).send
    assert gate.stops == {"link_lost": 1}
    idle = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    idle.step(0.0, link_connected=True, mode=LOITER, pose=pose, advice=None, heartbeat_age_s=0.0)
    d = idle.step(0.1, link_connected=True, mode=GUIDED, pose=pose, advice=advice, heartbeat_age_s=math.nan)
    assert not d.send and d.why == "no autopilot heartbeat for guidance.heartbeat_timeout_s"  # a NaN age: unheard

    now = [100.0]  # the tap asks the link how old its newest heartbeat is
    tap, link, sent = _in_loop_tap(now)
    age = [0.0]
    link.heartbeat_age_s = lambda: age[0]
    tap._pose = (now[0], np.array([0.0, 0.0, -60.0]), np.zeros(3))
    tap._advice = (now[0] + 3.0, np.array([1.0, 0.0, 0.0]), None)
    link.autopilot_mode = GUIDED
    assert tap.setpoint_step(now[0], link) and sent[-1][0] == 1.0
    age[0] = 2.6
    tap._pose = (now[0] + 0.5, *tap._pose[1:])
    assert tap.setpoint_step(now[0] + 0.5, link) and not sent[-1].any()
    assert tap.status()["setpoints"]["stops"] == {"link_lost": 1}


def test_an_unknown_vehicle_velocity_stops_the_setpoints():
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    advice = (10.0, np.array([3.0, 0.0, 0.0]))
    assert gate.step(0.0, link_connected=True, mode=LOITER, pose=None, advice=advice).state == "not_accepting"
    ok = (0.1, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    assert gate.step(0.1, link_connected=True, mode=GUIDED, pose=ok, advice=advice).send
    nan = (0.2, np.array([0.0, 0.0, -60.0]), np.array([np.nan, 0.0, 0.0]))
    d = gate.step(0.2, link_connected=True, mode=GUIDED, pose=nan, advice=advice)
    assert d.state == "stopped" and d.why.startswith("speed") and not d.v_ned_mps.any()


def _in_loop_tap(now, ns=(0,)):
    from types import SimpleNamespace

    from onboard.app.config import OnboardConfig
    from onboard.app.guidance_tap import make_guidance_tap
    from onboard.core.schema import build as build_cfg

    # frames handled as they arrive: FrameResult(0, ...) on a clock_ns that stands at 0
    tap = make_guidance_tap(
        build_cfg(OnboardConfig, {"guidance": {"enabled": True}}), clock=lambda: now[0], clock_ns=lambda: ns[0]
    )
    sent: list = []
    link = SimpleNamespace(
        state="connected",
        autopilot_mode=LOITER,
        send_setpoint=lambda v: sent.append(v) or True,
        home_alt_amsl_m=0.0,
        heartbeat_age_s=lambda: 0.0,
    )
    tap.setpoint_step(now[0] - 10.0, link)
    return tap, link, sent


def _pose(extrapolated_us=0):
    from types import SimpleNamespace

    cam = np.array([0.0, 40.0, -60.0])
    body = SimpleNamespace(p_ned_m=cam, v_ned_mps=np.array([0.0, 8.0, 0.0]))
    return SimpleNamespace(p_cam_ned_m=cam, body=body, origin=None, pos_extrapolated_us=extrapolated_us)


def test_a_pose_dead_reckoned_through_a_gnss_outage_is_not_fresh_for_the_gate():
    """Through a 7 s position outage the frames kept a dead-reckoned pose, stamped when the frame came: the gate's
    pose_timeout_s never fired and 28 setpoints went out on a position 40 m off.  The pose counts from its newest
    measured position."""
    from onboard.app.observers import FrameResult

    now = [100.0]
    tap, link, sent = _in_loop_tap(now)
    tap.on_frame(None, FrameResult(0, True, _pose(), None, None))
    tap._advice = (now[0] + 3.0, np.array([1.0, 0.0, 0.0]), None)
    link.autopilot_mode = GUIDED
    assert tap.setpoint_step(now[0], link) and sent
    now[0] += 0.5
    tap.on_frame(None, FrameResult(0, True, _pose(extrapolated_us=1_500_000), None, None))  # 1.5 s of dead reckoning
    assert tap.setpoint_step(now[0], link)  # the brake: zero velocity
    assert not sent[-1].any() and tap.status()["setpoints"]["state"] == "stopped"
    # what ends the stop, in the status too (not only in the log line)
    assert tap.status()["setpoints"]["resumes"].startswith("until the autopilot leaves the accepting mode")
    assert tap.status()["setpoints"]["why"].startswith("pose_lost")


def test_a_frame_handled_late_is_as_old_as_its_arrival_for_the_gate():
    """The gate's pose was stamped when the pipeline handled its frame: a frame that waited 1.5 s (queue, telemetry
    wait, a slow pipeline) counted as fresh, and 1.5 s old positions passed guidance.pose_timeout_s (1 s).  Its age
    counts from its arrival at the daemon (received_ns, the local clock of the gate's other ages); so does the
    validity of an advice planned on it."""
    from onboard.app.observers import FrameResult

    now, ns = [100.0], [100_000_000_000]
    tap, link, sent = _in_loop_tap(now, ns)
    tap.on_frame(None, FrameResult(ns[0], True, _pose(), None, None))
    tap._advice = (now[0] + 3.0, np.array([1.0, 0.0, 0.0]), None)
    link.autopilot_mode = GUIDED
    assert tap.setpoint_step(now[0], link) and sent[-1][0] == 1.0
    now[0] += 0.5
    ns[0] += 500_000_000
    tap.on_frame(None, FrameResult(ns[0] - 1_500_000_000, True, _pose(), None, None))  # arrived 1.5 s ago
    assert tap.setpoint_step(now[0], link) and not sent[-1].any()  # the brake
    assert tap.status()["setpoints"]["why"].startswith("pose_lost")
    # an advice planned on a frame that arrived 2 s ago holds valid_for_s (3 s) from then: 1 s more
    p = np.array([135.0, 50.0, -80.0])
    cam = _pose().p_cam_ned_m
    u = (p - cam) / np.linalg.norm(p - cam)
    cov = 4.0 * np.eye(3) + (0.5 * np.linalg.norm(p - cam)) ** 2 * np.outer(u, u)
    track = _track(5_000_000, p, (-3.0, -2.0, 0.0), cov)
    tap.on_frame(None, FrameResult(ns[0] - 2_000_000_000, True, _pose(), track, None))
    assert tap.plan_pending() is not None and tap._advice is not None
    assert tap._advice[0] == pytest.approx(now[0] - 2.0 + 3.0)


def test_a_camera_gap_stops_the_setpoints_saying_so_and_a_pose_stamp_that_is_not_a_number_is_not_recent():
    """The gate's pose comes with the frames: a camera gap over pose_timeout_s stopped it with "no measured vehicle
    position" while the telemetry was fine.  And a NaN stamp passed ``now - t > timeout`` as recent."""
    from onboard.app.observers import FrameResult
    from onboard.estimation.guidance import SetpointGate

    now = [100.0]
    tap, link, sent = _in_loop_tap(now)
    tap.on_frame(None, FrameResult(0, True, _pose(), None, None))
    tap._advice = (now[0] + 3.0, np.array([1.0, 0.0, 0.0]), None)
    link.autopilot_mode = GUIDED
    assert tap.setpoint_step(now[0], link) and sent[-1][0] == 1.0
    now[0] += 1.25  # no frame since: the link and its telemetry are fine
    assert tap.setpoint_step(now[0], link) and not sent[-1].any()
    why = tap.status()["setpoints"]["why"]
    assert why.startswith("pose_lost: no camera frame with a measured vehicle position") and "no frames" in why

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    p = np.array([0.0, 0.0, -60.0])
    advice = (10.0, np.array([3.0, 0.0, 0.0]))
    gate.step(0.0, link_connected=True, mode=LOITER, pose=None, advice=None)
    d = gate.step(0.1, link_connected=True, mode=GUIDED, pose=(math.nan, p, np.zeros(3)), advice=advice)
    assert not d.send and d.state == "waiting" and d.why.startswith("no camera frame")


def test_a_gnss_fix_lost_while_commanding_stops_the_setpoints():
    """GPS_RAW_INT fell from a 3-D fix to no fix during a manoeuvre while GLOBAL_POSITION_INT went on (the autopilot
    dead-reckons through the outage): its positions stayed fresh for pose_timeout_s, and a daemon on 127.0.0.1 sent
    20 setpoints of the advice over 5 s of no fix.  A fix lost after a 3-D one stops, latched, as a limit does; a
    vehicle that never had a 3-D fix (one positioned otherwise) is not stopped by it."""
    from onboard.core.gnss import GnssState
    from onboard.estimation.guidance import SetpointGate

    fix3 = GnssState.updated(None, 0.0, 3)
    lost = GnssState.updated(fix3, 1.0, 1)
    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    p = np.array([0.0, 0.0, -60.0])
    advice = (10.0, np.array([3.0, 0.0, 0.0]))

    def step(now, gnss, mode=GUIDED):
        return gate.step(now, link_connected=True, mode=mode, pose=(now, p, np.zeros(3)), advice=advice, gnss=gnss)

    step(0.0, fix3, LOITER)
    assert step(0.1, fix3).send and gate.state == "sending"
    d = step(1.0, lost)
    assert d.send and not d.v_ned_mps.any() and d.state == "stopped"  # the brake
    assert d.why.startswith("gnss: no_fix") and gate.stops == {"gnss": 1}
    assert not step(2.5, GnssState.updated(lost, 2.4, 3)).send and gate.state == "stopped"  # latched, fix back or not
    never = GnssState.updated(GnssState.updated(None, 0.0, 0), 1.0, 1)  # no 3-D fix ever: positioned otherwise
    other = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    other.step(0.0, link_connected=True, mode=LOITER, pose=None, advice=None)
    assert other.step(0.1, link_connected=True, mode=GUIDED, pose=(0.1, p, np.zeros(3)), advice=advice, gnss=never).send

    now = [100.0]  # the tap hands the gate the link's GPS_RAW_INT
    tap, link, sent = _in_loop_tap(now)
    link.gnss = fix3 = GnssState.updated(None, now[0], 3)
    tap._pose = (now[0], p, np.zeros(3))
    tap._advice = (now[0] + 3.0, np.array([1.0, 0.0, 0.0]), None)
    link.autopilot_mode = GUIDED
    assert tap.setpoint_step(now[0], link) and sent[-1][0] == 1.0
    link.gnss = GnssState.updated(fix3, now[0] + 0.2, 1)
    now[0] += 0.25
    tap._pose = (now[0], p, np.zeros(3))
    assert tap.setpoint_step(now[0], link) and not sent[-1].any()
    assert tap.status()["setpoints"]["why"].startswith("gnss: no_fix")


def test_a_gnss_report_that_stops_after_one_stops_the_setpoints():
    """PX4 stops GPS_RAW_INT when its receiver is gone, and GLOBAL_POSITION_INT goes on, dead-reckoned: the last
    report said a 3-D fix, and the gate flew on it.  A report older than GNSS_STALE_S stops, latched, as a fix lost
    does; one at the autopilot's rate (1-5 Hz) does not."""
    from onboard.core.gnss import GnssState
    from onboard.estimation.guidance import GNSS_STALE_S, SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    p = np.array([0.0, 0.0, -60.0])
    advice = (100.0, np.array([3.0, 0.0, 0.0]))
    fix3 = GnssState.updated(None, 0.0, 3)

    def step(now, mode=GUIDED):
        return gate.step(now, link_connected=True, mode=mode, pose=(now, p, np.zeros(3)), advice=advice, gnss=fix3)

    step(0.0, LOITER)
    assert step(0.1).send and step(GNSS_STALE_S).send and gate.state == "sending"
    d = step(GNSS_STALE_S + 0.5)
    assert d.send and not d.v_ned_mps.any() and d.state == "stopped"  # the brake
    assert d.why.startswith("gnss: no GPS_RAW_INT for 5.5 s after one") and gate.stops == {"gnss": 1}


def test_poses_lost_with_the_heartbeat_late_name_the_link_not_only_the_camera():
    """MAVLink gone both ways for 3 s: the frames lost their poses (pose_lost) before the heartbeat timed out, and the
    latched reason pointed at the camera alone (a fault-injection audit)."""
    from onboard.estimation.guidance import SetpointGate

    p = np.array([0.0, 0.0, -60.0])
    advice = (10.0, np.array([3.0, 0.0, 0.0]))
    for age_s, says_link in ((0.4, False), (1.8, True)):
        gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
        gate.step(0.0, link_connected=True, mode=LOITER, pose=None, advice=None)
        assert gate.step(0.1, link_connected=True, mode=GUIDED, pose=(0.1, p, np.zeros(3)), advice=advice).send
        d = gate.step(1.5, link_connected=True, mode=GUIDED, pose=(0.1, p, np.zeros(3)), advice=advice,
                      heartbeat_age_s=age_s)  # fmt: skip
        assert d.why.startswith("pose_lost: no camera frame"), d.why
        assert ("no autopilot heartbeat for 1.8 s: the MAVLink link" in d.why) == says_link, d.why
        # the heartbeat is late after (1.8 s: a cut shorter than the link's timeout), then times out: the latched
        # reason says so once, from the first
        d = gate.step(2.0, link_connected=True, mode=GUIDED, pose=None, advice=advice, heartbeat_age_s=1.8)
        assert d.why.count("heartbeat") == 1 and "MAVLink link" in d.why, d.why
        d = gate.step(2.5, link_connected=True, mode=GUIDED, pose=None, advice=advice, heartbeat_age_s=3.0)
        assert d.why.count("heartbeat") == 1 and "MAVLink link" in d.why, d.why


def _ranging_track(**kw):
    """A track at 135, 50, -80 m NED whose range sigma is half its range (a manoeuvre helps: advice is planned)."""
    p = np.array([135.0, 50.0, -80.0])
    cam = _pose().p_cam_ned_m
    u = (p - cam) / np.linalg.norm(p - cam)
    cov = 4.0 * np.eye(3) + (0.5 * np.linalg.norm(p - cam)) ** 2 * np.outer(u, u)
    return _track(5_000_000, p, (-3.0, -2.0, 0.0), cov, **kw)


def test_a_newer_answer_or_another_target_ends_the_advice_in_force():
    """The advice in force was replaced only by a newer recommended one: after an 'observable' answer, a lost target
    or a switch to another, the old manoeuvre kept going out for up to valid_for_s."""
    from onboard.app.observers import FrameResult

    now = [100.0]
    tap, _link, _sent = _in_loop_tap(now)
    track = _ranging_track()
    assert tap.step(track, _pose(), now[0]) is not None and tap._advice is not None
    tap.on_frame(None, FrameResult(0, True, _pose(), None, None))  # a frame without a track says nothing
    assert tap._advice is not None
    lost = dataclasses.replace(
        track,
        p_ned_m=None,
        lat_deg=None,
        lon_deg=None,
        alt_m=None,
        v_ned_mps=None,
        cov_p_ned_m2=None,
        cov_v_ned_m2ps2=None,
        range_m=None,
        range_sigma_ratio=None,
    )
    tap.on_frame(None, FrameResult(0, True, _pose(), lost, None))  # the target lost: no position
    assert tap._advice is None
    assert tap.step(track, _pose(), now[0]) is None  # not due again yet: nothing planned, nothing in force
    tap.advisor._next_us = 0
    assert tap.step(track, _pose(), now[0]) is not None and tap._advice is None  # planned before the loss: not kept
    tap.on_frame(None, FrameResult(0, True, _pose(), track, None))  # the target back
    tap.advisor._next_us = 0
    assert tap.step(track, _pose(), now[0]) is not None and tap._advice is not None
    other = dataclasses.replace(track, track_id=(track.track_id or 0) + 1)
    tap.on_frame(None, FrameResult(0, True, _pose(), other, None))  # another target selected
    assert tap._advice is None
    tap.on_frame(None, FrameResult(0, True, _pose(), track, None))
    tap.advisor._next_us = 0
    assert tap.step(track, _pose(), now[0]) is not None
    sharp = dataclasses.replace(track, cov_p_ned_m2=np.eye(3) * 0.01)  # observable with margin: no manoeuvre
    tap.advisor._next_us = 0
    assert tap.step(sharp, _pose(), now[0]) is None and tap._advice is None


def test_an_advice_ends_with_its_estimate_and_is_not_renewed_for_a_target_nobody_sees():
    """The advice in force was tied to the track_id alone: a new estimate_epoch on the same track (the estimate
    started again: a pose discontinuity, an autopilot reboot) kept the old manoeuvre going, and a coasting track (the
    target not seen, its position carried on) was planned on and renewed it.  The estimate's restart ends it, at
    once, with the gate's brake and a reason the status shows; a coasting frame plans nothing, so the advice runs
    out valid_for_s after the last frame that saw the target."""
    from onboard.app.observers import FrameResult

    now = [100.0]
    tap, link, sent = _in_loop_tap(now)
    track = _ranging_track(track_id=1, estimate_epoch=2)
    tap.on_frame(None, FrameResult(0, True, _pose(), track, None))
    assert tap.plan_pending() is not None and tap._advice is not None
    link.autopilot_mode = GUIDED
    assert tap.setpoint_step(now[0], link) and sent[-1].any()
    now[0] += 0.5
    reset = dataclasses.replace(track, time_boot_us=5_500_000, estimate_epoch=3)  # same target, a new estimate
    tap.on_frame(None, FrameResult(0, True, _pose(), reset, None))
    assert tap._advice is None
    assert tap.setpoint_step(now[0], link) and not sent[-1].any()  # the brake
    setpoints = tap.status()["setpoints"]
    assert setpoints["why"] == "no advice in force (estimate_reset): braking" and setpoints["state"] == "waiting"
    assert setpoints["advice_ends"] == {"estimate_reset": 1}

    # planned again on the new estimate, then the target coasts: nothing is planned on what nobody sees
    tap.advisor._next_us = 0
    fresh = dataclasses.replace(reset, time_boot_us=6_000_000)
    tap.on_frame(None, FrameResult(0, True, _pose(), fresh, None))
    assert tap.plan_pending() is not None and tap._advice is not None
    until = tap._advice[0]
    coasting = dataclasses.replace(fresh, time_boot_us=8_000_000, state="coasting")
    now[0] += 2.0
    tap.on_frame(None, FrameResult(0, True, _pose(), coasting, None))
    assert tap.plan_pending() is None and tap._advice[0] == until  # not renewed: it runs out at its own time


def test_an_observer_slower_than_min_speed_is_advised_up_to_it_not_left_outside_limits():
    """With min_speed_mps 3 an observer at 0 or 2 m/s (hovering after the gate's zero-velocity brake) was
    'outside_limits' for good: no advice ever again.  Every manoeuvre's setpoint is at least min_speed_mps, so a slow
    observer is advised up to it; and its climb keeps its heading instead of turning north."""
    cfg = build(GuidanceConfig, {"min_speed_mps": 3.0})
    slow_planner = GuidancePlanner.for_noise(cfg, RTK, F_PX)
    for v in ([0.0, 0.0, 0.0], [0.0, 2.0, 0.0]):
        obs = ObserverState(0.0, np.array([0.0, 40.0, -60.0]), np.array(v))
        advice = slow_planner.advise(obs, unobservable(obs, [135.0, 50.0, -80.0], (-3.0, -2.0, 0.0)))
        assert advice.status == "advise" and np.hypot(*advice.v_ned_mps[:2]) >= 3.0 - SLACK_MPS
    obs = ObserverState(0.0, np.array([0.0, 40.0, -60.0]), np.array([0.0, 2.0, 0.0]))
    climb = dict(slow_planner.candidates(obs, unobservable(obs, [135.0, 50.0, -80.0], (-3.0, -2.0, 0.0))))["climb"]
    np.testing.assert_allclose(climb, [0.0, 6.0, -2.0], atol=ATOL_M)  # east, at the manoeuvres' speed
    fast = ObserverState(0.0, np.array([0.0, 40.0, -60.0]), np.array([0.0, 13.0, 0.0]))  # over 12 + 0.5: outside
    assert slow_planner.advise(fast, unobservable(fast, [135.0, 50.0, -80.0], (-3.0, -2.0, 0.0))).status == (
        "outside_limits"
    )


def test_guidance_config_refuses_an_advice_longer_than_its_plan_and_a_loop_without_advice():
    with pytest.raises(Exception, match="valid_for_s"):
        build(GuidanceConfig, {"valid_for_s": 10.0, "horizon_s": 6.0})
    with pytest.raises(Exception, match="enabled"):
        build(GuidanceConfig, {"enabled": True, "advise": False})


def test_the_daemon_stopping_while_commanding_sends_zero_velocity_once():
    """SIGTERM while sending left the last setpoint running (ArduCopter flies it for its 3 s timeout): halt brakes."""
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    pose = (0.0, np.array([0.0, 0.0, -60.0]), np.array([0.0, 5.0, 0.0]))
    assert gate.step(0.0, link_connected=True, mode=LOITER, pose=pose, advice=None).state == "not_accepting"
    assert gate.step(0.1, link_connected=True, mode=GUIDED, pose=pose, advice=(5.0, np.array([6.0, 0.0, 0.0]))).send
    d = gate.halt(0.2)
    assert d.send and not d.v_ned_mps.any() and d.state == "stopped" and gate.stops == {"shutdown": 1}
    assert not gate.step(0.3, link_connected=True, mode=GUIDED, pose=pose, advice=(5.0, np.ones(3))).send  # latched
    assert not gate.halt(0.4).send and gate.stops == {"shutdown": 1}  # a second call: nothing more
    idle = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    assert not idle.halt(0.0).send  # never commanded: nothing to stop
    assert not SetpointGate(GuidanceConfig()).halt(0.0).send  # guidance off


def test_an_advice_whose_expiry_is_not_a_number_is_no_advice():
    from onboard.estimation.guidance import SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    pose = (0.0, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    gate.step(0.0, link_connected=True, mode=LOITER, pose=pose, advice=None)
    d = gate.step(0.1, link_connected=True, mode=GUIDED, pose=pose, advice=(math.nan, np.array([6.0, 0.0, 0.0])))
    assert not d.send and d.state == "waiting"


def test_px4_offboard_holds_between_advices_and_needs_a_stream_with_margin_over_2_hz():
    """PX4 leaves OFFBOARD when the setpoint stream stops or is not faster than 2 Hz: between advices the gate sends
    zero velocity (holding) instead of falling silent, and a configured rate below 3 Hz is refused (2.1 Hz was taken:
    3 of 33 gaps over 0.5 s, each setpoint up to a loop's idle turn late)."""
    from onboard.estimation.guidance import SetpointGate

    px4 = {"enabled": True, "accept_autopilot": 12, "accept_custom_mode": 393216}
    for hz in (2.0, 2.1, 2.9):
        with pytest.raises(SchemaError, match="setpoint_rate_hz.*>= 3 Hz for PX4"):
            build(GuidanceConfig, {**px4, "setpoint_rate_hz": hz})
    assert build(GuidanceConfig, {**px4, "setpoint_rate_hz": 3.0}).setpoint_rate_hz == 3.0
    assert build(GuidanceConfig, {"setpoint_rate_hz": 1.0}).setpoint_rate_hz == 1.0  # ArduPilot: its 3 s timeout
    gate = SetpointGate(build(GuidanceConfig, px4))
    offboard = (12, 129, 393216)
    pose = (0.0, np.array([0.0, 0.0, -60.0]), np.zeros(3))
    gate.step(0.0, link_connected=True, mode=(12, 129, 0), pose=pose, advice=None)
    d = gate.step(0.25, link_connected=True, mode=offboard, pose=(0.25, *pose[1:]), advice=None)
    assert d.send and d.state == "holding" and not d.v_ned_mps.any()
    d = gate.step(0.5, link_connected=True, mode=offboard, pose=(0.5, *pose[1:]), advice=(3.0, np.array([6.0, 0, 0])))
    assert d.send and d.state == "sending" and d.v_ned_mps[0] == 6.0
    d = gate.step(3.5, link_connected=True, mode=offboard, pose=(3.5, *pose[1:]), advice=(3.0, np.array([6.0, 0, 0])))
    assert d.send and d.state == "holding" and not d.v_ned_mps.any()
    assert gate.halt(3.6).send  # holding is commanding: the daemon stopping says so


def test_no_manoeuvre_is_planned_out_of_the_geofence(planner):
    """10 m inside the box's north edge, flying north at 8 m/s: a turn's predicted path left the box (north 303 m
    at 2 s, 308 m at 3 s) and was advised; the gate would stop the vehicle only once outside."""
    cfg = planner.config
    obs = ObserverState(0.0, np.array([290.0, 0.0, -60.0]), np.array([8.0, 0.0, 0.0]))
    p = np.array([400.0, 150.0, -80.0])
    r = float(np.linalg.norm(p - obs.p_ned_m))
    u = (p - obs.p_ned_m) / r
    tgt = TargetPosterior.from_track(
        0.0,
        p,
        np.array([0.0, -3.0, 0.0]),
        4 * np.eye(3) + (0.5 * r) ** 2 * np.outer(u, u),
        (1, 1, 0.5),
        obs.p_ned_m,
        obs.v_ned_mps,
    )
    a = planner.advise(obs, tgt)
    t = np.linspace(0.0, cfg.valid_for_s, 13)
    for k in a.candidates:
        path, _ = candidate_path(obs.p_ned_m, obs.v_ned_mps, k.v_ned_mps, cfg.max_accel_mps2, t)
        assert not k.feasible or cfg.inside_geofence(path), k.name
    if a.v_ned_mps is not None:
        path, _ = candidate_path(obs.p_ned_m, obs.v_ned_mps, a.v_ned_mps, cfg.max_accel_mps2, t)
        assert cfg.inside_geofence(path)


@pytest.mark.parametrize(
    "posed, why",
    [
        # a frame stating a zoom the intrinsics are not for (or a camera / gimbal mismatch) keeps the target
        # measured with a pose, its line of sight and position withheld: the status said 'target_lost' of a target
        # still tracked in 2-D (a newcomer's walkthrough)
        (True, "geometry_withheld"),
        # a MAVLink link cut for 3 s mid-manoeuvre (the simulator behind a UDP relay): the frames went on, the
        # target measured in each, but without telemetry they had no pose and so no position
        (False, "no_pose"),
    ],
)
def test_an_advice_ended_by_a_frame_without_a_position_says_why_not_target_lost(posed, why):
    """The advice ends, as for a lost target, and the status's advice_ends names why the frame had no position."""
    from onboard.app.observers import FrameResult

    now = [100.0]
    tap, _link, _sent = _in_loop_tap(now)
    track = _ranging_track()
    assert tap.step(track, _pose(), now[0]) is not None and tap._advice is not None
    no_position = {
        k: None
        for k in ("p_ned_m", "lat_deg", "lon_deg", "alt_m", "v_ned_mps", "cov_p_ned_m2", "cov_v_ned_m2ps2", "range_m")
    }
    measured = dataclasses.replace(
        track,
        measurement_valid=True,
        u_px=320.0,
        v_px=256.0,
        pose_valid=posed,
        los=None,
        range_sigma_ratio=None,
        **no_position,
    )
    tap.on_frame(None, FrameResult(0, True, _pose() if posed else None, measured, None))
    assert tap._advice is None and tap.status()["setpoints"]["advice_ends"] == {why: 1}


def test_a_gnss_report_that_stops_on_a_vehicle_that_never_had_a_3d_fix_does_not_stop_the_setpoints():
    """A vehicle positioned otherwise (VIO, beacons) whose GPS_RAW_INT never said a 3-D fix is not judged by its GNSS
    (SetpointGate's docstring, deploy/README.md, docs/design.md): its receiver going quiet says nothing of the
    position it flies on.  The staleness stop judged it all the same, and stopped it 5 s after its last no-fix report."""
    from onboard.core.gnss import GnssState
    from onboard.estimation.guidance import GNSS_STALE_S, SetpointGate

    gate = SetpointGate(build(GuidanceConfig, {"enabled": True}))
    p = np.array([0.0, 0.0, -60.0])
    advice = (100.0, np.array([3.0, 0.0, 0.0]))
    never = GnssState.updated(GnssState.updated(None, 0.0, 0), 0.0, 1)  # no 3-D fix ever, then no more reports

    def step(now, mode=GUIDED):
        return gate.step(now, link_connected=True, mode=mode, pose=(now, p, np.zeros(3)), advice=advice, gnss=never)

    step(0.0, LOITER)
    assert step(0.1).send
    d = step(GNSS_STALE_S + 0.5)
    assert d.send and d.v_ned_mps.any() and gate.state == "sending", d.why


def test_a_stop_is_logged_once_with_how_the_setpoints_resume(caplog):
    """In the loop against the simulator, a stop (the altitude band left, a MAVLink link cut, a restart found in
    GUIDED) was logged 'stopped (<reason>)' and nothing more: the operator read why it stopped, not that it stays
    stopped until the autopilot leaves the accepting mode and re-enters it (deploy/README.md)."""
    import logging

    from onboard.app.observers import FrameResult

    now = [100.0]
    tap, link, sent = _in_loop_tap(now)
    tap.on_frame(None, FrameResult(0, True, _pose(), None, None))
    tap._advice = (now[0] + 3.0, np.array([1.0, 0.0, 0.0]), None)
    link.autopilot_mode = GUIDED
    assert tap.setpoint_step(now[0], link) and sent
    with caplog.at_level(logging.WARNING, logger="onboard.app.guidance_tap"):
        for _ in range(8):  # no more frames: the pose ages past pose_timeout_s, the gate stops and brakes
            now[0] += 0.25
            tap.setpoint_step(now[0], link)
    stops = [r.getMessage() for r in caplog.records if "stopped" in r.getMessage()]
    assert tap.status()["setpoints"]["state"] == "stopped"
    assert len(stops) == 1 and "pose_lost" in stops[0], stops
    assert "until the autopilot leaves the accepting mode and re-enters it" in stops[0], stops[0]


def test_the_planner_keeps_its_manoeuvres_geofence_margin_m_inside_the_box_and_lets_a_vehicle_in_the_margin_move_in(
    planner,
):
    """The guidance audit flew a turn planned to graze the box's edge: the airframe lagged it, re-planning found
    nothing feasible mid-turn, and the vehicle coasted 0.2 m past the box (a latched stop).  The planner now keeps
    geofence_margin_m (10 m) inside; a vehicle already within the margin may only keep or gain its distance."""
    from onboard.core.errors import ConfigError

    c = build(GuidanceConfig, {"geofence_north_m": [-100.0, 100.0], "geofence_east_m": [-50.0, 50.0]})
    assert c.geofence_margin_m == 10.0
    pts = np.array([[0.0, 0.0, -60.0], [95.0, 0.0, -60.0], [0.0, -45.0, -60.0], [120.0, 60.0, -60.0]])
    assert c.fence_excess_m(pts).tolist() == [0.0, 5.0, 5.0, 30.0]
    with pytest.raises(ConfigError, match="geofence_margin_m"):
        build(GuidanceConfig, {"geofence_east_m": [-10.0, 10.0]})  # no room left inside a 10 m margin
    pl = GuidancePlanner(c, planner.estimator, F_PX)
    t = np.linspace(0.0, 4.0, 5)[:, None]
    tgt = np.tile([0.0, 200.0, -60.0], (5, 1))  # well in view of every path below

    def path(start_n: float, v_n: float):
        p = np.array([start_n, 0.0, -60.0]) + t * np.array([v_n, 0.0, 0.0])
        return pl.feasibility("turn_45", np.array([v_n, 0.0, 0.0]), p, tgt, np.tile([v_n, 0.0, 0.0], (5, 1)))

    assert path(70.0, 4.0) == (True, "")  # ends at 86 m: 14 m inside
    assert path(70.0, 6.0) == (False, "geofence")  # ends at 94 m: inside the box, within its margin
    assert path(95.0, -6.0) == (True, "")  # within the margin: back inwards
    assert path(95.0, 1.0) == (False, "geofence")  # within the margin: further out
