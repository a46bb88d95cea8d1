"""The pacing and speed probes printed by ``bench.onboard``: what they return and refuse (no timing asserted)."""

import math

import numpy as np
import pytest

from bench import _pacing_work, frame_speed_ms, pacing_factor


def test_pacing_work_is_a_fixed_workload():
    a = np.random.default_rng(0).random((84, 84))
    expected = sum(i * 0.5 for i in range(2000)) + 60 * float((a * 2.0 + 1.0).sum())
    assert _pacing_work(a, 2000) == pytest.approx(expected, rel=1e-12)


def test_pacing_factor_returns_a_cost_and_a_ratio():
    tight_ms, ratio = pacing_factor(rate_hz=500.0, calls=3)
    assert math.isfinite(tight_ms) and tight_ms > 0
    assert math.isfinite(ratio) and ratio > 0


@pytest.mark.parametrize("rate_hz, calls", [(0.0, 3), (-30.0, 3), (float("nan"), 3), (30.0, 0)])
def test_pacing_factor_refuses_bad_arguments(rate_hz, calls):
    with pytest.raises(ValueError, match="pacing_factor"):
        pacing_factor(rate_hz=rate_hz, calls=calls)


def test_frame_speed_is_a_cpu_time_and_refuses_no_repeats():
    ms = frame_speed_ms(repeats=1)
    assert math.isfinite(ms) and ms > 0
    with pytest.raises(ValueError, match="frame_speed_ms: repeats"):
        frame_speed_ms(repeats=0)


def test_bench_onboard_paced_processing_prints_its_figures():
    """``python -m bench.onboard --no-latency --paced``: the paced line, over the last half of the frames, with
    the CPU s per s that is its mean per frame at 30 Hz (a child: the bench pins its process to one CPU)."""
    import re
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "bench.onboard", "--no-latency", "--frames", "6", "--paced"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    m = re.search(
        r"paced as in flight .*the last (\d+) frames\): mean ([\d.]+) ms a frame against ([\d.]+) back to back"
        r" \(x([\d.]+)\) = ([\d.]+) CPU s per s",
        out,
    )
    assert m is not None, out
    # the machine's two speed probes head the output, so that runs on a drifting VM can be compared
    assert re.search(r"a fixed Python loop takes [\d.]+ CPU ms, fixed whole-frame passes [\d.]+ CPU ms", out), out
    n, paced_ms, b2b_ms, ratio, cpu_s_per_s = int(m[1]), *map(float, m.group(2, 3, 4, 5))
    assert n == 3
    assert paced_ms > 0 and b2b_ms > 0
    # from the printed figures, rounded to 0.01 ms: the ratio to within their rounding
    assert (paced_ms - 0.005) / (b2b_ms + 0.005) - 0.005 <= ratio <= (paced_ms + 0.005) / (b2b_ms - 0.005) + 0.005
    assert cpu_s_per_s == pytest.approx(paced_ms * 30 / 1000, abs=0.001)
