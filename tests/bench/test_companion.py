"""bench.companion's scoring and log reading on small inputs (the runs themselves print numbers)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.companion import format_table, overload_delay_s, score_row

TEXT_LOG = (
    '2026-12-03T08:17:52.000Z level=INFO logger=onboard msg="started"\n'
    '2026-12-03T08:17:55.250Z level=WARNING logger=onboard.rejects msg="dropped_queue: pipeline behind (total 1)"\n'
    '2026-12-03T08:17:55.750Z level=WARNING logger=onboard.app.watchdog msg="overload: 1 frames dropped"\n'
)
JSON_LOG = (
    '{"ts":"2026-12-03T08:17:52.000Z","level":"INFO","logger":"onboard","msg":"started"}\n'
    '{"ts":"2026-12-03T08:17:53.000Z","level":"WARNING","logger":"onboard.rejects","msg":"estimate_stale: old"}\n'
    '{"ts":"2026-12-03T08:17:54.500Z","level":"WARNING","logger":"onboard.app.watchdog","msg":"overload: x"}\n'
)
ATOL_S = 1e-6


@pytest.mark.parametrize("text, delay_s, cause_s", [(TEXT_LOG, 0.5, 3.25), (JSON_LOG, 1.5, 1.0)])
def test_overload_delay_from_the_log(text, delay_s, cause_s):
    d, c = overload_delay_s(text)
    assert d == pytest.approx(delay_s, abs=ATOL_S) and c == pytest.approx(cause_s, abs=ATOL_S)


def test_overload_not_warned_and_no_cause():
    d, c = overload_delay_s(TEXT_LOG.rsplit("\n", 2)[0] + "\n")
    assert d is None and c == pytest.approx(3.25)
    assert overload_delay_s("garbage\n{not json\n") == (None, None)


def test_score_row():
    F = 10
    t_us = np.arange(F, dtype=np.int64) * 1_000_000  # a frame a second: frames 5..9 are after 5 s
    truth = np.zeros((F, 3))
    est = np.full((F, 3), np.nan)
    P = np.full((F, 3, 3), np.nan)
    est[2:] = [1.0, 0.0, 0.0]  # 1 m off
    P[2:] = np.eye(3) * (1.0 / 3.0)  # 3 sqrt(trace) = 3 m: honest
    P[9] = np.eye(3) * 1e-4  # 3 sqrt(trace) = 0.05 m: not
    est[4] = np.nan  # a gap after the first position
    tracked = np.ones(F, dtype=bool)
    observable = np.zeros(F, dtype=bool)
    observable[7:] = True
    a = dict(t_us=t_us, truth_p=truth, est_p=est, est_P=P, tracked=tracked, observable=observable)
    r = score_row(a, None)
    assert r["tracks"] == 10 and r["positions"] == 7
    assert r["coverage"] == pytest.approx(7 / 8)
    assert r["observable_after_5s"] == pytest.approx(3 / 5)
    assert r["honest"] == pytest.approx(6 / 7)
    r.update(label="x", overload_s=None, first_cause_s=None, daemon_cpu=0.2, throttled=None)
    assert "| x | 10 of 10 |" in format_table([r])


def test_emulated_quota_stops_and_continues_a_busy_process():
    """The emulation on a real busy child: it is stopped once past its share of a period, and left running
    (continued) when the emulation ends."""
    import subprocess
    import sys
    import threading

    from bench.companion import EmulatedQuota

    child = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    em = EmulatedQuota(0.1, find_pid=lambda: child.pid)
    try:
        stopped = threading.Event()
        em.start()
        for _ in range(400):  # at most 20 s; a stop comes within the first periods
            if em.stopped_s > 0:
                stopped.set()
                break
            stopped.wait(0.05)
        em.close()
        assert stopped.is_set()
        state = open(f"/proc/{child.pid}/stat").read().rsplit(")", 1)[1].split()[0]
        assert state in ("R", "S")  # continued, not left stopped
    finally:
        em.close()
        child.kill()
        child.wait(5)
