"""The pacing probe printed by ``bench.onboard``: what it returns and what it refuses (no timing asserted)."""

import math

import numpy as np
import pytest

from bench import _pacing_work, pacing_factor


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
