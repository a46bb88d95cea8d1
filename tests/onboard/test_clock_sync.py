"""ClockSync: the local clock on the autopilot's boot clock from TIMESYNC exchanges (pure, no sockets)."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.core.clock_sync import ClockSync, ClockSyncConfig
from onboard.core.errors import ConfigError

SKEW_ATOL_PPM = 5.0  # a few times the spread of the fitted skew over seeds (60 exchanges, delays up to 4 ms)
BOOT_ATOL_US = 500  # 0.5 ms: a quarter of the mean one-way delay (about 2 ms), so a delay left in the offset is caught


def simulate_timesync(
    cs: ClockSync, rng, n, t0_local_ns, offset_ns, skew_ppm, period_ns=1_000_000_000, max_delay_ns=4_000_000
):
    """Autopilot clock = local + offset + skew * (local - t0); random one-way delays."""
    t = t0_local_ns
    for _ in range(n):
        d_up, d_down = rng.integers(100_000, max_delay_ns, size=2)
        t_remote_local = t + int(d_up)
        tc1 = t_remote_local + offset_ns + int(skew_ppm * 1e-6 * (t_remote_local - t0_local_ns))
        cs.add_exchange(int(t), int(tc1), int(t_remote_local + d_down))
        t += period_ns
    return t


def test_config_validates():
    with pytest.raises(ConfigError, match="min_samples"):
        ClockSyncConfig(window=2, min_samples=3)


def test_clock_sync_offset_and_skew():
    rng = np.random.default_rng(3)
    cs = ClockSync()
    t0 = 5_000_000_000_000
    offset = -4_321_987_654_321  # autopilot booted long after the local clock's epoch
    assert cs.to_boot_us(t0) is None  # not synced yet
    t_end = simulate_timesync(cs, rng, 60, t0, offset, skew_ppm=40.0)
    assert cs.synced
    assert cs.skew_ppm == pytest.approx(40.0, abs=SKEW_ATOL_PPM)
    for t_local in (t_end, t_end + 2_000_000_000):
        truth_us = (t_local + offset + 40e-6 * (t_local - t0)) / 1e3
        assert abs(cs.to_boot_us(t_local) - truth_us) < BOOT_ATOL_US
    assert abs(cs.to_local_ns(cs.to_boot_us(t_end)) - t_end) < 2_000


def test_clock_sync_rejects_long_and_negative_round_trips():
    cs = ClockSync(ClockSyncConfig(max_rtt_ns=10_000_000))
    assert not cs.add_exchange(1_000, 5_000_000, 1_000 + 20_000_000)
    assert not cs.add_exchange(1_000, 5_000_000, 500)
    assert not cs.add_exchange(1_000, 0, 2_000)  # tc1 = 0 is a request, not an answer
    assert cs.counter.counts == {"timesync_rtt": 2, "timesync_invalid": 1}
    assert cs.n_samples == 0


def test_clock_sync_reseeds_after_remote_clock_restart():
    rng = np.random.default_rng(4)
    cs = ClockSync()
    t = simulate_timesync(cs, rng, 10, 10**12, offset_ns=7 * 10**9, skew_ppm=0.0)
    # autopilot reboots: its clock now reads ~0 -> offset jumps by -7 s
    t = simulate_timesync(cs, rng, 2, t, offset_ns=-(10**12) + 3 * 10**9, skew_ppm=0.0)
    assert cs.counter["timesync_outlier"] == 2 and cs.resets == 0
    assert abs(cs.to_boot_us(t) - (t + 7 * 10**9) / 1e3) < 5_000  # old estimate still in force
    t = simulate_timesync(cs, rng, 1, t, offset_ns=-(10**12) + 3 * 10**9, skew_ppm=0.0)
    assert cs.resets == 1 and cs.counter["timesync_reset"] == 1
    assert abs(cs.to_boot_us(t) - (t - 10**12 + 3 * 10**9) / 1e3) < 5_000
    cs.reset()
    assert not cs.synced and cs.to_boot_us(t) is None


def _exchange(cs: ClockSync, t_local_ns: int, offset_ns: int, up_ns: int, down_ns: int) -> bool:
    """One round trip sent at ``t_local_ns``, ``up_ns`` to the autopilot (whose clock reads local + offset) and
    ``down_ns`` back."""
    return cs.add_exchange(t_local_ns, t_local_ns + up_ns + offset_ns, t_local_ns + up_ns + down_ns)


def test_short_round_trips_outweigh_long_lopsided_ones():
    """One exchange with a 0.1 ms symmetric round trip (its offset exact) and two of 20 ms that were all on the way
    up (their offsets 10 ms off: the rtt / 2 bound): weights 1 / (rtt + floor)^2 keep the estimate within a few
    microseconds of the truth; equal weights would put it 6.7 ms off."""
    cs = ClockSync()
    offset, t0 = 3_000_000_000, 1_000_000_000_000
    floor = cs.config.rtt_floor_ns
    assert _exchange(cs, t0, offset, 50_000, 50_000)
    assert _exchange(cs, t0 + 100_000_000, offset, 20_000_000, 0)
    assert _exchange(cs, t0 + 200_000_000, offset, 20_000_000, 0)
    assert cs.synced and cs.skew_ppm == 0.0  # 0.2 s of history: no skew fitted
    w = 1.0 / (np.array([100_000, 20_000_000, 20_000_000]) + floor) ** 2
    expected = offset + float(w @ np.array([0, 10_000_000, 10_000_000])) / float(w.sum())
    assert cs.offset_ns_at(t0 + 200_000_000) == round(expected)
    assert abs(cs.offset_ns_at(t0) - offset) < 10_000  # 10 us; equal weights: 6.7 ms


@pytest.mark.parametrize("skew_ppm, fitted_ppm", [(3000.0, 1000.0), (-3000.0, -1000.0), (400.0, 400.0)])
def test_a_skew_beyond_what_a_clock_does_is_clamped(skew_ppm, fitted_ppm):
    """Exact exchanges of a clock running 3000 ppm fast or slow (a crystal drifts by tens of ppm): the fitted skew
    stops at ``max_skew_ppm`` (1000); 400 ppm is fitted as it is."""
    cs = ClockSync(ClockSyncConfig(min_skew_span_ns=2_000_000_000))
    assert cs.config.max_skew_ppm == 1000.0
    t0 = 1_000_000_000_000
    for k in range(5):  # one a second, 1 us each way
        t = t0 + k * 1_000_000_000
        assert _exchange(cs, t, 5_000_000 + round(skew_ppm * 1e-6 * (t - t0)), 1_000, 1_000)
    assert cs.skew_ppm == pytest.approx(fitted_ppm, rel=1e-6)


@pytest.mark.parametrize("sub_us_ns, expected_extra_us", [(0, 0), (499, 0), (500, 1), (600, 1), (999, 1)])
def test_boot_time_is_rounded_to_the_nearest_microsecond(sub_us_ns, expected_extra_us):
    """An exact offset (zero round trips): local + offset ending in 500 ns or more is the next microsecond."""
    cs = ClockSync()
    offset, t0 = 7_000_000_000, 2_000_000_000_000
    for k in range(3):
        assert _exchange(cs, t0 + k * 1_000_000, offset, 0, 0)
    assert cs.offset_ns_at(t0) == offset
    local = t0 + 5_000_000_000 + sub_us_ns
    assert cs.to_boot_us(local) == (t0 + 5_000_000_000 + offset) // 1000 + expected_extra_us
