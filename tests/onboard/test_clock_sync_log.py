"""How ClockSync reports TIMESYNC round trips outside its bound: every one is counted and discarded;
one alone (a moment when either end was busy, e.g. the first exchange while the autopilot side is
still starting) is INFO, two in a row (a slow link) one WARNING per run."""

from __future__ import annotations

import logging

import pytest

from onboard.core.clock_sync import ClockSync, ClockSyncConfig
from onboard.core.counters import RejectCounter

MAX_RTT_NS = 50_000_000  # 50 ms, the default bound
SHORT_RTT_NS = 5_000_000  # 5 ms: the loopback demo's steady round trip
LONG_RTT_NS = 78_000_000  # 78 ms: the demo's first exchange on a busy machine
OFFSET_NS = 10**12  # autopilot clock minus local clock
PERIOD_NS = 10**9  # one exchange a second, as the link sends them


class Exchanges:
    """Feeds ``cs`` one exchange a second with a chosen round trip."""

    def __init__(self, cs: ClockSync) -> None:
        self.cs = cs
        self.t_ns = 5 * 10**12

    def __call__(self, rtt_ns: int) -> bool:
        self.t_ns += PERIOD_NS
        return self.cs.add_exchange(self.t_ns, self.t_ns + rtt_ns // 2 + OFFSET_NS, self.t_ns + rtt_ns)


@pytest.fixture(autouse=True)
def _loggers_reach_caplog(monkeypatch, caplog):
    """An earlier test in the same process may have configured logging for a program (a logging config
    disables the loggers that existed then, and a program's logger may stop propagating): these tests read
    the records through caplog, so the loggers they exercise must be enabled and propagate."""
    for name in ("onboard", "onboard.core", "onboard.core.counters", "onboard.core.clock_sync"):
        lg = logging.getLogger(name)
        monkeypatch.setattr(lg, "disabled", False)
        monkeypatch.setattr(lg, "propagate", True)
        caplog.set_level(logging.DEBUG, logger=name)


@pytest.fixture
def exchanges():
    counter = RejectCounter(log_interval_s=0.0)  # every count logged: the levels are what is tested
    return Exchanges(ClockSync(ClockSyncConfig(max_rtt_ns=MAX_RTT_NS), counter))


def _levels(caplog, needle: str = "timesync_rtt") -> list[int]:
    return [r.levelno for r in caplog.records if needle in r.getMessage()]


def test_one_long_round_trip_at_start_is_counted_and_logged_at_info(exchanges, caplog):
    caplog.set_level(logging.DEBUG)
    assert not exchanges(LONG_RTT_NS)
    assert all(exchanges(SHORT_RTT_NS) for _ in range(5))
    assert exchanges.cs.counter["timesync_rtt"] == 1 and exchanges.cs.synced
    assert _levels(caplog) == [logging.INFO]


def test_lone_long_round_trips_later_stay_at_info(exchanges, caplog):
    caplog.set_level(logging.DEBUG)
    for rtt in (SHORT_RTT_NS, LONG_RTT_NS, SHORT_RTT_NS, SHORT_RTT_NS, LONG_RTT_NS, SHORT_RTT_NS):
        exchanges(rtt)
    assert exchanges.cs.counter["timesync_rtt"] == 2
    assert _levels(caplog) == [logging.INFO, logging.INFO]


def test_long_round_trips_in_a_row_warn_once_per_run(exchanges, caplog):
    caplog.set_level(logging.DEBUG)
    for _ in range(4):
        assert not exchanges(LONG_RTT_NS)
    assert exchanges.cs.counter["timesync_rtt"] == 4 and not exchanges.cs.synced
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "twice in a row" in warnings[0].getMessage()
    assert "78.000 ms outside [0, 50] ms" in warnings[0].getMessage()
    exchanges(SHORT_RTT_NS)  # the run ends; a new run warns again
    exchanges(LONG_RTT_NS)
    exchanges(LONG_RTT_NS)
    assert len([r for r in caplog.records if r.levelno >= logging.WARNING]) == 2


def test_a_negative_round_trip_is_judged_the_same_way(exchanges, caplog):
    caplog.set_level(logging.DEBUG)
    assert not exchanges(-1_000)
    assert not exchanges(-1_000)
    assert exchanges.cs.counter["timesync_rtt"] == 2
    assert [r.levelno for r in caplog.records if r.levelno >= logging.WARNING] == [logging.WARNING]


def test_reset_forgets_a_run_of_long_round_trips(exchanges, caplog):
    caplog.set_level(logging.DEBUG)
    exchanges(LONG_RTT_NS)
    exchanges.cs.reset()  # an autopilot reboot: a fresh start, whose first exchange may be slow again
    exchanges(LONG_RTT_NS)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
