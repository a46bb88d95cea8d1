"""The figures of a lockstep run (:class:`groundsim.evaluation.eval.RunResult`) and their summary over seeds.

Scoring definitions (:func:`score_run`; metrics from :func:`onboard.estimation.metrics.evaluate`):

- *observable frames*: frames whose Track has a 3-D estimate flagged observable (all the daemon
  publishes with ``output.unobservable_positions: false``; the default, true, adds the others flagged so)
  -- the headline;
- *all frames with an estimate*: any finite 3-D estimate, observable or not;
- *continuity*: observable frames / all frames; *2-D continuity*: frames with a valid centroid /
  frames where the target is in the image;
- paper metric ``mean ||e|| / ||X||`` (world origin = the scenario's NED origin, on the ground under
  the observer's start), range-normalised error ``mean ||e|| / range``, RMSE, mean NEES (3 for a
  consistent covariance), fraction beyond 3 sigma;
- centroid error: image-chain centre minus truth pixel on frames with a valid centroid;
- closed-loop figures (:func:`closed_loop_figures`): published 3-D positions on tracking
  frames after 3 s, their honesty (beyond 3 sqrt(trace cov), and beyond the covariance's 3-sigma ellipsoid),
  observable share after 5 s, median
  error / range on observable frames.
"""

from __future__ import annotations

import math

import numpy as np

from groundsim.evaluation.report import BASELINE_FAIL_PCT, RATIO_LIMIT, markdown_head
from onboard.estimation.metrics import nees_per_point, score_frames

__all__ = [
    "PUBLISHED_AFTER_S",
    "OBSERVABLE_AFTER_S",
    "SUMMARY_FIELDS",
    "closed_loop_figures",
    "guidance_figures",
    "format_guidance_summary",
    "score_run",
    "summarise",
]


#: the closed-loop windows: published positions after the track settles, observability later
PUBLISHED_AFTER_S, OBSERVABLE_AFTER_S = 3.0, 5.0
#: the chi-square quantile of three degrees of freedom that a one-dimensional 3 sigma (99.73 %) corresponds to
CHI2_3DOF_3SIGMA = 14.156


def closed_loop_figures(r) -> dict:
    """The closed-loop figures of one run, from the pipeline's per-frame outputs (JSON-ready; None = no frame).

    *published*: a finite 3-D position in the frame's Track (lockstep publishes unobservable positions
    too, so this is what the daemon publishes once positions go out whenever the estimate is finite;
    with a daemon that publishes only observable positions it is an upper bound of that);
    ``published_share_after_3s``: published / tracking frames (state ``tracking``) at t >= 3 s;
    ``beyond_3sigma_published``: fraction of published positions with ``||e|| > 3 sqrt(trace cov)``
    (honesty; <= 0.01 asked); ``beyond_3sigma_ellipsoid_published``: the fraction beyond the covariance's own 3-sigma
    ellipsoid (NEES ``e' P^-1 e`` over :data:`CHI2_3DOF_3SIGMA`: the trace's test is blind to a covariance that is
    wide along the range and too tight across it); ``observable_share_after_5s``: observable / all frames at t >= 5 s;
    ``median_err_range_observable_pct``: median over observable frames of ``||e|| / range``, per cent;
    ``median_err_range_published_after_5s_pct``: the same over every published position at t >= 5 s;
    ``first_observable_s``: time of the first observable frame; ``observable_share_after_5s_at_bound``: the most
    of ``observable_share_after_5s`` an estimator at the Bayesian CRB could reach (:func:`_observable_share_at_bound`).
    """
    t = r.t_s - r.t_s[0] if r.t_s.size else r.t_s
    has = r.has_estimate
    obs = has & r.observable
    tracked = (r.state == "tracking") & (t >= PUBLISHED_AFTER_S)
    late = t >= OBSERVABLE_AFTER_S
    e = np.linalg.norm(r.est_p_ned_m - r.truth_p_ned_m, axis=1)
    with np.errstate(invalid="ignore"):
        sig3 = 3.0 * np.sqrt(np.maximum(np.einsum("fii->f", r.est_cov_ned_m2), 0.0))
    pub = has & np.isfinite(sig3)
    # a covariance that cannot be inverted claims no spread in some direction: any error there is beyond it
    nees = nees_per_point(r.est_p_ned_m[pub] - r.truth_p_ned_m[pub], r.est_cov_ned_m2[pub], singular=math.inf)
    return {
        "tracking_frames_after_3s": int(tracked.sum()),
        "published_share_after_3s": float((tracked & has).sum() / tracked.sum()) if tracked.any() else None,
        "published_frames": int(has.sum()),
        "beyond_3sigma_published": float((e[pub] > sig3[pub]).mean()) if pub.any() else None,
        "beyond_3sigma_ellipsoid_published": float((nees > CHI2_3DOF_3SIGMA).mean()) if pub.any() else None,
        "observable_share_after_5s": float((late & obs).sum() / late.sum()) if late.any() else None,
        "median_err_range_observable_pct": float(np.median(100.0 * e[obs] / r.range_m[obs])) if obs.any() else None,
        # what the verdict withheld: the error of every published position after 5 s, and when the first
        # observable frame came (the window's span, not the estimate, is what P1's weak manoeuvre needs)
        "median_err_range_published_after_5s_pct": (
            float(np.median(100.0 * e[pub & late] / r.range_m[pub & late])) if (pub & late).any() else None
        ),
        "first_observable_s": float(t[obs][0]) if obs.any() else None,
        "observable_share_after_5s_at_bound": _observable_share_at_bound(r),
    }


def bound_ratio_limit() -> float:
    """The largest range sigma over range at the Bayesian CRB with which the estimator can call a position
    observable: its verdict holds the reported sigma, the Laplace one times ``sigma_inflation``, under
    ``observability_max_sigma_range_ratio``; an estimator at the bound reports the bound times that factor."""
    from onboard.estimation.map_estimator import MapConfig

    c = MapConfig()
    return c.observability_max_sigma_range_ratio / c.sigma_inflation


def _observable_share_at_bound(r) -> float | None:
    """The share of the half-second samples at t >= 5 s at which the online verdict's figure at the bound (the
    batch's ``causal_bound_*``: :func:`onboard.estimation.crb.online_verdict_bound_ratios`, the sliding window's
    own rows up to that time) is under :func:`bound_ratio_limit`: the most of ``observable_share_after_5s`` an
    estimator at the bound could reach (a sample before the window publishes counts as not observable).  None
    without the batch's bound."""
    perfect = (r.batch or {}).get("perfect") or {}
    t, ratio = perfect.get("causal_bound_t_s"), perfect.get("causal_bound_range_sigma_ratio")
    if t is None or ratio is None:
        return None
    late = np.asarray(t) >= OBSERVABLE_AFTER_S
    if not late.any():
        return None
    with np.errstate(invalid="ignore"):
        ok = np.asarray(ratio)[late] < bound_ratio_limit()
    return float(ok.mean())


def score_run(r) -> dict:
    """The figures of one run (definitions in the module docstring); JSON-ready."""
    if r.error is not None:
        return {"scenario": r.scenario, "seed": r.seed, "error": r.error}
    F = r.frames
    has = r.has_estimate
    obs = has & r.observable
    base_obs = r.base_has_estimate & r.base_observable
    common = obs & base_obs
    out: dict = {
        "scenario": r.scenario,
        "seed": r.seed,
        "frames": F,
        "nav_noise": r.nav_noise,
        "estimator": getattr(r, "estimator", "map"),
        "tracker": getattr(r, "tracker", "objects"),
        "baseline_pixel_sigma_px": r.baseline_pixel_sigma_px,
        "chain_centroid_sigma_px": r.chain_centroid_sigma_px,
    }
    out["closed_loop"] = closed_loop_figures(r)
    out["perception"] = dict(getattr(r, "perception", None) or {})
    out["online_observable"] = score_frames(r.truth_p_ned_m, r.est_p_ned_m, r.cam_p_ned_m, r.est_cov_ned_m2, obs)
    out["online_all"] = score_frames(r.truth_p_ned_m, r.est_p_ned_m, r.cam_p_ned_m, r.est_cov_ned_m2, has)
    out["perfect_observable"] = score_frames(
        r.truth_p_ned_m, r.base_p_ned_m, r.cam_p_ned_m, r.base_cov_ned_m2, base_obs
    )
    on_c = score_frames(r.truth_p_ned_m, r.est_p_ned_m, r.cam_p_ned_m, None, common)
    pf_c = score_frames(r.truth_p_ned_m, r.base_p_ned_m, r.cam_p_ned_m, None, common)
    out["common_frames"] = int(common.sum())
    out["online_common_err_range_pct"] = None if on_c is None else on_c["err_range_pct"]
    out["perfect_common_err_range_pct"] = None if pf_c is None else pf_c["err_range_pct"]
    # None, not 0, where there is nothing to measure (no frame; the target never in the image): shown as '-'
    out["continuity"] = float(obs.sum() / F) if F else None
    out["estimate_fraction"] = float(has.sum() / F) if F else 0.0
    out["perfect_continuity"] = float(base_obs.sum() / F) if F else 0.0
    vis = int(r.visible.sum())
    out["continuity_2d"] = float((r.measurement_valid & r.visible).sum() / vis) if vis else None
    first = np.flatnonzero(obs)
    out["first_observable_s"] = float(r.t_s[first[0]] - r.t_s[0]) if first.size else None
    first_m = np.flatnonzero(r.measurement_valid)
    out["first_centroid_s"] = float(r.t_s[first_m[0]] - r.t_s[0]) if first_m.size else None
    cm = r.measurement_valid & np.all(np.isfinite(r.truth_uv_px), axis=1)
    if cm.any():
        d = r.uv_px[cm] - r.truth_uv_px[cm]
        out["centroid_rms_px"] = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
        out["centroid_bias_px"] = [float(x) for x in d.mean(axis=0)]
    else:
        out["centroid_rms_px"], out["centroid_bias_px"] = None, None
    out["range_m"] = [float(np.nanmin(r.range_m)), float(np.nanmax(r.range_m))] if F else None
    tm = r.timing
    pm = np.asarray(tm["process_ms"])
    out["timing"] = {
        "wall_s": tm["wall_s"],
        "cpu_s": tm["cpu_s"],
        "cpu_share": tm["cpu_s"] / max(tm["wall_s"], 1e-9),
        "flight_s": tm["flight_s"],
        "render_s": tm["render_s"],
        "pipeline_s": tm["pipeline_s"],
        "baseline_s": tm["baseline_s"],
        "batch_s": tm["batch_s"],
        "pipeline_fps": float(F / max(pm.sum() / 1e3, 1e-9)),
        "loop_fps": float(F / max(tm["wall_s"], 1e-9)),
        "latency_ms": _percentiles(pm),
        "render_ms": _percentiles(np.asarray(tm["render_ms"])),
    }
    if r.batch is not None:
        b = {}
        for name in ("pipeline", "perfect"):
            e = r.batch[name]
            m = None
            if e.get("p_ned_m") is not None:
                idx = e["frames"]
                m = score_frames(
                    r.truth_p_ned_m[idx], e["p_ned_m"], r.cam_p_ned_m[idx], e["cov_ned_m2"], np.ones(idx.size, bool)
                )
            b[name] = {
                "metrics": m,
                "observable": e["observable"],
                "model": e["model"],
                "solve_s": e["solve_s"],
                "windows": int(e.get("windows", 0)),
                "frames": int(len(e["frames"])),
                "error": e["error"],
            }
        b["crb_rms_m"] = r.batch["perfect"].get("crb_rms_m")
        b["crb_model_rms_m"] = r.batch["perfect"].get("crb_model_rms_m")
        b["crb_model_range_sigma_ratio"] = r.batch["perfect"].get("crb_model_range_sigma_ratio")
        out["batch"] = b
    out["counters"] = {str(k): int(v) for k, v in sorted(r.counters.items())}
    return out


def _percentiles(a: np.ndarray) -> dict:
    if a.size == 0:
        return {"p50": None, "p90": None, "p99": None, "max": None, "mean": None}
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {"p50": float(p50), "p90": float(p90), "p99": float(p99), "max": float(a.max()), "mean": float(a.mean())}


def _med(values) -> float | None:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.median(v)) if v else None


def _get(d: dict | None, *keys):
    for k in keys:
        if d is None:
            return None
        d = d.get(k)
    return d


#: per-run figure -> path in score_run's dict, summarised as the median over seeds
SUMMARY_FIELDS = {
    "err_paper_pct": ("online_observable", "err_paper_pct"),
    "err_range_pct": ("online_observable", "err_range_pct"),
    "rmse_m": ("online_observable", "rmse_m"),
    "nees": ("online_observable", "mean_nees"),
    "beyond_3sigma": ("online_observable", "outside_3sigma_trace_fraction"),
    "all_err_range_pct": ("online_all", "err_range_pct"),
    "all_rmse_m": ("online_all", "rmse_m"),
    "perfect_err_range_pct": ("perfect_observable", "err_range_pct"),
    "perfect_rmse_m": ("perfect_observable", "rmse_m"),
    "online_common_err_range_pct": ("online_common_err_range_pct",),
    "perfect_common_err_range_pct": ("perfect_common_err_range_pct",),
    "continuity": ("continuity",),
    "estimate_fraction": ("estimate_fraction",),
    "perfect_continuity": ("perfect_continuity",),
    "continuity_2d": ("continuity_2d",),
    "first_observable_s": ("first_observable_s",),
    "centroid_rms_px": ("centroid_rms_px",),
    "pipeline_fps": ("timing", "pipeline_fps"),
    "loop_fps": ("timing", "loop_fps"),
    "latency_p50_ms": ("timing", "latency_ms", "p50"),
    "latency_p99_ms": ("timing", "latency_ms", "p99"),
    "batch_err_range_pct": ("batch", "pipeline", "metrics", "err_range_pct"),
    "batch_perfect_err_range_pct": ("batch", "perfect", "metrics", "err_range_pct"),
    "crb_rms_m": ("batch", "crb_rms_m"),
    "published_share_after_3s": ("closed_loop", "published_share_after_3s"),
    "beyond_3sigma_published": ("closed_loop", "beyond_3sigma_published"),
    "beyond_3sigma_ellipsoid_published": ("closed_loop", "beyond_3sigma_ellipsoid_published"),
    "observable_share_after_5s": ("closed_loop", "observable_share_after_5s"),
    "median_err_range_observable_pct": ("closed_loop", "median_err_range_observable_pct"),
    "median_err_range_published_after_5s_pct": ("closed_loop", "median_err_range_published_after_5s_pct"),
    "closed_loop_first_observable_s": ("closed_loop", "first_observable_s"),
    "baseline_pixel_sigma_px": ("baseline_pixel_sigma_px",),
    "chain_centroid_sigma_px": ("chain_centroid_sigma_px",),
    "crb_model_rms_m": ("batch", "crb_model_rms_m"),
    "crb_model_range_sigma_ratio": ("batch", "crb_model_range_sigma_ratio"),
    "observable_share_after_5s_at_bound": ("closed_loop", "observable_share_after_5s_at_bound"),
    "batch_perfect_rmse_m": ("batch", "perfect", "metrics", "rmse_m"),
}


def _baseline_failed(pct) -> bool:
    return pct is None or pct > BASELINE_FAIL_PCT


def summarise(scores: list[dict]) -> list[dict]:
    """One row per (scenario, navigation-error case) (first-seen order): medians over seeds, ratios
    and their verdict.  ``label`` is the scenario's name, or ``<scenario>_<nav case>`` when the runs
    mix navigation cases.  A ratio gets no verdict when its baseline failed (perfect centroids
    unobservable or worse than ``BASELINE_FAIL_PCT`` err / range): ``baseline_failed`` /
    ``batch_baseline_failed`` say so (``batch_baseline_failed`` None: no batch was run), and ``within_ratio`` is
    None when no ratio has a sound baseline.
    """
    keys: list[tuple[str, str]] = []
    for s in scores:
        k = (s["scenario"], s.get("nav_noise", ""))
        if k not in keys:
            keys.append(k)
    multi = len({k[1] for k in keys}) > 1
    rows = []
    for name, nav in keys:
        runs = [s for s in scores if s["scenario"] == name and s.get("nav_noise", "") == nav]
        ok = [s for s in runs if "error" not in s]
        row: dict = {
            "scenario": name,
            "nav_noise": nav,
            "label": f"{name}_{nav}" if multi else name,
            "runs": len(runs),
            "failed_runs": len(runs) - len(ok),
        }
        for key, path in SUMMARY_FIELDS.items():
            row[key] = _med(_get(s, *path) for s in ok)
        on, pf = row["online_common_err_range_pct"], row["perfect_common_err_range_pct"]
        row["ratio_to_perfect"] = (on / pf) if (on is not None and pf not in (None, 0.0)) else None
        bo, bp = row["batch_err_range_pct"], row["batch_perfect_err_range_pct"]
        row["batch_ratio_to_perfect"] = (bo / bp) if (bo is not None and bp not in (None, 0.0)) else None
        row["baseline_failed"] = _baseline_failed(row["perfect_err_range_pct"])
        # no batch at all (eval --no-batch): not run, which is not a failed baseline
        row["batch_baseline_failed"] = None if bo is None and bp is None else _baseline_failed(bp)
        ratios = [
            x
            for x, failed in (
                (row["ratio_to_perfect"], row["baseline_failed"]),
                (row["batch_ratio_to_perfect"], row["batch_baseline_failed"]),
            )
            if x is not None and not failed
        ]
        row["within_ratio"] = bool(all(x <= RATIO_LIMIT for x in ratios)) if ratios else None
        rows.append(row)
    return rows


#: observable within this long of the first tracking frame: the guidance goal
GUIDANCE_OBSERVABLE_WITHIN_S = 10.0


def guidance_figures(r) -> dict:
    """One run's observer-guidance figures (JSON-ready; None = no such frame): ``first_track_s`` (the first frame
    with state ``tracking``, from the run's start), ``first_observable_after_track_s``, whether that is within
    :data:`GUIDANCE_OBSERVABLE_WITHIN_S`, and the advice the run followed (``RunResult.guidance``)."""
    t = r.t_s - r.t_s[0] if r.t_s.size else r.t_s
    obs = r.has_estimate & r.observable
    tracking = np.flatnonzero(r.state == "tracking")
    t_track = float(t[tracking[0]]) if tracking.size else None
    after = None
    if t_track is not None and obs.any():
        late = obs & (t >= t_track)
        after = float(t[late][0] - t_track) if late.any() else None
    g = r.guidance or {}
    return {
        "first_track_s": t_track,
        "first_observable_after_track_s": after,
        "observable_within_goal": after is not None and after <= GUIDANCE_OBSERVABLE_WITHIN_S,
        "advices": g.get("advices"),
        "first_advice_s": g.get("first_advice_s"),
    }


def format_guidance_summary(runs) -> str:
    """Lines per (scenario, navigation case) over seeds: observable within 10 s of the first track (share of seeds),
    median error / range pooled over every observable frame, share of published positions beyond 3 sigma (pooled:
    ``||e|| > 3 sqrt(trace cov)``), mean observable share of the frames after 5 s, and the advice followed."""
    groups: dict[tuple[str, str], list] = {}
    for r in runs:
        if r.error is None:
            groups.setdefault((r.scenario, r.nav_noise), []).append(r)
    lines = markdown_head(
        "| scenario | navigation errors | seeds | observable within 10 s of first track (>= 90 %) | median err / range,"
        " observable frames (<= 1 %) | beyond 3 sigma, published (<= 1 %) | observable, frames after 5 s |"
        " first observable after track s (median) | advices per run (median); first at s |"
    )
    for (name, nav), rs in groups.items():
        figs = [guidance_figures(r) for r in rs]
        within = sum(f["observable_within_goal"] for f in figs)
        err, beyond, pub = [], 0, 0
        shares = []
        for r in rs:
            e = np.linalg.norm(r.est_p_ned_m - r.truth_p_ned_m, axis=1)
            obs = r.has_estimate & r.observable
            err.extend((100.0 * e[obs] / r.range_m[obs]).tolist())
            with np.errstate(invalid="ignore"):
                sig3 = 3.0 * np.sqrt(np.maximum(np.einsum("fii->f", r.est_cov_ned_m2), 0.0))
            m = r.has_estimate & np.isfinite(sig3)
            beyond += int((e[m] > sig3[m]).sum())
            pub += int(m.sum())
            share = closed_loop_figures(r)["observable_share_after_5s"]
            if share is not None:
                shares.append(share)
        after = [f["first_observable_after_track_s"] for f in figs if f["first_observable_after_track_s"] is not None]
        adv = [f["advices"] for f in figs if f["advices"] is not None]
        first = [f["first_advice_s"] for f in figs if f["first_advice_s"] is not None]

        def f(x, fmt, unit=""):
            return "-" if x is None else format(x, fmt) + unit

        lines.append(
            f"| {name} | {nav or '-'} | {len(rs)} | {within}/{len(rs)} ({100.0 * within / len(rs):.0f} %) | "
            f"{f(float(np.median(err)) if err else None, '.2f', ' %')} ({len(err)} frames) | "
            f"{f(100.0 * beyond / pub if pub else None, '.2f', ' %')} ({pub} positions) | "
            f"{f(100.0 * float(np.mean(shares)) if shares else None, '.0f', ' %')} | "
            f"{f(float(np.median(after)) if after else None, '.1f')} | "
            f"{f(float(np.median(adv)) if adv else None, '.0f')}; {f(float(np.median(first)) if first else None, '.1f')} |"
        )
    return "\n".join(lines)


def gnss_dropout_figures(r) -> dict | None:
    """What a run did in its GNSS dropout (None without one): ``frames`` in the window with the target in view
    (visible and measured), the share of them with a line of sight (``los``) and with a 3-D position
    (``position``); ``beyond_3sigma`` among those positions (``||e|| > 3 sqrt(trace cov)``, the closed-loop
    figure's definition); ``warning_after_s``: from the window's start to the watchdog's ``gnss_dropout``."""
    if r.gnss_window_s is None or r.frames == 0:
        return None
    t0, t1 = r.gnss_window_s
    gap = (r.t_s >= t0) & (r.t_s < t1) & r.visible & r.measurement_valid
    n = int(gap.sum())
    if n == 0:
        return {"frames": 0}
    has = gap & r.has_estimate
    e = np.linalg.norm(r.est_p_ned_m[has] - r.truth_p_ned_m[has], axis=1)
    sig3 = 3.0 * np.sqrt(np.trace(r.est_cov_ned_m2[has], axis1=1, axis2=2))
    rng = r.range_m[has]
    return {
        "frames": n,
        "los": math.nan if r.los_valid is None else float((gap & r.los_valid).sum() / n),
        "position": float(has.sum() / n),
        "beyond_3sigma": float((e > sig3).mean()) if has.any() else None,
        "median_error_pct_range": float(np.median(100.0 * e / rng)) if has.any() else None,
        "warning_after_s": r.gnss_warning_t_s - t0,
    }


def format_gnss_dropout(runs: list) -> str:
    """One line per run: the GNSS dropout's figures (:func:`gnss_dropout_figures`)."""
    lines = ["GNSS dropout: frames in the window with the target in view, and what they got"]
    lines.append(f"{'run':<20} {'frames':>6} {'los':>7} {'3-D':>7} {'>3sigma':>8} {'med err':>8} {'warned after':>13}")
    for r in runs:
        f = gnss_dropout_figures(r)
        # the noise case in the name: one eval flies each seed once per case, and the rows must be told apart
        name = f"{r.scenario} {r.nav_noise} s{r.seed}" if r.nav_noise else f"{r.scenario} s{r.seed}"
        if f is None or not f.get("frames"):
            lines.append(f"{name:<20} {'no frames in the window' if f else 'no dropout'}")
            continue
        b3 = "-" if f["beyond_3sigma"] is None else f"{100 * f['beyond_3sigma']:.1f} %"
        med = "-" if f["median_error_pct_range"] is None else f"{f['median_error_pct_range']:.2f} %"
        warned = "never" if math.isnan(f["warning_after_s"]) else f"{f['warning_after_s']:.2f} s"
        lines.append(
            f"{name:<20} {f['frames']:>6} {100 * f['los']:>6.1f}% {100 * f['position']:>6.1f}%"
            f" {b3:>8} {med:>8} {warned:>13}"
        )
    return "\n".join(lines)
