"""In-the-loop multi-object files of ``groundsim eval`` in the layout TrackEval reads (MOT Challenge 2-D boxes).

Per run, ``SEQ = <scenario>-<nav>-s<seed>``::

    OUT/mot/gt/<SEQ>/gt/gt.txt          frame,id,x,y,w,h,visible,class,visibility   (truth of every object)
    OUT/mot/gt/<SEQ>/seqinfo.ini        name, seqLength, imWidth, imHeight, frameRate
    OUT/mot/trackers/irtrack/data/<SEQ>.txt   frame,id,x,y,w,h,score,-1,-1,-1   (the pipeline's objects)
    OUT/mot/seqmap.txt                  "name" then one SEQ a line (TrackEval's SEQMAP_FILE)

Frames are numbered from 1 in both (frame k of the run is k + 1); x, y 1-based (MOT's convention).
gt's 7th column is 1 for a visible object and 0 otherwise (occluded, out of frame); every object is class
1 (pedestrian, the class TrackEval evaluates): irtrack tracks every warm moving object.  Ids are the
scene's object id + 1 (the target is 1); without a scene only the target, from the truth row.

Boxes: the objects are points of a few pixels, and IoU of 2 x 2 px boxes is 0 after a 2 px shift, so
both the truth's and the tracker's boxes are squares of ``BOX_SIDE_PX`` about their centres (IoU 0.5 at
a 2 px offset along one axis).  The tracker's objects: every confirmed object of the objects image chain
(``imaging.chain: objects``), or the single chain's track while ``tracking``.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

__all__ = ["BOX_SIDE_PX", "gt_rows", "tracker_rows", "seq_name", "write_mot", "clear_mot"]

BOX_SIDE_PX = 6.0


def _box(u: float, v: float) -> str:
    h = BOX_SIDE_PX / 2
    return f"{u - h + 1.0:.3f},{v - h + 1.0:.3f},{BOX_SIDE_PX:.3f},{BOX_SIDE_PX:.3f}"


def gt_rows(frame: int, labels, truth_uv=None, truth_visible: bool = False) -> list[str]:
    """gt.txt lines of one frame (1-based ``frame``): ``labels`` the scene's ObjectLabels, else the
    target from ``truth_uv`` (u, v) and ``truth_visible``."""
    rows = []
    if labels:
        for o in labels:
            if not (math.isfinite(o.u_px) and math.isfinite(o.v_px)) or o.visibility == "out_of_frame":
                continue
            vis = 1 if o.visibility == "visible" else 0
            rows.append(f"{frame},{int(o.object_id) + 1},{_box(o.u_px, o.v_px)},{vis},1,{float(vis):.1f}\n")
    elif truth_uv is not None and all(math.isfinite(c) for c in truth_uv) and truth_visible:
        rows.append(f"{frame},1,{_box(truth_uv[0], truth_uv[1])},1,1,1.0\n")
    return rows


def tracker_rows(frame: int, objects=None, track=None) -> list[str]:
    """Tracker lines of one frame: ``objects`` an ObjectsUpdate (its confirmed objects), else ``track``
    (a Track: one line while tracking)."""
    if objects is not None:
        return [
            f"{frame},{o.object_id},{_box(o.u_px, o.v_px)},{max(o.score, 0.0):.3f},-1,-1,-1\n"
            for o in objects.confirmed
        ]
    if track is not None and track.state == "tracking" and track.u_px is not None and track.track_id is not None:
        return [f"{frame},{track.track_id},{_box(track.u_px, track.v_px)},1,-1,-1,-1\n"]
    return []


def seq_name(scenario: str, nav: str, seed: int) -> str:
    return f"{scenario}-{nav or 'nav'}-s{int(seed)}"


def clear_mot(out: Path, tracker: str = "irtrack") -> None:
    """Remove an earlier :func:`write_mot`'s files under ``out/mot``: ``gt/``, ``trackers/<tracker>/``,
    ``seqmap.txt`` and TrackEval's output folder ``trackeval/``.  Other trackers' folders under ``trackers/``
    stay (TrackEval compares every tracker there against the same gt)."""
    mot = Path(out) / "mot"
    for d in (mot / "gt", mot / "trackers" / tracker, mot / "trackeval"):
        if d.is_dir() and not d.is_symlink():
            shutil.rmtree(d)
    (mot / "seqmap.txt").unlink(missing_ok=True)
    try:
        (mot / "trackers").rmdir()
    except OSError:  # absent, or other trackers' files: kept
        pass


def write_mot(out: Path, runs, cameras: dict) -> list[str]:
    """Write every run's files under ``out/mot`` (see the module docstring), an earlier run's first removed
    (:func:`clear_mot`); the SEQ names written.  ``cameras``: scenario name -> (width_px, height_px,
    frame_rate_hz).  Failed runs are skipped; seqmap.txt is written even when every run failed (empty then),
    so it never lists an earlier run's sequences."""
    mot = Path(out) / "mot"
    clear_mot(out)
    mot.mkdir(parents=True, exist_ok=True)
    seqs = []
    for r in runs:
        gt, trk = getattr(r, "mot_gt", ""), getattr(r, "mot_tracker", "")
        if r.error or not r.frames:
            continue
        seq = seq_name(r.scenario, r.nav_noise, r.seed)
        d = mot / "gt" / seq
        (d / "gt").mkdir(parents=True, exist_ok=True)
        (d / "gt" / "gt.txt").write_text(gt, encoding="utf-8")
        width_px, height_px, rate_hz = cameras[r.scenario]
        (d / "seqinfo.ini").write_text(
            f"[Sequence]\nname={seq}\nimDir=img1\nframeRate={rate_hz:g}\n"
            f"seqLength={r.frames}\nimWidth={width_px}\nimHeight={height_px}\nimExt=.png\n",
            encoding="utf-8",
        )
        t = mot / "trackers" / "irtrack" / "data"
        t.mkdir(parents=True, exist_ok=True)
        (t / f"{seq}.txt").write_text(trk, encoding="utf-8")
        seqs.append(seq)
    (mot / "seqmap.txt").write_text("name\n" + "".join(s + "\n" for s in seqs), encoding="utf-8")
    return seqs


MOT_METRICS = ("HOTA", "DetA", "AssA", "MOTA", "IDSW", "IDF1")


def score_mot(out: Path, seqs: list[str], tracker: str = "irtrack") -> dict:
    """TrackEval's HOTA, CLEAR and Identity metrics of each SEQ under ``out/mot`` (class pedestrian):
    ``{seq: {HOTA, DetA, AssA (at alpha-averaged), MOTA, IDSW, IDF1}}``; {} when TrackEval is not
    installed (it is an optional, --no-deps install: it pins opencv-python)."""
    try:
        import trackeval  # type: ignore[import-not-found]
    except ImportError:
        return {}
    import numpy as np

    mot = Path(out) / "mot"
    cfg = dict(
        GT_FOLDER=str(mot / "gt"),
        TRACKERS_FOLDER=str(mot / "trackers"),
        SKIP_SPLIT_FOL=True,
        SEQMAP_FILE=str(mot / "seqmap.txt"),
        TRACKERS_TO_EVAL=[tracker],
        PRINT_CONFIG=False,
        OUTPUT_FOLDER=str(mot / "trackeval"),
    )
    ds = trackeval.datasets.MotChallenge2DBox(cfg)
    ev = trackeval.Evaluator(
        dict(
            USE_PARALLEL=False,
            PRINT_RESULTS=False,
            PRINT_CONFIG=False,
            OUTPUT_SUMMARY=False,
            OUTPUT_DETAILED=False,
            PLOT_CURVES=False,
            TIME_PROGRESS=False,
            DISPLAY_LESS_PROGRESS=True,
        )
    )
    metrics = [
        trackeval.metrics.HOTA(dict(PRINT_CONFIG=False)),
        trackeval.metrics.CLEAR(dict(PRINT_CONFIG=False)),
        trackeval.metrics.Identity(dict(PRINT_CONFIG=False)),
    ]
    res, _ = ev.evaluate([ds], metrics)
    out_rows = {}
    for seq in seqs:
        r = res["MotChallenge2DBox"][tracker][seq]["pedestrian"]
        out_rows[seq] = dict(
            HOTA=float(np.mean(r["HOTA"]["HOTA"])),
            DetA=float(np.mean(r["HOTA"]["DetA"])),
            AssA=float(np.mean(r["HOTA"]["AssA"])),
            MOTA=float(r["CLEAR"]["MOTA"]),
            IDSW=int(r["CLEAR"]["IDSW"]),
            IDF1=float(r["Identity"]["IDF1"]),
        )
    return out_rows
