"""What any detector could see of the primary target at its true place: a known-signal (matched-filter) bound.

``python -m bench.imaging --scene C2 --seed 1 5 --bound`` prints it below each row.  For each of the target's
frames the bench counts (visible, >= 3 NETD, after its first second) the registered difference is taken at the
truth, as the objects chain takes it about a prediction (this frame minus the one ``LAG`` frames before, shifted
by the camera's true rotation and the background's own displacement found about the target:
:func:`onboard.imaging.background_difference.background_difference`), and compared with what the target must
add there if it hides the background: a linear occlusion model ``d(x) = A g(x) (T - B(x))``, ``g`` the image of
a point (the renderer's Gaussian optics, sigma ``PSF_SIGMA_PX``, over the pixel's box), ``A`` the target's
apparent area (px^2), ``T`` its grey, ``B`` the background it hides (the earlier frame, registered).  ``A`` and
``T`` are fitted once over the run's frames (least squares, linear in ``A T`` and ``A``); each frame's
statistic is then the matched filter's ``z = d . s / (sigma |s|)`` with ``s`` that frame's modelled signal and
``sigma`` the difference's own noise away from the target and from where it was (``MEAN_ABS_TO_SIGMA`` times
the mean absolute value).  With the target's grey, size and place all known this is the most powerful test
there is in Gaussian noise (Neyman-Pearson): its ``z`` has mean ``|s| / sigma`` and unit spread, so no detector
working from that difference finds more of the frames at the same false-alarm rate per tested place.

Printed twice: with the earlier frame resampled bilinearly, and by Keys' cubic convolution as the chain now
resamples it (:func:`onboard.imaging.background_difference.cubic_square`), which reproduces a sharp, blurred edge
at a sub-pixel shift better: how much of the difference's noise at roof edges is the resampling's own.  The chain's
own test with a learned signature is :mod:`onboard.imaging.signature`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.imaging.background_difference import (
    background_difference,
    cubic_square,
    difference_centre,
    keys_weights,
    rotation_shift_px,
)
from onboard.imaging.clutter import MEAN_ABS_TO_SIGMA
from onboard.imaging.objects_detection import DIFFERENCE_HALF_PX, DIFFERENCE_LAG
from onboard.imaging.signature import PSF_SIGMA_PX, point_footprint

__all__ = [
    "PSF_SIGMA_PX",
    "LAG",
    "point_footprint",
    "keys_weights",
    "cubic_square",
    "SignatureFit",
    "known_signal_bound",
]

LAG = DIFFERENCE_LAG  # the objects chain's difference lag (frames)
HALF_PX = DIFFERENCE_HALF_PX  # the difference square's half side, as the chain's
WINDOW_PX = 3  # the signal's (2 WINDOW_PX + 1)^2 window about the target
AWAY_PX = 4.5  # pixels this far from the target and from where it was make the noise


@dataclass(frozen=True)
class SignatureFit:
    """The target's fitted occlusion signature: ``area_px2`` (A) and ``grey`` (T), and the frames it came from."""

    area_px2: float
    grey: float
    frames: int


@dataclass
class _Frame:
    k: int
    warm: bool
    diff: np.ndarray  # the window of the difference about the truth
    background: np.ndarray  # the registered earlier frame over the same window
    footprint: np.ndarray
    sigma: float


def _frames(run, lag: int, cubic: bool) -> tuple[list[_Frame], list[tuple[int, bool]]]:
    """The windows at the truth of the target's counted frames, and every counted frame as (k, warm)."""
    from groundsim.evaluation.mot import MIN_CONTRAST_NETD, SETTLE_S

    K = run.intrinsics
    side = 2 * HALF_PX + 1
    first = None
    out, counted = [], []
    for k, labels in enumerate(run.labels):
        mine = [lb for lb in labels if lb[0] == 0]
        if not mine or mine[0][4] != "visible":
            continue
        _, _, u, v, _, contrast, warm = mine[0]
        first = k if first is None else first
        if k < first + SETTLE_S * run.frame_rate_hz or not contrast >= MIN_CONTRAST_NETD or run.frames[k] is None:
            continue
        counted.append((k, bool(warm)))
        if k < lag or run.frames[k - lag] is None:
            continue
        shift = rotation_shift_px(K, u, v, run.R_ned_from_cam[k - lag], run.R_ned_from_cam[k])
        if shift is None:
            continue
        cur, prev = run.frames[k].astype(np.float32), run.frames[k - lag].astype(np.float32)
        d, (du, dv) = background_difference(cur, prev, (u, v), shift, half_px=HALF_PX)
        cu, cv_ = difference_centre((u, v))
        # the chain's displacement, the earlier square resampled either way
        if cubic:
            old = cubic_square(prev, side, cu - du, cv_ - dv)
        else:
            old = cv2.getRectSubPix(prev, (side, side), (cu - du - 0.5, cv_ - dv - 0.5), patchType=cv2.CV_32F)
        d = cv2.getRectSubPix(cur, (side, side), (cu - 0.5, cv_ - 0.5), patchType=cv2.CV_32F) - old
        # square coordinates: pixel (i, j) of the square has its centre at (j, i); the target and where it was
        tu, tv = u - (cu - HALF_PX - 0.5) - 0.5, v - (cv_ - HALF_PX - 0.5) - 0.5
        then = [lb for lb in run.labels[k - lag] if lb[0] == 0]
        ou, ov = (then[0][2] + du - (cu - HALF_PX), then[0][3] + dv - (cv_ - HALF_PX)) if then else (-1e9, -1e9)
        jj, ii = np.meshgrid(np.arange(side), np.arange(side))
        away = (np.hypot(jj - tu, ii - tv) > AWAY_PX) & (np.hypot(jj - ou, ii - ov) > AWAY_PX)
        sigma = MEAN_ABS_TO_SIGMA * float(np.mean(np.abs(d[away])))
        i0, j0 = int(math.floor(tv + 0.5)), int(math.floor(tu + 0.5))
        r = WINDOW_PX
        if not (r <= i0 < side - r and r <= j0 < side - r) or not sigma > 0.0:
            continue
        win = (slice(i0 - r, i0 + r + 1), slice(j0 - r, j0 + r + 1))
        out.append(
            _Frame(
                k, bool(warm), d[win].astype(float), old[win].astype(float), point_footprint(tu - j0, tv - i0), sigma
            )
        )
    return out, counted


def fit_signature(frames: list[_Frame]) -> SignatureFit:
    """A and T of ``d = A g (T - B)`` over all ``frames`` by weighted least squares (``1 / sigma^2``):
    linear in ``p = A T`` and ``A``."""
    rows, rhs = [], []
    for f in frames:
        rows.append(np.stack([f.footprint.ravel(), -(f.footprint * f.background).ravel()], axis=1) / f.sigma)
        rhs.append(f.diff.ravel() / f.sigma)
    (p, a), *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
    return SignatureFit(float(a), float(p / a) if a else math.nan, len(frames))


def known_signal_z(f: _Frame, fit: SignatureFit) -> tuple[float, float]:
    """``(z, |s| / sigma)``: the matched filter's statistic at the truth and its expected value."""
    s = fit.area_px2 * f.footprint * (fit.grey - f.background)
    norm = float(np.sqrt((s * s).sum()))
    if not norm > 0.0:
        return 0.0, 0.0
    return float((f.diff * s).sum()) / (f.sigma * norm), norm / f.sigma


def known_signal_bound(run, lag: int = LAG, cubic: bool = False, thresholds=(2.0, 3.0)) -> dict:
    """The bound for ``run`` (a :class:`bench.imaging_scenes.SceneRun` given the true attitude): the fit, per
    class of frame (warm / cold) the median ``z`` and ``|s| / sigma``, the median ``sigma`` and the share with
    ``z`` over each threshold, and the Pd (over the bench's counted frames) a detector would reach that found
    every warm frame and a cold one whenever its ``z`` passed the threshold (frames without a difference,
    the first ``lag``, counted as found)."""
    frames, counted = _frames(run, lag, cubic)
    out: dict = {"counted": len(counted), "cold_counted": sum(not w for _, w in counted)}
    if len(frames) < 2:
        return out
    fit = fit_signature(frames)
    out["fit"] = fit
    zs = {f.k: known_signal_z(f, fit) for f in frames}
    for name, warm in (("warm", True), ("cold", False)):
        sel = [f for f in frames if f.warm == warm]
        if not sel:
            continue
        z = np.array([zs[f.k][0] for f in sel])
        out[name] = {
            "n": len(sel),
            "z_median": float(np.median(z)),
            "snr_median": float(np.median([zs[f.k][1] for f in sel])),
            "sigma_median": float(np.median([f.sigma for f in sel])),
            "over": {t: float(np.mean(z > t)) for t in thresholds},
        }
    cold_z = {f.k: zs[f.k][0] for f in frames if not f.warm}
    out["pd_bound"] = {
        t: 100.0 * sum(1 for k, w in counted if w or cold_z.get(k, math.inf) > t) / len(counted) for t in thresholds
    }
    return out


def bound_lines(run) -> list[str]:
    """The ``--bound`` lines of one scene and seed (``run`` given the true attitude)."""
    lines = []
    for cubic in (False, True):
        b = known_signal_bound(run, cubic=cubic)
        how = "cubic background (the chain's)" if cubic else "bilinear background"
        if "fit" not in b:
            lines.append(f"known-signal bound, {how}: too few frames of the target")
            continue
        fit = b["fit"]
        parts = [
            f"known-signal bound, {how}: target A {fit.area_px2:.2f} px^2 at {fit.grey:.1f} grey ({fit.frames} frames)"
        ]
        for cls in ("warm", "cold"):
            if cls in b:
                c = b[cls]
                over = ", ".join(f"z > {t:g} {100 * v:.0f} %" for t, v in c["over"].items())
                parts.append(
                    f"{cls} {c['n']}: z median {c['z_median']:.2f} (|s|/sigma {c['snr_median']:.2f}, sigma"
                    f" {c['sigma_median']:.2f} grey), {over}"
                )
        pd = ", ".join(f"{v:.1f} % at z > {t:g}" for t, v in b["pd_bound"].items())
        parts.append(
            f"Pd with every warm frame and the cold ones over z: {pd} ({b['cold_counted']} cold of {b['counted']})"
        )
        lines.append("; ".join(parts))
    return lines
