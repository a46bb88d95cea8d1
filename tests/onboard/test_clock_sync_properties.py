"""Properties of onboard.core.clock_sync (hypothesis): the TIMESYNC filter that puts camera frames on the autopilot's
boot clock.

* Any triple of values is either used or counted once under its documented reason (``timesync_invalid`` for a
  non-integer, a bool or ``tc1 <= 0``; ``timesync_rtt`` for a round trip outside ``[0, max_rtt_ns]``), never an
  exception; a refused exchange changes nothing.
* A constant offset is recovered from exchanges with any one-way delays within half the longest round trip (Cristian's
  bound), and a skew exactly from symmetric ones.
* The mapping is monotonic in local time, ``to_local_ns`` inverts ``to_boot_us`` to within the microsecond's
  rounding, and a boot time is never negative.
* Fewer than ``jump_count`` exchanges off the estimate are outliers that change nothing; ``jump_count`` in a row
  re-seed the filter on the new offset.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.core.clock_sync import NS_PER_US, ClockSync, ClockSyncConfig
from onboard.core.counters import RejectCounter

CFG = ClockSyncConfig()
INT64 = st.integers(-(2**63), 2**63 - 1)
T0_NS = 10**12  # local monotonic clock: 1000 s since its start
PERIOD_NS = 1_000_000_000  # one exchange a second (the daemon's rate)
SPAN_BELOW_SKEW = CFG.min_skew_span_ns // PERIOD_NS  # exchanges that span less than the skew fit needs


def _sync() -> ClockSync:
    return ClockSync(CFG, RejectCounter())


def _state(cs: ClockSync) -> tuple:
    return (list(cs._window.samples), list(cs._window.outliers), cs._a_ns, cs._b, cs.resets, cs.offset_ns_at(T0_NS))


# any value the MAVLink adapter could be handed by a decoder, a bug or a test: numbers of every kind and the edges
values = st.one_of(
    INT64,
    st.sampled_from([0, 1, -1, 2**63 - 1, -(2**63)]),
    st.booleans(),
    st.floats(),
    st.none(),
    st.text(max_size=3),
    st.builds(np.int64, INT64),
    st.builds(np.uint64, st.integers(0, 2**64 - 1)),
    st.builds(np.float64, st.floats()),
    st.builds(np.bool_, st.booleans()),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(values, values, values), min_size=1, max_size=8))
@example([(True, 1, 2)])  # a bool is an int in Python: refused, not read as 1 ns
@example([(0, np.bool_(True), 2)])
@example([(0, 1.0, 2)])  # a whole float: refused, not read as 1 ns
@example([(0, 2**63 - 1, 2**63 - 1)])
@example([(-(2**63), 1, 2**63 - 1)])  # the longest round trip int64 holds
def test_any_exchange_is_used_or_counted_once_under_its_reason_never_raised(exchanges):
    cs = _sync()
    for ts1, tc1, t3 in exchanges:
        before, counts = _state(cs), dict(cs.counter.counts)
        used = cs.add_exchange(ts1, tc1, t3)
        new = {k: v - counts.get(k, 0) for k, v in cs.counter.counts.items() if v != counts.get(k, 0)}
        ints = all(not isinstance(v, (bool, np.bool_)) and isinstance(v, (int, np.integer)) for v in (ts1, tc1, t3))
        if not ints or tc1 <= 0:
            assert (used, new) == (False, {"timesync_invalid": 1})
        elif not 0 <= int(t3) - int(ts1) <= CFG.max_rtt_ns:
            assert (used, new) == (False, {"timesync_rtt": 1})
        else:
            assert new in ({}, {"timesync_outlier": 1}, {"timesync_reset": 1}) and used == (
                "timesync_outlier" not in new
            )
            continue
        assert _state(cs) == before  # a refused exchange changes nothing
    b = cs.to_boot_us(T0_NS)
    assert b is None or (type(b) is int and b >= 0)


delays = st.tuples(st.integers(0, CFG.max_rtt_ns // 2), st.integers(0, CFG.max_rtt_ns // 2))  # (up, down) ns


@settings(max_examples=80, deadline=None)
@given(
    offset_ns=st.integers(1 - T0_NS, 2**62),  # the autopilot's boot clock is > 0 at every answer (tc1 > 0)
    exchanges=st.lists(delays, min_size=CFG.min_samples, max_size=SPAN_BELOW_SKEW),
    at_ns=st.integers(0, SPAN_BELOW_SKEW * PERIOD_NS),
)
def test_a_constant_offset_is_recovered_within_half_the_longest_round_trip(offset_ns, exchanges, at_ns):
    cs = _sync()
    for k, (up, down) in enumerate(exchanges):
        ts1 = T0_NS + k * PERIOD_NS
        assert cs.add_exchange(ts1, ts1 + up + offset_ns, ts1 + up + down)  # remote answers at local ts1 + up
    worst_ns = max(up + down for up, down in exchanges) / 2 + 2  # the midpoint's floor and the estimate's rounding
    assert abs(cs.offset_ns_at(T0_NS + at_ns) - offset_ns) <= worst_ns
    assert cs.skew_ppm == 0.0  # spans less than min_skew_span_ns: no skew fitted
    if T0_NS + at_ns + offset_ns > worst_ns:  # after boot, whatever the estimate's error
        assert abs(cs.to_boot_us(T0_NS + at_ns) * NS_PER_US - (T0_NS + at_ns + offset_ns)) <= worst_ns + NS_PER_US / 2


@settings(max_examples=60, deadline=None)
@given(
    offset_ns=st.integers(1 - T0_NS, 10**15),
    skew_ppm=st.floats(-CFG.max_skew_ppm * 0.99, CFG.max_skew_ppm * 0.99),
    n=st.integers(SPAN_BELOW_SKEW + 2, CFG.window),
    delay_ns=st.integers(0, CFG.max_rtt_ns // 2),
)
def test_a_skew_is_recovered_from_symmetric_exchanges(offset_ns, skew_ppm, n, delay_ns):
    cs = _sync()
    for k in range(n):
        ts1 = T0_NS + k * PERIOD_NS
        at = ts1 + delay_ns
        tc1 = at + offset_ns + round(skew_ppm * 1e-6 * (at - T0_NS))
        assert cs.add_exchange(ts1, tc1, at + delay_ns)
    assert cs.skew_ppm == pytest.approx(skew_ppm, abs=1e-3)  # 1 ns of rounding over 20 s is 5e-5 ppm
    for k in (0, n // 2, n - 1):  # within the exchanges' span: each off by its 1 ns of rounding
        t = T0_NS + k * PERIOD_NS + delay_ns
        assert abs(cs.offset_ns_at(t) - (offset_ns + skew_ppm * 1e-6 * (t - T0_NS))) <= 5


@settings(max_examples=60, deadline=None)
@given(
    offset_ns=st.integers(-(10**12), 10**15),
    skew_ppm=st.floats(-2000.0, 2000.0),  # beyond max_skew_ppm too: clamped
    exchanges=st.lists(delays, min_size=CFG.min_samples, max_size=CFG.window),
    # frames within minutes of the exchanges (the daemon maps frames of now, against a fit of the last minute)
    queries=st.lists(st.integers(T0_NS - 100 * PERIOD_NS, T0_NS + 200 * PERIOD_NS), min_size=2, max_size=20),
)
def test_the_mapping_is_monotonic_and_inverted_within_the_microseconds_rounding(
    offset_ns, skew_ppm, exchanges, queries
):
    cs = _sync()
    for k, (up, down) in enumerate(exchanges):
        ts1 = T0_NS + k * PERIOD_NS
        cs.add_exchange(ts1, max(1, ts1 + up + offset_ns + round(skew_ppm * 1e-6 * k * PERIOD_NS)), ts1 + up + down)
    assert cs.synced
    last = None
    for local_ns in sorted(queries):
        boot_us = cs.to_boot_us(local_ns)
        if boot_us is None:
            assert local_ns + cs.offset_ns_at(local_ns) < 0  # before boot
            continue
        assert type(boot_us) is int and boot_us >= 0
        assert last is None or boot_us >= last
        last = boot_us
        back_ns = cs.to_local_ns(boot_us)
        # the microsecond's rounding, and what the one fixed-point step leaves: skew^2 times the distance from the
        # fit's reference (its offset's too, up to half a round trip): 1 ns a minute at 100 ppm
        b = cs.skew_ppm * 1e-6
        step_ns = b * b * (abs(local_ns - T0_NS) + CFG.max_rtt_ns)
        assert abs(back_ns - local_ns) <= NS_PER_US / 2 * (1 + abs(b)) + step_ns + 2


@settings(max_examples=60, deadline=None)
@given(
    offset_ns=st.integers(0, 10**15),
    jump_ns=st.one_of(
        st.integers(-(10**15), -(CFG.jump_ns + CFG.max_rtt_ns)), st.integers(CFG.jump_ns + CFG.max_rtt_ns, 10**15)
    ),
    before=st.integers(CFG.min_samples, 10),
    off_run=st.integers(1, CFG.jump_count),
    rtt_ns=st.integers(0, CFG.max_rtt_ns),
)
def test_outliers_change_nothing_and_jump_count_in_a_row_reseed_on_the_new_offset(
    offset_ns, jump_ns, before, off_run, rtt_ns
):
    cs = _sync()
    t = T0_NS

    def exchange(off: int) -> bool:
        nonlocal t
        t += PERIOD_NS
        return cs.add_exchange(t, max(1, t + rtt_ns // 2 + off), t + rtt_ns)

    for _ in range(before):
        assert exchange(offset_ns)
    est = cs.offset_ns_at(t)
    new_ns = offset_ns + jump_ns
    for i in range(off_run):
        used = exchange(new_ns)
        if i < CFG.jump_count - 1:
            assert not used and cs.offset_ns_at(t) == est and cs.resets == 0
    if off_run < CFG.jump_count:
        assert exchange(offset_ns)  # back on the estimate: those were outliers
        assert abs(cs.offset_ns_at(t) - offset_ns) <= rtt_ns / 2 + 2
        assert cs.counter["timesync_outlier"] == off_run and cs.resets == 0
    else:
        assert used and cs.resets == 1 and cs.counter["timesync_reset"] == 1
        assert cs.n_samples == CFG.jump_count
        if new_ns > 0:
            assert abs(cs.offset_ns_at(t) - new_ns) <= rtt_ns / 2 + 2
