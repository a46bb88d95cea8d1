"""Plots of a recorded flight (``python -m onboard.replay FILE.mcap --report DIR``), with the eval report's own
plotting functions (:func:`groundsim.evaluation.report_plots.plot_trajectory`, :func:`~groundsim.evaluation.report_plots.plot_errors`,
:func:`~groundsim.evaluation.report_plots.plot_frame`), so a field flight is reviewed like a simulated one.

The tracks (replayed, or as recorded) give the online reconstruction; the recorded poses give the camera's path;
the truth comes from a simulator recording (``groundsim run --record``, channel ``/groundsim/truth``) when one
is given, matched frame by frame on (seq, time_boot_us) and put in the tracks' local NED frame through its
WGS84 coordinates.  Without truth: the trajectory plot (estimate and camera path only) and the frame.
Writes ``trajectory.png``, ``errors.png`` (truth only), ``frame.png``, ``objects.png`` (the objects image chain's
objects against the simulator's labels of every object, ``/groundsim/truth/objects``: who was tracked when, as
``groundsim eval`` draws it), ``summary.json``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["REPORT_SCHEMA", "FlightRun", "flight_run", "holds_flight_report", "write_flight_report"]


@dataclass(frozen=True)
class FlightRun:
    """What :mod:`groundsim.evaluation.report`'s plots read of a run (the attributes they use), one row per track (F).

    ``t_s`` (F,) capture time on the boot clock; ``est_p_ned_m`` (F, 3) NaN without an estimate;
    ``est_cov_ned_m2`` (F, 3, 3); ``observable`` (F,); ``truth_p_ned_m`` (F, 3) NaN without truth;
    ``observer_p_ned_m`` (F, 3) the camera; ``range_m`` (F,) true range (else the estimate's)."""

    scenario: str
    seed: str
    t_s: np.ndarray
    est_p_ned_m: np.ndarray
    est_cov_ned_m2: np.ndarray
    observable: np.ndarray
    truth_p_ned_m: np.ndarray
    observer_p_ned_m: np.ndarray
    range_m: np.ndarray
    base_p_ned_m: np.ndarray
    base_observable: np.ndarray
    batch: dict | None = None

    @property
    def has_truth(self) -> bool:
        return bool(np.isfinite(self.truth_p_ned_m).all(axis=1).any())


def _nan3(n: int) -> np.ndarray:
    return np.full((n, 3), np.nan)


def flight_run(tracks: list, poses: dict, truth: list | None, name: str) -> FlightRun:
    """Arrays of a flight: ``tracks`` (irtrack.track dicts), ``poses`` {(seq, t_us): p_cam_ned_m}, ``truth``
    (irtrack.truth/1 dicts) or None."""
    from onboard.core.frames import GeodeticOrigin, ned_from_geodetic

    n = len(tracks)
    t = np.array([tr["time_boot_us"] / 1e6 for tr in tracks], dtype=float)
    est, cam, tru = _nan3(n), _nan3(n), _nan3(n)
    cov = np.full((n, 3, 3), np.nan)
    obs = np.zeros(n, dtype=bool)
    origin = next((tr["origin"] for tr in tracks if tr.get("origin")), None)
    by_key = {(int(r["seq"]), int(r["time_boot_us"])): r for r in (truth or [])}
    for i, tr in enumerate(tracks):
        if tr.get("ned_m") is not None:
            est[i] = tr["ned_m"]
            if tr.get("cov_ned_m2") is not None:
                cov[i] = tr["cov_ned_m2"]
            obs[i] = bool(tr.get("observable"))
        key = (int(tr["seq"]), int(tr["time_boot_us"]))
        p = poses.get(key)
        if p is not None:
            cam[i] = p
        elif tr.get("camera_ned_m") is not None:
            cam[i] = tr["camera_ned_m"]
        row = by_key.get(key)
        if row is not None and origin is not None:
            o = GeodeticOrigin(origin["lat_deg"], origin["lon_deg"], origin["alt_m"])
            tru[i] = ned_from_geodetic(row["target_lat_deg"], row["target_lon_deg"], row["target_alt_m"], o)
    with np.errstate(invalid="ignore"):
        rng = np.linalg.norm(np.where(np.isfinite(tru), tru, est) - cam, axis=1)
    return FlightRun(name, "", t, est, cov, obs, tru, cam, rng, _nan3(n), np.zeros(n, dtype=bool))


#: every file :func:`write_flight_report` may write in its folder
REPORT_FILES = ("trajectory.png", "errors.png", "frame.png", "objects.png", "summary.json")
#: summary.json's ``schema``: what marks a folder as a flight report's
REPORT_SCHEMA = "irtrack.flight_report/1"
#: the keys of a summary.json written before it carried ``schema``
_UNMARKED_SUMMARY_KEYS = frozenset({"frames", "with_3d", "observable", "truth"})


def holds_flight_report(out_dir) -> bool:
    """Whether ``out_dir`` holds an earlier :func:`write_flight_report`'s files, which the next one replaces: its
    summary.json (``schema`` :data:`REPORT_SCHEMA`, or the keys of one written before the schema), or nothing but
    files of its names (a report cut short before its summary.json)."""
    out = Path(out_dir)
    if (out / "summary.json").exists():
        try:
            summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(summary, dict) and (
            summary.get("schema") == REPORT_SCHEMA
            or ("schema" not in summary and _UNMARKED_SUMMARY_KEYS <= summary.keys())
        )
    try:  # summary.json is written last: without it, a report cut short holds its plots alone
        return all(p.name in REPORT_FILES and p.is_file() and not p.is_symlink() for p in out.iterdir())
    except OSError:
        return False


def write_flight_report(
    out_dir,
    tracks: list,
    poses: dict,
    frames: dict,
    truth: list | None,
    name: str,
    summary_extra: dict | None = None,
    objects: list | None = None,
    truth_objects: list | None = None,
) -> list[Path]:
    """Write the plots (module docstring); ``frames`` {(seq, t_us): pixels (H, W)} for the frame plot;
    ``summary_extra``: what the caller knows of its inputs, written into ``summary.json`` beside what the report
    drew.  ``objects`` (the image chain's ``irtrack.objects/1`` messages) and ``truth_objects`` (the simulator's
    ``irtrack.truth_objects/1``), both given: ``objects.png``, who was tracked when (as ``groundsim eval`` draws it).
    Returns the paths written."""
    from groundsim.evaluation.report_plots import plot_errors, plot_frame, plot_objects, plot_trajectory

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    run = flight_run(tracks, poses, truth, name)
    written = [
        plot_trajectory(
            out / "trajectory.png",
            run,
            f"{name}: reconstruction" + (" vs truth" if run.has_truth else " (no truth in the recording)"),
        )
    ]
    summary: dict = {
        "schema": REPORT_SCHEMA,
        "frames": len(tracks),
        "with_3d": int(np.isfinite(run.est_p_ned_m).all(axis=1).sum()),
        "observable": int(run.observable.sum()),
        "truth": run.has_truth,
    }
    if run.has_truth:
        written.append(plot_errors(out / "errors.png", run, f"{name}: reconstruction error"))
        has = np.isfinite(run.est_p_ned_m).all(axis=1) & np.isfinite(run.truth_p_ned_m).all(axis=1)
        sel = has & run.observable
        if sel.any():
            e = np.linalg.norm(run.est_p_ned_m[sel] - run.truth_p_ned_m[sel], axis=1) / run.range_m[sel]
            summary["median_error_over_range_observable"] = float(np.median(e))
    if truth:
        truth_by = {(int(r["seq"]), int(r["time_boot_us"])): r for r in truth}
        d_px = [
            math.hypot(tr["u_px"] - r["target_u_px"], tr["v_px"] - r["target_v_px"])
            for tr in tracks
            if tr.get("u_px") is not None
            and (r := truth_by.get((int(tr["seq"]), int(tr["time_boot_us"]))))
            and r.get("target_u_px") is not None
        ]
        if d_px:  # the truth matched to the right frames: the track centre sits on the true pixel
            summary["median_track_to_truth_px"] = float(np.median(d_px))
    # the frame: the middle one of those with a box (tracking), else the middle frame
    keyed = [(i, (int(tr["seq"]), int(tr["time_boot_us"]))) for i, tr in enumerate(tracks)]
    boxed = [(i, k) for i, k in keyed if tracks[i].get("bbox") is not None and k in frames]
    pick = boxed or [(i, k) for i, k in keyed if k in frames]
    if pick:
        i, k = pick[len(pick) // 2]
        tr = tracks[i]
        truth_row = {(int(r["seq"]), int(r["time_boot_us"])): r for r in (truth or [])}.get(k)
        tuv = None
        if truth_row is not None and truth_row.get("target_u_px") is not None:
            tuv = (truth_row["target_u_px"], truth_row["target_v_px"])
        rng = run.range_m[i]
        written.append(
            plot_frame(
                out / "frame.png",
                {
                    "pixels": frames[k],
                    "k": tr["seq"],
                    "t_s": tr["time_boot_us"] / 1e6,
                    "state": tr.get("state"),
                    "bbox": tr.get("bbox"),
                    "uv_px": None if tr.get("u_px") is None else (tr["u_px"], tr["v_px"]),
                    "truth_uv_px": tuv,
                    "range_m": float(rng) if math.isfinite(rng) else math.nan,
                },
                f"{name}: frame {tr['seq']}",
            )
        )
        summary["frame_seq"] = tr["seq"]
    if objects and (truth_objects or truth):  # (no scene: the target alone, from the truth rows)
        from groundsim.evaluation.mot import recorded_mot

        gt, trk, t_s = recorded_mot(truth_objects or [], objects, truth)
        if gt:
            written.append(
                plot_objects(out / "objects.png", gt, trk, t_s, f"{name}: objects tracked (paired within 3 px)")
            )
    (out / "summary.json").write_text(json.dumps(summary | (summary_extra or {}), indent=1) + "\n")
    written.append(out / "summary.json")
    # an earlier report in the same folder (with truth, or with a frame) must not leave its plot beside this one
    for stale in set(REPORT_FILES) - {p.name for p in written}:
        (out / stale).unlink(missing_ok=True)
    return written
