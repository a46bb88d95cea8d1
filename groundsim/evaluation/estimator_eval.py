"""Accuracy of the reconstruction core on the reference scenarios from perfect-geometry observations.

For each (scenario, noise case, seed): the analytic truth of ``groundsim.evaluation.synth`` (the scenario's
motion models, the reference gimbal pointing, the noise case), the default MAP estimator with
evidence-based model selection, the paper's closed form (first-order D, delta = 1) beside it, and
the Bayesian Cramer-Rao bound at the truth (``onboard.estimation.crb``).  Used by ``make bench``,
the foundation demo and the tests; the closed-loop evaluation with rendered frames is
``groundsim eval``.

Figures per run (all means over the window's points):
- ``err_range_pct``: ||X_hat - X|| / range (the range-normalised error, the table's headline);
- ``err_paper_pct``: ||X_hat - X|| / ||X|| with the scenario's world origin (the paper's metric);
- ``rmse_m``, ``crb_rms_m``; ``crb_err_range_pct``: the median ``err_range_pct`` an efficient estimator
  (errors distributed as the Bayesian CRB) would reach on this window -- the statistical floor;
- ``observable`` and ``range_sigma_ratio`` (the estimator's own verdict and its input), ``ambiguity``
  (posterior mass of far solutions), ``crb_range_sigma_pct`` (the bound's range sigma / range,
  median over the window: the smallest ratio an estimator knowing the motion model could report);
- ``beyond_3sigma``: fraction of points with ||e|| > 3 sqrt(trace P) (the honesty check);
- ``nees``: mean e^T P^-1 e (3 for a consistent 3-D covariance).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np

from groundsim.evaluation.report import PAPER_TABLE2_PCT, markdown_head
from groundsim.evaluation.synth import estimator_noise_model, synthesize_scenario
from groundsim.world.noise_cases import NoiseCase
from groundsim.world.scenario import Scenario
from onboard.core.errors import InputError
from onboard.estimation.crb import bayesian_crb
from onboard.estimation.map_estimator import EstimationError, MapEstimator
from onboard.estimation.metrics import evaluate

__all__ = [
    "CaseResult",
    "run_case",
    "run_cases",
    "summarise",
    "format_table",
    "verdict_rows",
    "format_verdict_table",
    "VERDICT_GOOD_PCT",
]


@dataclass(frozen=True)
class CaseResult:
    scenario: str
    noise: str
    seed: int
    err_range_pct: float
    err_paper_pct: float
    rmse_m: float
    crb_rms_m: float
    observable: bool
    range_sigma_ratio: float
    beyond_3sigma: float
    nees: float
    model: str
    q_m2ps3: float
    turn_rate_radps: float
    solve_ms: float
    paper_err_range_pct: float
    paper_solve_ms: float
    crb_err_range_pct: float = math.nan
    ambiguity: float = math.nan
    crb_range_sigma_pct: float = math.nan


def _paper_solve(obs):
    """The paper's closed form with its defaults (first-order D, delta = 1)."""
    from onboard.estimation.paper import PaperEstimator

    return PaperEstimator().solve(obs)


def run_case(
    scenario: Scenario,
    noise: NoiseCase,
    seed: int,
    with_paper: bool = True,
    with_crb: bool = True,
    with_efficient: bool = True,
) -> CaseResult:
    truth, obs = synthesize_scenario(scenario, noise, seed)
    est = MapEstimator(noise=estimator_noise_model(noise))
    t0 = time.perf_counter()
    try:
        res = est.solve(obs)
    except EstimationError:
        res = None
    solve_ms = (time.perf_counter() - t0) * 1e3
    if res is None:
        nan = math.nan
        e_rng = e_pap = rmse = crb = ratio = b3 = nees = nan
        observable, model, q, om = False, "failed", nan, nan
        crb_pct = amb = crb_sig = nan
    else:
        # the paper's world origin: the scenario's ENU/NED origin (on the ground under the observer start),
        # evaluate's default; a covariance it refuses scores the errors alone (NEES and honesty NaN)
        try:
            m = evaluate(truth.p_target_ned_m, res.p_ned_m, truth.p_cam_ned_m, res.cov_p_ned_m2)
        except InputError:
            m = evaluate(truth.p_target_ned_m, res.p_ned_m, truth.p_cam_ned_m)
        e_rng, e_pap, rmse = 100.0 * m.range_normalised_error, 100.0 * m.paper_relative_error, m.rmse_m
        b3 = math.nan if m.outside_3sigma_trace_fraction is None else m.outside_3sigma_trace_fraction
        nees = math.nan if m.mean_nees is None else m.mean_nees
        observable, ratio = res.observable, res.range_sigma_ratio
        model, q, om = res.model or "map", res.prior.q_horizontal_m2ps3, res.turn_rate_radps
        crb = crb_pct = crb_sig = math.nan
        if with_crb:
            bound = bayesian_crb(est, obs, truth.p_target_ned_m, res.prior, om)
            crb, crb_sig = bound.rms_m(), 100 * bound.range_sigma_ratio()
            if with_efficient:
                crb_pct = float(np.median(bound.efficient_error_range_pct(rng=np.random.default_rng(seed))))
        amb = res.ambiguity
    p_err, p_ms = math.nan, math.nan
    if with_paper:
        t1 = time.perf_counter()
        pres = _paper_solve(obs)
        p_ms = (time.perf_counter() - t1) * 1e3
        p_err = 100.0 * evaluate(truth.p_target_ned_m, pres.p_ned_m, truth.p_cam_ned_m).range_normalised_error
    return CaseResult(
        scenario.name,
        noise.name,
        seed,
        e_rng,
        e_pap,
        rmse,
        crb,
        bool(observable),
        ratio,
        b3,
        nees,
        model,
        q,
        om,
        solve_ms,
        p_err,
        p_ms,
        crb_pct,
        amb,
        crb_sig,
    )


def _run_one(args):
    scenario, noise, seed, with_paper, with_efficient = args
    return run_case(scenario, noise, seed, with_paper, with_efficient=with_efficient)


def run_cases(
    scenarios, noises, seeds, workers: int = 1, with_paper: bool = True, progress=None, with_efficient: bool = True
) -> list[CaseResult]:
    """All combinations; ``workers`` > 1 uses a process pool; ``progress(done, total)`` if given.  Ctrl-C
    raises KeyboardInterrupt here once the pool is terminated; its workers ignore SIGINT
    (:func:`~groundsim.evaluation.parallel.init_worker`), so none prints a traceback."""
    jobs = [(s, n, k, with_paper, with_efficient) for s in scenarios for n in noises for k in seeds]
    out: list[CaseResult] = []
    if workers > 1:
        import multiprocessing as mp

        from groundsim.evaluation.parallel import init_worker

        with mp.get_context("fork").Pool(workers, initializer=init_worker, initargs=(None, None, os.getpid())) as pool:
            for r in pool.imap(_run_one, jobs):
                out.append(r)
                if progress:
                    progress(len(out), len(jobs))
    else:
        for j in jobs:
            out.append(_run_one(j))
            if progress:
                progress(len(out), len(jobs))
    return out


def median_interval(values, level: float = 0.9, resamples: int = 2000) -> tuple[float, float]:
    """Bootstrap interval (percentile method) of the median of ``values`` at ``level``, NaNs dropped."""
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=float)
    if v.size == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(0)
    meds = np.median(v[rng.integers(0, v.size, (resamples, v.size))], axis=1)
    a = 100 * (1 - level) / 2
    lo, hi = np.percentile(meds, [a, 100 - a])
    return float(lo), float(hi)


def summarise(results: list[CaseResult]) -> list[dict]:
    """One row per (scenario, noise): medians over seeds (with a 90 % bootstrap interval for the headline),
    the RMSE pooled over seeds (the figure the CRB bounds), and the honesty counts."""
    rows = []
    keys = []
    for r in results:
        if (r.scenario, r.noise) not in keys:
            keys.append((r.scenario, r.noise))
    for sc, nz in keys:
        rs = [r for r in results if r.scenario == sc and r.noise == nz]

        def med(f, rs=rs):
            v = [getattr(r, f) for r in rs if math.isfinite(getattr(r, f))]
            return float(np.median(v)) if v else math.nan

        obs_runs = [r for r in rs if r.observable]
        rows.append(
            {
                "scenario": sc,
                "noise": nz,
                "runs": len(rs),
                "err_range_pct": med("err_range_pct"),
                "err_paper_pct": med("err_paper_pct"),
                "err_range_pct_interval": median_interval([r.err_range_pct for r in rs]),
                "rmse_m": med("rmse_m"),
                "crb_rms_m": med("crb_rms_m"),
                "rmse_pooled_m": float(np.sqrt(np.nanmean([r.rmse_m**2 for r in rs])))
                if any(math.isfinite(r.rmse_m) for r in rs)
                else math.nan,
                "crb_err_range_pct": med("crb_err_range_pct"),
                "observable_runs": len(obs_runs),
                "dishonest_runs": sum(1 for r in obs_runs if not (r.beyond_3sigma <= 0.01)),
                "nees": med("nees"),
                "paper_err_range_pct": med("paper_err_range_pct"),
                "solve_ms": med("solve_ms"),
                "models": ",".join(sorted({r.model for r in rs})),
                "err_range_pct_observable": float(np.median([r.err_range_pct for r in obs_runs]))
                if obs_runs
                else math.nan,
            }
        )
    return rows


def format_table(rows: list[dict]) -> str:
    """Markdown table of :func:`summarise` rows.  "efficient median" is what an estimator at the Bayesian
    CRB would reach on the same windows (the floor of the median column); RMSE is pooled over seeds."""
    lines = markdown_head(
        "| scenario | noise | runs | MAP err/range (median, 90 % interval) | efficient median | paper metric | "
        "RMSE m (pooled) | Bayesian CRB m | observable | "
        "honest (<=1% beyond 3 sigma) | NEES | paper closed form err/range | paper Table 2 |"
    )
    for r in rows:
        paper = PAPER_TABLE2_PCT.get(r["scenario"])
        lo, hi = r.get("err_range_pct_interval", (math.nan, math.nan))
        lines.append(
            f"| {r['scenario']} | {r['noise']} | {r['runs']} | {r['err_range_pct']:.2f} % ({lo:.2f}-{hi:.2f}) | "
            f"{r.get('crb_err_range_pct', math.nan):.2f} % | {r['err_paper_pct']:.2f} % | "
            f"{r.get('rmse_pooled_m', r['rmse_m']):.2f} | {r['crb_rms_m']:.2f} | {r['observable_runs']}/{r['runs']} | "
            f"{r['observable_runs'] - r['dishonest_runs']}/{r['observable_runs']} | {r['nees']:.1f} | "
            f"{r['paper_err_range_pct']:.0f} % | {f'{paper:.2f} %' if paper else '-'} |"
        )
    return "\n".join(lines)


#: the verdict table's "good run": mean error / range at most this, percent
VERDICT_GOOD_PCT = 2.0


def verdict_rows(results: list[CaseResult], good_pct: float = VERDICT_GOOD_PCT) -> list[dict]:
    """Precision and recall of the observability verdict per (scenario, noise).

    precision: the runs called observable, their median error / range and how many are honest (<= 1 %
    of points beyond 3 sqrt(trace P)); recall: of the runs whose error is <= ``good_pct``, the share
    called observable; honesty of every published result (observable or not); the evidence for a
    verdict that says no: the median reported range sigma ratio, the bound's (an estimator that knows
    the motion model) and the median ambiguity (posterior mass of far solutions).
    """
    rows = []
    keys = list(dict.fromkeys((r.scenario, r.noise) for r in results))
    for sc, nz in keys:
        rs = [r for r in results if (r.scenario, r.noise) == (sc, nz)]
        ok = [r for r in rs if r.model != "failed"]
        obs_runs = [r for r in ok if r.observable]
        good = [r for r in ok if r.err_range_pct <= good_pct]

        def med(vals):
            v = [x for x in vals if math.isfinite(x)]
            return float(np.median(v)) if v else math.nan

        rows.append(
            {
                "scenario": sc,
                "noise": nz,
                "runs": len(rs),
                "failed": len(rs) - len(ok),
                "observable": len(obs_runs),
                "err_observable_pct": med([r.err_range_pct for r in obs_runs]),
                "honest_observable": sum(1 for r in obs_runs if r.beyond_3sigma <= 0.01),
                "good": len(good),
                "good_observable": sum(1 for r in good if r.observable),
                "recall": (sum(1 for r in good if r.observable) / len(good)) if good else math.nan,
                "honest_all": sum(1 for r in ok if r.beyond_3sigma <= 0.01),
                "range_sigma_pct": med([100 * r.range_sigma_ratio for r in ok]),
                "crb_range_sigma_pct": med([r.crb_range_sigma_pct for r in ok]),
                "ambiguity": med([r.ambiguity for r in ok]),
                "err_pct": med([r.err_range_pct for r in ok]),
            }
        )
    return rows


def format_verdict_table(rows: list[dict], threshold_pct: float) -> str:
    """Markdown table of :func:`verdict_rows`; ``threshold_pct`` is the verdict's range-sigma threshold."""
    lines = markdown_head(
        "| scenario | noise | runs | called observable | their median err/range | honest (observable) | "
        f"runs with err <= {VERDICT_GOOD_PCT:g} % | recall | honest (all published) | median err/range | "
        f"reported range sigma (median; verdict < {threshold_pct:g} %) | CRB range sigma | ambiguity |"
    )
    for r in rows:
        rec = "-" if not r["good"] else f"{100 * r['recall']:.0f} %"
        eo = "-" if not r["observable"] else f"{r['err_observable_pct']:.2f} %"
        lines.append(
            f"| {r['scenario']} | {r['noise']} | {r['runs']} | {r['observable']} | {eo} | "
            f"{r['honest_observable']}/{r['observable']} | {r['good']} | {rec} | {r['honest_all']}/{r['runs'] - r['failed']} | "
            f"{r['err_pct']:.2f} % | {r['range_sigma_pct']:.1f} % | {r['crb_range_sigma_pct']:.1f} % | {r['ambiguity']:.2f} |"
        )
    return "\n".join(lines)
