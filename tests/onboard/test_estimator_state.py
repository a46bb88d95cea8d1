"""The sliding-window estimator's state interface, what the daemon's worker process uses to survive its own
death: ``snapshot`` / ``restore`` continue the same run bit for bit, ``rebuild`` solves a replayed window with
one model selection, and the worker reads the noise model through ``noise``."""

from __future__ import annotations

import numpy as np
import pytest

from bench.onboard import SyntheticScene
from onboard.app.config import OnboardConfig
from onboard.pipeline.frame_pipeline import make_estimator

N_BEFORE = 150  # 5 s at 30 Hz: past the window's first model selections
N_AFTER = 40


def _rows(scene: SyntheticScene, first: int, n: int) -> list[tuple]:
    out = []
    for k in range(first, first + n):
        p_cam, q = scene.camera(k / 30.0)
        uv = scene.uv(k / 30.0) + 0.2 * np.sin(np.array([k, 2.0 * k]))
        out.append((scene.t_us(k) / 1e6, uv, scene.intrinsics, p_cam, q))
    return out


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return bool(
        a.t_s == b.t_s
        and np.array_equal(a.p_ned_m, b.p_ned_m)
        and np.array_equal(a.cov_p_ned_m2, b.cov_p_ned_m2)
        and a.observable == b.observable
    )


def test_a_restored_snapshot_continues_the_run_bit_for_bit():
    scene = SyntheticScene()
    original = make_estimator(OnboardConfig())
    for args in _rows(scene, 0, N_BEFORE):
        original.add(*args)
    snap = original.snapshot()
    restored = make_estimator(OnboardConfig())
    restored.restore(snap)
    later = _rows(scene, N_BEFORE, N_AFTER)
    answers = [(original.add(*args), restored.add(*args)) for args in later]
    assert sum(a is not None for a, _ in answers) > N_AFTER // 2
    assert all(_same(a, b) for a, b in answers)
    assert original.noise is original.map.noise


def test_restore_refuses_bytes_that_are_not_a_snapshot():
    import pickle

    est = make_estimator(OnboardConfig())
    with pytest.raises(ValueError, match="not an estimator snapshot"):
        est.restore(pickle.dumps(["not", "a", "state"]))
    with pytest.raises(ValueError, match="not an estimator snapshot"):
        est.restore(pickle.dumps({"map": None}))


def test_rebuild_solves_the_window_once_and_keeps_the_configuration():
    scene = SyntheticScene()
    est = make_estimator(OnboardConfig())
    config = est.config
    rows = _rows(scene, 0, N_BEFORE)[::2]  # the rows a window keeps (min_spacing_s), as the worker's parent has them
    out = est.rebuild(rows)
    assert out is not None and out.t_s == rows[-1][0]
    assert est.stats["selections"] == 1  # one cold model selection, on the newest row
    assert est.config is config
    assert est.rebuild([]) is None and est.stats["selections"] == 0  # reset, nothing to add
