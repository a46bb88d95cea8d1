"""ClockSync: the local clock on the autopilot's boot clock from TIMESYNC exchanges (pure, no sockets)."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.core.clock_sync import ClockSync
from onboard.core.pose import ClockSyncConfig


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


def test_clock_sync_offset_and_skew():
    rng = np.random.default_rng(3)
    cs = ClockSync()
    t0 = 5_000_000_000_000
    offset = -4_321_987_654_321  # autopilot booted long after the local clock's epoch
    assert cs.to_boot_us(t0) is None  # not synced yet
    t_end = simulate_timesync(cs, rng, 60, t0, offset, skew_ppm=40.0)
    assert cs.synced
    assert cs.skew_ppm == pytest.approx(40.0, abs=15.0)
    for t_local in (t_end, t_end + 2_000_000_000):
        truth_us = (t_local + offset + 40e-6 * (t_local - t0)) / 1e3
        assert abs(cs.to_boot_us(t_local) - truth_us) < 2_000  # 2 ms; one-way delays are up to 4 ms
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
