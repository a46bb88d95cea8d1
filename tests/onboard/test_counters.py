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


def test_a_subject_has_its_own_interval_within_its_reason(caplog):
    clock = FakeClock(100.0)
    rc = RejectCounter(log_interval_s=10.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="onboard.core.counters"):
        rc.count("vehicle_silent", "uav1: no track", subject="uav1")
        rc.count("vehicle_silent", "uav2: no track", subject="uav2")  # another vehicle: not hidden by uav1's
        rc.count("vehicle_silent", "uav1: no track", subject="uav1")  # the same one again: held for the interval
        clock.t_s += 10.0
        rc.count("vehicle_silent", "uav1: no track", subject="uav1")
    msgs = [r.getMessage() for r in caplog.records]
    assert [m.split(":")[1].strip() for m in msgs] == ["uav1", "uav2", "uav1"]
    assert "total 4, 2 since last report" in msgs[2] and rc["vehicle_silent"] == 4


def test_subjects_whose_interval_passed_are_forgotten_beyond_the_bound(monkeypatch):
    monkeypatch.setattr("onboard.core.counters.MAX_LOG_KEYS", 8)
    clock = FakeClock(100.0)
    rc = RejectCounter(log_interval_s=10.0, clock=clock)
    for k in range(100):  # names that come and go, one every 11 s
        rc.count("vehicle_forgotten", subject=f"v{k}")
        clock.t_s += 11.0
    assert len(rc._last_log_s) <= 8 and rc["vehicle_forgotten"] == 100
