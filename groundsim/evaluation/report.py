"""Evaluation report files: ``report.json``, ``report.md``, PNG plots and TUM trajectories.

Pure writers over the results of :mod:`groundsim.evaluation.eval` (and the demo's live table); no simulation
here.  The plots are :mod:`groundsim.evaluation.report_plots`'s.

TUM trajectory format (one pose per line, as read by evo's ``file_interface.read_tum_trajectory_file``)::

    timestamp tx ty tz qx qy qz qw

``timestamp``: the frame's capture time in seconds on the vehicle's boot clock (``time_boot_us /
1e6``, microsecond resolution); ``tx ty tz``: the target's position in the scenario's local NED frame,
metres (north, east, down); the orientation is the identity (``0 0 0 1``: evo wants a unit
quaternion, the target's attitude is not estimated).  ``truth.tum`` holds every frame processed (the last one or
two, after the flight's last telemetry sample, have no pose and are not),
``estimate.tum`` the frames where the online track reported a 3-D position flagged observable (the
daemon publishes the unobservable ones too, flagged so, unless ``output.unobservable_positions`` is
false), ``estimate_perfect.tum`` the perfect-centroid baseline's observable frames.

:func:`ape_rmse_m` scores a pair the way ``evo_ape tum truth.tum estimate.tum`` does by default: each
stamp of the shorter trajectory is matched to the nearest stamp of the longer within
``max_diff_s`` = 0.01 s, no alignment, error = translation difference, RMSE over the matches.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path

import numpy as np

from groundsim.evaluation import report_plots
from groundsim.evaluation.out_dir import make_out_dir
from onboard.core.errors import InputError

__all__ = [
    "EVO_MAX_DIFF_S",
    "PAPER_TABLE2_PCT",
    "write_tum",
    "read_tum",
    "ape_rmse_m",
    "write_eval_report",
    "clear_eval_report",
    "holds_eval_report",
    "format_table2",
    "format_closed_loop",
    "closed_loop_notes",
    "json_ready",
]

log = logging.getLogger(__name__)

EVO_MAX_DIFF_S = 0.01  # evo's default --t_max_diff
#: The paper's Table 2 (relative error with its world origin, per cent) by scenario key.
PAPER_TABLE2_PCT = {"P1": 0.89, "P2": 1.09, "P3": 1.45}
#: The reference study's best MAP estimator and Bayesian CRB, px0.3 case (REFERENCE_SCENARIOS.md).
REFERENCE_PX03 = {"P1": (0.34, 0.85), "P2": (0.43, 1.5), "P3": (6.7, 6.1)}
SCHEMA = "irtrack.eval/1"
RATIO_LIMIT = 1.5  # the goal: the image chain within this factor of perfect centroids
BASELINE_FAIL_PCT = 5.0  # a perfect-centroid baseline worse than this (err / range) failed: no ratio verdict on it
EVAL_PLOTS = ("trajectory", "error", "frame", "objects")  # <label>_<plot>.png of write_eval_report
EVAL_TUM_FILES = ("truth.tum", "estimate.tum", "estimate_perfect.tum")  # in <label>/seed<N>/


# --------------------------------------------------------------------------- TUM


def write_tum(path, t_s, p_ned_m) -> int:
    """Write ``t_s`` (N,) and ``p_ned_m`` (N, 3) as a TUM file (rows with any NaN skipped); returns rows written."""
    t = np.asarray(t_s, dtype=float).reshape(-1)
    p = np.asarray(p_ned_m, dtype=float)
    if p.shape != (t.size, 3):
        raise InputError(f"write_tum {path}: p_ned_m must have shape ({t.size}, 3), got {p.shape}")
    ok = np.isfinite(t) & np.all(np.isfinite(p), axis=1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="ascii") as f:
        f.write("# timestamp tx ty tz qx qy qz qw  (boot-clock seconds; local NED metres; identity attitude)\n")
        for ti, pi in zip(t[ok], p[ok]):
            f.write(f"{ti:.6f} {pi[0]:.6f} {pi[1]:.6f} {pi[2]:.6f} 0 0 0 1\n")
    return int(ok.sum())


def read_tum(path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM file -> ``(t_s (N,), p (N, 3))``; comment lines (``#``) and blank lines are skipped.

    Raises InputError naming the file and line for a row that is not 8 numbers.
    """
    path = Path(path)
    t, p = [], []
    try:
        lines = path.read_text(encoding="ascii").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read TUM file: {exc}") from None
    for n, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(f"{path}: line {n}: expected 8 numbers (timestamp tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise InputError(f"{path}: line {n}: not numbers: {s!r}") from None
        t.append(vals[0])
        p.append(vals[1:4])
    return np.asarray(t, dtype=float), np.asarray(p, dtype=float).reshape(-1, 3)


def ape_rmse_m(t_ref_s, p_ref, t_est_s, p_est, max_diff_s: float = EVO_MAX_DIFF_S) -> tuple[float, int]:
    """Absolute position error RMSE (metres) and the number of matched poses, evo's default way
    (see the module docstring).  NaN and 0 when nothing matches."""
    t1, p1 = np.asarray(t_ref_s, dtype=float), np.asarray(p_ref, dtype=float).reshape(-1, 3)
    t2, p2 = np.asarray(t_est_s, dtype=float), np.asarray(p_est, dtype=float).reshape(-1, 3)
    if t1.size == 0 or t2.size == 0:
        return math.nan, 0
    second_longer = t2.size > t1.size
    ts, ps, tl, pl = (t1, p1, t2, p2) if second_longer else (t2, p2, t1, p1)
    d = np.abs(tl[None, :] - ts[:, None])
    j = np.argmin(d, axis=1)
    ok = d[np.arange(ts.size), j] <= max_diff_s
    if not ok.any():
        return math.nan, 0
    e = np.linalg.norm(ps[ok] - pl[j[ok]], axis=1)
    return float(np.sqrt(np.mean(e**2))), int(ok.sum())


# --------------------------------------------------------------------------- JSON


def json_ready(obj):
    """numpy -> Python, non-finite floats -> None, recursively (for ``json.dumps(allow_nan=False)``)."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


# --------------------------------------------------------------------------- tables


def _f(x, fmt: str = ".2f", unit: str = "") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:{fmt}}{unit}"


def _ratio_text(x, baseline_failed: bool) -> str:
    """A ratio with its verdict; never "ok" on a failed baseline."""
    if x is None:
        return "-"
    if baseline_failed:
        return f"{x:.2f} (baseline failed)"
    return f"{x:.2f}" + (" ok" if x <= RATIO_LIMIT else " **over**")


def markdown_head(head: str) -> list[str]:
    """A markdown table's first two lines: ``head`` (``"| a | b |"``) and its delimiter row, one ``---`` a column
    (counted from ``head``, so the two cannot disagree)."""
    return [head, "|" + "---|" * (head.count("|") - 1)]


def format_table2(summary: list[dict], descriptions: dict[str, str] | None = None) -> str:
    """The Table-2 style markdown table of :func:`groundsim.evaluation.eval.summarise` rows, the paper's figure beside ours."""
    descriptions = descriptions or {}
    lines = markdown_head(
        "| scenario | geometry | paper Table 2 | ours: paper metric | ours: err / range | RMSE m | NEES | "
        "continuity | perfect centroids: err / range | ratio (<= 1.5) | CRB RMS m | batch err / range | "
        "batch perfect err / range | batch ratio (<= 1.5) |"
    )
    for r in summary:
        paper = PAPER_TABLE2_PCT.get(r["scenario"])
        lines.append(
            f"| {r.get('label', r['scenario'])} | {descriptions.get(r.get('label', r['scenario']), descriptions.get(r['scenario'], ''))} | {_f(paper, '.2f', ' %')} | "
            f"{_f(r.get('err_paper_pct'), '.2f', ' %')} | {_f(r.get('err_range_pct'), '.2f', ' %')} | "
            f"{_f(r.get('rmse_m'))} | {_f(r.get('nees'), '.2f')} | {_f(_pct(r.get('continuity')), '.0f', ' %')} | "
            f"{_f(r.get('perfect_err_range_pct'), '.2f', ' %')} | "
            f"{_ratio_text(r.get('ratio_to_perfect'), bool(r.get('baseline_failed')))} | {_f(r.get('crb_rms_m'))} | "
            f"{_f(r.get('batch_err_range_pct'), '.2f', ' %')} | {_f(r.get('batch_perfect_err_range_pct'), '.2f', ' %')} | "
            f"{_ratio_text(r.get('batch_ratio_to_perfect'), bool(r.get('batch_baseline_failed')))} |"
        )
    return "\n".join(lines)


#: The closed-loop goals: published after 3 s, beyond 3 sigma, observable after 5 s (P2: 40 %), median err / range
CLOSED_LOOP_GOALS = {
    "published": 0.95,
    "beyond": 0.01,
    "observable": {"P2": 0.40},
    "observable_default": 0.60,
    "err_pct": 2.0,
}


def format_closed_loop(summary: list[dict]) -> str:
    """The closed-loop figures per (scenario, navigation case), medians over seeds, with the goal
    beside each (:func:`groundsim.evaluation.eval.closed_loop_figures` defines them); under the table, after a
    blank line, :func:`closed_loop_notes` when there are any."""
    g = CLOSED_LOOP_GOALS
    lines = markdown_head(
        "| scenario | navigation errors | published 3-D position, tracking frames after 3 s (>= 95 %) | "
        "published beyond 3 sigma (<= 1 %); its ellipsoid | observable, frames after 5 s (>= 60 %; P2 40 %) | "
        "median err / range, observable frames (<= 2 %) | median err / range, all published after 5 s | "
        "first observable s | centroid sigma px per axis (chain; baseline) | observable after 5 s at the bound |"
    )
    for r in summary:
        obs_goal = g["observable"].get(r["scenario"], g["observable_default"])

        def mark(x, ok):
            return "" if x is None else ("" if ok(x) else " **miss**")

        pub, bey = r.get("published_share_after_3s"), r.get("beyond_3sigma_published")
        ell = r.get("beyond_3sigma_ellipsoid_published")
        obs, err = r.get("observable_share_after_5s"), r.get("median_err_range_observable_pct")
        at_bound = r.get("observable_share_after_5s_at_bound")
        obs_mark = mark(obs, lambda x, goal=obs_goal: x >= goal)
        if obs_mark and at_bound is not None and at_bound < obs_goal:
            obs_mark += " (the bound's too)"
        lines.append(
            f"| {r.get('label', r['scenario'])} | {r.get('nav_noise') or '-'} | "
            f"{_f(_pct(pub), '.0f', ' %')}{mark(pub, lambda x: x >= g['published'])} | "
            f"{_f(_pct(bey), '.1f', ' %')}{mark(bey, lambda x: x <= g['beyond'])}; {_f(_pct(ell), '.1f', ' %')} | "
            f"{_f(_pct(obs), '.0f', ' %')}{obs_mark} | "
            f"{_f(err, '.2f', ' %')}{mark(err, lambda x: x <= g['err_pct'])} | "
            f"{_f(r.get('median_err_range_published_after_5s_pct'), '.2f', ' %')} | {_f(r.get('closed_loop_first_observable_s'), '.1f')} | "
            f"{_f(r.get('chain_centroid_sigma_px'), '.3f')}; {_f(r.get('baseline_pixel_sigma_px'), '.3f')} | "
            f"{_f(_pct(at_bound), '.0f', ' %')} |"
        )
    notes = closed_loop_notes(summary)
    return "\n".join(lines + ([""] + notes if notes else []))


#: a chain whose centroids lie farther than this from the target's pixel (RMS per axis over the frames it measured)
#: followed something else for much of the flight: the perfect-centroid baseline, fed that as noise, means nothing
CHAIN_OFF_TARGET_PX = 5.0


def closed_loop_notes(summary: list[dict]) -> list[str]:
    """Lines under the closed-loop table for the rows whose image chain was off its target (its centroid error
    above :data:`CHAIN_OFF_TARGET_PX`): what it means and what to run instead.  Empty when none was."""
    notes = []
    for r in summary:
        sigma = r.get("chain_centroid_sigma_px")
        if sigma is not None and math.isfinite(sigma) and sigma > CHAIN_OFF_TARGET_PX:
            notes.append(
                f"- {r.get('label', r['scenario'])}: the image chain's centroids lie {sigma:.1f} px (RMS) from the "
                "target's pixel: it followed something else (clutter, another object) for much of the flight, and "
                "the perfect-centroid baseline, given that as its noise, is no yardstick. In clutter run the objects "
                "chain (the default) if the run set `imaging: {chain: single}` in its --onboard-config file "
                "(README, Perception in clutter)."
            )
    return notes


def _pct(x):
    return None if x is None else 100.0 * x


def _short_geometry(description: str) -> str:
    d = description.split(":", 1)[-1].strip() if ":" in description else description
    return d.replace("|", "/")


# --------------------------------------------------------------------------- the eval report


DEFINITIONS = {
    "observable frames": "frames whose online Track has a 3-D position flagged observable (the daemon's "
    "observable: true; with the default output.unobservable_positions: true it publishes the unobservable "
    "positions too, flagged false, and with false only these); the headline",
    "all frames with an estimate": "frames with any finite 3-D estimate, observable or not",
    "paper metric": "mean ||X_hat - X|| / ||X|| x 100 %, X relative to the scenario's local origin (on the ground "
    "under the observer's start), as the paper's relative error",
    "err / range": "mean ||X_hat - X|| / range x 100 % (range = camera to target)",
    "RMSE": "sqrt(mean ||X_hat - X||^2), metres; equals evo_ape's RMSE on the TUM files",
    "NEES": "mean e^T P^-1 e with the reported covariance P (3 when consistent; < 3 conservative)",
    "continuity": "observable frames / all frames of the run",
    "continuity 2-D": "frames with a valid centroid / frames with the target inside the image",
    "perfect centroids": "the same sliding-window estimator fed with the true pixel + white noise of the image "
    "chain's own centroid error (measured per run: RMS per axis of centroid - truth pixel; "
    "--pixel-sigma overrides it), through the same camera poses as the pipeline (navigation "
    "errors included); scored on its observable frames",
    "baseline failed": f"the perfect-centroid baseline had no observable frame or an error over {BASELINE_FAIL_PCT:g} % of range: "
    "a ratio to it says nothing, so it gets no verdict",
    "navigation errors": "the simulated telemetry's errors (config/noise_cases.yaml case, groundsim/world/nav_errors.py): "
    "attitude bias + white noise on #31/#285, position offset + drift + white noise on #33",
    "published (closed loop)": "frames whose Track carries a finite 3-D position, observable or not (what the "
    "daemon publishes with the default output.unobservable_positions: true); share over frames in state "
    "tracking after the first 3 s",
    "beyond 3 sigma (published)": "fraction of published positions with ||e|| > 3 sqrt(trace cov): honesty",
    "observable after 5 s": "observable frames / all frames after the first 5 s",
    "ratio": "online track: image chain err/range / perfect-centroid err/range, both on the frames where both are "
    "observable (median over seeds of each, then the ratio); batch ratio: the same for the whole-flight "
    "smoother on all frames with a centroid; the goal is <= 1.5 (the verdict needs every ratio whose baseline is "
    "sound: a ratio whose perfect-centroid baseline failed, or a batch not run, is left out and said)",
    "CRB": "Bayesian Cramer-Rao bound of the flown trajectory (RMS over the flight of sqrt(trace)), with the "
    "simulated noise (the baseline's pixel noise and the run's navigation-error case) and the motion prior the batch estimator selected "
    "on perfect centroids",
    "observable after 5 s at the bound": "every half second after 5 s, the Bayesian CRB of the flown trajectory "
    "from the rows the online window holds then (its last estimator.window_s, thinned as it keeps them, solved on "
    "its knots), for the estimator's own noise model and the motion prior the batch selected on perfect centroids: "
    "the share of those times at which an estimator at the bound could pass the online verdict (the window's median "
    "range sigma over range, and its newest over edge_sigma_factor, each the bound's times sigma_inflation at best, "
    "under observability_max_sigma_range_ratio).  A miss on 'observable' that the bound shares ('the bound's too') "
    "is the flight's geometry, not the estimator; the bound is local, so a flight whose bearings have a second "
    "explanation (P1's mirror target) can fall short of it",
    "batch": "whole-flight MAP smoother with model selection on the pipeline's centroids (and on perfect centroids);"
    " a flight over 60 s in windows of 60 s, one every 30 s (model 'mixed' when they chose different ones)",
    "medians": "every figure of the scenario tables is the median over seeds (the runs table is per run, the "
    "perception table lists each seed's)",
}


def clear_eval_report(out_dir) -> None:
    """Remove what an earlier :func:`write_eval_report` left in ``out_dir``, so that a reused folder describes
    the new run only (an earlier run's other scenarios and seeds would otherwise sit beside it, looking current).

    Only this report's own names go: ``report.json``, ``report.md``, ``performance.png``, the files the earlier
    report.json lists, and for every label with a ``<label>/seed<N>/`` folder holding TUM files, those TUM files
    and ``<label>_{trajectory,error,frame,objects}.png``.  A folder left empty goes too; anything else stays.  Nothing goes
    unless ``out_dir`` holds an earlier report (:func:`holds_eval_report`): those names in another folder are not
    this report's to remove.
    """
    out = Path(out_dir)
    earlier = _earlier_report(out)
    if earlier is None:
        return
    names = {"report.json", "report.md", "performance.png"}
    if isinstance(earlier.get("files"), dict):
        # plain names only: a report.json edited by hand must not point this outside the folder
        names |= {f for f in earlier["files"].values() if isinstance(f, str) and f == Path(f).name}
    for seed_dir in sorted(out.glob("*/seed*")):
        if not (seed_dir.is_dir() and seed_dir.name[4:].isdigit()):
            continue
        tum = [seed_dir / n for n in EVAL_TUM_FILES if (seed_dir / n).is_file()]
        if not tum:
            continue
        names |= {f"{seed_dir.parent.name}_{plot}.png" for plot in EVAL_PLOTS}
        for f in tum:
            f.unlink()
        _remove_if_empty(seed_dir)
        _remove_if_empty(seed_dir.parent)
    for name in names:
        f = out / name
        if f.is_file() and not f.is_symlink():
            f.unlink()


def _earlier_report(out: Path) -> dict | None:
    """``out``'s report.json when an earlier :func:`write_eval_report` wrote it (its ``schema``), else None."""
    try:
        earlier = json.loads((out / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return earlier if isinstance(earlier, dict) and earlier.get("schema") == SCHEMA else None


def holds_eval_report(out_dir) -> bool:
    """Whether ``out_dir`` holds an earlier eval's report: a report.json whose ``schema`` is :data:`SCHEMA`."""
    return _earlier_report(Path(out_dir)) is not None


def _remove_if_empty(d: Path) -> None:
    try:
        d.rmdir()
    except OSError:  # not empty: it holds something this report did not write
        pass


def write_eval_report(out_dir, result, planned: int | None = None) -> dict:
    """Write everything for an :class:`groundsim.evaluation.eval.EvalResult` into ``out_dir``; returns ``{what: path}``.

    Files: ``report.json``, ``report.md``, ``<scenario>_trajectory.png``, ``<scenario>_error.png``,
    ``<scenario>_frame.png`` and ``<scenario>_objects.png`` (from the MOT files: every object of a scene, else the target) (first seed of
    each scenario), ``performance.png``, and
    ``<scenario>/seed<N>/{truth,estimate,estimate_perfect}.tum`` for every run; an earlier report's files go
    first (:func:`clear_eval_report`).  ``planned``: the runs asked for, when fewer finished (an interrupted
    eval): both reports then say ``interrupted: N of M runs``.
    """
    out = make_out_dir(out_dir)
    clear_eval_report(out)
    files: dict[str, str] = {}
    ape: dict[str, dict] = {}
    by_scenario: dict[str, list] = {}  # by label: the scenario, or <scenario>_<nav case> when cases are mixed
    multi = len({getattr(r, "nav_noise", "") for r in result.runs}) > 1
    for run in result.runs:
        label = f"{run.scenario}_{run.nav_noise}" if multi else run.scenario
        by_scenario.setdefault(label, []).append(run)
        if run.error is not None:
            continue
        d = out / label / f"seed{run.seed}"
        t = run.time_boot_us / 1e6
        write_tum(d / "truth.tum", t, run.truth_p_ned_m)
        obs = np.all(np.isfinite(run.est_p_ned_m), axis=1) & run.observable
        rows = write_tum(d / "estimate.tum", t[obs], run.est_p_ned_m[obs])
        bobs = np.all(np.isfinite(run.base_p_ned_m), axis=1) & run.base_observable
        write_tum(d / "estimate_perfect.tum", t[bobs], run.base_p_ned_m[bobs])
        tt, pt = read_tum(d / "truth.tum")
        te, pe = read_tum(d / "estimate.tum")
        rmse, n = ape_rmse_m(tt, pt, te, pe)
        ape[f"{label}/seed{run.seed}"] = {
            "rmse_m": rmse,
            "matched": n,
            "estimate_poses": rows,
            "dir": str(d.relative_to(out)),
        }

    descriptions = {}
    tasks: list[tuple] = []  # (key, plot function name, path, args...)
    for name, runs in by_scenario.items():
        descriptions[name] = _short_geometry(runs[0].description)
        ok = [r for r in runs if r.error is None]
        if not ok:
            continue
        r0 = ok[0]
        tasks.append(
            (
                f"{name}_trajectory",
                "plot_trajectory",
                out / f"{name}_trajectory.png",
                r0,
                f"{name} seed {r0.seed}: {descriptions[name]}",
            )
        )
        tasks.append(
            (f"{name}_error", "plot_errors", out / f"{name}_error.png", r0, f"{name} seed {r0.seed}: error over time")
        )
        if r0.frame is not None:
            tasks.append(
                (f"{name}_frame", "plot_frame", out / f"{name}_frame.png", r0.frame, f"{name} seed {r0.seed}: IR frame")
            )
        if getattr(r0, "mot_gt", ""):
            tasks.append(
                (
                    f"{name}_objects",
                    "plot_objects",
                    out / f"{name}_objects.png",
                    r0.mot_gt,
                    r0.mot_tracker,
                    r0.t_s,
                    f"{name} seed {r0.seed}: objects tracked (the MOT files' truth and tracker, paired within 3 px)",
                )
            )
    perf = _performance(result)
    lat = {
        name: np.concatenate([np.asarray(r.timing["process_ms"]) for r in runs if r.error is None] or [np.zeros(0)])
        for name, runs in by_scenario.items()
    }
    tasks.append(
        (
            "performance",
            "plot_performance",
            out / "performance.png",
            perf["per_scenario"],
            lat,
            "processing performance (analogue of the paper's Fig. 9)",
        )
    )
    for key, path in _run_plots(tasks, getattr(result, "workers", 1)):
        files[key] = path

    summary = result.summary
    for row in summary:
        keys = [k for k in ape if k.startswith(row.get("label", row["scenario"]) + "/")]
        vals = [ape[k]["rmse_m"] for k in keys if ape[k]["rmse_m"] is not None and math.isfinite(ape[k]["rmse_m"])]
        row["ape_rmse_m"] = float(np.median(vals)) if vals else None
    report = {
        "schema": SCHEMA,
        "generated_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "options": {
            "seeds": sorted({r.seed for r in result.runs}),
            "workers": result.workers,
            "duration_s": result.options.duration_s,
            "pixel_sigma_px": result.options.pixel_sigma_px,
            "nav_noise": sorted({getattr(r, "nav_noise", "") for r in result.runs}),
            "batch": result.options.batch,
            "onboard_config": result.config_source,
        },
        "interrupted": (
            f"{len(result.runs)} of {planned} runs" if planned is not None and planned > len(result.runs) else None
        ),
        "wall_s": result.wall_s,
        "paper_table2_pct": PAPER_TABLE2_PCT,
        "summary": summary,
        "performance": perf,
        "runs": result.scores,
        "tum_ape": ape,
        "definitions": DEFINITIONS,
        "files": files,
    }
    (out / "report.json").write_text(json.dumps(json_ready(report), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    files["report.json"] = "report.json"
    (out / "report.md").write_text(_markdown(report, descriptions, result), encoding="utf-8")
    files["report.md"] = "report.md"
    return {k: str(out / v) for k, v in files.items()}


def _plot_task(task: tuple) -> tuple[str, str]:
    key, fn, path, *args = task
    return key, str(getattr(report_plots, fn)(path, *args).name)


def _run_plots(tasks: list[tuple], workers: int) -> list[tuple[str, str]]:
    """Draw the plots, over ``workers`` forked processes when more than one (each plot is ~0.5-1 s of CPU)."""
    workers = max(1, min(int(workers or 1), len(tasks)))
    if workers == 1:
        return [_plot_task(t) for t in tasks]
    from groundsim.evaluation.parallel import init_worker, mp_context

    # the workers ignore SIGINT, as the eval's own: a Ctrl-C to the terminal's group must not kill a plot; and they
    # end with this process however it ends
    with mp_context().Pool(workers, initializer=init_worker, initargs=(None, None, os.getpid())) as pool:
        return pool.map(_plot_task, tasks)


def _performance(result) -> dict:
    per = []
    names: list[str] = []
    for r in result.runs:
        if r.scenario not in names:
            names.append(r.scenario)
    for name in names:
        runs = [r for r in result.runs if r.scenario == name and r.error is None]
        if not runs:
            continue
        frames = sum(r.frames for r in runs)
        pm = np.concatenate([np.asarray(r.timing["process_ms"]) for r in runs])
        p50, p90, p99 = np.percentile(pm, [50, 90, 99])
        wall = sum(r.timing["wall_s"] for r in runs)
        cpu = sum(r.timing["cpu_s"] for r in runs)
        per.append(
            {
                "scenario": name,
                "runs": len(runs),
                "frames": frames,
                "pipeline_fps": frames / max(pm.sum() / 1e3, 1e-9),
                "latency_ms": {"p50": p50, "p90": p90, "p99": p99, "max": float(pm.max()), "mean": float(pm.mean())},
                "flight_ms_per_frame": 1e3 * sum(r.timing["flight_s"] for r in runs) / frames,
                "render_ms_per_frame": 1e3 * sum(r.timing["render_s"] for r in runs) / frames,
                "pipeline_ms_per_frame": 1e3 * sum(r.timing["pipeline_s"] for r in runs) / frames,
                "baseline_ms_per_frame": 1e3 * sum(r.timing["baseline_s"] for r in runs) / frames,
                "batch_s_per_run": sum(r.timing["batch_s"] for r in runs) / len(runs),
                "run_wall_s": wall / len(runs),
                "run_cpu_share": cpu / max(wall, 1e-9),
                "loop_fps": frames / max(wall, 1e-9),
            }
        )
    total_cpu = sum(r.timing.get("cpu_s", 0.0) for r in result.runs if r.error is None)
    return {
        "per_scenario": per,
        "eval_wall_s": result.wall_s,
        "eval_frames": sum(r.frames for r in result.runs),
        "eval_fps": sum(r.frames for r in result.runs) / max(result.wall_s, 1e-9),
        "workers": result.workers,
        "worker_cpu_share": total_cpu / max(result.wall_s * result.workers, 1e-9),
    }


def _markdown(report: dict, descriptions: dict, result) -> str:
    o = report["options"]
    perf = report["performance"]
    L = []
    L.append("# irtrack evaluation: lockstep closed loop against the truth\n")
    if report.get("interrupted"):
        L.append(f"**interrupted: {report['interrupted']}**: a partial report, of the runs that finished.\n")
    L.append(
        f"Generated {report['generated_utc']} by `python -m groundsim eval`; scenarios "
        f"{', '.join(r['scenario'] for r in report['summary'])}; seeds {o['seeds']}; {o['workers']} worker process(es); "
        f"wall {report['wall_s']:.1f} s for {perf['eval_frames']} frames ({perf['eval_fps']:.1f} frames/s overall). "
        f"Onboard configuration: {o['onboard_config']} (with the scenario's camera, mount and origin). "
        f"Navigation errors of the telemetry: {', '.join(o['nav_noise'])} (config/noise_cases.yaml). Perfect-centroid "
        f"noise: "
        + (
            "the image chain's measured centroid error per run (table below)"
            if o["pixel_sigma_px"] is None
            else f"{o['pixel_sigma_px']:g} px per axis"
        )
        + ".\n"
    )
    L.append("## Closed loop: what a user gets\n")
    L.append(
        "Medians over seeds, from the pipeline's per-frame Tracks (definitions below), with the goals. "
        "Run `groundsim eval --nav-noise RTK exact` to see realistic and exact navigation side by side.\n"
    )
    L.append(format_closed_loop(report["summary"]))
    L.append("")
    L.append("## Perception: every object, and the selected target\n")
    L.append(
        "Per seed, from the pipeline's tracked objects (the objects chain's confirmed objects, or the single chain's "
        "track) against the scene's truth of every object; the MOT files TrackEval reads are under `mot/`, and its "
        "HOTA is in the table below when it is installed.\n"
    )
    from groundsim.evaluation.mot import format_perception

    L.append(format_perception(report["runs"]))
    L.append("")
    timelines = [(n, report["files"][f"{n}_objects"]) for n in descriptions if f"{n}_objects" in report["files"]]
    if timelines:
        L.append(
            "Who was tracked when (first seed of each scene): a row per object, coloured by the tracked id paired with "
            "it within 3 px (a change of colour is an id switch), red where it was visible and untracked, false "
            "tracks below.\n"
        )
        L += [f"![{n} objects]({f})" for n, f in timelines]
        L.append("")
    L.append("## Reconstruction error beside the paper's Table 2\n")
    L.append(
        "Medians over seeds. Headline: the online track on its observable frames (those the daemon publishes "
        "flagged observable). "
        "The paper's figure is its relative error with its own world origin; ours in the same metric is the "
        '"paper metric" column (definitions below).\n'
    )
    L.append(format_table2(report["summary"], descriptions))
    L.append("")
    L += markdown_head(
        "| scenario | all frames with an estimate: err / range | RMSE m | 2-D continuity | first observable s | "
        "centroid error RMS px (2-D) | perfect-centroid continuity | APE RMSE m (TUM, evo way) | runs failed | reference study: best MAP / CRB m (px0.3) |"
    )
    for r in report["summary"]:
        ref = REFERENCE_PX03.get(r["scenario"])
        L.append(
            f"| {r.get('label', r['scenario'])} | {_f(r.get('all_err_range_pct'), '.2f', ' %')} | {_f(r.get('all_rmse_m'))} | "
            f"{_f(_pct(r.get('continuity_2d')), '.0f', ' %')} | {_f(r.get('first_observable_s'), '.2f')} | "
            f"{_f(r.get('centroid_rms_px'), '.3f')} | {_f(_pct(r.get('perfect_continuity')), '.0f', ' %')} | "
            f"{_f(r.get('ape_rmse_m'), '.3f')} | {r['failed_runs']}/{r['runs']} | "
            f"{'-' if ref is None else f'{ref[0]:.2f} % / {ref[1]:.2f}'} |"
        )
    L.append("")
    verdicts = []
    for r in report["summary"]:
        lab = r.get("label", r["scenario"])
        used = [
            name
            for name, key, failed in (
                ("online", "ratio_to_perfect", "baseline_failed"),
                ("batch", "batch_ratio_to_perfect", "batch_baseline_failed"),
            )
            if r.get(key) is not None and not r.get(failed)
        ]
        failed = [
            name
            for name, failed in (("online", "baseline_failed"), ("batch", "batch_baseline_failed"))
            if r.get(failed)
        ]
        note = f"; {' and '.join(failed)} baseline failed" if failed else ""
        if r.get("within_ratio") is None:
            verdicts.append(f"{lab}: no verdict (no ratio with a sound baseline{note})")
        else:
            verdicts.append(
                f"{lab}: {'within' if r['within_ratio'] else '**NOT within**'} "
                f"{RATIO_LIMIT:g}x ({' and '.join(used)} ratio{note})"
            )
    L.append("Image chain vs perfect centroids: " + "; ".join(verdicts) + ".\n")
    L.append("## Performance (the analogue of the paper's Fig. 9)\n")
    L.append(
        "Lockstep: one process per run does everything in turn, so these are single-core figures. "
        '"pipeline" = `FramePipeline.process` (imaging + pose lookup + estimator), the daemon\'s per-frame work; '
        '"baseline" = the perfect-centroid baseline (the same estimator on true pixels + noise), evaluation only. '
        "Lockstep runs the estimator synchronously, so its model re-selection (about once a second, tenths of a "
        "second) lands on single frames: that is the p99 / max; the daemon runs it in a worker thread (see "
        "`python -m groundsim demo` for its real-time latency).\n"
    )
    L += markdown_head(
        "| scenario | pipeline fps | latency p50 / p90 / p99 / max ms | flight ms/frame | render ms/frame | "
        "pipeline ms/frame | baseline ms/frame | batch s/run | run wall s | CPU share of the run's process |"
    )
    for p in perf["per_scenario"]:
        lm = p["latency_ms"]
        L.append(
            f"| {p['scenario']} | {p['pipeline_fps']:.0f} | {lm['p50']:.1f} / {lm['p90']:.1f} / {lm['p99']:.1f} / "
            f"{lm['max']:.0f} | {p['flight_ms_per_frame']:.1f} | {p['render_ms_per_frame']:.1f} | "
            f"{p['pipeline_ms_per_frame']:.1f} | {p['baseline_ms_per_frame']:.1f} | {p['batch_s_per_run']:.2f} | "
            f"{p['run_wall_s']:.1f} | {100 * p['run_cpu_share']:.0f} % |"
        )
    L.append("")
    L.append(
        f"Whole evaluation: {perf['eval_frames']} frames in {perf['eval_wall_s']:.1f} s with {perf['workers']} worker "
        f"process(es); worker CPU share {100 * perf['worker_cpu_share']:.0f} % of {perf['workers']} core(s) "
        "(below 100 % = the machine was shared or workers idled at the end).\n"
    )
    L.append("![performance](performance.png)\n")
    L.append("## Figures (the analogue of the paper's Fig. 8)\n")
    for name in descriptions:
        for kind in ("trajectory", "error", "frame"):
            f = report["files"].get(f"{name}_{kind}")
            if f:
                L.append(f"![{name} {kind}]({f})")
        L.append("")
    L.append("## Runs\n")
    L += markdown_head(
        "| scenario | seed | err / range | RMSE m | NEES | continuity | perfect err / range | batch err / range | CRB m | "
        "centroid RMS px | pipeline fps | wall s | note |"
    )
    for s in report["runs"]:
        if "error" in s:
            L.append(
                f"| {s['scenario']} | {s['seed']} | - | - | - | - | - | - | - | - | - | - | failed: {s['error']} |"
            )
            continue
        on = s.get("online_observable") or {}
        pf = s.get("perfect_observable") or {}
        b = s.get("batch") or {}
        L.append(
            f"| {s['scenario']} | {s['seed']} | {_f(on.get('err_range_pct'), '.2f', ' %')} | {_f(on.get('rmse_m'))} | "
            f"{_f(on.get('mean_nees'))} | {_f(_pct(s.get('continuity')), '.0f', ' %')} | "
            f"{_f(pf.get('err_range_pct'), '.2f', ' %')} | "
            f"{_f(_get(b, 'pipeline', 'metrics', 'err_range_pct'), '.2f', ' %')} | {_f(b.get('crb_rms_m'))} | "
            f"{_f(s.get('centroid_rms_px'), '.3f')} | {s['timing']['pipeline_fps']:.0f} | {s['timing']['wall_s']:.1f} | "
            f"{on.get('note', '')} |"
        )
    L.append("")
    L.append("## TUM trajectories\n")
    L.append(
        "Per run: `<scenario>/seed<N>/truth.tum` (every frame processed), `estimate.tum` (online track, observable frames), "
        "`estimate_perfect.tum` (perfect-centroid baseline). Columns `timestamp tx ty tz qx qy qz qw`: boot-clock "
        "seconds, local NED metres about the scenario origin, identity attitude. Score one with evo:\n"
    )
    # evo refuses a TUM file without poses ("must have 8 entries per row"): the example takes one that has some
    first = next(((k, v) for k, v in report["tum_ape"].items() if v.get("estimate_poses", 1) > 0), None)
    empty = [k for k, v in report["tum_ape"].items() if v.get("estimate_poses", 1) == 0]
    if empty:
        L.append(
            f"No frame was observable in {', '.join(empty)}: `estimate.tum` there holds its header line only, which "
            "evo refuses.\n"
        )
    if first is not None:
        key, v = first
        L.append(f"    evo_ape tum {v['dir']}/truth.tum {v['dir']}/estimate.tum\n")
        L.append(
            f"Our APE RMSE for {key} the same way (nearest stamp within {EVO_MAX_DIFF_S} s, no alignment, "
            f"translation): {_f(v['rmse_m'], '.4f')} m over {v['matched']} poses.\n"
        )
    L.append("## Definitions\n")
    for k, v in DEFINITIONS.items():
        L.append(f"- **{k}**: {v}")
    L.append("")
    return "\n".join(L)


def _get(d, *keys):
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d
