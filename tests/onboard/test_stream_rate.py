"""StreamRates: the measured rate of each requested stream, and when it counts as slow."""

from __future__ import annotations

import pytest

from onboard.core.stream_rate import MIN_SPAN_S, SLOW_PERSIST_S, StreamRates

ATT, POS = 31, 33
HZ_TOL = 1e-9


def _meter() -> StreamRates:
    return StreamRates({ATT: ("ATTITUDE_QUATERNION", 100.0), POS: ("GLOBAL_POSITION_INT", 25.0)})


def _feed(m: StreamRates, t0_s: float, seconds: int, att_hz: int, pos_hz: int) -> float:
    """Whole seconds of messages, a look at the end of each; returns the last look's time."""
    t = t0_s
    for _ in range(seconds):
        for _ in range(att_hz):
            m.count(ATT)
        for _ in range(pos_hz):
            m.count(POS)
        m.count(999)  # not requested: ignored
        t += 1.0
        m.rates(t)
    return t


def test_rates_are_the_messages_over_the_last_seconds():
    m = _meter()
    first = {r.name: r for r in m.rates(0.0)}
    assert first["ATTITUDE_QUATERNION"].measured_hz is None  # no span yet (MIN_SPAN_S)
    t = _feed(m, 0.0, 8, 100, 25)
    got = {r.msg_id: r for r in m.rates(t)}
    assert got[ATT].measured_hz == pytest.approx(100.0, abs=HZ_TOL)
    assert got[POS].measured_hz == pytest.approx(25.0, abs=HZ_TOL)
    assert got[ATT].as_dict() == {"msg_id": ATT, "requested_hz": 100.0, "measured_hz": 100.0}
    t = _feed(m, t, 6, 20, 25)  # capped: the window forgets the earlier 100 Hz
    assert {r.msg_id: r.measured_hz for r in m.rates(t)}[ATT] == pytest.approx(20.0, abs=HZ_TOL)
    assert 999 not in m.counts


def test_slow_only_after_the_rate_was_confirmed_and_for_a_few_seconds():
    m = _meter()
    t = _feed(m, 0.0, 3, 20, 25)
    assert m.slow(t, m.rates(t)) == []  # 20 of 100 Hz, but never confirmed
    m.confirmed(ATT, t)
    m.confirmed(POS, t)
    t1 = _feed(m, t, int(MIN_SPAN_S), 20, 25)
    assert m.slow(t1, m.rates(t1)) == []  # measured, but not for SLOW_PERSIST_S yet
    t2 = _feed(m, t1, int(SLOW_PERSIST_S), 20, 25)
    slow = m.slow(t2, m.rates(t2))
    assert [r.msg_id for r in slow] == [ATT]  # 25 of 25 Hz is not slow; 20 of 100 Hz is
    t3 = _feed(m, t2, 6, 60, 25)  # above half the rate: no longer slow
    assert m.slow(t3, m.rates(t3)) == []
    m.reset()
    t4 = _feed(m, t3, 6, 20, 25)
    assert m.slow(t4, m.rates(t4)) == []  # re-requested: not confirmed again yet


def test_a_stream_that_stopped_is_not_slow():
    """A simulator that ended: its streams' rates over the window, the silence included, fell under half the requested
    rate and were warned as an autopilot capping them (stream_rate_low), 2.5 s after the end of every simulated run.
    Silence is the link's to say (no_mavlink, autopilot_lost)."""
    m = _meter()
    t = _feed(m, 0.0, 1, 100, 25)
    m.confirmed(ATT, t)
    m.confirmed(POS, t)
    t = _feed(m, t, 6, 100, 25)
    assert m.slow(t, m.rates(t)) == []
    t = _feed(m, t, 4, 0, 0)  # stopped: 20 Hz and 5 Hz over the last 5 s
    rates = {r.msg_id: r.measured_hz for r in m.rates(t)}
    assert rates[ATT] == pytest.approx(20.0, abs=HZ_TOL) and rates[POS] == pytest.approx(5.0, abs=HZ_TOL)
    assert m.slow(t, m.rates(t)) == []
    t = _feed(m, t, 6, 20, 25)  # back, the attitude capped: slow again
    assert [r.msg_id for r in m.slow(t, m.rates(t))] == [ATT]
    t = _feed(m, t, 6, 100, 0)  # the position alone silent while the attitude arrives: slow (0 Hz)
    assert [r.msg_id for r in m.slow(t, m.rates(t))] == [POS]


def test_slow_when_looked_at_twice_in_a_row():
    """The daemon's watchdog asks the link's status (a look) and then the slow streams (another look) on the thread
    that takes the messages, microseconds apart: nothing arrives between the two, which is no stopped telemetry.
    Judged against the look just before, a capped stream was never warned (a router's client capping the position
    stream at 4 Hz of 25 for 6 s: no stream_rate_low)."""
    m = _meter()
    t = _feed(m, 0.0, 1, 100, 25)
    m.confirmed(ATT, t)
    m.confirmed(POS, t)
    t = _feed(m, t, 6, 100, 4)
    m.rates(t)  # the status's look
    t_watch = t + 1e-6
    assert [r.msg_id for r in m.slow(t_watch, m.rates(t_watch))] == [POS]


def test_a_stream_at_half_its_rate_is_slow_until_it_is_clearly_faster():
    """An autopilot that caps a 100 Hz request at 50 Hz measures 49.8-50.0 Hz: below half, then not, every look,
    and the warning came and went every second (33 log lines in 75 s, a status at each change).  Slow once, a
    stream stays slow until it is above CLEAR_FRACTION of its requested rate."""
    from onboard.core.stream_rate import CLEAR_FRACTION, SLOW_FRACTION

    m = _meter()
    m.confirmed(ATT, 0.0)
    m.confirmed(POS, 0.0)
    t = _feed(m, 0.0, int(SLOW_PERSIST_S) + 2, 49, 25)
    assert [r.msg_id for r in m.slow(t, m.rates(t))] == [ATT]
    for hz in (51, 49, 51, 52):  # around half: still slow
        t = _feed(m, t, 6, hz, 25)
        assert [r.msg_id for r in m.slow(t, m.rates(t))] == [ATT], hz
    t = _feed(m, t, 6, int(CLEAR_FRACTION * 100) + 1, 25)
    assert m.slow(t, m.rates(t)) == []
    t = _feed(m, t, 6, int(SLOW_FRACTION * 100) + 1, 25)  # above half: not slow again from there
    assert m.slow(t, m.rates(t)) == []
