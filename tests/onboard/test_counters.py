"""RejectCounter: counts by reason, logs each reason at most once per interval."""

from __future__ import annotations

import logging

import pytest

from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError
from tests.fakes import FakeClock


def test_reject_counter_logs_once_per_reason_per_interval(caplog):
    clock = FakeClock(100.0)
    rc = RejectCounter(log_interval_s=10.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="onboard.core.counters"):
        for _ in range(5):
            rc.count("attitude_zero", "zero quaternion")
        rc.count("position_zero")
        clock.t_s += 10.0
        rc.count("attitude_zero")
    assert rc.counts == {"attitude_zero": 6, "position_zero": 1} and rc.total == 7
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 3
    assert msgs[2].startswith("attitude_zero") and "total 6, 5 since last report" in msgs[2]


def test_a_broken_clock_does_not_break_the_caller():
    def clock() -> float:
        raise OSError("no clock")

    rc = RejectCounter(clock=clock)
    rc.count("frame_short")
    rc.count("frame_short")
    assert rc["frame_short"] == 2 and rc["other"] == 0


def test_the_interval_must_be_a_non_negative_number():
    with pytest.raises(ConfigError, match="log_interval_s"):
        RejectCounter(log_interval_s=-1.0)
