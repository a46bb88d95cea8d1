"""Properties of onboard.io.fleet_wire (hypothesis): what the fusion reads off the wire from other vehicles, and the
clock that puts their times on one UTC clock.

* :func:`parse_track`: any JSON object, and any valid ``irtrack.track/2`` with a field set to any JSON value or left
  out, is a track whose fields obey their documented ranges (``time_unix_us`` None or an integer in [0, 2**63), never
  a bool; no NaN or infinity where a number must be finite) or an :class:`InputError`, never another exception; a
  valid track's JSON reads back as the same track; an accepted track's ray (:func:`ray_from_track`) is finite with a
  unit direction, or refused with InputError.
* :class:`CommonClock`: a stamped frame's time is its stamp; a configured or remembered offset maps ``time_boot_us``
  monotonically; the arrival estimate never runs backwards while arrivals and boot times advance, is never later
  than the arrival and recovers the true offset to within the shortest latency in its window; a reboot (the boot
  clock back by more than 1 s) forgets the vehicle's offsets; one glitched stamp is held and changes nothing, a step
  of ``STEP_STAMPS`` stamps in a row becomes the vehicle's offset.
* :class:`ClockConsistency` names exactly the one vehicle of three or more whose stamps are shifted past the tolerance.
* :class:`StreamCheck`: one vehicle's stream, redelivered and reordered by the link, is never called a name clash.
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin
from onboard.core.track import MAX_COMPENSATED_US, ORIGIN_ALT_RANGE_M, LineOfSight, Track, track_to_json
from onboard.io.fleet_wire import (
    CLOCK_DRIFT_PPM,
    STAMP_JUMP_S,
    STEP_STAMPS,
    ClockConsistency,
    CommonClock,
    StreamCheck,
    TimedTrack,
    parse_track,
    ray_from_track,
)

UNIT_TOL = 1e-6  # LineOfSight's unit check
FLEET_ORIGIN = GeodeticOrigin(47.0, 8.0, 400.0)
T0_UNIX_S = 1.75e9  # UTC seconds of a flight in 2025

finite = st.floats(allow_nan=False, allow_infinity=False)
local_m = st.floats(-1e5, 1e5)  # metres from a local origin: within a radio link's range


@st.composite
def unit3(draw) -> tuple[float, float, float]:
    v = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3)))
    n = float(np.linalg.norm(v))
    assume(n > 0.1)
    x, y, z = (v / n).tolist()
    return x, y, z


@st.composite
def tracks(draw) -> Track:
    u = draw(unit3())
    los = LineOfSight(
        u_ned=u,
        azimuth_deg=math.degrees(math.atan2(u[1], u[0])),
        elevation_deg=math.degrees(math.atan2(-u[2], math.hypot(u[0], u[1]))),
        sigma_azimuth_deg=draw(st.floats(0.0, 180.0)),
        sigma_elevation_deg=draw(st.floats(0.0, 180.0)),
        p_cam_ned_m=tuple(draw(st.lists(local_m, min_size=3, max_size=3))),
        sigma_bias_deg=draw(st.one_of(st.none(), st.floats(0.0, 90.0))),
    )
    stamped = draw(st.booleans())
    position = {}
    if draw(st.booleans()):
        var = draw(st.lists(st.floats(0.0, 1e6), min_size=3, max_size=3))
        position = dict(
            lat_deg=draw(st.floats(-90.0, 90.0)),
            lon_deg=draw(st.floats(-180.0, 180.0)),
            alt_m=draw(st.floats(-1000.0, 1e5)),
            p_ned_m=tuple(draw(st.lists(local_m, min_size=3, max_size=3))),
            v_ned_mps=tuple(draw(st.lists(st.floats(-300.0, 300.0), min_size=3, max_size=3))),
            cov_p_ned_m2=np.diag(var),
            range_m=draw(st.floats(0.0, 2e5)),
            range_sigma_ratio=draw(st.floats(0.0, 10.0)),
        )
    return Track(
        vehicle=draw(st.sampled_from(["uav1", "uav-2", "x"])),
        seq=draw(st.integers(0, 2**32 - 1)),
        time_boot_us=draw(st.integers(0, 2**64 - 1)),
        state=draw(st.sampled_from(["tracking", "coasting"])),
        track_id=draw(st.integers(1, 2**31)),
        measurement_valid=True,
        u_px=draw(st.floats(0.0, 640.0)),
        v_px=draw(st.floats(0.0, 512.0)),
        pose_valid=True,
        los=los,
        origin=GeodeticOrigin(
            draw(st.floats(-89.0, 89.0)), draw(st.floats(-180.0, 180.0)), draw(st.floats(*ORIGIN_ALT_RANGE_M))
        ),
        observable=draw(st.booleans()),
        window_frames=draw(st.integers(0, 2**31)),
        time_unix_us=draw(st.integers(0, 2**63 - 1)) if stamped else None,
        time_unix_sigma_us=draw(st.one_of(st.none(), st.integers(0, 2**63 - 1))) if stamped else None,
        compensated_us=draw(st.integers(-MAX_COMPENSATED_US, MAX_COMPENSATED_US)),
        **position,
    )


def _json_text_roundtrip(obj):
    return json.loads(json.dumps(obj, allow_nan=False))


@settings(max_examples=60, deadline=None)
@given(tracks())
def test_a_valid_track_reads_back_as_itself(track):
    obj = _json_text_roundtrip(track_to_json(track))
    back, time_unix_us = parse_track(obj)
    assert time_unix_us == track.time_unix_us
    assert track_to_json(back) == track_to_json(track)


# what json.loads can hand the reader: any JSON value, Python's Infinity/NaN and integers of any size included, and
# the edges as often as the rest
json_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.sampled_from([0, -1, 2**32, 2**63 - 1, 2**63, 2**64, 2**1100, -(2**1100)]),
    st.floats(),
    st.sampled_from([0.5, 1.5, -0.0, math.inf, -math.inf, math.nan, 1e300, 1e6]),
    st.text(max_size=4),
)
json_values = st.recursive(
    json_leaf,
    lambda kids: st.one_of(st.lists(kids, max_size=5), st.dictionaries(st.text(max_size=8), kids, max_size=4)),
    max_leaves=12,
)
KEYS = tuple(track_to_json(Track("v", 0, 0, "searching")).keys())


def _is_int_in(v, lo: int, hi: int) -> bool:
    return type(v) is int and lo <= v <= hi


def _finite_vec(v, n: int) -> bool:
    a = np.asarray(v, dtype=float)
    return a.shape == (n,) and bool(np.all(np.isfinite(a)))


def check_accepted(track: Track, time_unix_us) -> None:
    """The documented ranges of a track :func:`parse_track` accepted, and its ray's."""
    assert time_unix_us is track.time_unix_us
    for v in (track.time_unix_us, track.time_unix_sigma_us):
        assert v is None or _is_int_in(v, 0, 2**63 - 1), v
    assert _is_int_in(track.seq, 0, 2**32 - 1)
    assert _is_int_in(track.time_boot_us, 0, 2**64 - 1)
    assert _is_int_in(track.compensated_us, -MAX_COMPENSATED_US, MAX_COMPENSATED_US)
    assert track.track_id is None or _is_int_in(track.track_id, 1, 2**64)
    assert isinstance(track.vehicle, str) and track.vehicle
    for flag in (track.measurement_valid, track.pose_valid, track.observable):
        assert type(flag) is bool
    o = track.origin
    if o is not None:
        assert -90 <= o.lat_deg <= 90 and -180 <= o.lon_deg <= 360 and math.isfinite(o.lon_deg)
        assert ORIGIN_ALT_RANGE_M[0] <= o.alt_m <= ORIGIN_ALT_RANGE_M[1]
    los = track.los
    if los is not None:
        assert _finite_vec(los.u_ned, 3) and abs(float(np.linalg.norm(los.u_ned)) - 1.0) <= UNIT_TOL
        assert _finite_vec(los.p_cam_ned_m, 3)
        assert 0 <= los.sigma_azimuth_deg <= 180 and 0 <= los.sigma_elevation_deg <= 180
    if track.p_ned_m is not None:
        assert _finite_vec(track.p_ned_m, 3) and _finite_vec(track.v_ned_mps, 3)
        assert all(math.isfinite(x) for x in (track.lat_deg, track.lon_deg, track.alt_m, track.range_m))
        assert track.cov_p_ned_m2 is not None and np.all(np.isfinite(track.cov_p_ned_m2))
    if los is None or o is None:
        with pytest.raises(InputError):
            ray_from_track(TimedTrack(track, T0_UNIX_S, "vehicle"), FLEET_ORIGIN)
        return
    if los.sigma_azimuth_deg == 0 or los.sigma_elevation_deg == 0:
        # the track schema allows a zero sigma (a direction it states as exact); a ray of infinite weight would
        # decide a triangulation alone, so the fusion refuses it (counted bad_track, onboard/app/fuse.py)
        with pytest.raises(InputError, match="must be a positive finite number of radians"):
            ray_from_track(TimedTrack(track, T0_UNIX_S, "vehicle"), FLEET_ORIGIN)
        return
    ray = ray_from_track(TimedTrack(track, T0_UNIX_S, "vehicle"), FLEET_ORIGIN)
    assert np.all(np.isfinite(ray.p_cam_ned_m)) and np.all(np.isfinite(ray.los_ned))
    assert abs(float(np.linalg.norm(ray.los_ned)) - 1.0) <= 1e-9
    assert math.isfinite(ray.sigma_az_rad) and math.isfinite(ray.sigma_el_rad)
    if ray.own_p_ned_m is not None:
        assert np.all(np.isfinite(ray.own_p_ned_m)) and np.all(np.isfinite(ray.own_cov_ned_m2))


def _parse_or_refuse(obj) -> None:
    try:
        track, time_unix_us = parse_track(obj)
    except InputError:
        return
    check_accepted(track, time_unix_us)


VALID = track_to_json(
    Track(
        vehicle="uav1",
        seq=7,
        time_boot_us=12_000_000,
        state="tracking",
        track_id=3,
        measurement_valid=True,
        u_px=320.0,
        v_px=256.0,
        pose_valid=True,
        los=LineOfSight((1.0, 0.0, 0.0), 0.0, 0.0, 0.1, 0.1, (10.0, -5.0, -100.0), 0.05),
        origin=GeodeticOrigin(47.001, 8.002, 420.0),
        lat_deg=47.01,
        lon_deg=8.0,
        alt_m=300.0,
        p_ned_m=(1000.0, 0.0, 100.0),
        v_ned_mps=(5.0, 0.0, 0.0),
        cov_p_ned_m2=np.diag([4.0, 9.0, 16.0]),
        range_m=1004.0,
        range_sigma_ratio=0.01,
        observable=True,
        window_frames=30,
        time_unix_us=int(T0_UNIX_S * 1e6),
        time_unix_sigma_us=500,
    )
)


@settings(max_examples=120, deadline=None)
@given(st.dictionaries(st.sampled_from(KEYS), json_values, min_size=1, max_size=3), st.sets(st.sampled_from(KEYS)))
@example({"time_unix_us": True}, set())  # True is an int in Python: refused, not read as 1 us after 1970
@example({"time_unix_us": 2**63 - 1}, set())  # the largest accepted stamp
@example({"time_unix_us": 2**63}, set())
@example({"time_unix_us": -1}, set())
@example({"time_unix_us": 1.75e15}, set())  # a float, even a whole one
@example({"time_unix_us": None}, set())  # with a sigma and no time
@example({"origin": {"lat_deg": 47.0, "lon_deg": 8.0, "alt_m": 1e200}}, set())
@example({"camera_ned_m": [1e300, 0.0, 0.0]}, set())
@example({"los_ned": [2**1100, 0, 0]}, set())
@example({"los_sigma_az_deg": 0}, set())  # found by CI: in the schema's range, refused by the fusion's ray
def test_a_valid_track_with_fields_changed_or_left_out_reads_in_range_or_is_refused(changed, dropped):
    obj = copy.deepcopy(VALID)
    obj.update(changed)
    for key in dropped:
        obj.pop(key, None)
    _parse_or_refuse(obj)


@settings(max_examples=100, deadline=None)
@given(st.one_of(json_values, st.dictionaries(st.sampled_from(KEYS), json_values, max_size=8)))
def test_any_json_value_reads_in_range_or_is_refused(value):
    if isinstance(value, dict):
        value = {**value, "schema": VALID["schema"]}  # past the schema check, into the fields
    _parse_or_refuse(value)


@settings(max_examples=100, deadline=None)
@given(
    st.binary(max_size=64)
    | st.builds(lambda b, i: json.dumps(VALID).encode()[:i] + b, st.binary(max_size=8), st.integers(0, 900))
)
def test_any_bytes_off_the_wire_parse_or_are_refused(payload):
    """The fusion's receive path: json.loads, then parse_track on an object."""
    try:
        obj = json.loads(payload)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return
    if isinstance(obj, dict):
        _parse_or_refuse(obj)


# --------------------------------------------------------------------------- CommonClock

boot_steps_us = st.lists(st.integers(0, 200_000), min_size=1, max_size=40)  # frame spacing: up to 5 Hz gaps
latencies_s = st.floats(0.0, 0.5)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**64 - 1), st.integers(0, 2**63 - 1))
def test_a_stamped_frame_is_placed_at_its_stamp(boot_us, unix_us):
    reading = CommonClock().place("uav1", boot_us, unix_us, T0_UNIX_S)
    assert (reading.t_s, reading.source) == (unix_us / 1e6, "vehicle")
    assert reading.held_jump_s is None and reading.step_s is None  # the first stamp is the vehicle's offset


@settings(max_examples=60, deadline=None)
@given(st.floats(-2e9, 2e9), st.integers(0, 2**62), boot_steps_us)
def test_a_configured_offset_maps_boot_time_monotonically(offset_s, boot0_us, steps):
    clock = CommonClock({"uav1": offset_s})
    boot_us, last = boot0_us, -math.inf
    for d in steps:
        boot_us += d
        t_s, source = clock.time_s("uav1", boot_us, None, 0.0)
        assert source == "configured" and t_s >= last and math.isfinite(t_s)
        last = t_s


@settings(max_examples=60, deadline=None)
@given(
    offset_s=st.floats(1e9, 2e9),
    boot0_us=st.integers(0, 10**12),
    frames=st.lists(st.tuples(st.integers(1, 200_000), latencies_s), min_size=1, max_size=60),
    window_s=st.floats(0.1, 20.0),
)
def test_the_arrival_estimate_runs_forward_stays_before_the_arrival_and_recovers_the_offset(
    offset_s, boot0_us, frames, window_s
):
    clock = CommonClock(window_s=window_s)
    boot_us, last, lat_hist, arrival_s = boot0_us, -math.inf, [], -math.inf
    eps_s = 1e-6  # float round-off of UTC seconds near 2e9 (2.4e-7 s a bit), with margin
    for d_us, latency_s in frames:
        boot_us += d_us
        # received in order: a frame queued behind a slower one arrives after it
        arrival_s = max(arrival_s, boot_us / 1e6 + offset_s + latency_s)
        lat_hist.append((arrival_s, arrival_s - (boot_us / 1e6 + offset_s)))
        t_s, source = clock.time_s("uav1", boot_us, None, arrival_s)
        assert source == "arrival"
        assert t_s >= last - eps_s  # never backwards while boot time and arrivals advance
        assert t_s <= arrival_s + eps_s
        in_window = [lat for a, lat in lat_hist if a >= arrival_s - window_s]
        true_s = boot_us / 1e6 + offset_s
        assert -eps_s <= t_s - true_s <= min(in_window) + eps_s  # off by the window's shortest latency
        last = t_s


@settings(max_examples=60, deadline=None)
@given(
    offset_s=st.floats(1e9, 2e9),
    stamps=st.integers(1, 10),
    boot0_us=st.integers(2_000_000, 10**12),
    back_us=st.integers(1_000_001, 2_000_000),
    latency_s=latencies_s,
)
def test_a_reboot_forgets_the_remembered_offset_and_the_arrival_history(offset_s, stamps, boot0_us, back_us, latency_s):
    clock = CommonClock()
    boot_us = boot0_us
    for k in range(3):  # unstamped first (a daemon's first seconds): the arrival estimate has a history
        boot_us += 33_333
        assert clock.place("uav1", boot_us, None, T0_UNIX_S + k * 0.033).source == "arrival"
    for _ in range(stamps):
        boot_us += 33_333
        clock.place("uav1", boot_us, round((boot_us / 1e6 + offset_s) * 1e6), T0_UNIX_S)
    t_s, source = clock.time_s("uav1", boot_us + 33_333, None, 0.0)
    assert source == "remembered" and t_s == pytest.approx((boot_us + 33_333) / 1e6 + offset_s, abs=2e-6)
    rebooted_us = max(boot_us + 33_333 - back_us, 0)
    assume(rebooted_us / 1e6 < (boot_us + 33_333) / 1e6 - 1.0)
    arrival_s = T0_UNIX_S + latency_s
    reading = clock.place("uav1", rebooted_us, None, arrival_s)
    assert reading.source == "arrival" and reading.t_s == pytest.approx(arrival_s, abs=1e-6)
    assert clock.remembered_sigma_s("uav1", rebooted_us) == 0.0


@settings(max_examples=80, deadline=None)
@given(
    offset_s=st.floats(1e9, 2e9),
    boot0_us=st.integers(0, 10**12),
    before=st.integers(1, 5),
    jump_s=st.one_of(st.floats(-100.0, -2 * STAMP_JUMP_S), st.floats(2 * STAMP_JUMP_S, 100.0)),
    step=st.booleans(),
)
@example(offset_s=1.7e9, boot0_us=0, before=1, jump_s=0.02, step=False)
def test_a_glitched_stamp_is_held_and_a_step_of_step_stamps_becomes_the_offset(
    offset_s, boot0_us, before, jump_s, step
):
    clock = CommonClock()
    boot_us = boot0_us

    def stamp(off_s: float):
        nonlocal boot_us
        boot_us += 33_333
        return clock.place("uav1", boot_us, round((boot_us / 1e6 + off_s) * 1e6), T0_UNIX_S)

    for _ in range(before):
        r = stamp(offset_s)
        assert r.held_jump_s is None and r.step_s is None
    new_s = offset_s + jump_s
    if not step:
        r = stamp(new_s)
        assert r.held_jump_s == pytest.approx(jump_s, abs=2e-6) and r.step_s is None
        r = stamp(offset_s)  # the next stamp agrees with the vehicle's offset: it was a glitch
        assert r.held_jump_s is None and r.step_s is None
        kept_s = offset_s
    else:
        for i in range(STEP_STAMPS):
            r = stamp(new_s)
            if i < STEP_STAMPS - 1:
                assert r.held_jump_s == pytest.approx(jump_s, abs=2e-6) and r.step_s is None
        assert r.held_jump_s is None and r.step_s == pytest.approx(jump_s, abs=2e-6)
        kept_s = new_s
    t_s, source = clock.time_s("uav1", boot_us + 33_333, None, T0_UNIX_S)
    assert source == "remembered" and t_s == pytest.approx((boot_us + 33_333) / 1e6 + kept_s, abs=2e-6)
    sigma_s = clock.remembered_sigma_s("uav1", boot_us + 33_333 + 10**9)  # 1000 s on
    assert sigma_s == pytest.approx((10**9 + 33_333) / 1e6 * CLOCK_DRIFT_PPM * 1e-6, rel=1e-6)


# --------------------------------------------------------------------------- ClockConsistency


@settings(max_examples=40, deadline=None)
@given(
    n_vehicles=st.integers(3, 5),
    shifted=st.integers(0, 4),
    shift_s=st.floats(-0.5, 0.5),
    floor_s=st.floats(0.001, 0.05),
    extra=st.lists(st.floats(0.0, 0.1), min_size=20, max_size=40),
)
def test_the_clock_check_names_exactly_the_one_vehicle_whose_stamps_are_shifted(
    n_vehicles, shifted, shift_s, floor_s, extra
):
    tol_s = 0.010
    assume(abs(abs(shift_s) - tol_s) > 1e-6)  # not on the tolerance's edge, where round-off decides
    shifted %= n_vehicles
    check = ClockConsistency(window_s=100.0, tolerance_s=tol_s, min_samples=20)
    now_s = T0_UNIX_S
    for k, lat_s in enumerate([0.0, *extra]):  # every vehicle's floor is floor_s: one frame arrives that fast
        for v in range(n_vehicles):
            now_s = T0_UNIX_S + k * 0.1 + v * 1e-3
            capture_s = now_s - floor_s - lat_s
            check.add(f"v{v}", capture_s + (shift_s if v == shifted else 0.0), now_s)
    named = check.inconsistent(now_s)
    assert named == ([f"v{shifted}"] if abs(shift_s) > tol_s else [])
    if named:
        assert check.errors_s(now_s)[named[0]] == pytest.approx(shift_s, abs=1e-6)


# --------------------------------------------------------------------------- StreamCheck


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(2, 80),
    swaps=st.sets(st.integers(1, 78)),
    repeats=st.sets(st.integers(0, 79)),
    speed_mps=st.floats(0.0, 90.0),
)
def test_one_vehicles_stream_redelivered_and_reordered_is_never_a_name_clash(n, swaps, repeats, speed_mps):
    msgs = [(i, 1_000_000 + 33_333 * i) for i in range(n)]
    order = list(range(n))
    for i in sorted(swaps):  # the link delivers message i late, after i + 1 (never the first one: nothing to slot in)
        if i + 1 < n:
            order[i], order[i + 1] = order[i + 1], order[i]
    delivered = []
    for i in order:
        delivered.append(i)
        if i in repeats:
            delivered.append(i)  # redelivered
    check = StreamCheck()
    for k, i in enumerate(delivered):
        seq, boot_us = msgs[i]
        t_s = T0_UNIX_S + boot_us / 1e6
        p = np.array([speed_mps * boot_us / 1e6, 0.0, -100.0])
        verdict = check.add("uav1", seq, boot_us, t_s, p, T0_UNIX_S + k * 0.033)
        assert verdict in (None, "duplicate"), (k, i, verdict)
    assert check.clashing(T0_UNIX_S + len(delivered) * 0.033) == []
