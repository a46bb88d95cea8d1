"""A campaign's runs: their identity (:func:`run_id`, what resuming keys on), the plan of a spec's runs, one run's
figures (:func:`score_track`, pure) and the pure function that makes one job's runs (:func:`run_job`, what every
executor carries).  :mod:`groundsim.evaluation.campaign` describes the campaign, its metrics and its modes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from groundsim.evaluation.campaign_spec import CampaignSpec, Geometry
from groundsim.world.noise_cases import NoiseCase, load_noise_cases
from groundsim.world.scenario import Scenario, load_scenario, scenario_digest
from onboard.core.errors import ConfigError
from onboard.estimation.metrics import nees_per_point

__all__ = [
    "RESULT_SCHEMA",
    "RunParams",
    "run_id",
    "plan_runs",
    "settle_s",
    "score_track",
    "geometry_figures",
    "Job",
    "run_job",
    "run_row",
    "short_digest",
]

RESULT_SCHEMA = 1  # bump when a metric's definition changes: every run's id changes, nothing is reused
MIN_ASSUMED_PIXEL_SIGMA_PX = 0.05  # the estimator is never told "no pixel noise" (a zero weight is singular)


# --------------------------------------------------------------------------- runs and their identity


def short_digest(data: bytes) -> str:
    """12 hex digits of the SHA-256 of ``data``: a digest a run's id covers (noise case, onboard configuration)."""
    return hashlib.sha256(data).hexdigest()[:12]


@dataclass(frozen=True)
class RunParams:
    """Everything that determines one run's result (its identity, :func:`run_id`)."""

    mode: str
    scenario: str
    scenario_digest: str
    range_scale: float
    aspect_deg: float
    manoeuvre_scale: float
    noise: str
    noise_digest: str
    algorithm: str
    seed: int
    duration_s: float | None
    noise_model: str
    crb: bool
    onboard_digest: str
    schema: int = RESULT_SCHEMA

    @property
    def geometry(self) -> Geometry:
        return Geometry(self.range_scale, self.aspect_deg, self.manoeuvre_scale)

    def case_key(self) -> tuple:
        """The run's case: everything but the algorithm (runs of one case share observations and bound)."""
        d = dataclasses.asdict(self)
        d.pop("algorithm")
        return tuple(sorted(d.items()))


def run_id(params: RunParams) -> str:
    """Stable 16-hex id of a run: SHA-256 of its parameters as sorted JSON."""
    text = json.dumps(dataclasses.asdict(params), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def plan_runs(spec: CampaignSpec, onboard_digest: str) -> list[RunParams]:
    """Every run of the spec, in the table's order: scenario, geometry, noise, algorithm, seed."""
    cases = load_noise_cases()
    out = []
    for path in spec.scenario_paths:
        sdig = scenario_digest(path)  # what the file says: a comment or the layout edited reruns nothing
        sc_name = load_scenario(path).name
        for g in spec.geometries:
            for n in spec.noise:
                ndig = short_digest(repr(cases[n]).encode("utf-8"))
                for a in spec.algorithms:
                    for s in spec.seeds:
                        out.append(
                            RunParams(
                                spec.mode,
                                sc_name,
                                sdig,
                                g.range_scale,
                                g.aspect_deg,
                                g.manoeuvre_scale,
                                n,
                                ndig,
                                a,
                                int(s),
                                spec.duration_s,
                                spec.noise_model,
                                spec.crb,
                                onboard_digest,
                            )
                        )
    return out


# --------------------------------------------------------------------------- scoring (pure)


OBSERVABLE_AFTER_S = 5.0  # = groundsim.evaluation.scoring.OBSERVABLE_AFTER_S (the closed-loop windows)


def settle_s(duration_s: float) -> float:
    """Where the "settled" figures start: 5 s (the eval's window), or half the run when it is shorter than 10 s."""
    return min(OBSERVABLE_AFTER_S, 0.5 * float(duration_s))


def _nan_to_none(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def score_track(t_s, truth_p_ned_m, cam_p_ned_m, est_p_ned_m, est_cov_ned_m2, observable) -> dict:
    """One run's figures from its per-frame estimates (F frames; NaN rows = no estimate).

    ``err_range_observable_pct``: median over observable frames of ||e|| / range, per cent;
    ``err_range_published_settled_pct``: the same over every finite estimate at t >= :func:`settle_s` (5 s);
    ``err_range_final_pct``: at the last frame (NaN without an estimate there); ``rmse_observable_m``,
    ``rmse_published_settled_m``; ``observable_share_settled``: observable / all frames at t >= settle_s;
    ``beyond_3sigma_published``: fraction of finite estimates with ||e|| > 3 sqrt(trace cov);
    ``beyond_3sigma_observable``: the same over the observable ones (the confident wrong positions; NaN without);
    ``nees_observable`` / ``nees_published_settled``: mean e^T P^-1 e (3 when consistent);
    ``first_observable_s``.  Missing figures are NaN.
    """
    t = np.asarray(t_s, dtype=float)
    truth = np.asarray(truth_p_ned_m, dtype=float)
    est = np.asarray(est_p_ned_m, dtype=float)
    P = np.asarray(est_cov_ned_m2, dtype=float)
    obs_flag = np.asarray(observable, dtype=bool)
    F = t.size
    rel_t = t - t[0] if F else t
    has = np.all(np.isfinite(est), axis=1) & np.all(np.isfinite(P.reshape(F, 9)), axis=1)
    obs = has & obs_flag
    settle = settle_s(rel_t[-1] + (rel_t[1] - rel_t[0] if F > 1 else 0.0)) if F else OBSERVABLE_AFTER_S
    late = rel_t >= settle - 1e-9
    e_vec = est - truth
    e = np.linalg.norm(e_vec, axis=1)
    rng_m = np.linalg.norm(truth - np.asarray(cam_p_ned_m, dtype=float), axis=1)
    rel = 100.0 * e / rng_m
    nees = np.full(F, np.nan)
    nees[has] = nees_per_point(e_vec[has], P[has])
    with np.errstate(invalid="ignore"):
        sig3 = 3.0 * np.sqrt(np.maximum(np.einsum("fii->f", P), 0.0))
    nan = math.nan

    def med(sel):
        return float(np.median(rel[sel])) if sel.any() else nan

    def rms(sel):
        return float(np.sqrt(np.mean(e[sel] ** 2))) if sel.any() else nan

    def mean_finite(x):
        x = x[np.isfinite(x)]
        return float(np.mean(x)) if x.size else nan

    pub_late = has & late
    return {
        "frames": int(F),
        "published_frames": int(has.sum()),
        "observable_frames": int(obs.sum()),
        "settle_s": float(settle),
        "observable_share_settled": float((late & obs).sum() / late.sum()) if late.any() else nan,
        "err_range_observable_pct": med(obs),
        "err_range_published_settled_pct": med(pub_late),
        "err_range_final_pct": float(rel[-1]) if F and has[-1] else nan,
        "rmse_observable_m": rms(obs),
        "rmse_published_settled_m": rms(pub_late),
        "beyond_3sigma_published": float(np.mean(e[has] > sig3[has])) if has.any() else nan,
        "beyond_3sigma_observable": float(np.mean(e[obs] > sig3[obs])) if obs.any() else nan,
        "nees_observable": mean_finite(nees[obs]),
        "nees_published_settled": mean_finite(nees[pub_late]),
        "first_observable_s": float(rel_t[obs][0]) if obs.any() else nan,
    }


def geometry_figures(scenario: Scenario, seed: int, t_s) -> dict:
    """What a variant's geometry measures on its commanded paths: initial and median range, the observer's
    RMS acceleration (total, and normal to the line of sight: what makes range observable), the aspect
    at the start (angle between the target's velocity and its line of sight to the observer, degrees)."""
    t = np.asarray(t_s, dtype=float)
    o = scenario.observer_motion(seed).state(t)
    g = scenario.target_motion(seed).state(t)
    los = g.p_ned_m - o.p_ned_m
    r = np.linalg.norm(los, axis=1)
    u = los / r[:, None]
    a = o.a_ned_mps2
    a_perp = a - np.sum(a * u, axis=1)[:, None] * u
    v0 = g.v_ned_mps[0]
    sp = float(np.linalg.norm(v0))
    aspect = math.degrees(math.acos(float(np.clip(np.dot(v0, -u[0]) / sp, -1, 1)))) if sp > 1e-9 else math.nan
    return {
        "range_start_m": float(r[0]),
        "range_median_m": float(np.median(r)),
        "observer_accel_rms_mps2": float(np.sqrt(np.mean(np.sum(a**2, axis=1)))),
        "observer_accel_perp_los_rms_mps2": float(np.sqrt(np.mean(np.sum(a_perp**2, axis=1)))),
        "aspect_start_deg": aspect,
    }


# --------------------------------------------------------------------------- one job: a case, its algorithms (or one)


@dataclass(frozen=True)
class Job:
    """One case and the algorithms still to run on it, or one of them (:func:`_jobs`; all picklable: any executor
    can carry it)."""

    scenario: Scenario  # the variant
    noise: NoiseCase
    runs: tuple  # RunParams of the pending algorithms, same case
    base_config: Any  # OnboardConfig


def _assumed_config(cfg, noise: NoiseCase, noise_model: str):
    """The onboard configuration with the estimator's noise model set to the case (``noise_model: case``)."""
    if noise_model == "config":
        return cfg
    e = dataclasses.replace(
        cfg.estimator,
        pixel_sigma_px=max(float(noise.pixel_sigma_px), MIN_ASSUMED_PIXEL_SIGMA_PX),
        attitude_white_sigma_deg=math.degrees(noise.attitude_white_sigma_rad),
        attitude_bias_sigma_deg=math.degrees(noise.attitude_bias_sigma_rad),
        camera_position_white_sigma_m=noise.camera_position_white_sigma_m,
        camera_position_offset_sigma_m=noise.camera_position_offset_m / math.sqrt(3.0),
        camera_position_drift_sigma_mps=noise.camera_position_drift_mps / math.sqrt(3.0),
    )
    return dataclasses.replace(cfg, estimator=e)


def _case_bound(cfg, obs, truth) -> dict:
    """Whole-window MAP (model selection; a run over 60 s in windows: :mod:`onboard.estimation.windows`) and the
    Bayesian CRB at the truth with the prior it selected (each window's)."""
    from onboard.estimation.crb import bayesian_crb_in_windows
    from onboard.estimation.map_estimator import EstimationError, MapEstimator
    from onboard.estimation.metrics import evaluate
    from onboard.estimation.windows import DEFAULT_WINDOW_S, solve_in_windows

    nan = math.nan
    out = {
        "crb_rms_m": nan,
        "crb_range_sigma_pct": nan,
        "batch_err_range_pct": nan,
        "batch_observable": None,
        "bound_note": "",
    }
    est = MapEstimator(noise=cfg.estimator.noise_model())
    try:
        res = solve_in_windows(est.solve, obs, DEFAULT_WINDOW_S, est.config.min_frames)
    except (EstimationError, ConfigError, ValueError, np.linalg.LinAlgError) as exc:
        out["bound_note"] = f"batch MAP failed: {type(exc).__name__}: {' '.join(str(exc).split())}"
        return out
    out["batch_err_range_pct"] = (
        100.0 * evaluate(truth.p_target_ned_m, res.p_ned_m, truth.p_cam_ned_m).range_normalised_error
    )
    out["batch_observable"] = bool(res.observable)
    try:
        bound = bayesian_crb_in_windows(est, res, obs, truth.p_target_ned_m)
        out["crb_rms_m"] = bound.rms_m()
        out["crb_range_sigma_pct"] = 100 * bound.range_sigma_ratio()
    except (EstimationError, ValueError, np.linalg.LinAlgError) as exc:
        out["bound_note"] = f"CRB failed: {type(exc).__name__}: {' '.join(str(exc).split())}"
    return out


def _frame_times(scenario: Scenario, duration_s: float | None) -> np.ndarray:
    t = scenario.frame_times_s()
    if duration_s is not None:
        t = t[t < duration_s - 1e-9]
    return t


def _run_synthetic(job: Job) -> list[dict]:
    from groundsim.evaluation.eval import onboard_config_for
    from groundsim.evaluation.synth import synthesize_scenario
    from onboard.pipeline.plugins import build

    p0 = job.runs[0]
    sc, noise, seed = job.scenario, job.noise, p0.seed
    c0 = time.perf_counter()
    t = _frame_times(sc, p0.duration_s)
    truth, obs = synthesize_scenario(sc, noise, seed, t_s=t)
    # every algorithm of the case reads the same observations: read-only, so that one writing into its inputs
    # fails its own frames and cannot move the next algorithm's row
    for a in (obs.t_s, obs.uv_px, obs.p_cam_ned_m, obs.q_ned_from_cam):
        a.setflags(write=False)
    cfg = _assumed_config(onboard_config_for(sc, job.base_config), noise, p0.noise_model)
    case = geometry_figures(sc, seed, t)
    case.update(_case_bound(cfg, obs, truth) if p0.crb else {})
    K = sc.camera.intrinsics
    F = len(obs)
    rows = []
    for params in job.runs:
        w0 = time.perf_counter()
        est_p, est_P, observable = np.full((F, 3), np.nan), np.full((F, 3, 3), np.nan), np.zeros(F, dtype=bool)
        errors = 0
        first_error = ""
        try:
            est = build(params.algorithm, cfg, option="algorithms")
            for k in range(F):
                try:
                    uv = (float(obs.uv_px[k, 0]), float(obs.uv_px[k, 1]))  # a tuple, as the pipeline passes it
                    e = est.add(float(obs.t_s[k]), uv, K, obs.p_cam_ned_m[k], obs.q_ned_from_cam[k])
                except Exception as exc:  # noqa: BLE001 - as the pipeline: the frame goes on without 3-D
                    errors += 1
                    first_error = first_error or f"{type(exc).__name__}: {' '.join(str(exc).split())}"
                    continue
                if e is None:
                    continue
                try:
                    p, P = np.asarray(e.p_ned_m, dtype=float), np.asarray(e.cov_p_ned_m2, dtype=float)
                    bad = "" if p.shape == (3,) and P.shape == (3, 3) else f"position {p.shape}, covariance {P.shape}"
                    if not bad and not (np.all(np.isfinite(p)) and np.all(np.isfinite(P))):
                        bad = "a position or covariance that is not finite"
                    if not bad:
                        est_p[k], est_P[k], observable[k] = p, P, bool(e.observable)
                except Exception as exc:  # noqa: BLE001 - an estimate without the protocol's fields or numbers
                    bad = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
                if bad:  # the pipeline does not publish such an estimate, and counts it: so does the row
                    errors += 1
                    first_error = first_error or f"invalid estimate: {bad}"
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # noqa: BLE001 - a plug-in that cannot be built or exits fails its runs alone
            rows.append(_failed_row(params, exc, w0, case))
            continue
        m = score_track(truth.t_s, truth.p_target_ned_m, truth.p_cam_ned_m, est_p, est_P, observable)
        m.update(case)
        m.update(status="ok", error=first_error, estimator_errors=errors, wall_s=time.perf_counter() - w0)
        rows.append(run_row(params, m))
    wall = time.perf_counter() - c0
    for r in rows:
        r["case_wall_s"] = wall
    return rows


def _failed_row(params, exc: BaseException, w0: float, case: dict | None = None) -> dict:
    """The row of a run that could not be made: status failed, the exception on one line naming the algorithm
    (a plug-in's SystemExit included: in a pool worker it had ended the worker and hung the campaign), its wall
    time."""
    error = f"{type(exc).__name__} in algorithm {params.algorithm}: {' '.join(str(exc).split())}"
    return run_row(params, {**(case or {}), "status": "failed", "error": error, "wall_s": time.perf_counter() - w0})


#: a closed-loop run's counters of the estimator's frames that gave no estimate because it failed: raised, was refused
#: its inputs, gave an estimate not fit to publish (the pipeline's), or raised in the perfect-centroid baseline
ESTIMATOR_ERROR_COUNTERS = (
    "estimator_error",
    "estimator_input",
    "estimator_output_invalid",
    "baseline_estimator_error",
)


def _run_closed_loop(job: Job) -> list[dict]:
    from groundsim.evaluation.eval import EvalOptions, run_lockstep
    from groundsim.evaluation.scoring import score_run
    from groundsim.world.nav_errors import InjectedErrors

    rows = []
    for params in job.runs:
        w0 = time.perf_counter()
        opts = EvalOptions(
            duration_s=params.duration_s,
            batch=params.crb,
            keep_frame=False,
            injected=InjectedErrors(job.noise.name),
            estimator=params.algorithm,
        )
        try:
            r = run_lockstep(job.scenario, params.seed, opts, job.base_config)
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # noqa: BLE001 - a run that cannot be made (flight envelope, plug-in) fails alone
            rows.append(_failed_row(params, exc, w0))
            continue
        s = score_run(r)
        m = score_track(r.t_s, r.truth_p_ned_m, r.cam_p_ned_m, r.est_p_ned_m, r.est_cov_ned_m2, r.observable)
        m.update(geometry_figures(job.scenario, params.seed, r.t_s - r.t_s[0]))
        b = s.get("batch") or {}
        bm = (b.get("pipeline") or {}).get("metrics") or {}
        perception = s.get("perception") or {}
        m.update(
            pd_pct=perception.get("pd_pct"),
            false_tracks_per_min=perception.get("false_tracks_per_min"),
            id_switches=perception.get("id_switches"),
            state_accuracy=perception.get("state_accuracy"),
        )
        m.update(
            crb_rms_m=b.get("crb_rms_m"),
            crb_range_sigma_pct=math.nan,
            batch_err_range_pct=bm.get("err_range_pct"),
            batch_observable=(b.get("pipeline") or {}).get("observable"),
            published_share_after_3s=s["closed_loop"]["published_share_after_3s"],
            chain_centroid_sigma_px=s.get("chain_centroid_sigma_px"),
            status="ok",
            error=", ".join(f"{k} {r.counters[k]}" for k in ESTIMATOR_ERROR_COUNTERS if r.counters.get(k)),
            estimator_errors=sum(int(r.counters.get(k, 0)) for k in ESTIMATOR_ERROR_COUNTERS),
            wall_s=time.perf_counter() - w0,
        )
        rows.append(run_row(params, m))
    for row in rows:
        row["case_wall_s"] = sum(x["wall_s"] for x in rows)
    return rows


def run_row(params: RunParams, metrics: dict) -> dict:
    row = {"run_id": run_id(params)}
    row.update(dataclasses.asdict(params))
    row["geometry"] = params.geometry.label
    row.update(metrics)
    return {
        k: _nan_to_none(float(v) if isinstance(v, (np.floating, np.integer)) and not isinstance(v, np.bool_) else v)
        for k, v in row.items()
    }


def run_job(job: Job) -> list[dict]:
    """Run one case's pending algorithms; one row (dict, JSON-ready) per run.  Never raises for a run's
    own failure: that run's row says ``status: failed`` and why."""
    if job.runs[0].mode == "closed_loop":
        return _run_closed_loop(job)
    return _run_synthetic(job)
