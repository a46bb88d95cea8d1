"""UtcClock: the autopilot's boot clock onto UTC from SYSTEM_TIME samples (pure, no sockets)."""

from __future__ import annotations

import math

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError
from onboard.core.utc_clock import BOOT_QUANTUM_US, UtcClock, UtcClockConfig, with_utc
from tests.fakes import positioned_track

UNIX0_US = 1_800_000_000_000_000  # 2027-01-15
QUANT_SIGMA_US = BOOT_QUANTUM_US / math.sqrt(12.0)


def system_time(true_boot_us: int, offset_us: int, skew: float = 0.0, jitter_us: int = 0) -> tuple[int, int]:
    """What an autopilot sends at ``true_boot_us``: ``time_boot_ms * 1000`` (truncated) and its UTC."""
    unix = true_boot_us + offset_us + int(round(skew * true_boot_us)) + jitter_us
    return true_boot_us // 1000 * 1000, unix


def feed(clock: UtcClock, boots_us, offset_us: int, skew: float = 0.0, jitter=None) -> None:
    for k, b in enumerate(boots_us):
        clock.add_system_time(*system_time(b, offset_us, skew, 0 if jitter is None else jitter[k]))


@settings(max_examples=60, deadline=None)
@given(
    offset_us=st.integers(UNIX0_US - 10**12, UNIX0_US + 10**12),
    start_us=st.integers(1_000_000, 10**10),
    period_us=st.integers(900_000, 1_100_000),
    phase_us=st.lists(st.integers(0, 999), min_size=60, max_size=60),
    skew_ppm=st.floats(-100.0, 100.0),
)
@example(offset_us=1_799_000_000_000_000, start_us=1_000_000, period_us=934_009, phase_us=[0] * 60, skew_ppm=0.0)
def test_the_mapping_recovers_utc_within_its_sigma_for_any_offset_phase_and_skew(
    offset_us, start_us, period_us, phase_us, skew_ppm
):
    """Samples at ~1 Hz with any sub-millisecond phase: the mapped UTC of a frame just after the newest sample is
    within 4 sigma of the truth, and the sigma is honest but not lax (a few hundred us, never below the
    quantisation's 289 us)."""
    clock = UtcClock()
    skew = skew_ppm * 1e-6
    boots = [start_us + k * period_us + phase_us[k] for k in range(60)]
    feed(clock, boots, offset_us, skew)
    m = clock.mapping
    assert m is not None and m.n_samples == 60 and m.skew_fitted
    frame_boot_us = boots[-1] + 400_000
    utc_us, sigma_us = m.at(frame_boot_us)
    truth = frame_boot_us + offset_us + skew * frame_boot_us
    assert abs(utc_us - truth) <= 4 * sigma_us
    assert QUANT_SIGMA_US - 1 <= sigma_us <= 1500
    # the slope's own 4 sigma (~10 ppm) holds for quantisation errors that vary from sample to sample; samples at an
    # exact period with one phase (the shrunk example: 934.009 ms, phase 0) truncate to a sawtooth instead, whose
    # least-squares slope reaches 1.5 quanta over the span (9.6 ppm against a 9.2 ppm 4 sigma there)
    sawtooth = 1.5 * BOOT_QUANTUM_US / (boots[-1] - boots[0])
    assert abs(m.skew - skew) <= max(4 * m.resid_rms_us / math.sqrt(m.sxx_us2), sawtooth)


@settings(max_examples=40, deadline=None)
@given(
    offset_us=st.integers(UNIX0_US, UNIX0_US + 10**12),
    jitter=st.lists(st.integers(-2000, 2000), min_size=30, max_size=30),
)
def test_jitter_widens_the_sigma_and_the_truth_stays_inside(offset_us, jitter):
    clock = UtcClock()
    boots = [5_000_000 + k * 1_000_000 + 317 * k % 1000 for k in range(30)]
    feed(clock, boots, offset_us, jitter=jitter)
    utc_us, sigma_us = clock.mapping.at(boots[-1])
    assert abs(utc_us - (boots[-1] + offset_us)) <= 4 * sigma_us


def test_whole_millisecond_samples_are_within_sigma_too():
    """A simulator that sends SYSTEM_TIME on whole milliseconds: every sample's quantisation error is the same
    (-500 us after the half-quantum correction) and averaging cannot remove it; the sigma says so."""
    clock = UtcClock()
    feed(clock, [1_000_000 * k for k in range(1, 61)], UNIX0_US)
    utc_us, sigma_us = clock.mapping.at(60_500_000)
    err = utc_us - (60_500_000 + UNIX0_US)
    assert err == pytest.approx(-500, abs=5)
    assert abs(err) < 2 * sigma_us


def test_nothing_before_min_samples_and_nothing_far_beyond_the_newest_sample():
    counter = RejectCounter()
    clock = UtcClock(UtcClockConfig(max_age_us=30_000_000), counter)
    feed(clock, [1_000_000, 2_000_000], UNIX0_US)
    assert clock.mapping is None and clock.status()["state"] == "none" and clock.status()["offset_us"] is None
    track = positioned_track(time_boot_us=2_500_000)
    assert with_utc(track, clock.mapping) is track and track.time_unix_us is None
    feed(clock, [3_000_000], UNIX0_US)
    assert clock.mapping is not None and clock.status()["state"] == "ok"
    stamped = with_utc(track, clock.mapping)
    assert stamped.time_unix_us == pytest.approx(2_500_000 + UNIX0_US, abs=2 * stamped.time_unix_sigma_us)
    assert clock.mapping.at(3_000_000 + 30_000_001) is None  # the mapping is too old for that frame
    assert with_utc(positioned_track(time_boot_us=40_000_000), clock.mapping).time_unix_us is None
    assert counter.total == 0


@pytest.mark.parametrize(
    "boot_us, unix_us, reason",
    [
        (4_000_000, 0, "utc_no_time"),  # PX4 / ArduPilot: no GNSS time yet
        (4_000_000, 1_000_000, "utc_implausible"),  # a clock that counts from power-on
        (-1, UNIX0_US, "utc_implausible"),
        (4_000_000, 2**64 - 1, "utc_implausible"),  # a corrupt field: would overflow the track's time
        (4_000_000, 1.5e15, "utc_implausible"),  # not an integer
        (3_000_000, UNIX0_US + 3_000_000, "utc_duplicate"),  # the newest sample again
        (4_000_000, UNIX0_US + 4_000_000 + 60_000, "utc_outlier"),  # 60 ms off: one wild sample
    ],
)
def test_wild_samples_are_refused_counted_and_change_nothing(boot_us, unix_us, reason):
    counter = RejectCounter()
    clock = UtcClock(counter=counter)
    feed(clock, [1_000_000, 2_000_000, 3_000_000], UNIX0_US)
    before = clock.mapping
    assert clock.add_system_time(boot_us, unix_us) is False
    assert counter.counts == {reason: 1}
    if reason != "utc_outlier":
        assert clock.mapping is before
        return
    # an outlier may be the first sample of a step: the offset stays, its sigma covers the disagreement
    assert clock.mapping.offset_us(boot_us) == before.offset_us(boot_us)
    assert 60_000 <= clock.mapping.at(boot_us)[1] < 61_000
    assert clock.status()["disputed_us"] == pytest.approx(60_000, abs=1000)


def test_a_utc_step_confirmed_by_agreeing_samples_reseeds_and_a_reboot_forgets():
    counter = RejectCounter()
    clock = UtcClock(counter=counter)
    feed(clock, [k * 1_000_000 for k in range(1, 11)], UNIX0_US)
    step_us = 250_000  # e.g. an RTC guess replaced by GNSS time
    feed(clock, [11_000_000, 12_000_000], UNIX0_US + step_us)
    assert counter["utc_outlier"] == 2 and clock.steps == 0
    # not yet known which clock is right: the old offset, with a sigma that covers the new one
    t_unix, sigma = clock.mapping.at(12_000_000)
    assert t_unix == pytest.approx(12_000_000 + UNIX0_US, abs=2000)
    assert step_us <= sigma < step_us + 2000
    feed(clock, [13_000_000], UNIX0_US + step_us)
    assert counter["utc_step"] == 1 and clock.steps == 1
    t_unix, sigma = clock.mapping.at(13_500_000)
    assert t_unix == pytest.approx(13_500_000 + UNIX0_US + step_us, abs=2000)
    assert sigma < 2000 and clock.status()["disputed_us"] == 0
    assert clock.status()["steps"] == 1
    clock.reset()
    assert clock.mapping is None and clock.resets == 1


def test_an_agreeing_sample_after_a_wild_one_ends_the_dispute():
    clock = UtcClock()
    feed(clock, [k * 1_000_000 for k in range(1, 11)], UNIX0_US)
    quiet = clock.mapping.at(11_000_000)[1]
    assert clock.add_system_time(11_000_000, 11_000_000 + UNIX0_US + 2_000_000) is False  # 2 s off, alone
    assert clock.mapping.at(11_000_000)[1] >= 2_000_000
    assert clock.add_system_time(12_000_000, 12_000_000 + UNIX0_US) is True
    assert clock.mapping.at(12_000_000)[1] <= quiet + 100


def test_scattered_wild_samples_never_reseed():
    """Outliers that disagree with each other are not a step: each is refused."""
    counter = RejectCounter()
    clock = UtcClock(counter=counter)
    feed(clock, [k * 1_000_000 for k in range(1, 11)], UNIX0_US)
    for k, off in enumerate((80_000, -90_000, 200_000, -50_000)):
        clock.add_system_time(11_000_000 + k * 1_000_000, 11_000_000 + k * 1_000_000 + UNIX0_US + off)
    assert counter.counts == {"utc_outlier": 4} and clock.steps == 0


def test_status_reports_the_offset_its_sigma_and_source():
    clock = UtcClock()
    feed(clock, [k * 1_000_000 + 123 for k in range(1, 21)], UNIX0_US, skew=20e-6)
    s = clock.status()
    assert s["state"] == "ok" and s["source"] == "SYSTEM_TIME" and s["samples"] == 20
    assert s["offset_us"] == pytest.approx(UNIX0_US + 20e-6 * 20_000_123, abs=1000)
    assert QUANT_SIGMA_US - 1 <= s["sigma_us"] < 1000
    assert s["skew_ppm"] == pytest.approx(20.0, abs=10.0)


@pytest.mark.parametrize("field, value", [("window", 0), ("min_samples", 100), ("max_skew_ppm", -1.0)])
def test_bad_settings_name_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        UtcClockConfig(**{field: value})


def test_the_watchdog_warns_while_the_mapping_is_disputed_and_clears_after():
    from onboard.app.watchdog import Watchdog

    wd = Watchdog(
        started_s=0.0, frame_key="k", zenoh_where="w", mavlink_connection="udpin:0.0.0.0:1", camera_size_px=(1, 1)
    )
    clock = UtcClock()
    wd.utc(0.0, clock.mapping)  # no mapping yet: nothing to say
    feed(clock, [k * 1_000_000 for k in range(1, 11)], UNIX0_US)
    wd.utc(10.0, clock.mapping)
    assert wd.active == ()
    clock.add_system_time(11_000_000, 11_000_000 + UNIX0_US + 1_000_000)  # 1 s off
    wd.utc(11.0, clock.mapping)
    assert [w.code for w in wd.active] == ["utc_disputed"] and "1000 ms" in wd.active[0].message
    clock.add_system_time(12_000_000, 12_000_000 + UNIX0_US)  # the old clock was right
    wd.utc(12.0, clock.mapping)
    assert wd.active == ()
