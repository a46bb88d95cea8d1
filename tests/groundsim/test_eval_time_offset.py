"""groundsim eval's camera clock lines (format_time_offset): times counted from the first measured frame."""

from __future__ import annotations

import math
from types import SimpleNamespace

from groundsim.app.eval_command import format_time_offset


def _run(time_offset):
    return SimpleNamespace(scenario="P2", seed=1, time_offset=time_offset)


def test_time_offset_lines_give_the_estimate_and_the_times_since_tracking_began():
    to = {
        "estimate_ms": 48.93,
        "sigma_ms": 3.28,
        "state": "confident",
        "compensated_ms": 48.93,
        "first_measurement_t_s": 0.5,
        "confident_t_s": 6.5,
        "warning_t_s": 7.0,
        "injected_ms": 50.0,
    }
    zero = {**to, "estimate_ms": None, "sigma_ms": None, "state": "unknown", "compensated_ms": 0.0, "injected_ms": 0.0}
    zero.update(confident_t_s=math.nan, warning_t_s=math.nan)
    text = format_time_offset([_run(to), _run(zero), _run(None)])
    lines = text.splitlines()
    assert "injected 50 ms, estimate +48.9 +- 3.3 ms (confident), compensated 48.9 ms" in lines[1]
    assert "confident after 6.0 s, warned after 6.5 s" in lines[1]
    assert "estimate - (unknown)" in lines[2] and "warned after never" in lines[2]
    assert "no estimate" in lines[3]
