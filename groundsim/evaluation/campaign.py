"""``python -m groundsim campaign SPEC.yaml``: a sweep of runs, one tidy table, resumable, and its report.

A campaign crosses scenarios (and variants of their geometry), navigation-noise cases
(``config/noise_cases.yaml``), trajectory-estimator plug-ins (``onboard.pipeline.plugins``) and run seeds.
The spec file's schema is in ``docs/campaigns.md``; :func:`load_spec` validates it completely before
anything runs (errors are one line ``<spec>: <field>: expected <what>, got <value>``, exit 2).

Geometry variants (:func:`derive_scenario`) are made from a reference scenario's motion models, so
every model (straight, accelerating, cubic, circle, figure-eight, waypoints, Singer-disturbed) works:

- ``range_scale`` k: the target's whole path is moved along the initial line of sight, by
  ``(k - 1) (p_target(0) - p_observer(0))``: the initial range is k times the reference's, the
  target's motion (speed, turns) unchanged, so the bearing rates shrink roughly as 1/k;
- ``aspect_deg`` psi: the target's path is rotated about the vertical through its start point by psi
  (positive from north towards east): the same speed and manoeuvre, another heading relative to the
  line of sight (the aspect);
- ``manoeuvre_scale`` m: the observer's acceleration history is multiplied by m, from the same start
  position and velocity: ``p(t) = p0 + v0 t + m (p_ref(t) - p0 - v0 t)``.  m = 0 is the straight line
  at constant velocity (no range information from the observer's motion), m = 1 the reference.

``(1, 0, 1)`` is the reference scenario itself, unchanged (same name, same runs as ``groundsim eval``).

Modes.  ``synthetic`` (default; fast): the analytic truth and noisy observations of
:func:`groundsim.evaluation.synth.synthesize_scenario` (the noise case's pixel and navigation errors) fed frame by
frame to the plug-in through its step interface (``add``), exactly as the daemon's pipeline would feed
it; the estimator assumes the noise case (``noise_model: case``, the pixel sigma floored at
:data:`MIN_ASSUMED_PIXEL_SIGMA_PX`) or the onboard configuration's model (``noise_model: config``).
``closed_loop``: :func:`groundsim.evaluation.eval.run_lockstep` (JSBSim, rendered frames, the image chain, the
noise case as the telemetry's navigation errors, the shipped daemon configuration).

Metrics of a run (:func:`score_track`, the same for both modes; the closed-loop windows of the eval):
median err/range on observable frames, median err/range of every published (finite) estimate after
5 s (half the run when it is shorter than 10 s: :func:`settle_s`), err/range at the last frame, RMSE,
observable share after that, honesty (fraction of published
estimates beyond 3 sqrt(trace cov); a run is honest at <= 1 %), mean NEES, first observable time.
The bound: the Bayesian CRB (``onboard.estimation.crb``) of the case's window, at the truth, with the
motion prior a whole-window MAP solve selects (synthetic: computed once per case and shared by its
algorithms; closed loop: ``groundsim eval``'s batch columns); ``crb_range_sigma_pct`` is the smallest
range sigma an estimator knowing the motion model could report.

Resumability.  A run is identified by :func:`run_id`, a SHA-256 of its parameters (scenario and the
digest of what its file says (:func:`~groundsim.world.scenario.scenario_digest`: not its comments or layout), geometry, noise case and the digest of its numbers, algorithm, seed, mode, duration,
noise model, the onboard configuration's digest, :data:`RESULT_SCHEMA`).  Each finished run is appended
to ``OUT/runs.jsonl`` as one line, flushed and fsynced, the moment its result arrives; a new invocation
reads it (a line cut short by a kill, damaged, or not a run's row is skipped, one warning names the
lines, and their runs are redone) and runs only what is missing.  ``runs.csv`` (and
``runs.parquet`` when pyarrow is installed), ``report.md`` and ``manoeuvre.png`` are rebuilt from the
log every time, in the spec's order, so the table does not depend on the order runs finished in, nor
on interruptions.

Execution.  One *job* is a case (scenario variant, noise case, seed): it synthesises once, computes the
bound once and runs each pending algorithm.  :func:`run_job` is a pure function of a picklable job.
Jobs go to a local process pool (forkserver, one BLAS thread per worker), or, with ``--workers 1``, run
in this process, or, with ``--scheduler tcp://HOST:PORT``, to the workers of a Dask distributed cluster
(``dask scheduler`` / ``dask worker``; docs/campaigns.md).  Pool and cluster take one path: every job
submitted as a future, the rows taken as each completes and appended by this process (the coordinator)
with :func:`append_rows`; workers never see the output directory, so the log, the resumption and the
table are the same whichever executor ran the jobs.  Before submitting, the coordinator asks every
connected worker for its :func:`code_fingerprint` and refuses workers running other irtrack code.
A tqdm bar counts runs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from groundsim.evaluation.campaign_report import (
    COLUMN_ORDER,
    FIGURE_NAME,
    PARQUET_NAME,
    REPORT_NAME,
    TABLE_NAME,
    write_report,
    write_table,
)
from groundsim.evaluation.campaign_spec import (
    CampaignSpec,
    Geometry,
    derive_scenario,
    load_spec,
)
from groundsim.evaluation.out_dir import make_out_dir, refuse_foreign_out, write_replacing
from groundsim.evaluation.parallel import (
    auto_deadline_s,
    check_run_timeout,
    finish_pool,
    limit_blas_threads,
    pool_results,
    pool_workers,
    progress_bar,
    quiet_run_logs,
    start_pool,
    stop_pool,
)
from groundsim.io.stop_signals import finish_despite_signals, first_signal_stops, signals_held
from groundsim.world.noise_cases import NoiseCase, load_noise_cases
from groundsim.world.scenario import Scenario, load_scenario, scenario_digest
from onboard.core.errors import ConfigError
from onboard.estimation.metrics import nees_per_point

__all__ = [
    "LOG_NAME",
    "MARK_NAME",
    "check_same_campaign",
    "RESULT_SCHEMA",
    "RunParams",
    "run_id",
    "plan_runs",
    "score_track",
    "run_job",
    "read_log",
    "reusable_rows",
    "append_rows",
    "check_outputs",
    "run_campaign",
    "CampaignResult",
    "cmd_campaign",
    "code_fingerprint",
    "check_workers",
    "check_scheduler_address",
]

log = logging.getLogger(__name__)

RESULT_SCHEMA = 1  # bump when a metric's definition changes: every run's id changes, nothing is reused
MIN_ASSUMED_PIXEL_SIGMA_PX = 0.05  # the estimator is never told "no pixel noise" (a zero weight is singular)
LOG_NAME = "runs.jsonl"
MARK_NAME = "campaign.json"  # which campaign's runs the folder's log holds: {"name": ..., "spec": ...}
SCHEDULER_CONNECT_TIMEOUT_S = 10.0  # --scheduler: how long to wait for the Dask scheduler to answer


# --------------------------------------------------------------------------- runs and their identity


def _digest(data: bytes) -> str:
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
                ndig = _digest(repr(cases[n]).encode("utf-8"))
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
        rows.append(_row(params, m))
    wall = time.perf_counter() - c0
    for r in rows:
        r["case_wall_s"] = wall
    return rows


def _failed_row(params, exc: BaseException, w0: float, case: dict | None = None) -> dict:
    """The row of a run that could not be made: status failed, the exception on one line naming the algorithm
    (a plug-in's SystemExit included: in a pool worker it had ended the worker and hung the campaign), its wall
    time."""
    error = f"{type(exc).__name__} in algorithm {params.algorithm}: {' '.join(str(exc).split())}"
    return _row(params, {**(case or {}), "status": "failed", "error": error, "wall_s": time.perf_counter() - w0})


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
        rows.append(_row(params, m))
    for row in rows:
        row["case_wall_s"] = sum(x["wall_s"] for x in rows)
    return rows


def _row(params: RunParams, metrics: dict) -> dict:
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


# --------------------------------------------------------------------------- the append-only log


#: columns of a log row that hold text, and flags (true, false or null); the table's other columns hold numbers or
#: null: the report sorts, compares and takes medians of them, so a row with another type there is not reused
_TEXT_COLUMNS = frozenset(
    {"run_id", "mode", "scenario", "geometry", "noise", "algorithm", "noise_model", "status", "error", "bound_note"}
    | {"scenario_digest", "noise_digest", "onboard_digest"}
)
_FLAG_COLUMNS = frozenset({"crb", "batch_observable"})
_NUMBER_COLUMNS = frozenset(COLUMN_ORDER) - _TEXT_COLUMNS - _FLAG_COLUMNS
_STATUSES = ("ok", "failed")
_PARAM_FIELDS = tuple(f.name for f in dataclasses.fields(RunParams))
#: at most this many line numbers are listed in the warning about skipped lines (the count is always given)
_LINES_SHOWN = 10


def _not_a_row(row: Any) -> bool:
    """Whether a parsed log line is not a row :func:`append_rows` could have written: an object whose ``run_id``
    is text, and whose known columns hold their type (other keys are left alone: a newer version's columns)."""
    if not isinstance(row, dict) or not isinstance(row.get("run_id"), str):
        return True
    for key, value in row.items():
        if key in _TEXT_COLUMNS:
            ok = isinstance(value, str) and (key != "status" or value in _STATUSES)
        elif key in _FLAG_COLUMNS:
            ok = value is None or isinstance(value, bool)
        elif key in _NUMBER_COLUMNS:
            ok = value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
        else:
            continue
        if not ok:
            return True
    return False


def _is_row_of(row: dict, rid: str) -> bool:
    """Whether ``row`` is the result of run ``rid``: it carries the run's parameters, which hash to ``rid``, and the
    columns every row of the table and the report has."""
    if any(key not in row for key in (*_PARAM_FIELDS, "geometry", "status")):
        return False
    return run_id(RunParams(**{key: row[key] for key in _PARAM_FIELDS})) == rid


def _scan_log(path: Path, planned: frozenset[str] = frozenset()) -> tuple[dict[str, dict], list[int]]:
    """``runs.jsonl`` -> ({run_id: row}, [numbers of the lines skipped]); a later row of a run replaces an earlier
    one (``--retry-failed`` appends).  Read as bytes, line by line, so a line that is not UTF-8, not JSON or not a
    row (:func:`_not_a_row`) is skipped without stopping the others; a row under a ``planned`` run id must be that
    run's (:func:`_is_row_of`), so a damaged one cannot replace a good one before it."""
    done: dict[str, dict] = {}
    bad: list[int] = []
    if not path.is_file():
        return done, bad
    try:
        with path.open("rb") as f:
            for number, raw in enumerate(f, start=1):
                if not raw.strip():
                    continue
                try:
                    row = json.loads(raw.decode("utf-8"))
                except (ValueError, RecursionError):  # not UTF-8 (UnicodeDecodeError is one), not JSON, too deep
                    bad.append(number)
                    continue
                if _not_a_row(row) or (row["run_id"] in planned and not _is_row_of(row, row["run_id"])):
                    bad.append(number)
                    continue
                done[row["run_id"]] = row
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return done, bad


def read_log(path: Path) -> tuple[dict[str, dict], int]:
    """``runs.jsonl`` -> ({run_id: row}, lines skipped).  A torn or foreign line is skipped, not fatal."""
    done, bad = _scan_log(path)
    return done, len(bad)


def reusable_rows(path: Path, planned_ids: Iterable[str]) -> tuple[dict[str, dict], list[int]]:
    """The rows of the log a campaign of ``planned_ids`` can reuse, and the numbers of the lines skipped: those
    :func:`read_log` skips, and rows under a planned run id that are not that run's (:func:`_is_row_of`)."""
    return _scan_log(path, frozenset(planned_ids))


def _skipped_text(path: Path, lines: list[int]) -> str:
    shown = ", ".join(map(str, lines[:_LINES_SHOWN])) + (", ..." if len(lines) > _LINES_SHOWN else "")
    return (
        f"{path}: {len(lines)} line(s) skipped, not a run's row (line {shown}): cut short by an interruption, "
        "damaged or written by something else; any run they held is run again"
    )


def append_rows(path: Path, rows: Iterable[dict]) -> None:
    """Append rows to the log, one JSON line each, flushed and fsynced (a kill loses no finished run).
    An OSError (the log unwritable, the disk full) is a one-line ConfigError naming the file."""
    try:
        with path.open("a+b") as f:
            # a line cut short by a kill has no newline: ended here, so the row written next is a line of its
            # own (glued onto the fragment it was lost with it, and reading the log skipped both)
            if f.seek(0, os.SEEK_END) > 0:
                f.seek(-1, os.SEEK_END)
                if f.read(1) != b"\n":
                    f.write(b"\n")
        with path.open("a", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(row, sort_keys=True, allow_nan=False) + "\n")
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write: {exc.strerror or exc}") from None


def check_outputs(out: Path) -> None:
    """Refuses, before any run, outputs that could not be written after the runs: the log must open for
    appending, and the table, the report and the figure must not be directories (one-line ConfigError)."""
    for name in (LOG_NAME, MARK_NAME, TABLE_NAME, PARQUET_NAME, REPORT_NAME, FIGURE_NAME):
        if (out / name).is_dir():
            raise ConfigError(f"{out / name}: cannot write: Is a directory")
    append_rows(out / LOG_NAME, ())


def _held_campaign(out: Path) -> tuple[str, str] | None:
    """(name, spec file) of the campaign whose runs ``out``'s log holds, None when it holds none (no log, or one
    emptied by ``--fresh``): read from :data:`MARK_NAME`, or, in a folder written before it existed, from the
    report's title (the spec file then unknown)."""
    log_path = out / LOG_NAME
    if not log_path.is_file() or log_path.stat().st_size == 0:
        return None
    try:
        mark = json.loads((out / MARK_NAME).read_text(encoding="utf-8"))
        if isinstance(mark, dict) and isinstance(mark.get("name"), str):
            return mark["name"], str(mark.get("spec", "?"))
    except (OSError, ValueError):
        pass
    try:
        with (out / REPORT_NAME).open(encoding="utf-8") as f:
            title = f.readline().strip()
    except (OSError, ValueError):
        return None
    prefix = "# Campaign "
    return (title[len(prefix) :], "unknown") if title.startswith(prefix) else None


def check_same_campaign(out: Path, spec: CampaignSpec) -> None:
    """ConfigError naming ``out`` and both campaigns when its log holds another campaign's runs: its table and
    report would be this one's while its log held both, and each campaign run there in turn would overwrite the
    other's.  A campaign is its name (what names its default folder): a spec edited (a seed added) or moved
    keeps resuming its folder."""
    held = _held_campaign(out)
    if held is None or held[0] == spec.name:
        return
    raise ConfigError(
        f"--out {out}: holds the runs of campaign {held[0]!r} (spec {held[1]}), not of {spec.name!r} "
        f"(spec {spec.source}); give another --out, or --fresh to forget the runs of {held[0]!r} and start "
        f"{spec.name!r} there"
    )


def _mark_campaign(out: Path, spec: CampaignSpec) -> None:
    """Record in ``out`` that its log is ``spec``'s campaign's (:func:`check_same_campaign` reads it)."""
    text = json.dumps({"name": spec.name, "spec": str(spec.source)}, indent=1) + "\n"
    try:
        write_replacing(out / MARK_NAME, lambda p: p.write_text(text, encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{out / MARK_NAME}: cannot write: {exc.strerror or exc}") from None


# --------------------------------------------------------------------------- execution


#: what the campaign's fork server imports once for its workers
CAMPAIGN_PRELOAD = ("groundsim.evaluation.campaign", "groundsim.evaluation.eval", "onboard.estimation.sliding")


@dataclass(frozen=True)
class CampaignResult:
    """What one invocation did: ``planned`` runs, ``reused`` from the log, ``ran`` now (``failed`` of
    them), ``wall_s`` of the runs' execution, ``workers``, ``interrupted``, and the files written."""

    planned: int
    reused: int
    ran: int
    failed: int
    wall_s: float
    workers: int
    interrupted: bool
    files: dict = field(default_factory=dict)


def _jobs(spec: CampaignSpec, runs: list[RunParams], base_config) -> list[Job]:
    """The runs as jobs: a synthetic case's algorithms in one (they share its observations and bound), a closed-loop
    run alone (its flight is its own: one job a case had a plug-in that hangs or ends its worker lose the case's
    other algorithms' finished runs with its own)."""
    cases = load_noise_cases()
    scen = {}
    for p in spec.scenario_paths:
        sc = load_scenario(p)
        scen[sc.name] = sc
    groups: dict[tuple, list[RunParams]] = {}
    for r in runs:
        key = r.case_key() if r.mode != "closed_loop" else (r.case_key(), r.algorithm)
        groups.setdefault(key, []).append(r)
    jobs = []
    for rs in groups.values():
        r0 = rs[0]
        variant = derive_scenario(scen[r0.scenario], r0.geometry)
        jobs.append(Job(variant, cases[r0.noise], tuple(rs), base_config))
    return jobs


def check_scheduler_address(scheduler: str) -> None:
    """ConfigError naming ``--scheduler`` unless it is ``PROTOCOL://HOST:PORT`` with a port 1-65535 (an IPv6
    host in brackets): dask reads a malformed one as an address it cannot reach, so the mistake surfaced as a
    timeout after 20 s, as a traceback."""
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(scheduler)
        port = parts.port
    except ValueError as exc:  # a port that is not a number or beyond 65535, an unclosed IPv6 bracket
        why = str(exc)
    else:
        checks = (
            ("://" in scheduler, "no protocol"),
            (bool(parts.hostname), "no host"),
            (port is not None and 1 <= port <= 65535, "no port in 1-65535"),
            (not (parts.path or parts.query or parts.fragment), "more after the port"),
        )
        why = next((w for ok, w in checks if not ok), "")
    if why:
        raise ConfigError(f"--scheduler: expected an address tcp://HOST:PORT, got {scheduler!r} ({why})")


def _cluster_client(scheduler: str):
    """A ``distributed.Client`` on ``scheduler`` (``tcp://HOST:PORT``); ConfigError naming ``--scheduler``
    when dask is missing, the address is malformed or nothing answers there."""
    check_scheduler_address(scheduler)
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--scheduler: needs dask.distributed (pip install 'irtrack[sim]')") from None
    try:
        client = Client(scheduler, timeout=SCHEDULER_CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ConfigError(
            f"--scheduler {scheduler}: no scheduler answered within {SCHEDULER_CONNECT_TIMEOUT_S:g} s "
            f"({type(exc).__name__}: {' '.join(str(exc).split())})"
        ) from None
    return client


def code_fingerprint() -> str:
    """Digest of the irtrack code a process runs (every ``.py`` under ``onboard/`` and ``groundsim/`` as
    imported, path and bytes), so a coordinator can refuse cluster workers running other code."""
    import onboard

    h = hashlib.sha256()
    groundsim_root = Path(__file__).resolve().parents[1]  # this module is groundsim/evaluation/campaign.py
    for root in (Path(onboard.__file__).resolve().parent, groundsim_root):
        for f in sorted(root.rglob("*.py")):
            h.update(str(f.relative_to(root.parent)).encode("utf-8") + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def _remote_job(job: Job) -> list[dict]:
    """:func:`run_job` on a cluster worker, with one BLAS thread (as the local pool's initializer sets)."""
    limit_blas_threads(1)
    return run_job(job)


def check_workers(client, scheduler: str) -> int:
    """Threads the cluster offers; ConfigError when it has none or a worker runs other irtrack code."""
    nthreads = client.nthreads()
    if not nthreads:
        raise ConfigError(
            f"--scheduler {scheduler}: the scheduler has no workers (start some: dask worker {scheduler})"
        )
    mine = code_fingerprint()
    theirs = client.run(code_fingerprint)
    other = sorted(w for w, fp in theirs.items() if fp != mine)
    if other:
        raise ConfigError(
            f"--scheduler {scheduler}: worker(s) {', '.join(other)} run other irtrack code than this "
            f"coordinator (fingerprint {mine}); install the same checkout there"
        )
    return sum(nthreads.values())


def _deadline_s(job: Job, run_timeout_s: float | None) -> float:
    """A job's deadline on a pool: ``--run-timeout``, else the automatic one for its runs' flights."""
    if run_timeout_s is not None:
        return run_timeout_s
    d = job.runs[0].duration_s
    return auto_deadline_s(job.scenario.duration_s if d is None else d, len(job.runs))


def _lost_rows(job: Job, why: str) -> list[dict]:
    """The failed rows of a job whose pool worker ended under it (a plug-in's os._exit, a crash)."""
    return [_row(p, {"status": "failed", "error": f"WorkerLost in algorithm {p.algorithm}: {why}"}) for p in job.runs]


def run_campaign(
    spec: CampaignSpec,
    out: Path,
    workers: int = 2,
    progress: bool = True,
    fresh: bool = False,
    retry_failed: bool = False,
    base_config=None,
    onboard_digest: str = "defaults",
    scheduler: str | None = None,
    run_timeout_s: float | None = None,
) -> CampaignResult:
    """Plan, skip what the log has, run the rest, append each case's rows as they come, then rebuild the
    table and the report.  Ctrl-C stops cleanly: the runs finished so far are kept, the table and report
    show them, and the same command resumes.

    Executors: ``workers`` processes of a local pool (1 = in this process), or, with ``scheduler``
    (``tcp://HOST:PORT``), the workers of a Dask distributed cluster (``workers`` is then the threads the
    cluster offers).  Pool and cluster share one path: every job is submitted as a future, results are
    taken as they complete and appended here; workers never touch ``out``.  ``run_timeout_s``: each job's
    wall-clock deadline on a local pool, its runs failed past it (None: per run 20 x its simulated seconds + 120 s,
    summed over the job's runs); not enforced in this process or on a cluster."""
    run_timeout_s = check_run_timeout(run_timeout_s)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / LOG_NAME
    check_outputs(out)
    if not fresh:  # before anything runs or is written: another campaign's folder is refused as it is
        check_same_campaign(out, spec)
    planned = plan_runs(spec, onboard_digest)
    ids = [run_id(p) for p in planned]
    client = None
    if scheduler is not None:  # before --fresh removes anything: a wrong address or cluster changes nothing
        client = _cluster_client(scheduler)
        try:
            workers = check_workers(client, scheduler)
        except BaseException:
            client.close()
            raise
    try:
        if fresh and log_path.exists():
            # emptied, not removed: the folder stays a campaign's (refuse_foreign_out reads the log's presence),
            # so the same command run again after an interruption before the first result still resumes it
            log_path.write_bytes(b"")
        _mark_campaign(out, spec)
        done, bad = reusable_rows(log_path, ids)
        if bad:  # said once: the log is read again below for the table, its skipped lines not repeated
            log.warning("%s", _skipped_text(log_path, bad))
        if retry_failed:
            done = {k: v for k, v in done.items() if v.get("status") == "ok"}
        pending = [p for p, i in zip(planned, ids) if i not in done]
        reused = len(planned) - len(pending)
        jobs = _jobs(spec, pending, base_config)
    except BaseException:
        if client is not None:
            client.close()
        raise
    limit_blas_threads(1)
    if client is not None:
        where = f"the cluster at {scheduler}"
    else:
        workers = max(1, min(workers, len(jobs))) if jobs else 1
        where = "this process" if workers == 1 else "a local process pool"
    log.info(
        "campaign %s: %d runs planned, %d already done, %d to run in %d jobs on %d worker(s) (%s)",
        spec.name,
        len(planned),
        reused,
        len(pending),
        len(jobs),
        workers,
        where,
    )
    bar = None
    ran = failed = 0
    interrupted = False
    t0 = time.perf_counter()
    pool = None
    futures: list = []
    received: list[int] = []
    with contextlib.ExitStack() as finishing:
        try:
            if progress and pending:
                bar = progress_bar(len(pending), "run", f"campaign {spec.name} ({workers} worker(s))")
            if client is not None:  # submit every job, take them as they complete
                import uuid

                from distributed import as_completed

                batch = uuid.uuid4().hex[:8]
                futures = [
                    client.submit(_remote_job, j, key=f"irtrack-{spec.name}-{batch}-{k}", pure=False)
                    for k, j in enumerate(jobs)
                ]
                results = (f.result() for f in as_completed(futures, loop=client.loop))
            elif workers > 1:  # the same, on a local pool
                # every worker started before Ctrl-C is taken (a half-started forkserver worker printed a traceback)
                pool, _ = start_pool(workers, CAMPAIGN_PRELOAD, progress=False)
                results = (
                    rows
                    for _, rows in pool_results(
                        pool, run_job, jobs, on_lost=_lost_rows, deadline_s=lambda j: _deadline_s(j, run_timeout_s)
                    )
                )
            else:
                results = (run_job(j) for j in jobs)
            for rows in results:
                with signals_held():  # logged and counted together: the interrupted line's count is the log's
                    append_rows(log_path, rows)
                    ran += len(rows)
                    failed += sum(1 for r in rows if r.get("status") != "ok")
                if bar is not None:
                    bar.update(len(rows))
                    bar.set_postfix_str(
                        f"{rows[0]['scenario']} {rows[0]['geometry']} {rows[0]['noise']} seed {rows[0]['seed']}"
                    )
            if pool is not None:
                finish_pool(pool)
                pool = None
        except KeyboardInterrupt:
            interrupted = True
        finally:
            # from here on a signal is noted, not raised: a second Ctrl-C (or a SIGTERM) had cut the table short
            # and lost the finished runs' report; the runs it stops are already stopped
            received = finishing.enter_context(finish_despite_signals("the table and the report"))
            # interrupted or failed: drop what is still queued or running (its runs are redone on resume)
            if pool is not None:
                stop_pool(pool)
            if client is not None:
                try:
                    if futures:
                        client.cancel(futures)
                finally:
                    client.close()
            if bar is not None:
                bar.close()
        wall = time.perf_counter() - t0
        done, _ = reusable_rows(log_path, ids)
        rows = [done[i] for i in ids if i in done]
        result = CampaignResult(len(planned), reused, ran, failed, wall, workers, interrupted)
        try:
            files = write_table(out, rows)
            files.update(write_report(out, spec, rows, dataclasses.asdict(result)))  # the report states these counts
        except OSError as exc:
            raise ConfigError(f"{out}: cannot write the table or the report: {exc}") from None
    # a Ctrl-C while writing ends the command as one during the runs would (the interrupted line, its exit code);
    # a SIGTERM then, as in eval, only waited for the writing: every run is done and written
    return dataclasses.replace(result, files=files, interrupted=interrupted or signal.SIGINT in received)


# --------------------------------------------------------------------------- command line


def _all_failed(name: str, table_path) -> int:
    """1, with one line on stderr naming the first error, when every run of the table failed (nothing came of the
    campaign: a plug-in that cannot run, say), else 0.  Some failed runs are results, said in the table and report."""
    import csv

    if table_path is None or not os.path.isfile(table_path):
        return 0
    with open(table_path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or any(r.get("status") != "failed" for r in rows):
        return 0
    print(
        f"error: campaign {name}: every one of its {len(rows)} runs failed; the first: {rows[0].get('error', '?')}",
        file=sys.stderr,
    )
    return 1


def cmd_campaign(args) -> int:
    """``groundsim campaign SPEC``: validate, run what is missing, write table + report, print the summary.
    Ctrl-C or SIGTERM: the runs done are kept and in the table, the interrupted line, exit 130."""
    from groundsim.evaluation.eval import DEFAULT_ONBOARD_CONFIG, load_base_config

    # the first SIGTERM, or Ctrl-C, stops it cleanly; a later one cannot cut that stop short, even one arriving as the
    # first is caught.  SIGINT ignored on entry (started with & by a non-interactive shell) stays ignored
    with quiet_run_logs("groundsim.evaluation.eval"), first_signal_stops("the table and the report"):
        spec = load_spec(args.spec)
        scheduler = getattr(args, "scheduler", None)
        if scheduler is not None:  # before --out is made
            check_scheduler_address(scheduler)
        if scheduler is not None and args.workers is not None:
            raise ConfigError(
                f"--workers: not with --scheduler (the cluster's workers run the jobs), got --workers {args.workers}"
            )
        workers = pool_workers(args.workers if args.workers is not None else spec.workers)
        run_timeout = check_run_timeout(getattr(args, "run_timeout", None))
        cfg_path = spec.onboard_config
        if cfg_path is None and DEFAULT_ONBOARD_CONFIG.is_file():
            cfg_path = DEFAULT_ONBOARD_CONFIG
        base = load_base_config(cfg_path)
        digest = _digest(Path(cfg_path).read_bytes()) if cfg_path is not None else "defaults"
        out_path = Path(args.out) if args.out else Path("out/campaigns") / spec.name
        # a campaign reads its folder's runs.jsonl as its own, removes it with --fresh and overwrites its table and
        # report: a folder of anything else is refused before it is touched
        refuse_foreign_out(out_path, lambda o: (o / LOG_NAME).is_file(), "groundsim campaign", LOG_NAME)
        out = make_out_dir(out_path)
        res = run_campaign(
            spec,
            out,
            workers=workers,
            progress=not args.no_progress,
            fresh=args.fresh,
            retry_failed=args.retry_failed,
            base_config=base,
            onboard_digest=digest,
            scheduler=scheduler,
            run_timeout_s=run_timeout,
        )
        load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
        rate = 60.0 * res.ran / res.wall_s if res.ran and res.wall_s > 0 else math.nan
        print(
            f"campaign {spec.name}: {res.planned} runs planned, {res.reused} reused from {out / LOG_NAME}, "
            f"{res.ran} run now ({res.failed} failed) in {res.wall_s:.1f} s on {res.workers} worker(s)"
            f"{f' of {scheduler}' if scheduler else ''}"
            f"{f' = {rate:.1f} runs/min' if math.isfinite(rate) else ''} (load {load1:.1f})"
        )
        print(
            f"table: {res.files.get(TABLE_NAME)}; report: {res.files.get(REPORT_NAME)}"
            f"{'; figure: ' + str(res.files[FIGURE_NAME]) if FIGURE_NAME in res.files else ''}"
        )
        sys.stdout.flush()
        if res.interrupted:
            print(
                f"interrupted: {res.reused + res.ran} of {res.planned} runs done; the same command resumes",
                file=sys.stderr,
            )
            return 130
        return _all_failed(spec.name, res.files.get(TABLE_NAME))
