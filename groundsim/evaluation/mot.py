"""In-the-loop multi-object files of ``groundsim eval`` in the layout TrackEval reads (MOT Challenge 2-D boxes).

Per run, ``SEQ = <scenario>-<nav>-s<seed>``::

    OUT/mot/gt/<SEQ>/gt/gt.txt          frame,id,x,y,w,h,visible,class,visibility   (truth of every object)
    OUT/mot/gt/<SEQ>/seqinfo.ini        name, seqLength, imWidth, imHeight, frameRate
    OUT/mot/trackers/irtrack/data/<SEQ>.txt   frame,id,x,y,w,h,score,-1,-1,-1   (the pipeline's objects)
    OUT/mot/seqmap.txt                  "name" then one SEQ a line (TrackEval's SEQMAP_FILE)

Frames are numbered from 1 in both (frame k of the run is k + 1); x, y 1-based (MOT's convention).
gt's 7th column is 1 for a visible object and 0 otherwise (occluded, out of frame: a row for every object with a
place in the image plane, none for one behind the camera).  A visible object is class 1 (pedestrian, the class
TrackEval evaluates): irtrack tracks every warm moving object.  A hidden one (consider 0) is class
``HIDDEN_CLASS`` (8, MOT17's "distractor"): TrackEval leaves every row that is not class 1 or has consider 0 out
of the truth, but a tracker box on such a row still counts as a false positive unless the row's class is a
distractor one, whose matched tracker boxes it removes (``MotChallenge2DBox.get_preprocessed_seq_data``); a track
coasting on an object through a cloud or across the image edge is right, neither a detection nor a false alarm
(as :class:`PerceptionScore` counts it).  Ids are the scene's object id + 1 (the target is 1); without a scene
only the target, from the truth row.

Boxes: the objects are points of a few pixels, and IoU of 2 x 2 px boxes is 0 after a 2 px shift, so
both the truth's and the tracker's boxes are squares of ``BOX_SIDE_PX`` about their centres (IoU 0.5 at
a 2 px offset along one axis).  The tracker's objects: every confirmed object of the objects image chain
(``imaging.chain: objects``), or the single chain's track while ``tracking``.
"""

from __future__ import annotations

import contextlib
import io
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

__all__ = [
    "BOX_SIDE_PX",
    "HIDDEN_CLASS",
    "square_box",
    "gt_rows",
    "gt_line",
    "tracker_rows",
    "tracker_line",
    "seq_name",
    "write_mot",
    "clear_mot",
    "PerceptionScore",
    "tracker_positions",
    "unscorable_objects",
    "nearest_within",
    "object_timeline",
    "recorded_mot",
    "format_perception",
    "format_mot_scores",
]

BOX_SIDE_PX = 6.0
#: MOT17's "distractor": the class of a hidden object's row (consider 0), whose tracker box TrackEval drops
HIDDEN_CLASS = 8
#: a tracked object within this of an object's true centre detects it (the perception issue's 3 px)
MATCH_PX = 3.0
#: objects count for the detection probability from this long after they first show, at this contrast and above
SETTLE_S = 1.0
MIN_CONTRAST_NETD = 3.0


def square_box(u: float, v: float) -> str:
    """``x,y,w,h`` of the ``BOX_SIDE_PX`` square about the centre ``(u, v)`` (the chain's pixels: pixel i spans
    [i, i + 1)) in MOT's 1-based pixels, not clipped to the image: a point target's box in every MOT file here."""
    h = BOX_SIDE_PX / 2
    return f"{u - h + 1.0:.3f},{v - h + 1.0:.3f},{BOX_SIDE_PX:.3f},{BOX_SIDE_PX:.3f}"


def gt_rows(frame: int, labels, truth_uv=None, truth_visible: bool = False) -> list[str]:
    """gt.txt lines of one frame (1-based ``frame``): ``labels`` the scene's ObjectLabels, else the
    target from ``truth_uv`` (u, v) and ``truth_visible``; a hidden object's row ``HIDDEN_CLASS`` (the module
    docstring says why)."""
    rows = []
    if labels:
        for o in labels:
            if not (math.isfinite(o.u_px) and math.isfinite(o.v_px)):
                continue  # behind the camera: nowhere in the image to put it
            visible = o.visibility == "visible"
            rows.append(gt_line(frame, int(o.object_id) + 1, o.u_px, o.v_px, 1 if visible else None, 1.0))
    elif truth_uv is not None and all(math.isfinite(c) for c in truth_uv):
        rows.append(gt_line(frame, 1, truth_uv[0], truth_uv[1], 1 if truth_visible else None, 1.0))
    return rows


def gt_line(frame: int, mot_id: int, u: float, v: float, cls: int | None, visibility: float, digits: int = 1) -> str:
    """One gt.txt line, the ``BOX_SIDE_PX`` square about ``(u, v)``: a visible object of MOT class ``cls``, consider 1
    and its ``visibility``; a hidden one (``cls`` None) consider 0, ``HIDDEN_CLASS`` and visibility 0 (the module
    docstring says why), here and in ``groundsim dataset``'s files.  ``digits``: the visibility's decimals."""
    if cls is None:
        return f"{frame},{mot_id},{square_box(u, v)},0,{HIDDEN_CLASS},{0.0:.{digits}f}\n"
    return f"{frame},{mot_id},{square_box(u, v)},1,{cls},{visibility:.{digits}f}\n"


def _tracked_all(objects=None, track=None) -> list[tuple[int, float, float, float | None]]:
    if objects is not None:
        return [(o.object_id, o.u_px, o.v_px, o.score) for o in objects.confirmed]
    if track is not None and track.state == "tracking" and track.u_px is not None and track.track_id is not None:
        return [(track.track_id, track.u_px, track.v_px, None)]
    return []


def _tracked(objects=None, track=None) -> list[tuple[int, float, float, float | None]]:
    """``(id, u, v, score)`` of what the pipeline tracks on one frame: ``objects`` an ObjectsUpdate (its confirmed
    objects), else ``track`` (a Track: itself while tracking; score None).  An object whose centre is not a finite
    number is left out (:func:`unscorable_objects` counts them): a NaN in the tracker file made TrackEval refuse the
    whole sequence, its HOTA lost."""
    return [t for t in _tracked_all(objects, track) if math.isfinite(t[1]) and math.isfinite(t[2])]


def unscorable_objects(objects=None, track=None) -> int:
    """How many of one frame's tracked objects :func:`tracker_rows` leaves out (a centre not a finite number)."""
    return len(_tracked_all(objects, track)) - len(_tracked(objects, track))


def tracker_rows(frame: int, objects=None, track=None) -> list[str]:
    """Tracker lines of one frame: ``objects`` an ObjectsUpdate (its confirmed objects), else ``track``
    (a Track: one line while tracking)."""
    return [tracker_line(frame, i, u, v, score) for i, u, v, score in _tracked(objects, track)]


def tracker_line(frame: int, object_id: int, u: float, v: float, score: float | None = None) -> str:
    """One tracker-file line: ``object_id``'s ``BOX_SIDE_PX`` square about ``(u, v)`` on 1-based ``frame``, its
    detection ``score`` (3 decimals, at least 0; 1 when None)."""
    return f"{frame},{object_id},{square_box(u, v)},{'1' if score is None else f'{max(score, 0.0):.3f}'},-1,-1,-1\n"


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
            LOG_ON_ERROR=None,  # its default appends to error_log.txt in its own package folder
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
    # its banner ("Evaluating 1 tracker(s) on ...") goes to stdout whatever the options; ours are the printed lines
    with contextlib.redirect_stdout(io.StringIO()):
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


def tracker_positions(objects=None, track=None) -> dict[int, tuple[float, float]]:
    """``{id: (u, v)}`` of what :func:`tracker_rows` writes for one frame."""
    return {int(i): (float(u), float(v)) for i, u, v, _ in _tracked(objects, track)}


def nearest_within(
    tracks: dict[int, tuple[float, float]], u: float, v: float, radius_px: float = MATCH_PX
) -> int | None:
    """The id of the tracked object nearest (u, v) within ``radius_px``, or None: the match of every figure here."""
    best, best_d = None, radius_px
    for tid, (tu, tv) in tracks.items():
        d = math.hypot(tu - u, tv - v)
        if d <= best_d:
            best, best_d = tid, d
    return best


def _square_iou(a: tuple[float, float], b: tuple[float, float]) -> float:
    """IoU of two ``BOX_SIDE_PX`` squares about centres ``a`` and ``b`` (the MOT files' boxes)."""
    w = max(0.0, BOX_SIDE_PX - abs(a[0] - b[0])) * max(0.0, BOX_SIDE_PX - abs(a[1] - b[1]))
    return w / (2.0 * BOX_SIDE_PX * BOX_SIDE_PX - w)


class PerceptionScore:
    """A run's perception figures, frame by frame (pure; the same definitions as ``bench.imaging --scene``):

    * ``pd_pct``: of the processed frames where an object is visible at ``MIN_CONTRAST_NETD`` or more (any contrast
      without a scene's labels), from ``SETTLE_S`` after it first showed, the share with a tracked object within
      ``MATCH_PX``;
    * ``false_tracks_per_min``: tracked ids farther than ``MATCH_PX`` from every object (visible or not) on more than
      half of their frames, per minute of the frames the pipeline processed;
    * ``id_switches``: per object, changes of the tracked id matched to it (the nearest within ``MATCH_PX``);
    * ``state_accuracy``: the Anti-UAV benchmarks' SA of the selected target (object 0): per frame the IoU of the
      selected track's box with the target's (``BOX_SIDE_PX`` squares about the centres; 0 without a track) while
      the target is visible, else 1 when no track is reported and 0 when one is; the mean over frames."""

    def __init__(self, frame_rate_hz: float) -> None:
        self.frame_rate_hz = float(frame_rate_hz)
        self.frames = 0
        self.processed = 0
        self._first_visible: dict[int, int] = {}
        self._counted = self._detected = 0
        self._last_id: dict[int, int] = {}
        self._switches = 0
        self._track_frames: dict[int, list[int]] = {}  # id -> [frames, frames off every object]
        self._sa_sum = 0.0

    def add(
        self,
        objects,
        tracks: dict[int, tuple[float, float]],
        selected: tuple[float, float] | None,
        processed: bool = True,
    ) -> None:
        """One frame: ``objects`` the truth, ``(object_id, u_px, v_px, visible, contrast_netd)`` each (contrast None:
        unknown, counted); ``tracks`` the tracked objects ``{id: (u, v)}``; ``selected`` the selected target's
        reported centre, or None when no track is reported; ``processed``: the pipeline made a track of the frame
        (a frame it refused reports nothing and tracks nothing: it counts for SA, an empty report, and not for Pd,
        id switches or the minutes of false tracks, as ``bench.imaging`` counts only the frames it ran the chain on)."""
        k = self.frames
        self.frames += 1
        self.processed += bool(processed)
        known = [(u, v) for _, u, v, _, _ in objects if math.isfinite(u) and math.isfinite(v)]
        for tid, (u, v) in tracks.items():
            rec = self._track_frames.setdefault(tid, [0, 0])
            rec[0] += 1
            rec[1] += all(math.hypot(u - a, v - b) > MATCH_PX for a, b in known)
        target_visible = None
        for oid, u, v, visible, contrast in objects:
            if oid == 0:
                target_visible = (u, v) if visible else None
            if not visible:
                continue
            first = self._first_visible.setdefault(oid, k)
            if not processed:
                continue  # no track made of the frame: nothing detected or missed on it (bench.imaging skips it too)
            best = nearest_within(tracks, u, v)
            if best is not None:
                if oid in self._last_id and self._last_id[oid] != best:
                    self._switches += 1
                self._last_id[oid] = best
            if (contrast is None or contrast >= MIN_CONTRAST_NETD) and k >= first + SETTLE_S * self.frame_rate_hz:
                self._counted += 1
                self._detected += best is not None
        if target_visible is not None:
            self._sa_sum += 0.0 if selected is None else _square_iou(selected, target_visible)
        else:
            self._sa_sum += 1.0 if selected is None else 0.0

    def figures(self) -> dict:
        minutes = self.processed / self.frame_rate_hz / 60.0
        false_tracks = sum(1 for n, off in self._track_frames.values() if off > 0.5 * n)
        return {
            "pd_pct": 100.0 * self._detected / self._counted if self._counted else None,
            "pd_counted": self._counted,
            "false_tracks_per_min": false_tracks / minutes if minutes else None,
            "id_switches": self._switches,
            "state_accuracy": self._sa_sum / self.frames if self.frames else None,
        }


def _table_head(head: str) -> list[str]:
    # report.markdown_head's two lines; report imports this module, so this module does not import it back
    return [head, "|" + "---|" * (head.count("|") - 1)]


def format_perception(runs: list[dict]) -> str:
    """The perception figures per (scenario, navigation case), one value per seed (the run rows' ``perception``,
    :class:`groundsim.evaluation.mot.PerceptionScore`), with the perception issue's goals; HOTA and its parts are
    TrackEval's, in the table :func:`format_mot_scores` adds when TrackEval is installed."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in runs:
        if row.get("error") is None and row.get("perception"):
            groups.setdefault((row["scenario"], row.get("nav_noise", "")), []).append(row)

    def each(rows, key, fmt):
        vals = [r["perception"].get(key) for r in rows]
        return " / ".join("-" if v is None else fmt.format(v) for v in vals)

    lines = _table_head(
        "| scenario | navigation errors | seed(s) | Pd, visible objects >= 3 NETD after 1 s (>= 95 %) | "
        "false tracks a minute (<= 1) | id switches | selected target's state accuracy (Anti-UAV SA) |"
    )
    for (name, nav), rows in groups.items():
        seeds = " / ".join(str(r["seed"]) for r in rows)
        lines.append(
            f"| {name} | {nav or '-'} | {seeds} | {each(rows, 'pd_pct', '{:.1f} %')} | "
            f"{each(rows, 'false_tracks_per_min', '{:.1f}')} | {each(rows, 'id_switches', '{:d}')} | "
            f"{each(rows, 'state_accuracy', '{:.3f}')} |"
        )
    return "\n".join(lines)


def format_mot_scores(scores: dict[str, dict]) -> str:
    """TrackEval's figures per run (SEQ = ``<scenario>-<nav>-s<seed>``), a markdown table."""
    lines = _table_head("| run | HOTA | DetA | AssA | MOTA | IDF1 | id switches (TrackEval) |")
    for seq, m in scores.items():
        lines.append(
            f"| {seq} | {m['HOTA']:.3f} | {m['DetA']:.3f} | {m['AssA']:.3f} | {m['MOTA']:.3f} | {m['IDF1']:.3f} |"
            f" {m['IDSW']} |"
        )
    return "\n".join(lines)


def _mot_centres(text: str, gt: bool) -> dict[int, dict[int, tuple[float, float, bool]]]:
    """frame -> {id: (u, v, visible)} of MOT lines (``frame,id,x,y,w,h,...``; x, y 1-based): the box centres in the
    chain's pixels; ``visible`` gt's 7th column (1), always True for a tracker's line.  Blank lines are skipped."""
    out: dict[int, dict[int, tuple[float, float, bool]]] = {}
    for line in text.splitlines():
        if not line.strip():
            continue
        f = line.split(",")
        frame, oid = int(f[0]), int(f[1])
        x, y, w, h = (float(c) for c in f[2:6])
        visible = not gt or f[6].strip() == "1"
        out.setdefault(frame, {})[oid] = (x - 1.0 + w / 2.0, y - 1.0 + h / 2.0, visible)
    return out


def object_timeline(gt_text: str, tracker_text: str, radius_px: float = MATCH_PX) -> dict:
    """Who was tracked on which frame, from a run's MOT files (gt.txt and the tracker's file, the module docstring's
    layout): ``{"objects": {gt id: [(frame, visible, tracked id or None), ...]}, "false": {tracked id: [frame,
    ...]}}``.  Each frame's objects (visible or hidden) and tracked ids are paired one to one, nearest first, within
    ``radius_px`` (a coasting track on a hidden object is right, as :class:`PerceptionScore` counts it); a tracked id
    paired with no object on a frame is a false one there."""
    gt, trk = _mot_centres(gt_text, True), _mot_centres(tracker_text, False)
    objects: dict[int, list] = {}
    false: dict[int, list[int]] = {}
    for frame in sorted(set(gt) | set(trk)):
        g, t = gt.get(frame, {}), trk.get(frame, {})
        pairs = sorted(
            (math.hypot(gu - tu, gv - tv), gid, tid)
            for gid, (gu, gv, _) in g.items()
            for tid, (tu, tv, _) in t.items()
            if math.hypot(gu - tu, gv - tv) <= radius_px
        )
        matched: dict[int, int] = {}
        taken: set[int] = set()
        for _, gid, tid in pairs:
            if gid not in matched and tid not in taken:
                matched[gid] = tid
                taken.add(tid)
        for gid, (_, _, visible) in g.items():
            objects.setdefault(gid, []).append((frame, visible, matched.get(gid)))
        for tid in t:
            if tid not in taken:
                false.setdefault(tid, []).append(frame)
    return {"objects": dict(sorted(objects.items())), "false": dict(sorted(false.items()))}


def recorded_mot(
    truth_objects: list[dict], objects: list[dict], truth: list[dict] | None = None
) -> tuple[str, str, list[float]]:
    """The MOT files of a recorded flight, for :func:`object_timeline`: ``truth_objects`` the simulator's
    ``irtrack.truth_objects/1`` messages (one a rendered frame), ``objects`` the daemon's ``irtrack.objects/1`` (one
    a frame its image chain took, recorded or replayed); without truth objects (a scenario without a scene), the
    target alone from ``truth``, the simulator's ``irtrack.truth/1`` rows, as the eval's files have it
    (:func:`gt_rows`).  Frame k (from 1) is the k-th truth message in time; a daemon's message counts on the frame
    of the same ``time_boot_us`` (its confirmed objects, as :func:`tracker_rows` writes them), none on a frame it did
    not take.  Returns ``(gt text, tracker text, each frame's time in s from the first)``."""

    def num(x) -> float:  # (null, JSON's not-a-number: behind the camera)
        return math.nan if x is None else float(x)

    gt: list[str] = []
    if truth_objects:
        frames = sorted({int(m["time_boot_us"]): m for m in truth_objects}.items())
        for k, (_t_us, m) in enumerate(frames):
            labels = [
                SimpleNamespace(object_id=int(o["id"]), u_px=num(o.get("u_px")), v_px=num(o.get("v_px")),
                                visibility=o.get("visibility"))
                for o in m.get("objects") or []
            ]  # fmt: skip
            gt += gt_rows(k + 1, labels)
    else:
        frames = sorted({int(r["time_boot_us"]): r for r in truth or []}.items())
        for k, (_t_us, r) in enumerate(frames):
            uv = (num(r.get("target_u_px")), num(r.get("target_v_px")))
            gt += gt_rows(k + 1, None, uv, bool(r.get("target_visible")))
    number = {t_us: k + 1 for k, (t_us, _) in enumerate(frames)}
    trk: list[str] = []
    for m in objects:
        k = number.get(int(m["time_boot_us"]))
        if k is None:
            continue
        for o in m.get("objects") or []:
            if o.get("state") != "confirmed":
                continue
            trk.append(tracker_line(k, int(o["id"]), float(o["u_px"]), float(o["v_px"])))
    t0 = frames[0][0] if frames else 0
    return "".join(gt), "".join(trk), [(t_us - t0) / 1e6 for t_us, _ in frames]
