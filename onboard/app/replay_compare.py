"""``onboard.replay --compare``: a replay's tracks and objects against the recorded ones (:mod:`onboard.app.replay`).

Pure: lists of JSON dicts in, differences out, and the lines that say them.  A recording of the inline estimator is
compared field by field (:func:`compare_tracks`, floats bit for bit); a worker's, whose estimates depend on its
timing, within the two estimates' covariances together (:func:`compare_within_sigma`, judged by
:func:`beyond_a_workers_sigma`); the objects frame by frame (:func:`compare_objects`).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

__all__ = [
    "SIGMA_GATE",
    "WORKER_BEYOND_SHARE",
    "WORKER_GROSS_SIGMA",
    "WORKER_ONLY_ONE_MAX_COUNT",
    "FrameDiff",
    "SigmaComparison",
    "compare_tracks",
    "compare_within_sigma",
    "compare_objects",
    "beyond_a_workers_sigma",
    "print_compare",
]

#: a replayed 3-D position is "within" the recorded one when their difference is at most this many sigmas of
#: the two covariances' sum (the Mahalanobis distance)
SIGMA_GATE = 3.0
#: a worker's recording matches its replay while at most this share of the positions lie beyond SIGMA_GATE
#: sigmas (an honest estimate puts a few tenths of a per cent of two estimates' differences there by chance: the
#: honesty rule's 1 %) and none beyond WORKER_GROSS_SIGMA (a chance of ~1e-7 a position)
WORKER_BEYOND_SHARE = 0.01
WORKER_GROSS_SIGMA = 6.0
#: frames where only one of the two has a 3-D position: a worker's first estimate, or its first after a reset, may
#: come a frame or two apart from a replay's; more than this many, or than WORKER_BEYOND_SHARE of the positions,
#: is a replay that lost (or invented) positions, whatever the ones it kept look like
WORKER_ONLY_ONE_MAX_COUNT = 3


@dataclass(frozen=True)
class FrameDiff:
    seq: int
    time_boot_us: int
    fields: tuple  # names of the differing fields
    d_pos_m: float | None  # |ned_m difference|, when both have one
    d_uv_px: float | None


def _matched(
    recorded: list, replayed: list, keys: tuple[str, ...] = ("seq", "time_boot_us")
) -> tuple[list[tuple[dict, dict]], int]:
    """The two message lists' pairs matched on ``keys`` (a track's seq and time_boot_us by default), in recorded
    order (duplicates in turn), and the number of messages of either list left unmatched."""

    def key(t):
        return tuple(t.get(k) for k in keys)

    theirs: dict = {}
    for t in replayed:
        theirs.setdefault(key(t), []).append(t)
    pairs, unmatched = [], 0
    for a in recorded:
        lst = theirs.get(key(a))
        if not lst:
            unmatched += 1
            continue
        pairs.append((a, lst.pop(0)))
    unmatched += sum(len(v) for v in theirs.values())
    return pairs, unmatched


#: keys added to the track after recordings that lack them were made, with the value their absence means
_ABSENT_MEANS = {"compensated_us": 0, "estimate_epoch": 0}
#: ... and keys whose absence means "not stated", which a replay does state: compared only where both have them
_ABSENT_UNSTATED = frozenset({"los_sigma_bias_deg"})


def _differs(a: dict, b: dict, k: str) -> bool:
    if k in _ABSENT_UNSTATED and (k not in a or k not in b):
        return False
    return a.get(k, _ABSENT_MEANS.get(k)) != b.get(k, _ABSENT_MEANS.get(k))


def compare_tracks(recorded: list, replayed: list) -> tuple[list[FrameDiff], int, int]:
    """Per-frame differences of two track lists matched on (seq, time_boot_us); returns (diffs, matched,
    unmatched).  A field differs when its JSON values differ at all (floats bit for bit)."""
    pairs, unmatched = _matched(recorded, replayed)
    diffs = []
    for a, b in pairs:
        names = tuple(sorted(k for k in set(a) | set(b) if _differs(a, b, k)))
        if not names:
            continue
        dp = duv = None
        if a.get("ned_m") and b.get("ned_m"):
            dp = math.dist(a["ned_m"], b["ned_m"])
        if a.get("u_px") is not None and b.get("u_px") is not None:
            duv = math.hypot(a["u_px"] - b["u_px"], a["v_px"] - b["v_px"])
        diffs.append(FrameDiff(int(a["seq"]), int(a["time_boot_us"]), names, dp, duv))
    return diffs, len(pairs), unmatched


@dataclass(frozen=True)
class SigmaComparison:
    """Replayed 3-D positions against the recorded ones, in the two estimates' uncertainty together."""

    compared: int  # matched frames with a position in both and a recorded covariance
    beyond: int  # of those, farther apart than the gate (Mahalanobis distance under the two covariances' sum)
    max_sigma: float  # the largest such distance (0 when none compared)
    position_only_one: int  # matched frames where one of the two has a position and the other not
    gate_sigma: float
    # matched frames whose track follows another object (track_id) in the replay: not compared, a difference
    # whatever the worker (the image chain does not depend on the estimator's timing; an operator's selection,
    # which a replay does not make again, is one cause)
    other_object: int = 0


def beyond_a_workers_sigma(within: SigmaComparison) -> bool:
    """Whether a worker's recording and its replay differ by more than the worker's timing explains: more than
    :data:`WORKER_BEYOND_SHARE` of the positions beyond the gate, one beyond :data:`WORKER_GROSS_SIGMA`, or more
    frames with a position in one of them only than :data:`WORKER_ONLY_ONE_MAX_COUNT` and that share."""
    positions = within.compared + within.position_only_one
    only_one = within.position_only_one > max(WORKER_ONLY_ONE_MAX_COUNT, WORKER_BEYOND_SHARE * positions)
    beyond = within.beyond > WORKER_BEYOND_SHARE * within.compared or within.max_sigma > WORKER_GROSS_SIGMA
    return only_one or beyond or within.other_object > 0


def compare_within_sigma(recorded: list, replayed: list, gate_sigma: float = SIGMA_GATE) -> SigmaComparison:
    """How many replayed positions lie farther from the recorded ones than ``gate_sigma`` sigmas: the Mahalanobis
    distance ``sqrt(d^T P^-1 d)`` of the difference ``d`` under ``P``, the recorded position covariance
    (``cov_ned_m2``) plus the replayed one (the recorded alone when the replay has none).  The test for recordings
    whose estimates depend on timing (a worker estimator): a replay cannot give them bit for bit, but two honest
    estimates of the same target differ by no more than their errors together.  Under the recorded covariance
    alone, a worker's answer a frame late that chose another motion model than the replay's, both estimates
    unobservable and honest, lay far outside it: a clean recording failed its comparison."""
    import numpy as np

    compared = beyond = one_only = other = 0
    worst = 0.0
    for a, b in _matched(recorded, replayed)[0]:
        if a.get("track_id") != b.get("track_id"):
            # two objects' positions, however close in sigma (an unobservable estimate's covariance spans both)
            other += 1
            continue
        pa, pb = a.get("ned_m"), b.get("ned_m")
        if (pa is None) != (pb is None):
            one_only += 1
            continue
        cov = a.get("cov_ned_m2")
        if pa is None or cov is None:
            continue
        d = np.asarray(pb, dtype=float) - np.asarray(pa, dtype=float)
        P = np.asarray(cov, dtype=float)
        if b.get("cov_ned_m2") is not None:
            P = P + np.asarray(b["cov_ned_m2"], dtype=float)
        try:
            m2 = float(d @ np.linalg.solve(P, d))
        except np.linalg.LinAlgError:
            m2 = float(d @ np.linalg.pinv(P) @ d)
        m = math.sqrt(max(m2, 0.0)) if math.isfinite(m2) else math.inf
        compared += 1
        beyond += m > gate_sigma
        worst = max(worst, m)
    return SigmaComparison(compared, beyond, worst, one_only, gate_sigma, other)


def compare_objects(recorded: list, replayed: list) -> tuple[int, int, int]:
    """Two lists of ``irtrack.objects/1`` messages matched on (time_boot_us, frame_index) in order; returns
    (matched, identical, unmatched): a frame is identical when its message is equal (floats bit for bit)."""
    pairs, unmatched = _matched(recorded, replayed, ("time_boot_us", "frame_index"))
    return len(pairs), sum(a == b for a, b in pairs), unmatched


def print_compare(diffs, matched: int, unmatched: int, within=None, worker=None, file=None) -> None:
    """The per-frame differences, then (``within``, a :class:`SigmaComparison`) the positions against the
    recorded sigma, with why a worker's recording cannot replay bit for bit, then the summary line; on ``file``,
    by default the ``sys.stdout`` of the call (not of the import: a redirected or captured stdout gets them)."""
    file = sys.stdout if file is None else file
    timed = worker is not None and worker != "inline"
    if timed and diffs:
        # the lines below would read as failures: a worker's estimates differ by timing, judged by the sigma test
        print(
            f"compare: {len(diffs)} frames differ in their fields (a worker's recording: expected; whether the replay "
            "is the recording's is judged by the 3-D positions' sigma test below):",
            file=file,
        )
    for d in diffs:
        extra = []
        if d.d_pos_m is not None:
            extra.append(f"|d ned| {d.d_pos_m:.6g} m")
        if d.d_uv_px is not None:
            extra.append(f"|d uv| {d.d_uv_px:.6g} px")
        print(
            f"seq {d.seq} t {d.time_boot_us} us: {', '.join(d.fields)}" + (f" ({'; '.join(extra)})" if extra else ""),
            file=file,
        )
    if timed:
        print(
            f"compare: recorded with estimator.worker: {worker}, whose estimates depend on its timing (a late answer "
            "is the newest estimate propagated to the frame), so no replay gives them bit for bit: only "
            "estimator.worker: inline recordings do; this replay ran the estimator inline",
            file=file,
        )
    if within is not None:
        print(
            f"compare: 3-D positions within {within.gate_sigma:g} sigma of the recorded and replayed covariances: "
            f"{within.compared - within.beyond}/{within.compared}, {within.beyond} beyond"
            + (f" (max {within.max_sigma:.3g} sigma)" if within.compared else "")
            + f"; {within.position_only_one} with a position in one only"
            + (
                f"; {within.other_object} frames tracking another object (track_id; operator selections are not "
                "replayed), not compared"
                if within.other_object
                else ""
            )
            + (
                f" (a worker's recording matches with at most {100 * WORKER_BEYOND_SHARE:g} % beyond and none beyond "
                f"{WORKER_GROSS_SIGMA:g} sigma)"
                if worker is not None and worker != "inline"
                else ""
            ),
            file=file,
        )
    dp = [d.d_pos_m for d in diffs if d.d_pos_m is not None]
    print(
        f"compare: {matched - len(diffs)}/{matched} frames identical, {len(diffs)} differ"
        + (f" (max |d ned| {max(dp):.6g} m)" if dp else "")
        + f", {unmatched} unmatched",
        file=file,
    )
