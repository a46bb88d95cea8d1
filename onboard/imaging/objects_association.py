"""The object tracker's association and track-management rules (:class:`onboard.imaging.objects.ObjectTracker`):
pure functions over predicted pixels, candidates and track records, testable without an image.  Pixels in the
frames.py convention; a track's history is its last measured frames as ``(frame index, los, u, v)``."""

from __future__ import annotations

import math

import numpy as np

from onboard.imaging.objects_model import ObjectParams, TrackRecord, unit_vector

__all__ = [
    "COAST_FIT_MIN",
    "COMMON_SHIFT_MAX_PX",
    "OWNED_PX",
    "common_shift",
    "continue_with",
    "fitted_coast",
    "in_own_gate",
    "merged_to_the_elder",
    "owning_tracks",
    "relative_to_median",
    "track_gate",
]

# a candidate this near another held track's prediction is that track's object (C3's primary: within 1 px of
# its prediction); a fainter one beside it, 3 px or more away, may be nearer the bright one's prediction than
# its own coasting track's and is still its own
OWNED_PX = 2.0

COMMON_SHIFT_MAX_PX = 3.0  # ~3 sigma of RTK's frame-to-frame attitude error in the image: more is not that


def common_shift(puv, cuv, d, gate, held) -> np.ndarray | None:
    """The frame's common offset (px) of measurements ``cuv`` (m, 2) from predictions ``puv`` (n, 2), ``d`` their
    distances, ``gate`` (n,) each prediction's gate, ``held`` (n,) the confirmed tracks measured on the frame
    before: the median, per axis, over the held tracks with exactly one candidate in their gate that lies in
    no other track's gate; None with fewer than two such tracks (one track's own innovation is not the
    frame's) or an offset over COMMON_SHIFT_MAX_PX."""
    inside = d <= gate[:, None]
    idx = np.argmax(inside, axis=1)  # each track's candidate, where it has exactly one
    ok = np.asarray(held, dtype=bool) & (inside.sum(axis=1) == 1) & (inside.sum(axis=0)[idx] == 1)
    if int(ok.sum()) < 2:
        return None
    shift = np.median(cuv[idx[ok]] - puv[ok], axis=0)
    return shift if float(np.hypot(*shift)) <= COMMON_SHIFT_MAX_PX else None


def track_gate(p: ObjectParams, misses):
    """The association gate (px) of a track that missed ``misses`` frames (a number or an array of them):
    ``gate_px`` widened by ``gate_growth_px`` per frame it coasted, up to ``max_gate_px``."""
    return np.minimum(p.gate_px + p.gate_growth_px * misses, p.max_gate_px)


COAST_FIT_MIN = 6  # measured positions a coasting track's line is fitted on (fewer: its filter's rate)


def fitted_coast(history: list, k: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A confirmed track's line of sight on frame ``k`` and its rate per frame from a straight-line fit of its
    ``history`` ((frame, los, u, v), the last measured frames), for it to coast on; None with fewer than
    ``COAST_FIT_MIN`` positions.  The filter's rate follows its last few measurements, each with its own
    frame's attitude error (RTK's white 0.05 deg, 0.67 px per axis): a second target coasting through
    C3's crossing on it drifted off its object and took a noise point in its widened gate.  Over
    ``confirm_window`` frames the fit's rate is off by ~0.04 px a frame under that error: 30 frames on, a median
    1.7 px from the object against the filter's 4.4 (tested)."""
    if len(history) < COAST_FIT_MIN:
        return None
    f = np.array([h[0] for h in history], dtype=np.float64)
    z = np.array([h[1] for h in history], dtype=np.float64)
    f -= f.mean()
    var = float(f @ f)
    if var <= 0.0:
        return None
    mean = z.mean(axis=0)
    rate = (f @ (z - mean)) / var
    los = unit_vector(mean + rate * (k - history[-1][0] + f[-1]))
    return los, rate


def continue_with(o: TrackRecord, t: TrackRecord, window: int) -> None:
    """The coasting confirmed track ``o`` takes the tentative track ``t``'s state and measured positions (its id,
    hits and age go on)."""
    o.los, o.rate, o.uv, o.bbox, o.score = t.los, t.rate, t.uv, t.bbox, t.score
    o.hits += t.hits
    o.misses = 0
    o.aided_run, o.dim_hits = t.aided_run, o.dim_hits + t.dim_hits
    o.history = list(t.history[-window:])
    o.velocity_pxpf, o.fit_rms_px, o.difference = t.velocity_pxpf, t.fit_rms_px, t.difference


def merged_to_the_elder(
    pairs: list[tuple[bool, float, int, int]], held: list[bool], hits: list[int]
) -> list[tuple[bool, float, int, int]]:
    """``pairs`` (not held, distance, track, candidate) without those that would hand a merged image to the
    younger track: a candidate within ``OWNED_PX`` of two or more held tracks' predictions is the image of
    their objects merged, and only the track with the most hits may take it; the others coast on their own
    rates until the images part.  Nearest-first gave it to whichever prediction lay nearer, so a bird crossing
    the primary target took the target's track over its own rate while the primary coasted into the bird's
    (C3 seed 3, frames 162-166: the primary on the target 48 % of the frames)."""
    claims: dict[int, list[int]] = {}
    for _, d, ti, ci in pairs:
        if held[ti] and d <= OWNED_PX:
            claims.setdefault(ci, []).append(ti)
    drop: set[tuple[int, int]] = set()
    for ci, tis in claims.items():
        if len(tis) > 1:
            elder = max(tis, key=lambda ti: (hits[ti], -ti))
            drop.update((ti, ci) for ti in tis if ti != elder)
    return [q for q in pairs if (q[2], q[3]) not in drop] if drop else pairs


def owning_tracks(u: float, v: float, held: list[tuple[TrackRecord, tuple[float, float]]]) -> list[TrackRecord]:
    """The tracks of ``held`` (track, predicted pixel) whose prediction lies within ``OWNED_PX`` of (u, v)."""
    return [t for t, q in held if math.hypot(u - q[0], v - q[1]) <= OWNED_PX]


def in_own_gate(u: float, v: float, puv: tuple[float, float], gate: float, others: list[tuple[float, float]]) -> bool:
    """(u, v) lies within ``gate`` of the prediction ``puv`` and farther than ``OWNED_PX`` from each of
    ``others`` (px)."""
    return math.hypot(u - puv[0], v - puv[1]) <= gate and all(math.hypot(u - q[0], v - q[1]) > OWNED_PX for q in others)


def relative_to_median(v_pxpf: tuple[float, float], tracks: list[TrackRecord]) -> float:
    """|v - the median velocity of ``tracks``| (px/frame)."""
    m = np.median(np.asarray([o.velocity_pxpf for o in tracks]), axis=0)
    return math.hypot(v_pxpf[0] - float(m[0]), v_pxpf[1] - float(m[1]))
