"""The model selection's cost (MapConfig.coarse_q_grid_m2ps3, hopeless_nats, same_basin_ratio): fewer models
and starts than the whole grid, the same choice where the skipped models carry no posterior weight."""

from __future__ import annotations

import numpy as np
import pytest

from groundsim.evaluation.synth import estimator_noise_model, synthesize_scenario
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths
from onboard.estimation.map_estimator import MapConfig, MapEstimator

#: the selection before the cost settings: every family over the whole q grid, every mode a start
WHOLE_GRID = {"coarse_q_grid_m2ps3": (), "hopeless_nats": 0.0, "same_basin_ratio": 0.0}
#: two selections that choose the same model and basin agree on the positions to this fraction of range (the
#: ca/ct chains start elsewhere, so their near solutions in the model average move a little)
SAME_SOLUTION_RANGE_RATIO = 0.01
#: the posterior weight a model the cheaper selection leaves out may have had: on these short windows (100 rows)
#: the evidence is flat, and a loose model 7-8 nats below the best (weight up to 6e-4) is left out when its
#: family peaks at a stiffer intensity; on full windows they sit 20-140 nats below (docs/performance.md)
NEGLIGIBLE_WEIGHT = 1e-3


def _window(name: str, seed: int, step: int = 3):
    """A reference flight's 10 s under RTK navigation errors, every ``step``-th frame."""
    sc = load_scenario(reference_scenario_paths()[name])
    nc = load_noise_cases()["RTK"]
    truth, obs = synthesize_scenario(sc, nc, seed, t_s=sc.frame_times_s()[::step])
    return nc, obs


def _select(nc, obs, **settings):
    """(result, work): the selection run to its end, and the work it reported (residual evaluations)."""
    est = MapEstimator(MapConfig(knot_spacing_s=1.0, **settings), estimator_noise_model(nc))
    steps = est.selection(obs)
    work = 0
    while True:
        try:
            work += next(steps)
        except StopIteration as done:
            return done.value, work


@pytest.mark.parametrize("name, seed", [("P1", 0), ("P2", 1), ("P3", 0)])
def test_the_cheaper_selection_chooses_what_the_whole_grid_chooses(name, seed):
    nc, obs = _window(name, seed)
    whole, whole_work = _select(nc, obs, **WHOLE_GRID)
    res, work = _select(nc, obs)
    # the whole-grid settings are the selection before them: the chosen family at every intensity
    assert {q for q, _ in whole.grid_log_evidence[whole.model]} == set(MapConfig().q_grid_m2ps3)
    assert (res.model, res.prior, res.observable) == (whole.model, whole.prior, whole.observable)
    rng = np.linalg.norm(whole.p_ned_m - obs.p_cam_ned_m, axis=1)
    assert np.max(np.linalg.norm(res.p_ned_m - whole.p_ned_m, axis=1) / rng) < SAME_SOLUTION_RANGE_RATIO
    assert res.range_sigma_ratio == pytest.approx(whole.range_sigma_ratio, rel=0.05)
    assert work < whole_work  # (on these small windows 0.6-0.8 of it; bench.estimator prints the full ones)
    # every model the whole grid solved and this one did not had a negligible share of the posterior
    evs = [ev for grid in whole.grid_log_evidence.values() for _, ev in grid]
    norm = float(np.logaddexp.reduce(evs))
    for fam, grid in whole.grid_log_evidence.items():
        kept = dict(res.grid_log_evidence.get(fam, []))
        for q, ev in grid:
            if q not in kept:
                assert np.exp(ev - norm) < NEGLIGIBLE_WEIGHT, (fam, q)


def test_a_family_solves_its_loosest_intensity_only_while_its_evidence_rises_towards_it():
    """H1 (a figure-eight, gusty): CA's evidence rises to the loose edge of the coarse grid, so its loosest q is
    solved (and chosen); CV, the first family, cold, solves from the loosest q and stops before its stiffest
    when its evidence falls by hundreds of nats.  P1: every family's evidence peaks at a stiff q, so no later
    family solves the loosest; the cold first family does."""
    nc, obs = _window("H1", 0)
    res, _ = _select(nc, obs)
    grid = {f: [q for q, _ in g] for f, g in res.grid_log_evidence.items()}
    loosest, stiffest = max(MapConfig().q_grid_m2ps3), min(MapConfig().q_grid_m2ps3)
    assert loosest in grid["ca"] and (res.model, res.prior.q_horizontal_m2ps3) == ("ca", loosest)
    assert stiffest not in grid["cv"]
    nc, obs = _window("P1", 0)
    res, _ = _select(nc, obs)
    grid = {f: [q for q, _ in g] for f, g in res.grid_log_evidence.items()}
    assert loosest in grid["cv"] and loosest not in grid["ca"] and loosest not in grid["ct"]
    assert all(stiffest in g for g in grid.values())


def test_a_trusted_warm_start_runs_the_first_family_over_the_coarse_grid_only():
    nc, obs = _window("P1", 0)
    cold, cold_work = _select(nc, obs)
    est = MapEstimator(MapConfig(knot_spacing_s=1.0), estimator_noise_model(nc))
    warm = est.selection(obs, warm=cold.theta, trust_warm=True)
    work = 0
    while True:
        try:
            work += next(warm)
        except StopIteration as done:
            res = done.value
            break
    assert max(MapConfig().q_grid_m2ps3) not in [q for q, _ in res.grid_log_evidence["cv"]]
    assert (res.model, res.prior) == (cold.model, cold.prior) and work < cold_work
