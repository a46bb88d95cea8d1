"""The fusion's clocks under a vehicle whose UTC is wrong: a constant error the clock check names, a step of its
UTC offset, one glitched stamp.  Two or three synthetic vehicles on a fast crossing target (20 m/s across their
lines of sight, where a timing error moves the fused point), driven through :class:`~onboard.app.fuse.Fusion`
payload by payload, no sockets; every fused point is scored against the truth."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable

import numpy as np
import pytest

from groundsim.evaluation.fleet_synth import SynthTarget, SynthVehicle, measure, track_payload
from onboard.app.fuse import Fusion, build_parser
from onboard.app.fuse_noise import noise_models
from onboard.core.counters import RejectCounter
from onboard.core.frames import GeodeticOrigin
from onboard.estimation.fleet import FleetConfig, Ray
from onboard.estimation.fleet_tracker import FleetTracker
from onboard.io.fleet_wire import CommonClock, fleet_track_key

ORIGIN = GeodeticOrigin(32.0, 118.8, 20.0)
T0_UNIX_S = 1_800_000_000.0
FRAME_S = 1 / 30
LATENCY_S = 0.005  # capture to arrival on the fusion's clock
WHITE_RAD = 0.3e-3
BIAS_PRIOR_RAD = math.radians(0.1)  # the fusion's default attitude-bias prior, and each vehicle's drawn bias
NEES_MAX = 16.3  # chi-square(3) at 0.999
UAV1 = SynthVehicle("uav1", (0.0, -145.0, -100.0), (3.0, 0.0, 0.0))
UAV2 = SynthVehicle("uav2", (0.0, 145.0, -100.0), (3.0, 0.0, 0.0))
UAV3 = SynthVehicle("uav3", (-200.0, 0.0, -120.0), (0.0, 8.0, 0.0))
TARGET = SynthTarget((592.0, -20.0, -120.0), (0.0, 20.0, 0.0))

#: changes one payload dict in place: (vehicle name, time since the start s, the dict)
Change = Callable[[str, float, dict], None]


def new_fusion(argv: tuple[str, ...] = (), **kw) -> Fusion:
    """A fusion with the command line's defaults (``argv`` changes them)."""
    args = build_parser().parse_args(list(argv))
    return Fusion(
        FleetTracker(FleetConfig(), noise_models(args), RejectCounter()),
        CommonClock(),
        max_time_sigma_s=args.max_time_sigma_ms / 1e3,
        **kw,
    )


def biased(vehicle: SynthVehicle, rng) -> SynthVehicle:
    """``vehicle`` with a constant attitude error drawn from the prior the fusion assumes."""
    return SynthVehicle(
        vehicle.name, vehicle.p0_ned_m, vehicle.v_ned_mps, (0.0, 0.0, 0.0), rng.normal(0, BIAS_PRIOR_RAD, 3)
    )


def fly(
    fusion: Fusion, vehicles, t_range, rng, change: Change | None = None, judged: dict[str, float] | None = None
) -> list[dict]:
    """Every vehicle's track at each time of ``t_range`` (s after T0_UNIX_S), its ``time_unix_us`` the true capture
    time unless ``change`` says otherwise; the fleet tracks published.  ``judged``: filled with the time each vehicle
    was first named by the clock check (the status's ``clock_inconsistent``, looked at every 0.1 s)."""
    out = []
    for i, t in enumerate(t_range):
        k = int(round(t / FRAME_S))
        for v in vehicles:
            obj = track_payload(
                v.name,
                k,
                int(round((1.0 + t) * 1e6)),
                measure(v, TARGET, t, rng, WHITE_RAD, BIAS_PRIOR_RAD),
                ORIGIN,
                time_unix_us=int(round((T0_UNIX_S + t) * 1e6)),
            )
            if change is not None:
                change(v.name, t, obj)
            fusion.receive(f"irtrack/{v.name}/track", json.dumps(obj).encode(), T0_UNIX_S + t + LATENCY_S)
        out += [p for key, p in fusion.flush() if key == fleet_track_key()]
        if judged is not None and i % 3 == 2:
            for name in fusion.status(T0_UNIX_S + t + LATENCY_S)["clock_inconsistent"]:
                judged.setdefault(name, t)
    return out


def nees(track: dict) -> float:
    """The fused point's squared error in its own covariance (3 dof)."""
    e = np.asarray(track["ned_m"]) - TARGET.p_ned_m(track["time_unix_us"] / 1e6 - T0_UNIX_S)
    return float(e @ np.linalg.solve(np.asarray(track["cov_ned_m2"]), e))


def seconds(start_s: float, end_s: float) -> np.ndarray:
    return np.arange(round(start_s / FRAME_S), round(end_s / FRAME_S)) * FRAME_S


def spy_rays(fusion: Fusion) -> list[Ray]:
    """The rays the fusion hands its tracker from now on."""
    seen: list[Ray] = []
    add = fusion.tracker.add
    fusion.tracker.add = lambda ray: seen.append(ray) or add(ray)  # type: ignore[method-assign]
    return seen


# --------------------------------------------------------------------------- a constant error, two vehicles


@pytest.mark.parametrize("max_time_sigma_ms", [50.0, 200.0])
def test_with_two_vehicles_the_one_named_carries_its_whole_error_in_its_time_sigma(max_time_sigma_ms, caplog):
    """uav2's UTC 90 ms ahead, two vehicles: the check's deviations from their median are 45 ms each, and the named
    vehicle's rays took 45 ms of time sigma: fused observable at NEES ~7 (1.2 without the error).  Its rays carry
    the whole 90 ms now, refused beyond --max-time-sigma-ms with a message that says why (it cited a
    time_unix_sigma_us the vehicle never sent)."""
    rng = np.random.default_rng(7)
    vehicles = [biased(v, rng) for v in (UAV1, UAV2)]
    fusion = new_fusion(("--max-time-sigma-ms", f"{max_time_sigma_ms:g}"))

    def ahead(name, t, obj):
        if name == "uav2":
            obj["time_unix_us"] += 90_000

    fly(fusion, vehicles, seconds(0.0, 1.5), rng, ahead)
    assert fusion.status(T0_UNIX_S + 1.5)["clock_inconsistent"] == ["uav2"]
    seen = spy_rays(fusion)
    with caplog.at_level(logging.WARNING):
        out = fly(fusion, vehicles, seconds(1.5, 4.0), rng, ahead)
    uav2 = [r.time_sigma_s for r in seen if r.vehicle == "uav2"]
    if max_time_sigma_ms < 90.0:
        assert not uav2 and fusion.counter["time_sigma"] >= 70
        (line,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("time_sigma")]
        assert "clock check" in line and "+90 ms" in line and "time_unix_sigma_us" not in line, line
    else:
        assert uav2 and min(uav2) >= 0.089
    observable = [p for p in out if p["observable"]]
    assert all(nees(p) < NEES_MAX for p in observable), max(map(nees, observable))


# --------------------------------------------------------------------------- one stamp off


@pytest.mark.parametrize("vehicles", [2, 3])
def test_one_stamp_half_a_second_ahead_is_held_alone_and_does_not_shut_its_vehicle_out(vehicles):
    """One uav2 frame stamped 0.5 s ahead, within --max-age-s: it reached the clock check and became uav2's latency
    floor for the check's 10 s window; uav2 was named clock_inconsistent and its next 300 rays refused clock_off.
    Its UTC - boot offset jumps from uav2's others: held (stamp_jump), and the next frame, back on uav2's offset, is
    fused as before."""
    rng = np.random.default_rng(7)
    fleet = [biased(v, rng) for v in (UAV1, UAV2, UAV3)[:vehicles]]
    fusion = new_fusion()
    glitch_s = 3.0

    def glitch(name, t, obj):
        if name == "uav2" and abs(t - glitch_s) < FRAME_S / 2:
            obj["time_unix_us"] += 500_000

    judged: dict[str, float] = {}
    out = fly(fusion, fleet, seconds(0.0, 6.0), rng, glitch, judged)
    assert judged == {} and fusion.counter["clock_off"] == 0 and fusion.counter["stamp_jump"] == 1
    t_of = [(p["time_unix_us"] / 1e6 - T0_UNIX_S, p) for p in out]
    soon = [p for t, p in t_of if glitch_s < t <= glitch_s + 0.5 and p["observable"] and len(p["vehicles"]) == vehicles]
    assert soon, "no observable fleet track of every vehicle within 0.5 s of the glitch"
    observable = [p for p in out if p["observable"]]
    assert all(nees(p) < NEES_MAX for p in observable), max(map(nees, observable))
    assert fusion.counter["ray_out_of_order"] == 0  # the held ray was not fused 0.5 s ahead of uav2's next ones


def test_the_common_clock_holds_a_jumped_stamp_until_the_next_ones_say_glitch_or_step():
    clock = CommonClock()
    utc_minus_boot_s = 1_700_000_000.0

    def place(boot_s: float, error_s: float = 0.0):
        return clock.place("uav1", int(boot_s * 1e6), int(round((boot_s + utc_minus_boot_s + error_s) * 1e6)), 0.0)

    assert place(10.0).held_jump_s is None and place(10.1, 0.002).held_jump_s is None  # the fit moving a little
    assert place(10.2, 0.5).held_jump_s == pytest.approx(0.498, abs=1e-5)  # from the newest of its offset
    assert place(10.3).held_jump_s is None  # back on its offset: a glitch
    # a step: held until STEP_STAMPS stamps in a row agree on the new offset (a copy of one is no second stamp)
    assert place(11.0, -0.28).held_jump_s == pytest.approx(-0.28, abs=1e-5)
    assert place(11.0, -0.28).held_jump_s is not None
    assert place(11.1, -0.28).held_jump_s is not None
    stepped = place(11.2, -0.28)
    assert stepped.held_jump_s is None and stepped.step_s == pytest.approx(-0.28, abs=1e-5)
    assert place(11.3, -0.28).step_s is None  # the vehicle's offset now
    # an unstamped frame then takes the offset the vehicle has, not a held one
    assert clock.time_s("uav1", 12_000_000, None, 0.0)[0] == pytest.approx(12.0 + utc_minus_boot_s - 0.28, abs=1e-5)


# --------------------------------------------------------------------------- a step of a vehicle's UTC


@pytest.mark.parametrize("vehicles", [2, 3])
def test_a_clock_that_steps_back_is_named_within_a_second_and_never_fused_confidently(vehicles):
    """uav2's time_unix_us steps back 280 ms at t = 4 s (its boot clock goes on): the check kept its lowest arrival
    lag over 10 s, so the higher lags after the step were unseen until the window passed: 140 observable fleet tracks
    in those 10 s, 11 m off at a 3.6 m sigma (NEES ~19), and the status said nothing until t = 14 s."""
    rng = np.random.default_rng(7)
    fleet = [biased(v, rng) for v in (UAV1, UAV2, UAV3)[:vehicles]]
    fusion = new_fusion()
    step_s = 4.0

    def step_back(name, t, obj):
        if name == "uav2" and t >= step_s - FRAME_S / 2:
            obj["time_unix_us"] -= 280_000

    judged: dict[str, float] = {}
    out = fly(fusion, fleet, seconds(0.0, 8.0), rng, step_back, judged)
    assert fusion.counter["clock_step"] == 1
    assert set(judged) == {"uav2"} and judged["uav2"] - step_s <= 1.0, judged
    late = [p for p in out if p["time_unix_us"] / 1e6 - T0_UNIX_S > step_s + 0.1 and p["observable"]]
    assert all(nees(p) < NEES_MAX for p in late), max(map(nees, late))
    if vehicles == 3:  # the other two fuse on
        assert late and all(sorted(c["vehicle"] for c in p["vehicles"]) == ["uav1", "uav3"] for p in late[-30:])


def test_a_clock_that_steps_back_into_agreement_is_fused_again_within_a_second():
    """uav2 280 ms ahead from the start (named, its rays refused clock_off), then its UTC steps to the truth: its old
    frames' low latency floor held it named for the check's 10 s window; the step starts the check's judgement over."""
    rng = np.random.default_rng(8)
    fleet = [biased(v, rng) for v in (UAV1, UAV2)]
    fusion = new_fusion()
    fixed_s = 3.0

    def ahead_then_right(name, t, obj):
        if name == "uav2" and t < fixed_s - FRAME_S / 2:
            obj["time_unix_us"] += 280_000

    out = fly(fusion, fleet, seconds(0.0, 5.0), rng, ahead_then_right)
    assert fusion.counter["clock_off"] > 0 and fusion.counter["clock_step"] == 1
    fused = [p for p in out if p["observable"] and p["time_unix_us"] / 1e6 - T0_UNIX_S > fixed_s]
    assert fused and min(p["time_unix_us"] / 1e6 - T0_UNIX_S for p in fused) < fixed_s + 1.0
    assert fusion.status(T0_UNIX_S + 5.0)["clock_inconsistent"] == []
    assert all(nees(p) < NEES_MAX for p in fused), max(map(nees, fused))


# --------------------------------------------------------------------------- a clock named off, then no stamps


def test_a_vehicle_named_off_that_loses_its_stamps_is_timed_by_arrival_not_by_its_bad_offset(caplog):
    """uav3's UTC 300 ms ahead: named and refused (clock_off).  Then its tracks lose time_unix_us (its GNSS time
    gone): they were timed by the UTC - boot offset remembered from its stamps, the one the check had refused, with no
    time sigma and no stamp left to refuse (in the fleet audit's run 13 confidently wrong points in the next 14 s,
    NEES up to 127, and the rest unobservable).  That offset is dropped, said once, and its frames are timed by their
    arrival: uav3 fuses again, honestly."""
    rng = np.random.default_rng(11)
    vehicles = [biased(v, rng) for v in (UAV1, UAV2, UAV3)]
    fusion = new_fusion()

    def ahead_then_none(name, t, obj):
        if name == "uav3":
            obj["time_unix_us"] = None if t >= 2.0 else obj["time_unix_us"] + 300_000

    fly(fusion, vehicles, seconds(0.0, 2.0), rng, ahead_then_none)
    assert fusion.counter["clock_off"] > 0
    with caplog.at_level(logging.WARNING):
        out = fly(fusion, vehicles, seconds(2.0, 5.0), rng, ahead_then_none)
    assert fusion.counter["clock_memory_dropped"] == 1
    assert [r.getMessage() for r in caplog.records if r.getMessage().startswith("clock_memory_dropped")]
    late = [p for p in out if p["time_unix_us"] >= (T0_UNIX_S + 2.5) * 1e6]
    assert all(nees(p) < NEES_MAX for p in late if p["observable"]), max(nees(p) for p in late if p["observable"])
    assert sum(p["observable"] for p in late) > 0.9 * len(late)
    assert {c["vehicle"]: c["time_source"] for c in late[-1]["vehicles"]}["uav3"] == "arrival"


# --------------------------------------------------------------------------- a clock off from the first frame


@pytest.mark.parametrize("ahead_ms", [150, 300])
def test_a_clock_off_from_its_first_frame_is_never_fused_confidently_before_it_is_judged(ahead_ms):
    """uav3's UTC ahead from its first frame: the clock check names it at its 20th frame, and before, its rays paired
    at the wrong place with a time sigma of a fraction of a millisecond (300 ms: 6 fleet points up to NEES 111; 150
    ms: 2, NEES 22).  A stamped vehicle's rays now wait for the check's verdict (at most 1.5 s): no fleet point is
    beyond NEES 16.3 at any time, and the fleet track starts once the clocks are judged."""
    rng = np.random.default_rng(3)
    vehicles = [biased(v, rng) for v in (UAV1, UAV2, UAV3)]
    fusion = new_fusion()

    def ahead(name, t, obj):
        if name == "uav3":
            obj["time_unix_us"] += ahead_ms * 1000

    fleet = fly(fusion, vehicles, seconds(0.0, 3.0), rng, ahead)
    assert fleet, "no fleet track"
    worst = max(nees(m) for m in fleet if m["observable"]) if any(m["observable"] for m in fleet) else 0.0
    assert worst <= NEES_MAX, worst
    first_s = min(m["time_unix_us"] / 1e6 - T0_UNIX_S for m in fleet)
    assert 0.6 <= first_s <= 1.0, first_s  # the 20th frame's verdict, at 30 Hz
    assert fusion.counter["ray_clock_unjudged"] >= 3 * 19


# --------------------------------------------------------------------------- the verdict's cost per ray


def test_a_vehicle_the_check_cannot_judge_does_not_have_the_verdict_made_again_for_each_of_its_rays():
    """uav3's stamps stop after 2 s: its tracks go on timed by the offset remembered from them, and once its stamps
    have left the check's 10 s window it is neither judged nor being judged.  The verdict over every vehicle is made
    every CLOCK_RECHECK_S (0.1 s), and at once only for a vehicle the check has judged since the last one: not again
    for each of uav3's rays (30 a second, each a pass over every vehicle's window)."""
    rng = np.random.default_rng(5)
    vehicles = [biased(v, rng) for v in (UAV1, UAV2, UAV3)]
    fusion = new_fusion()

    def stamps_stop(name, t, obj):
        if name == "uav3" and t >= 2.0:
            obj["time_unix_us"] = None

    fly(fusion, vehicles, seconds(0.0, 12.5), rng, stamps_stop)
    verdicts = []
    errors_s = fusion.clock_check.errors_s
    fusion.clock_check.errors_s = lambda now_unix_s: verdicts.append(now_unix_s) or errors_s(now_unix_s)
    fly(fusion, vehicles, seconds(12.5, 14.5), rng, stamps_stop)
    assert len(verdicts) <= 2.0 / 0.1 + 2, len(verdicts)  # one per CLOCK_RECHECK_S, not one per uav3 ray (60)
