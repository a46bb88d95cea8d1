"""The image chain over rendered scene frames, scored against every object's truth.

``python -m bench.imaging --scene C1 C2 C3 C4 C5 P2 [--chain tracker|single|objects|objects-notbd|both] [--seed 0 [1 ...]]
[--frames N] [--duration S] [--nav-noise CASE] [--cache DIR] [--repeat N] [--encoding mono8|mono16] [--terrain-resolution full|half] [--stages] [--misses]``.  Each scenario is rendered through ``groundsim.world.sim.SimCore``
(its own scene, camera model and flown poses; frames the camera dropped are skipped, as the daemon
never receives them) and the frames are fed in lockstep to

* ``tracker``: the single chain, :class:`onboard.imaging.TargetTracker` as the daemon configures it with
  ``imaging.chain: single`` (``tracker_mode`` auto): one track, reported while its state is ``tracking``;
* ``objects``: :class:`onboard.imaging.objects.ObjectTracker` (clutter-suppressed detection, every
  object a track; the camera's rotation from each frame's attitude as the telemetry reports it: the
  scenario's navigation errors, RTK by default, ``--nav-noise exact`` for the truth); its confirmed tracks
  and its primary target (``objects-notbd``: the same without track-before-detect, ``imaging.tbd: false``).

Rendered frames are cached (``--cache``, default ``/tmp/irtrack-scene-frames``) so that a second run
times only the chain (a file is named by a digest of ``groundsim/world``'s source and the scenario's file: frames
rendered before a change there are rendered again, not read).  Per scene it prints (frames: those the camera delivered):

* ``on target``: frames where the chain's primary output is within 3 px of the target (object 0), over
  the frames where the target is visible;
* ``Pd``: visible objects with contrast >= 3 NETD, on frames at least 1 s after the object first became
  visible, that have a confirmed track within 3 px (all classes; ``Pd tgt``: objects of class target;
  ``Pd warm``: objects of class target that are also warm, their signal above the local background: the
  label's contrast is a magnitude, and a target colder than the roof behind it is a cold point, which the
  chains, looking for warm points, do not see by design);
* ``false/min``: confirmed track ids farther than 3 px from every labelled object on more than half of
  their confirmed frames, per minute of scene;
* ``id sw``: per object, changes of the track id matched to it (nearest confirmed track within 3 px)
  between its matched frames, summed over objects (``tgt``: over objects of class target);
* ``prim``: primary targets the chain chose over the run (1: chosen once and kept; the single chain's
  primary is its one track, so this counts its track ids);
* ``conf s``: seconds from the target's first visible frame to the first frame the primary is on it
  (``nan``: never); ``after``: the on-target fraction over the visible frames from then on;
* ``ffc s``: per flat-field event (a run of frames identical to the one before: the shutter closed), seconds
  from its first frame to the first frame the primary is on the target again (``-``: no event);
  ``defect``: confirmed-track frames within 2 px of a stuck pixel (at the frame's lowest or highest grey on
  every frame: the camera model's dead and hot pixels; ``-``: none);
* ``HOTA`` (and ``DetA``, ``AssA``): TrackEval's HOTA of the chain's confirmed tracks against every
  labelled object (visible and occluded), in the layout and with the 6 px boxes ``groundsim eval`` writes
  (:mod:`groundsim.evaluation.mot`), so the figure is the one the loop reports; nan without TrackEval;
* ``ms p50``, ``ms p95``, ``cpu p50``: wall ms (median, 95th percentile) and median CPU ms of the
  chain's update per frame (OpenCV on one thread; the machine is shared, so the figures are noisy;
  CPU ms is the steadier of the two, at the clock's granularity).  ``--repeat N`` runs each chain N
  times and takes each frame's least time over the runs (the closest to an idle core's figure on a
  loaded machine; the scores are the same every run).
* ``--misses``: below each row, the frames ``Pd tgt`` counts where object 0 (the target) had no confirmed
  track within 3 px, as ranges of frame indices, warm and cold apart, and the warm ones by what the frame
  shows there (:func:`miss_cause`): a brighter surround (the target warmer than the pixels under it but not
  than a road or roof edge 2-4 px away: its point contrast, as the objects chain measures it on the raw
  frame, at most 0), a faint peak (at most ``FAINT_GREY`` 8-bit grey levels over the median about it), or
  neither.
* ``Pd point`` (below each row with ``--misses``, and in the seeds' summary line): the target's ``Pd tgt`` frames
  where it is a warm point against that surround (warm, neither a brighter surround nor at the edge), and the
  share of them it was found on: what a point-target detector can be asked for (C2's roof edges:
  docs/perception.md, "What the cold frames allow").  A dim target on a sky with a gradient (C4 in haze) is no
  point by this measure on any frame (nan): track-before-detect, not the point contrast, finds it.
* ``--seed`` with several seeds: a row per scene and seed (``C2/s3``), then per scene and chain one line
  over its seeds: the Pd of each, on how many it reaches 95 %, the worst false tracks a minute and
  HOTA's range (a figure met on seed 0 alone may not hold on the next: C2).
* ``--stages`` (objects chains): below each row, the chain's CPU ms by stage
  (:class:`onboard.imaging.objects_model.StageTimes` on ``time.process_time``), each frame's least over the
  runs: the median frame's and the mean (the mean carries the stages that run every few frames: the
  column offsets every 8th, the defect map every 4th, and the background motion where it is asked for).

Numbers only: nothing asserts.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from bench import frame_speed_ms, machine_speed_ms
from groundsim.evaluation.mot import (
    MATCH_PX,
    MIN_CONTRAST_NETD,
    SETTLE_S,
    gt_rows,
    nearest_within,
    score_mot,
    tracker_rows,
    write_mot,
)

DEFECT_PX = 2.0
FAINT_GREY = 2.0  # a target's peak this close to the median about it is at the 8-bit grey's own step
CAUSE_HALF_PX = 15  # the square about a target its point contrast is measured in (past the chain's border band)
DEFAULT_CACHE = Path("/tmp/irtrack-scene-frames")
LABEL_FIELDS = 7  # (object_id, cls, u_px, v_px, visibility, contrast_netd, warm); 6 before warm


@dataclass
class SceneRun:
    """Rendered frames of one scenario: ``frames`` list of (H, W) arrays (None: dropped), ``labels``
    per frame a list of (object_id, cls, u_px, v_px, visibility, contrast_netd, warm), ``R_ned_from_cam``
    (N, 3, 3) the camera attitude the chain is given (the truth's, or the one the telemetry reports:
    :func:`reported_rotations`), ``intrinsics`` the camera's PinholeIntrinsics, ``frame_rate_hz``,
    ``nav_noise`` the navigation-error case of that attitude (``exact``: the truth)."""

    name: str
    frames: list
    labels: list
    R_ned_from_cam: np.ndarray
    intrinsics: object  # onboard.core.frames.PinholeIntrinsics
    frame_rate_hz: float
    nav_noise: str = "exact"


@functools.cache
def _world_source_digest() -> str:
    """The digest of ``groundsim/world``'s source as this process found it, taken once, right after
    :func:`render_scene` first imported the simulator: a file saved while a long bench runs does not name the
    frames the code imported before it rendered."""
    world = Path(__file__).resolve().parent.parent / "groundsim" / "world"
    h = hashlib.sha256()
    for f in sorted(world.rglob("*.py")):
        h.update(str(f.relative_to(world)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def world_digest(name: str) -> str:
    """A digest of what makes a scene's frames and labels: the simulated world's source (``groundsim/world``)
    and the scenario's file.  Part of a cached file's name, so that frames rendered before a change of the
    renderer, the flight or the scene are rendered again rather than measured as the new code's."""
    from groundsim.world.scenario import scenarios_dir

    h = hashlib.sha256(_world_source_digest().encode())
    h.update((scenarios_dir() / f"{name}.yaml").read_bytes())
    return h.hexdigest()[:12]


def render_scene(
    name: str,
    seed: int,
    n_frames: int | None,
    cache: Path | None,
    encoding: str | None = None,
    terrain_resolution: str | None = None,
    duration_s: float | None = None,
    nav_noise: str | None = None,
) -> SceneRun:
    """``nav_noise``: the navigation-error case whose attitude the chain is given (a name in
    config/noise_cases.yaml; None: the scenario's ``nav_noise``, RTK by default; ``exact``: the truth), drawn
    as ``groundsim eval`` draws it for that scenario, seed and duration (:func:`reported_rotations`; the
    cache holds the truth, the error is applied on reading).
    ``encoding`` (mono8 / mono16): render with it instead of the scenario's ``ir.encoding``;
    ``terrain_resolution`` (full / half): ``scene.terrain.full_resolution`` true / false instead of the
    scenario's; ``duration_s``: fly this long instead of the scenario's ``duration_s`` (its motions
    continued, as ``groundsim eval --duration`` flies them); ``n_frames`` then the first N of those."""
    import dataclasses

    from groundsim.world.scenario import load_scenario, scenarios_dir
    from groundsim.world.sim import SimCore
    from onboard.core.frames import rotmat_from_quat

    sc = load_scenario(scenarios_dir() / f"{name}.yaml")
    if encoding is not None:
        sc = dataclasses.replace(sc, ir=dataclasses.replace(sc.ir, encoding=encoding))
    if terrain_resolution is not None:
        terrain = dataclasses.replace(sc.scene.terrain, full_resolution=terrain_resolution == "full")
        sc = dataclasses.replace(sc, scene=dataclasses.replace(sc.scene, terrain=terrain))
    # frames cached before the terrain was looked up at full resolution have no tag: never read for it
    full = sc.scene.terrain.enabled and sc.scene.terrain.full_resolution
    flown = sc.duration_s if duration_s is None else float(duration_s)
    duration = flown if n_frames is None else min(flown, n_frames / sc.frame_rate_hz)
    K = sc.camera.intrinsics
    # the encoding in the name: a scene's frames cached before its encoding changed are not taken for it
    tag = "-fullterrain" if full else ""
    path = None
    if cache is not None:
        path = cache / f"{name}-{sc.ir.encoding}{tag}-s{seed}-{duration:.3f}-{world_digest(name)}.npz"
    cached = None if path is None or not path.exists() else load_cache(path)
    if cached is not None:
        frames, labels, R = cached
        R_rep, case = reported_rotations(sc, seed, duration, R, nav_noise)
        return SceneRun(name, frames, labels, R_rep, K, float(sc.frame_rate_hz), case)
    if path is not None and path.exists():
        print(f"{path}: cached before the labels carried warm; rendering it again", file=sys.stderr, flush=True)
    core = SimCore(sc, seed, duration_s=duration)
    frames, labels, Rs = [], [], []
    truth_only = not core.scene_enabled
    for k in range(core.frame_count):
        f = core.frame(k)
        frames.append(f.pixels)
        if truth_only:  # a clean scenario has the target only, in its truth row
            r = f.truth
            # no labels to say it: the clean renderer's target is the warm quad-rotor against the sky
            vis = "visible" if r.target_visible else "out_of_frame"
            labels.append([(0, "target", r.target_u_px, r.target_v_px, vis, math.inf, True)])
        else:
            labels.append(
                [(lb.object_id, lb.cls, lb.u_px, lb.v_px, lb.visibility, lb.contrast_netd, lb.warm) for lb in f.labels]
            )
        q = np.array(
            [f.truth.q_ned_from_cam_w, f.truth.q_ned_from_cam_x, f.truth.q_ned_from_cam_y, f.truth.q_ned_from_cam_z]
        )
        Rs.append(rotmat_from_quat(q))
    R = np.asarray(Rs)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        farr = np.empty(len(frames), dtype=object)
        for i, fr in enumerate(frames):
            farr[i] = np.zeros(0, np.uint8) if fr is None else fr
        larr = np.empty(len(labels), dtype=object)
        for i, lb in enumerate(labels):
            larr[i] = lb
        # written aside and renamed into place: a second bench reading the cache meanwhile (two trees compared
        # side by side) found a half-written file and stopped on a BadZipFile
        part = path.with_name(f"{path.stem}.{os.getpid()}.part.npz")
        np.savez(part, frames=farr, labels=larr, R=R)
        os.replace(part, path)
    R_rep, case = reported_rotations(sc, seed, duration, R, nav_noise)
    return SceneRun(name, frames, labels, R_rep, K, float(sc.frame_rate_hz), case)


def reported_rotations(sc, seed: int, duration_s: float, R_true: np.ndarray, nav_noise: str | None):
    """``(R_reported (N, 3, 3), case name)``: each frame's true camera attitude rotated by the attitude error
    the simulated autopilot reports it with at that frame's tick, ``Exp(phi) R_true``
    (:mod:`groundsim.world.nav_errors`: the same ``phi`` moves the body's and an earth-frame gimbal's
    attitude, so the camera's too), from the run's own draws (``SimCore(sc, seed, duration_s).nav_errors``,
    flown nowhere).  The daemon interpolates its telemetry (attitude at 100 Hz) to each frame's time instead: the same
    bias, white noise of the same size.  An unknown case is a ConfigError naming the file and the names."""
    from groundsim.world.sim import SimCore
    from onboard.core.frames import quat_from_rotvec, rotmat_from_quat

    core = SimCore(sc, seed, duration_s=duration_s, render=False, nav_noise=nav_noise)
    phi = core.nav_errors.att_err_ned_rad()[:: core.ticks_per_frame]
    R_true = np.asarray(R_true, dtype=np.float64)
    if not np.any(phi):
        return R_true, core.nav_noise.name
    R_rep = np.array([rotmat_from_quat(quat_from_rotvec(phi[k])) @ R_true[k] for k in range(len(R_true))])
    return R_rep, core.nav_noise.name


def load_cache(path: Path) -> tuple[list, list, np.ndarray] | None:
    """``(frames, labels, R)`` of a cache file, or None when its labels predate ``warm`` (six fields): read
    with every object taken as warm, a cold target would count in ``Pd warm`` and raise it silently."""
    z = np.load(path, allow_pickle=True)
    labels = list(z["labels"])
    if any(len(lb) != LABEL_FIELDS for frame in labels for lb in frame):
        return None
    frames = [None if f.size == 0 else f for f in z["frames"]]
    return frames, labels, z["R"]


class _TrackerChain:
    """TargetTracker as the daemon builds it with ``imaging.chain: single``: one output, confirmed while ``tracking``."""

    name = "tracker"
    stage_s = None  # not timed by stage

    def __init__(self, run: SceneRun, stages: bool = False) -> None:
        from onboard.imaging import ImagingParams, TargetTracker, TrackState

        self._tr = TargetTracker(ImagingParams(), mode="auto")
        self._tracking = TrackState.TRACKING

    def update(self, image, R_ned_from_cam):
        out = self._tr.update(image)
        if out.state is self._tracking and out.u_px is not None:
            return [(out.track_id, out.u_px, out.v_px)], out.track_id
        return [], None


class _ObjectsChain:
    name = "objects"
    tbd = True

    def __init__(self, run: SceneRun, stages: bool = False) -> None:
        from onboard.imaging import ImagingParams
        from onboard.imaging.objects import ObjectTracker

        imaging = ImagingParams(chain="objects", tbd=self.tbd)
        clock = time.process_time if stages else None
        self._tr = ObjectTracker(run.intrinsics, frame_rate_hz=run.frame_rate_hz, imaging=imaging, stage_clock=clock)

    @property
    def stage_s(self) -> dict[str, float] | None:
        """The last frame's seconds by stage (None when not timed)."""
        return self._tr.stages.seconds if self._tr.stages.clock is not None else None

    def update(self, image, R_ned_from_cam):
        out = self._tr.update(image, R_ned_from_cam)
        tracks = [(t.object_id, t.u_px, t.v_px) for t in out.confirmed]
        return tracks, out.primary_id


class _ObjectsNoTbdChain(_ObjectsChain):
    """The objects chain without track-before-detect (``imaging.tbd: false``): its cost and scores without it."""

    name = "objects-notbd"
    tbd = False


CHAINS = {"tracker": _TrackerChain, "objects": _ObjectsChain, "objects-notbd": _ObjectsNoTbdChain}
#: the names the daemon's imaging.chain, eval --tracker and bench.companion --chain give the chains
CHAIN_ALIASES = {"single": "tracker"}


def score(run: SceneRun, chain) -> dict[str, float]:
    """Run ``chain`` over ``run``'s frames and score it (see the module docstring)."""
    fr = run.frame_rate_hz
    first_visible: dict[int, int] = {}
    on_target = target_frames = 0
    first_on: int | None = None  # the frame the primary is first on the target
    on_after = frames_after = 0  # visible frames from then on, and those with the primary on the target
    det = det_all = det_t = det_t_all = det_w = det_w_all = 0
    det_p = det_p_all = 0  # the target's counted frames where it is a warm point against its surround (Pd point)
    # (frame, warm, cause) of the target's frames Pd tgt counts and it missed (cause: miss_cause's, None when cold)
    misses: list[tuple[int, bool, str | None]] = []
    counted0 = 0  # the target's frames Pd tgt counts
    last_id: dict[int, int] = {}
    switches: dict[int, int] = {}
    cls_of: dict[int, str] = {}
    track_frames: dict[int, list[int]] = {}  # track id -> [confirmed frames, frames off every object]
    ms: list[float] = []
    cpu_ms: list[float] = []
    stage_ms: list[dict[str, float]] = []  # per frame, when the chain times its stages
    n_frames = 0
    selections = 0  # primary targets chosen (the first one included)
    last_primary = None
    mot_gt: list[str] = []
    mot_tracker: list[str] = []
    stuck = _stuck_pixels(run.frames)
    on_defect = 0
    ffc_starts: list[int] = []
    prev_img, was_frozen = None, False
    on_frames: set[int] = set()  # frames with the primary on the target
    for k, (img, labels) in enumerate(zip(run.frames, run.labels)):
        mot_gt += gt_rows(k + 1, [_Label(*lb) for lb in labels])
        vis = []
        for oid, cls, u, v, visibility, contrast, warm in labels:
            cls_of[oid] = cls
            if visibility == "visible":
                first_visible.setdefault(oid, k)
                vis.append((oid, cls, u, v, contrast, warm))
        if img is None:
            continue
        frozen = prev_img is not None and np.array_equal(img, prev_img)
        if frozen and not was_frozen:  # the shutter closed: the camera repeats its last image
            ffc_starts.append(k)
        was_frozen, prev_img = frozen, img
        n_frames += 1
        t0, c0 = time.perf_counter(), time.process_time()
        tracks, primary = chain.update(img, run.R_ned_from_cam[k])
        ms.append((time.perf_counter() - t0) * 1e3)
        cpu_ms.append((time.process_time() - c0) * 1e3)
        if chain.stage_s is not None:
            stage_ms.append({k: v * 1e3 for k, v in chain.stage_s.items()})
        if primary is not None and primary != last_primary:
            selections += 1
            last_primary = primary
        tpos = {tid: (u, v) for tid, u, v in tracks}
        confirmed = SimpleNamespace(
            confirmed=[SimpleNamespace(object_id=t, u_px=u, v_px=v, score=1.0) for t, u, v in tracks]
        )
        mot_tracker += tracker_rows(k + 1, confirmed)
        all_pos = [(u, v) for _, _, u, v, *_ in labels if math.isfinite(u) and math.isfinite(v)]
        for tid, u, v in tracks:
            if len(stuck) and float(np.min(np.hypot(stuck[:, 0] - u, stuck[:, 1] - v))) <= DEFECT_PX:
                on_defect += 1
            rec = track_frames.setdefault(tid, [0, 0])
            rec[0] += 1
            if all(math.hypot(u - a, v - b) > MATCH_PX for a, b in all_pos):
                rec[1] += 1
        for oid, cls, u, v, contrast, warm in vis:
            if oid == 0:
                target_frames += 1
                if primary is not None and primary in tpos:
                    pu, pv = tpos[primary]
                    on_target += math.hypot(pu - u, pv - v) <= MATCH_PX
                    if math.hypot(pu - u, pv - v) <= MATCH_PX:
                        on_frames.add(k)
                    if first_on is None and math.hypot(pu - u, pv - v) <= MATCH_PX:
                        first_on = k
                if first_on is not None:
                    frames_after += 1
                    on_after += (
                        primary is not None
                        and primary in tpos
                        and math.hypot(tpos[primary][0] - u, tpos[primary][1] - v) <= MATCH_PX
                    )
            best = nearest_within(tpos, u, v)
            if best is not None:
                if oid in last_id and last_id[oid] != best:
                    switches[oid] = switches.get(oid, 0) + 1
                last_id[oid] = best
            if contrast >= MIN_CONTRAST_NETD and k >= first_visible[oid] + SETTLE_S * fr:
                det_all += 1
                det += best is not None
                if cls == "target":
                    det_t_all += 1
                    det_t += best is not None
                    det_w_all += warm
                    det_w += warm and best is not None
                if oid == 0:
                    counted0 += 1
                    cause = miss_cause(img, u, v) if warm else None
                    if cause in POINT_CAUSES:
                        det_p_all += 1
                        det_p += best is not None
                    if best is None:
                        misses.append((k, bool(warm), cause))
    minutes = n_frames / fr / 60.0
    false_tracks = sum(1 for n, off in track_frames.values() if off > 0.5 * n)
    pct = lambda a, b: 100.0 * a / b if b else math.nan  # noqa: E731
    mot_gt_text, mot_tracker_text = "".join(mot_gt), "".join(mot_tracker)
    hota = _hota(run, mot_gt_text, mot_tracker_text)
    return dict(
        **hota,
        mot_gt=mot_gt_text,
        mot_tracker=mot_tracker_text,
        frames=n_frames,
        on_target=pct(on_target, target_frames),
        confirm_s=(first_on - first_visible[0]) / fr if first_on is not None else math.nan,
        tracked_after=pct(on_after, frames_after),
        pd=pct(det, det_all),
        pd_target=pct(det_t, det_t_all),
        pd_warm=pct(det_w, det_w_all),
        pd_point=pct(det_p, det_p_all),
        point_counted=det_p_all,
        target_counted=counted0,
        misses=misses,
        false_per_min=false_tracks / minutes if minutes else math.nan,
        id_switches=sum(switches.values()),
        id_switches_target=sum(n for o, n in switches.items() if cls_of.get(o) == "target"),
        ms_p50=float(np.median(ms)) if ms else math.nan,
        ms_p95=float(np.percentile(ms, 95)) if ms else math.nan,
        cpu_ms_p50=float(np.median(cpu_ms)) if cpu_ms else math.nan,
        primary_selections=selections,
        ffc_s=[min((f - k0 for f in on_frames if f >= k0), default=math.nan) / fr for k0 in ffc_starts],
        on_defect=on_defect if len(stuck) else None,
        ms_frames=ms,
        cpu_ms_frames=cpu_ms,
        stage_ms_frames=stage_ms,
    )


def _stuck_pixels(frames) -> np.ndarray:
    """(n, 2) centres (u, v) of the pixels at the frame type's lowest or highest grey on every frame."""
    lo = hi = None
    for f in frames:
        if f is not None:
            lo = f.copy() if lo is None else np.minimum(lo, f)
            hi = f.copy() if hi is None else np.maximum(hi, f)
    if lo is None or hi is None:
        return np.zeros((0, 2))
    top = np.iinfo(lo.dtype).max if np.issubdtype(lo.dtype, np.integer) else np.inf
    i, j = np.nonzero((lo == hi) & ((lo == 0) | (lo == top)))
    return np.stack([j + 0.5, i + 0.5], axis=1)


class _Label(SimpleNamespace):
    """A cached label tuple with the attribute names :func:`groundsim.evaluation.mot.gt_rows` reads."""

    def __init__(self, object_id, cls, u_px, v_px, visibility, contrast_netd, warm) -> None:
        super().__init__(object_id=object_id, cls=cls, u_px=u_px, v_px=v_px, visibility=visibility)


def _hota(run: SceneRun, gt: str, tracker: str) -> dict[str, float]:
    """TrackEval's HOTA, DetA and AssA of one run's MOT lines (nan each without TrackEval)."""
    K = run.intrinsics
    r = SimpleNamespace(
        mot_gt=gt, mot_tracker=tracker, error=None, frames=len(run.frames), scenario=run.name, nav_noise="bench", seed=0
    )
    with tempfile.TemporaryDirectory(prefix="irtrack-bench-mot-") as d:
        seqs = write_mot(Path(d), [r], {run.name: (K.width_px, K.height_px, run.frame_rate_hz)})
        with contextlib.redirect_stdout(io.StringIO()):  # TrackEval prints its progress
            res = score_mot(Path(d), seqs) if seqs else {}
    m = res.get(seqs[0], {}) if seqs else {}
    return {k: float(m.get(k, math.nan)) for k in ("HOTA", "DetA", "AssA")}


def score_repeated(run: SceneRun, chain_cls, repeat: int, stages: bool = False) -> dict:
    """:func:`score` ``repeat`` times with a fresh chain each time (the chains are deterministic: the
    same scores), the times per frame being the least over the runs: on a shared machine the least of
    several runs of the same work is the closest to its cost on an idle core.  ``stages``: time the
    chain's stages too; ``stages_ms`` is then {stage: (median, mean) over the frames of each frame's least}."""
    runs = [score(run, chain_cls(run, stages)) for _ in range(max(repeat, 1))]
    s = dict(runs[0])
    if len(runs) > 1:
        ms = np.min(np.array([r["ms_frames"] for r in runs]), axis=0)
        cpu = np.min(np.array([r["cpu_ms_frames"] for r in runs]), axis=0)
        s.update(ms_p50=float(np.median(ms)), ms_p95=float(np.percentile(ms, 95)), cpu_ms_p50=float(np.median(cpu)))
        s.update(ms_frames=ms.tolist(), cpu_ms_frames=cpu.tolist())  # the summary's median over seeds reads these
    if runs[0]["stage_ms_frames"]:
        names = list(dict.fromkeys(k for r in runs for f in r["stage_ms_frames"] for k in f))
        s["stages_ms"] = {}
        for k in names:
            least = np.min(np.array([[f.get(k, 0.0) for f in r["stage_ms_frames"]] for r in runs]), axis=0)
            s["stages_ms"][k] = (float(np.median(least)), float(np.mean(least)))
    return s


def frame_ranges(frames: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    runs: list[list[int]] = []  # [first, last] of each run of consecutive frames
    for k in sorted(frames):
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def miss_cause(image: np.ndarray, u_px: float, v_px: float) -> str:
    """What the frame shows at a warm target (each one ``Pd point`` counts, and why one was missed): ``edge`` (within
    the frame's border band, where the chain measures no point contrast), ``surround`` (its point contrast, the
    objects chain's statistic on the raw frame, is at most 0 within a pixel of it: something 2-4 px away is
    brighter), ``faint`` (its 3 x 3 peak is at most ``FAINT_GREY`` 8-bit grey levels over the median of the ring
    3-5 px about it), else ``other``."""
    from onboard.imaging.clutter import ClutterParams, point_contrast
    from onboard.imaging.objects import GREY16_PER_GREY8

    h, w = image.shape
    j, i = int(u_px), int(v_px)
    params = ClutterParams()
    band = params.reach_px  # the chain measures no contrast this near the frame's edges
    if not (band <= i < h - band and band <= j < w - band):
        return "edge"
    r = CAUSE_HALF_PX
    y0, x0 = max(i - r, 0), max(j - r, 0)
    square = np.asarray(image[y0 : min(i + r + 1, h), x0 : min(j + r + 1, w)], dtype=np.float32)
    contrast = point_contrast(square, params)
    ci, cj = i - y0, j - x0
    if float(contrast[max(ci - 1, 0) : ci + 2, max(cj - 1, 0) : cj + 2].max()) <= 0.0:
        return "surround"
    grey8 = 1.0 / GREY16_PER_GREY8 if image.dtype == np.uint16 else 1.0
    yy, xx = np.ogrid[y0 : y0 + square.shape[0], x0 : x0 + square.shape[1]]
    ring = np.maximum(np.abs(yy - i), np.abs(xx - j))
    peak = float(square[(ring <= 1)].max())
    background = float(np.median(square[(ring >= 3) & (ring <= 5)]))
    return "faint" if (peak - background) * grey8 <= FAINT_GREY else "other"


def misses_line(misses: list[tuple[int, bool, str | None]], counted: int) -> str:
    """The ``--misses`` line: how many of the target's counted frames were missed, warm and cold apart, the warm
    ones by :func:`miss_cause`."""
    warm = [k for k, w, _ in misses if w]
    cold = [k for k, w, _ in misses if not w]
    causes = [c for _, w, c in misses if w]
    by_cause = ", ".join(f"{name} {causes.count(c)}" for c, name in MISS_CAUSES if causes.count(c))
    return (
        f"target missed on {len(misses)} of {counted} frames (visible, >= {MIN_CONTRAST_NETD:.0f} NETD, after"
        f" {SETTLE_S:.0f} s); warm {len(warm)}{f' ({by_cause})' if by_cause else ''}: {frame_ranges(warm) or '-'};"
        f" cold {len(cold)}: {frame_ranges(cold) or '-'}"
    )


def point_line(s: dict) -> str:
    """The target's Pd over the frames where it is a warm point against its surround (``Pd point``)."""
    return (
        f"where the target is a warm point against its surround ({s['point_counted']} of {s['target_counted']} counted"
        f" frames): Pd {s['pd_point']:.1f} %"
    )


# the causes of a frame where the target is a warm point against the surround a point detector compares it with
POINT_CAUSES = ("faint", "other")
MISS_CAUSES = (
    ("edge", "at the edge"),
    ("surround", "brighter surround"),
    ("faint", f"<= {FAINT_GREY:.0f} grey"),
    ("other", "other"),
)


def _cache_dir(text: str) -> Path | None:
    """``--cache``: the rendered frames' folder (made when the first frames are written), or None for ``''``.  A
    file in its place, or a folder that takes no file, is refused when the command line is read rather than once
    a whole scene has been rendered."""
    import argparse

    from bench.options import cannot_write_in

    if not text:
        return None
    why = cannot_write_in(text)
    if why is not None:
        raise argparse.ArgumentTypeError(why)
    return Path(text)


def main(argv: list[str]) -> None:
    from bench.options import BenchParser, known_nav_noise, name_in, nonnegative_int, positive_float, positive_int
    from groundsim.world.scenario import reference_scenario_paths

    # every value is checked here, before anything is rendered (render_scene reads the shipped scenarios by name)
    ap = BenchParser(prog="python -m bench.imaging --scene", description=__doc__.splitlines()[0])
    ap.add_argument(
        "--scene",
        nargs="+",
        required=True,
        type=name_in(reference_scenario_paths, "scenario"),
        help="scenario names (config/scenarios), e.g. C1 P2",
    )
    ap.add_argument(
        "--chain",
        choices=(*CHAINS, *CHAIN_ALIASES, "both"),
        default="both",
        help="tracker (or single): the single chain (imaging.chain single); objects: the daemon's default; both "
        "(default)",
    )
    ap.add_argument(
        "--seed",
        type=nonnegative_int,
        nargs="+",
        default=[0],
        help="run seed(s) (default 0); several: a row each and a summary",
    )
    ap.add_argument(
        "--frames", type=positive_int, default=None, help="first N frames only (default: the whole scenario)"
    )
    ap.add_argument(
        "--duration",
        type=positive_float,
        default=None,
        help="seconds flown instead of the scenario's (its motions continued, as groundsim eval --duration)",
    )
    ap.add_argument(
        "--cache", type=_cache_dir, default=DEFAULT_CACHE, help="rendered frames cache directory ('' = none)"
    )
    ap.add_argument(
        "--repeat",
        type=positive_int,
        default=1,
        help="run each chain N times; times per frame are the least over the runs",
    )
    ap.add_argument(
        "--encoding", choices=("mono8", "mono16"), default=None, help="render so instead of the scenario's ir.encoding"
    )
    ap.add_argument(
        "--terrain-resolution",
        choices=("full", "half"),
        default=None,
        help="render the terrain so (scene.terrain.full_resolution) instead of as the scenario has it",
    )
    ap.add_argument(
        "--nav-noise",
        type=known_nav_noise,
        default=None,
        help="navigation-error case of the attitude the chains are given (config/noise_cases.yaml; default: the"
        " scenario's, RTK; exact: the truth)",
    )
    ap.add_argument("--stages", action="store_true", help="objects chains: CPU ms by stage below each row")
    ap.add_argument("--misses", action="store_true", help="the target's missed frames below each row")
    ap.add_argument(
        "--bound",
        action="store_true",
        help="below each seed: what a matched filter knowing the target's grey, size and place finds at the truth "
        "(bench/imaging_bound.py), with the chain's bilinear background and a cubic one",
    )
    ap.add_argument(
        "--plots",
        metavar="DIR",
        help="draw each run's objects timeline (who was tracked when, as groundsim eval's <scenario>_objects.png) "
        "into DIR/<scene>-s<seed>-<chain>.png",
    )
    # '--scene --help' (or '--loop --help'): the mode's help, not 'expected at least one argument' for the mode's
    # option, which argparse says before it reads --help
    a = ap.parse_args(["--help"] if {"-h", "--help"} & set(argv) else argv)
    cv2.setNumThreads(1)
    chains = ("tracker", "objects") if a.chain == "both" else (CHAIN_ALIASES.get(a.chain, a.chain),)
    print(
        f"image chain over rendered scenes (seed {', '.join(map(str, a.seed))}); match {MATCH_PX:.0f} px, Pd over contrast >= "
        f"{MIN_CONTRAST_NETD:.0f} NETD after {SETTLE_S:.0f} s visible; the chains given the camera attitude with the"
        f" navigation errors {a.nav_noise or 'of each scenario (RTK unless it says)'}; wall ms on a shared machine (noisy);"
        f" machine speed: a fixed Python loop {machine_speed_ms():.1f} CPU ms, fixed whole-frame passes"
        f" {frame_speed_ms():.2f} CPU ms (lower is faster)"
    )
    print(
        f"{'scene':<6s} {'chain':<13s} {'frames':>6s} {'on target':>9s} {'Pd':>6s} {'Pd tgt':>6s} {'Pd warm':>7s}"
        f" {'false/min':>9s}"
        f" {'id sw':>5s} {'tgt':>3s} {'prim':>4s} {'HOTA':>5s} {'DetA':>5s} {'AssA':>5s}"
        f" {'ms p50':>6s} {'ms p95':>6s} {'cpu p50':>7s} {'conf s':>6s} {'after':>6s} {'ffc s':>6s} {'defect':>6s}"
    )
    several = len(a.seed) > 1
    for name in a.scene:
        per_chain: dict[str, list[tuple[int, dict]]] = {c: [] for c in chains}
        for seed in a.seed:
            run = render_scene(name, seed, a.frames, a.cache, a.encoding, a.terrain_resolution, a.duration, a.nav_noise)
            for c in chains:
                s = score_repeated(run, CHAINS[c], a.repeat, a.stages)
                per_chain[c].append((seed, s))
                _print_row(f"{name}/s{seed}" if several else name, c, s, a)
                if a.plots:
                    _plot_objects(Path(a.plots), name, seed, c, s, run)
            if a.bound:
                from bench.imaging_bound import bound_lines

                truth = render_scene(
                    name, seed, a.frames, a.cache, a.encoding, a.terrain_resolution, a.duration, "exact"
                )
                for line in bound_lines(truth):
                    print("       " + line, flush=True)
        if several:
            for c in chains:
                print("       " + seeds_summary(name, c, per_chain[c]), flush=True)


def _plot_objects(out: Path, name: str, seed: int, chain: str, s: dict, run: SceneRun) -> None:
    from groundsim.evaluation.report_plots import plot_objects

    t_s = np.arange(len(run.frames)) / run.frame_rate_hz
    title = f"{name} seed {seed}, {chain} chain: objects tracked (paired within {MATCH_PX:.0f} px)"
    path = plot_objects(out / f"{name}-s{seed}-{chain}.png", s["mot_gt"], s["mot_tracker"], t_s, title)
    print(f"       objects timeline: {path}", flush=True)


def seeds_summary(name: str, chain: str, runs: list[tuple[int, dict]]) -> str:
    """One line over a scene's seeds for one chain: Pd per seed, how many reach the issue's 95 %, the
    false tracks a minute at worst, HOTA's range, and the chain's CPU per frame: the median over every frame
    of every seed beside the seeds' medians' range (when the runs carry their frames' times)."""
    pd = [s["pd"] for _, s in runs]
    point = [s["pd_point"] for _, s in runs]
    hota = [s["HOTA"] for _, s in runs]
    line = (
        f"{name} {chain}, seeds {', '.join(str(k) for k, _ in runs)}: Pd {' / '.join(f'{x:.1f}' for x in pd)} %"
        f" (>= 95 % on {sum(x >= 95.0 for x in pd)} of {len(pd)}); the target where it is a warm point"
        f" {' / '.join(f'{x:.1f}' for x in point)} % (>= 95 % on {sum(x >= 95.0 for x in point)} of"
        f" {sum(math.isfinite(x) for x in point)} with such frames);"
        f" false tracks/min at most {max(s['false_per_min'] for _, s in runs):.1f}, HOTA {min(hota):.3f}-{max(hota):.3f}"
    )
    frames = [ms for _, s in runs for ms in s.get("cpu_ms_frames", [])]
    if frames:
        per_seed = [s["cpu_ms_p50"] for _, s in runs]
        line += (
            f", CPU ms per frame p50 {float(np.median(frames)):.2f} over all {len(frames)} frames"
            f" ({min(per_seed):.2f}-{max(per_seed):.2f} by seed)"
        )
    return line


def _print_row(label: str, c: str, s: dict, a) -> None:
    """One scene row of :func:`main`'s table (and its misses and stages when asked)."""
    print(
        f"{label:<6s} {c:<13s} {s['frames']:6d} {s['on_target']:8.1f}% {s['pd']:5.1f}% {s['pd_target']:5.1f}%"
        f" {s['pd_warm']:6.1f}% {s['false_per_min']:9.1f} {s['id_switches']:5d} {s['id_switches_target']:3d} {s['primary_selections']:4d}"
        f" {s['HOTA']:5.3f} {s['DetA']:5.3f} {s['AssA']:5.3f}"
        f" {s['ms_p50']:6.2f} {s['ms_p95']:6.2f} {s['cpu_ms_p50']:7.2f} {s['confirm_s']:6.2f} {s['tracked_after']:5.1f}%"
        f" {' '.join(f'{x:.2f}' for x in s['ffc_s']) or '-':>6s} {'-' if s['on_defect'] is None else s['on_defect']:>6}",
        flush=True,
    )
    if a.misses:
        print("       " + misses_line(s["misses"], s["target_counted"]), flush=True)
        print("       " + point_line(s), flush=True)
    if "stages_ms" in s:
        st = s["stages_ms"]
        print(
            f"       stages, CPU ms p50 / mean (each frame's least of {max(a.repeat, 1)}; sum of means"
            f" {sum(m for _, m in st.values()):.2f}): "
            + ", ".join(f"{k} {p:.2f} / {m:.2f}" for k, (p, m) in st.items()),
            flush=True,
        )
