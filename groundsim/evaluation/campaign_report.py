"""A campaign's table (``runs.csv``, ``runs.parquet``) and report (``report.md``, ``manoeuvre.png``), rebuilt from
its run log every time (:mod:`groundsim.evaluation.campaign` describes the campaign and its figures).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from groundsim.evaluation.campaign_spec import CampaignSpec
from groundsim.evaluation.out_dir import write_replacing
from groundsim.evaluation.report import markdown_head

__all__ = [
    "TABLE_NAME",
    "PARQUET_NAME",
    "REPORT_NAME",
    "FIGURE_NAME",
    "TIMING_COLUMNS",
    "GOOD_ERR_PCT",
    "COLUMN_ORDER",
    "table_rows",
    "write_table",
    "table2_rows",
    "paper_table2_pct",
    "manoeuvre_rows",
    "works_from",
    "write_report",
]

log = logging.getLogger(__name__)

#: the noise cases of the reference study the paper's scenarios come with (/work/shared/REFERENCE_SCENARIOS.md);
#: ``exact`` is the simulator's own, no measurement the paper could have made
PAPER_NOISE_CASES = frozenset({"px0.3", "RTK", "GNSS"})
PAPER_DURATION_S = 10.0  # the paper's Table 2: F = 300 frames at 30 Hz
GOOD_ERR_PCT = 2.0  # "reconstruction works": median err/range at most this (the verdict table's good run)
HONEST_BEYOND_3SIGMA = 0.01  # a run is honest when at most this fraction of published estimates is beyond 3 sigma
TABLE_NAME, PARQUET_NAME, REPORT_NAME, FIGURE_NAME = "runs.csv", "runs.parquet", "report.md", "manoeuvre.png"
#: columns that are measurements of the machine, not results: left out when tables are compared
TIMING_COLUMNS = ("wall_s", "case_wall_s")


# --------------------------------------------------------------------------- the table


#: the table's columns, in order: identity and parameters, geometry measured, the run's figures, the case's
#: bound, status, provenance, timings (columns a newer version adds come after, alphabetically)
COLUMN_ORDER = (
    "run_id",
    "mode",
    "scenario",
    "geometry",
    "range_scale",
    "aspect_deg",
    "manoeuvre_scale",
    "noise",
    "algorithm",
    "seed",
    "duration_s",
    "noise_model",
    "status",
    "range_start_m",
    "range_median_m",
    "aspect_start_deg",
    "observer_accel_rms_mps2",
    "observer_accel_perp_los_rms_mps2",
    "frames",
    "published_frames",
    "observable_frames",
    "settle_s",
    "err_range_observable_pct",
    "err_range_published_settled_pct",
    "err_range_final_pct",
    "rmse_observable_m",
    "rmse_published_settled_m",
    "observable_share_settled",
    "beyond_3sigma_published",
    "beyond_3sigma_observable",
    "nees_observable",
    "nees_published_settled",
    "first_observable_s",
    "published_share_after_3s",
    "chain_centroid_sigma_px",
    "pd_pct",
    "false_tracks_per_min",
    "id_switches",
    "state_accuracy",
    "crb",
    "crb_rms_m",
    "crb_range_sigma_pct",
    "batch_err_range_pct",
    "batch_observable",
    "bound_note",
    "error",
    "estimator_errors",
    "scenario_digest",
    "noise_digest",
    "onboard_digest",
    "schema",
) + TIMING_COLUMNS


def table_rows(rows: list[dict]):
    """Rows -> a pandas DataFrame with a fixed column order (parameters, then figures, then timings)."""
    import pandas as pd

    df = pd.DataFrame(rows)
    if df.empty:
        return pd.DataFrame(columns=list(COLUMN_ORDER))
    known = [c for c in COLUMN_ORDER if c in df.columns]
    return df[known + sorted(c for c in df.columns if c not in COLUMN_ORDER)]


def write_table(out: Path, rows: list[dict]) -> dict:
    """``runs.csv`` (always) and ``runs.parquet`` (when pyarrow is installed), each replaced whole."""
    df = table_rows(rows)
    files = {TABLE_NAME: out / TABLE_NAME}
    write_replacing(out / TABLE_NAME, lambda p: df.to_csv(p, index=False))
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        pass
    else:
        write_replacing(out / PARQUET_NAME, lambda p: df.to_parquet(p, index=False))
        files[PARQUET_NAME] = out / PARQUET_NAME
    return files


# --------------------------------------------------------------------------- the report


def _med(values) -> float:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.median(v)) if v else math.nan


def _pct(x, nd=2) -> str:
    return "-" if not math.isfinite(x) else f"{x:.{nd}f} %"


def _num(x, nd=2) -> str:
    return "-" if not math.isfinite(x) else f"{x:.{nd}f}"


# the per-run figures summarised by their median over a group's runs: table key -> runs.csv column
_ACCURACY_MEDIANS = {
    "err_obs": "err_range_observable_pct",
    "err_pub": "err_range_published_settled_pct",
    "err_final": "err_range_final_pct",
    "rmse_obs": "rmse_observable_m",
    "rmse_pub": "rmse_published_settled_m",
    "obs_share": "observable_share_settled",
    "nees": "nees_observable",
    "nees_pub": "nees_published_settled",
    "crb": "crb_rms_m",
    "crb_sig": "crb_range_sigma_pct",
    "batch": "batch_err_range_pct",
}
_MANOEUVRE_MEDIANS = {
    "accel_perp_mps2": "observer_accel_perp_los_rms_mps2",
    "accel_mps2": "observer_accel_rms_mps2",
    "err_pub": "err_range_published_settled_pct",
    "err_obs": "err_range_observable_pct",
    "err_final": "err_range_final_pct",
    "obs_share": "observable_share_settled",
}


def _medians(rs: list[dict], columns: dict[str, str]) -> dict:
    """``{key: median of column over rs}`` (None values skipped, as :func:`_med`)."""
    return {key: _med(r.get(col) for r in rs) for key, col in columns.items()}


def table2_rows(rows: list[dict], shipped: dict[str, str] | None = None) -> tuple[list[dict], bool]:
    """Per (algorithm, scenario, noise): medians over the runs at the reference geometry (or over every
    geometry when the campaign has no reference-geometry runs: the flag says which), and ``paper_pct``, the paper's
    figure where it applies (:func:`paper_table2_pct` with ``shipped``, the shipped scenarios' digests; NaN
    without them)."""
    ok = [r for r in rows if r.get("status") == "ok"]
    ref = [r for r in ok if r["range_scale"] == 1.0 and r["aspect_deg"] == 0.0 and r["manoeuvre_scale"] == 1.0]
    use, at_ref = (ref, True) if ref else (ok, False)
    keys = list(dict.fromkeys((r["algorithm"], r["scenario"], r["noise"]) for r in use))
    out = []
    for a, s, n in keys:
        rs = [r for r in use if (r["algorithm"], r["scenario"], r["noise"]) == (a, s, n)]
        honest = [
            r
            for r in rs
            if r.get("beyond_3sigma_published") is not None and r["beyond_3sigma_published"] <= HONEST_BEYOND_3SIGMA
        ]
        out.append(
            {
                "algorithm": a,
                "scenario": s,
                "noise": n,
                "runs": len(rs),
                **_medians(rs, _ACCURACY_MEDIANS),
                "honest": len(honest),
                "paper_pct": paper_table2_pct(rs, at_ref, shipped) if shipped is not None else math.nan,
            }
        )
    return out, at_ref


def paper_table2_pct(rs: list[dict], at_ref: bool, shipped_digests: dict[str, str]) -> float:
    """The paper's Table 2 figure for a group of runs (one scenario and noise case), NaN where the paper has none:
    unless the runs are at the reference geometry (``at_ref``), of one of its scenarios as shipped (the row's
    ``scenario_digest`` is ``shipped_digests[name]``: a file of that name saying something else is another
    scenario), under a noise case of the reference study (:data:`PAPER_NOISE_CASES`) and flown whole
    (:data:`PAPER_DURATION_S`)."""
    from groundsim.evaluation.report import PAPER_TABLE2_PCT

    if not rs or not at_ref:
        return math.nan
    s = rs[0]["scenario"]
    if s not in PAPER_TABLE2_PCT or any(r.get("scenario_digest") != shipped_digests.get(s) for r in rs):
        return math.nan
    if any(r["noise"] not in PAPER_NOISE_CASES for r in rs):
        return math.nan
    if any(r.get("duration_s") is not None and r["duration_s"] < PAPER_DURATION_S - 1e-9 for r in rs):
        return math.nan
    return float(PAPER_TABLE2_PCT[s])


def _shipped_digests() -> dict[str, str]:
    """Digest of each of the paper's scenarios as shipped (config/scenarios), by name."""
    from groundsim.evaluation.report import PAPER_TABLE2_PCT
    from groundsim.world.scenario import reference_scenario_paths, scenario_digest

    paths = reference_scenario_paths()
    return {name: scenario_digest(paths[name]) for name in PAPER_TABLE2_PCT if name in paths}


def manoeuvre_rows(rows: list[dict]) -> list[dict]:
    """Per (algorithm, scenario, noise, manoeuvre_scale) over reference range and aspect if swept at
    those (else all): the measured observer acceleration (RMS normal to the line of sight, median) and
    the median err/range of the published estimates once settled; the CRB as RMS / median range."""
    ok = [r for r in rows if r.get("status") == "ok"]
    base = [r for r in ok if r["range_scale"] == 1.0 and r["aspect_deg"] == 0.0]
    use = base if len({r["manoeuvre_scale"] for r in base}) > 1 else ok
    keys = list(dict.fromkeys((r["algorithm"], r["scenario"], r["noise"], r["manoeuvre_scale"]) for r in use))
    out = []
    for a, s, n, m in keys:
        rs = [r for r in use if (r["algorithm"], r["scenario"], r["noise"], r["manoeuvre_scale"]) == (a, s, n, m)]
        crb_pct = [
            100 * r["crb_rms_m"] / r["range_median_m"]
            for r in rs
            if r.get("crb_rms_m") is not None and r.get("range_median_m")
        ]
        out.append(
            {
                "algorithm": a,
                "scenario": s,
                "noise": n,
                "manoeuvre_scale": m,
                "runs": len(rs),
                **_medians(rs, _MANOEUVRE_MEDIANS),
                "crb_pct": _med(crb_pct),
            }
        )
    return out


#: how confident_wrong_rows groups the runs: a label and the row's key (None: every run)
_CONFIDENT_WRONG_GROUPS = (
    ("all runs", None),
    ("scenario", "scenario"),
    ("manoeuvre_scale", "manoeuvre_scale"),
    ("range_scale", "range_scale"),
    ("aspect_deg", "aspect_deg"),
)


def confident_wrong_rows(rows: list[dict]) -> list[dict]:
    """Per algorithm and group (every run, then per scenario and per geometry axis): the frames called
    observable, how many of them lie beyond 3 sqrt(trace cov) (each run's ``beyond_3sigma_observable`` times its
    ``observable_frames``, summed: the confident and wrong positions), their share, and the runs with more than
    1 % of their observable frames beyond."""
    ok = [r for r in rows if r.get("status") == "ok"]
    out = []
    for a in dict.fromkeys(r["algorithm"] for r in ok):
        rs_a = [r for r in ok if r["algorithm"] == a]
        for label, key in _CONFIDENT_WRONG_GROUPS:
            values = [None] if key is None else list(dict.fromkeys(r[key] for r in rs_a))
            if key is not None and len(values) < 2:
                continue  # one value: the same figures as "all runs"
            for v in values:
                rs = rs_a if key is None else [r for r in rs_a if r[key] == v]
                frames = wrong = over = 0
                for r in rs:
                    n = int(r.get("observable_frames") or 0)
                    b = r.get("beyond_3sigma_observable")
                    if not n or b is None or not math.isfinite(b):
                        continue
                    frames += n
                    wrong += round(n * b)
                    over += b > HONEST_BEYOND_3SIGMA
                out.append(
                    {
                        "algorithm": a,
                        "group": label if key is None else f"{label} {v:g}" if isinstance(v, float) else f"{label} {v}",
                        "runs": len(rs),
                        "observable_frames": frames,
                        "beyond_frames": wrong,
                        "beyond_pct": 100.0 * wrong / frames if frames else math.nan,
                        "runs_over": over,
                    }
                )
    return out


def works_from(mrows: list[dict], good_pct: float = GOOD_ERR_PCT) -> list[dict]:
    """Per (algorithm, scenario, noise): the smallest measured manoeuvre (RMS acceleration normal to the
    line of sight) from which every larger swept level has a median err/range <= ``good_pct``."""
    out = []
    for key in dict.fromkeys((r["algorithm"], r["scenario"], r["noise"]) for r in mrows):
        rs = sorted(
            (r for r in mrows if (r["algorithm"], r["scenario"], r["noise"]) == key), key=lambda r: r["accel_perp_mps2"]
        )
        good = [math.isfinite(r["err_pub"]) and r["err_pub"] <= good_pct for r in rs]
        start = None
        for i in range(len(rs) - 1, -1, -1):
            if not good[i]:
                break
            start = rs[i]
        out.append(
            {
                "algorithm": key[0],
                "scenario": key[1],
                "noise": key[2],
                "levels": len(rs),
                "works_from_mps2": start["accel_perp_mps2"] if start else math.nan,
                "works_from_scale": start["manoeuvre_scale"] if start else math.nan,
            }
        )
    return out


def write_report(out: Path, spec: CampaignSpec, rows: list[dict], run_info: dict) -> dict:
    """``report.md`` (+ ``manoeuvre.png`` when two or more manoeuvre levels were swept), each replaced whole."""
    from groundsim.evaluation.report import PAPER_TABLE2_PCT

    files = {}
    ok = [r for r in rows if r.get("status") == "ok"]
    failed = [r for r in rows if r.get("status") != "ok"]
    t2, at_ref = table2_rows(rows, _shipped_digests())
    mrows = manoeuvre_rows(rows)
    from groundsim.evaluation.campaign_plots import plot_manoeuvre
    from groundsim.evaluation.scoring import OBSERVABLE_AFTER_S

    has_fig = write_replacing(out / FIGURE_NAME, lambda p: plot_manoeuvre(p, mrows, GOOD_ERR_PCT, OBSERVABLE_AFTER_S))
    if has_fig:
        files[FIGURE_NAME] = out / FIGURE_NAME
    else:  # an earlier sweep's figure beside this sweep's report would be read as this one's
        (out / FIGURE_NAME).unlink(missing_ok=True)
    L = [f"# Campaign {spec.name}\n"]
    L.append(
        f"Spec `{spec.source}`: mode {spec.mode}, scenarios {', '.join(spec.scenarios)}, noise "
        f"{', '.join(spec.noise)}, algorithms {', '.join(spec.algorithms)}, seeds {len(spec.seeds)}, "
        f"{len(spec.geometries)} geometr{'y' if len(spec.geometries) == 1 else 'ies'}, estimator noise model: "
        f"{spec.noise_model}.\n"
    )
    ri = run_info
    rate = 60.0 * ri["ran"] / ri["wall_s"] if ri["wall_s"] > 0 and ri["ran"] else math.nan
    L.append(
        f"{len(rows)} of {ri['planned']} runs in the table ({len(failed)} failed); this invocation reused "
        f"{ri['reused']}, ran {ri['ran']} in {ri['wall_s']:.1f} s on {ri['workers']} worker(s)"
        f"{f' ({rate:.1f} runs/min)' if math.isfinite(rate) else ''}"
        f"{'; INTERRUPTED: run the same command to resume' if ri['interrupted'] else ''}. "
        f"Table: `{TABLE_NAME}` (one row per run).\n"
    )
    L.append("## Table 2 analogue, per algorithm\n")
    L.append(
        (
            "Runs at the reference geometry (range, aspect and manoeuvre of the shipped scenario)."
            if at_ref
            else "No run at the reference geometry: medians over every geometry of the campaign."
        )
        + " Medians over the runs that have the figure (a run with no observable frame has no err/range observable)."
        " *observable*: err/range on the frames the algorithm called observable; *published*: "
        "every finite estimate once *settled* (from 5 s on; half the run if shorter than 10 s); *final*: last frame. Honest: runs with at most 1 % of published "
        "estimates beyond 3 sqrt(trace cov), from the first frame (NEES (published) is over the settled ones). CRB: "
        "Bayesian bound at the truth (RMS over the window); CRB range sigma: its median range sigma over range. "
        f"*paper Table 2*: the paper's figure, given only beside its own scenarios ({', '.join(PAPER_TABLE2_PCT)} "
        "as shipped) at the reference geometry, flown whole "
        f"({PAPER_DURATION_S:g} s) under a noise case of the reference study ({', '.join(sorted(PAPER_NOISE_CASES))}); "
        "'-' elsewhere, where the paper has no figure.\n"
    )
    for a in dict.fromkeys(r["algorithm"] for r in t2):
        L.append(f"### {a}\n")
        L += markdown_head(
            "| scenario | noise | runs | paper Table 2 | err/range observable | err/range published | final | "
            "RMSE m (published) | observable share (settled) | honest | NEES (published, settled) | CRB RMS m | "
            "CRB range sigma | batch MAP err/range |"
        )
        for r in (x for x in t2 if x["algorithm"] == a):
            L.append(
                f"| {r['scenario']} | {r['noise']} | {r['runs']} | {_pct(r['paper_pct'])} | "
                f"{_pct(r['err_obs'])} | {_pct(r['err_pub'])} | {_pct(r['err_final'])} | {_num(r['rmse_pub'])} | "
                f"{_pct(100 * r['obs_share'], 0)} | {r['honest']}/{r['runs']} | {_num(r['nees_pub'], 1)} | "
                f"{_num(r['crb'])} | {_pct(r['crb_sig'], 1)} | {_pct(r['batch'])} |"
            )
        L.append("")
    if mrows and len({r["manoeuvre_scale"] for r in mrows}) > 1:
        L.append("## Error vs observer manoeuvre\n")
        L.append(f"![error vs manoeuvre]({FIGURE_NAME})\n")
        L.append(
            "The observer's acceleration is scaled (manoeuvre_scale), measured as its RMS normal to the line "
            f"of sight over the window. *Works from*: the smallest measured level from which every larger "
            f"level swept has a median err/range <= {GOOD_ERR_PCT:g} % (published estimates, settled).\n"
        )
        L += markdown_head(
            "| algorithm | scenario | noise | levels | works from (m/s^2, normal to LOS) | manoeuvre_scale |"
        )
        for w in works_from(mrows):
            L.append(
                f"| {w['algorithm']} | {w['scenario']} | {w['noise']} | {w['levels']} | "
                f"{_num(w['works_from_mps2'], 3) if math.isfinite(w['works_from_mps2']) else 'not in the range swept'} | "
                f"{_num(w['works_from_scale'], 3)} |"
            )
        L.append("")
        L += markdown_head(
            "| algorithm | scenario | noise | manoeuvre_scale | runs | accel normal to LOS m/s^2 | err/range published | "
            "err/range last frame | err/range observable | observable share | CRB / range |"
        )
        for r in mrows:
            L.append(
                f"| {r['algorithm']} | {r['scenario']} | {r['noise']} | {r['manoeuvre_scale']:g} | {r['runs']} | "
                f"{_num(r['accel_perp_mps2'], 3)} | {_pct(r['err_pub'])} | {_pct(r['err_final'])} | {_pct(r['err_obs'])} | "
                f"{_pct(100 * r['obs_share'], 0)} | {_pct(r['crb_pct'])} |"
            )
        L.append("")
    L.append("## Confident and wrong\n")
    L.append(
        "Observable frames (positions the algorithm called observable) beyond 3 sqrt(trace cov): the positions a "
        f"consumer would trust and should not. Runs over {100 * HONEST_BEYOND_3SIGMA:g} %: runs with more than "
        f"{100 * HONEST_BEYOND_3SIGMA:g} % of their observable frames beyond. Every geometry of the campaign, grouped "
        "by each axis it sweeps.\n"
    )
    L += markdown_head(
        f"| algorithm | runs of | runs | observable frames | beyond 3 sigma | share | runs over {100 * HONEST_BEYOND_3SIGMA:g} % |"
    )
    for r in confident_wrong_rows(rows):
        L.append(
            f"| {r['algorithm']} | {r['group']} | {r['runs']} | {r['observable_frames']} | {r['beyond_frames']} | "
            f"{_pct(r['beyond_pct'])} | {r['runs_over']} |"
        )
    L.append("")
    if failed:
        L.append("## Failed runs\n")
        for r in failed[:50]:
            L.append(
                f"- {r['scenario']} {r['geometry']} {r['noise']} {r['algorithm']} seed {r['seed']}: {r.get('error')}"
            )
        L.append("")
    # a plug-in that raised on frames finishes its run (status ok, the frames it failed on counted): its table row
    # above reads '-' with nothing saying why, so the runs and their first error are named here
    erred = [r for r in ok if (r.get("estimator_errors") or 0) > 0]
    if erred:
        L.append("## Runs with estimator errors\n")
        L.append("Runs that finished while their estimator raised on frames (those frames have no estimate):\n")
        for r in erred[:50]:
            L.append(
                f"- {r['scenario']} {r['geometry']} {r['noise']} {r['algorithm']} seed {r['seed']}: "
                f"{int(r['estimator_errors'])} frames, the first: {r.get('error') or '-'}"
            )
        L.append("")
    write_replacing(out / REPORT_NAME, lambda p: p.write_text("\n".join(L), encoding="utf-8"))
    files[REPORT_NAME] = out / REPORT_NAME
    log.debug("report: %d ok rows", len(ok))
    return files
