"""Fixtures shared by the estimator-worker tests (restart, rebuild): one synthetic reference flight, made once."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def one_blas_thread():
    """The workers' BLAS on one thread, as the daemon runs them (a worker forked with more competes with pytest)."""
    from groundsim.evaluation.parallel import limit_blas_threads

    limit_blas_threads(1)


@pytest.fixture(scope="session")
def p3_px03_flight():
    """(intrinsics, truth, observations) of P3 with 0.3 px pixel noise, seed 1."""
    from groundsim.evaluation.synth import synthesize_scenario
    from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths

    sc = load_scenario(reference_scenario_paths()["P3"])
    truth, obs = synthesize_scenario(sc, load_noise_cases()["px0.3"], seed=1)
    return sc.camera.intrinsics, truth, obs
