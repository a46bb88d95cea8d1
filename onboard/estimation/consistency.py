"""A consistency monitor on the published estimates: does the estimate published a moment ago, carried to
now, predict the bearing measured now, within its own covariance?

The sliding window's verdict is taken at its model selections; between them (up to 20 s once selections
agree) a target that starts to turn leaves a stiff constant-velocity model confidently wrong along range
while the spline still follows every bearing (on synthetic racetrack targets under RTK, 2-minute flights
published 7 % of their positions beyond 3 sigma, all of them called observable, errors 4-30 % of range
with a range sigma of 0.3-5 %).  A bearing predicted over ``horizon_s`` by an estimate whose velocity and
motion model are wrong misses by more than that estimate's covariance allows, long before the window's
own innovations call a new selection.  While the normalised innovation squared (2 degrees of freedom:
the bearing's two angles) of that prediction exceeds ``nis_threshold``, and for ``hold_s`` after, the
estimate is demoted: called unobservable, with the estimator's range floor applied (honest, not
confident), through ``demote``.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["ConsistencyMonitor", "ManoeuvreDetector", "SelectionHistory", "unsteady_evidence_nats"]


#: an :class:`~onboard.estimation.sliding.TrackEstimate` (its ``t_s``, ``observable``, ``model``,
#: ``motion_prior``, ``cov_p_ned_m2`` and ``propagated``): sliding calls this monitor, so it is not imported here
TrackEstimate = Any


class ConsistencyMonitor:
    """``bearing_sigma_rad``: one bearing's 1-sigma per axis without the attitude's constant bias (common to the
    carried estimate and the new bearing); ``horizon_s``: how old the estimate that predicts the bearing is
    (over 1 s a target turning at 0.7 m/s^2 leaves its constant-velocity prediction by 0.35 m, less than
    RTK navigation's bearing noise at 250 m; over 2 s by 1.4 m); ``model_hold_s``: how long an estimate
    is demoted after the selected motion model (family or intensity) changed (0: not at all), a new
    selection being unconfirmed (a constant-velocity model selected over a window that holds a turn can
    be a wrong-range solution that explains every bearing, which no bearing innovation shows)."""

    def __init__(
        self,
        bearing_sigma_rad: float,
        horizon_s: float = 2.0,
        nis_threshold: float = 13.8,  # chi-square(2) at 1e-3
        hold_s: float = 3.0,
        model_hold_s: float = 0.0,
    ):
        self.bearing_sigma_rad = float(bearing_sigma_rad)
        self.horizon_s = float(horizon_s)
        self.nis_threshold = float(nis_threshold)
        self.hold_s = float(hold_s)
        self.model_hold_s = float(model_hold_s)
        self._model: str | None = None
        self._past: deque[TrackEstimate] = deque()
        self._inconsistent_until = -math.inf
        self.last_nis = math.nan
        self.demoted = 0

    def nis(self, est_then: TrackEstimate, t_s: float, p_cam_ned_m, los_unit_ned) -> float:
        """The normalised innovation squared of the bearing ``los_unit_ned`` seen from ``p_cam_ned_m`` at
        ``t_s`` against ``est_then`` carried to ``t_s``."""
        pred = est_then.propagated(t_s, p_cam_ned_m)
        d = pred.p_ned_m - np.asarray(p_cam_ned_m, dtype=float)
        rng = float(np.linalg.norm(d))
        if rng <= 0:
            return math.nan
        u = d / rng
        # the tangent plane of the predicted direction: two unit vectors across it
        a = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(u, a)
        T = np.stack([a, b])
        m = np.asarray(los_unit_ned, dtype=float)
        innov = T @ m / max(float(u @ m), 1e-9)  # the measured direction's tangent-plane offset, radians
        S = T @ pred.cov_p_ned_m2 @ T.T / rng**2 + self.bearing_sigma_rad**2 * np.eye(2)
        return float(innov @ np.linalg.solve(S, innov))

    def check(
        self,
        est: TrackEstimate,
        p_cam_ned_m,
        los_unit_ned,
        demote: Callable[[TrackEstimate], TrackEstimate],
    ) -> TrackEstimate:
        """``est`` as published: demoted (``demote``) while the estimate of ``horizon_s`` ago fails to predict
        this bearing, and for ``hold_s`` after."""
        t = est.t_s
        then = None
        while self._past and self._past[0].t_s <= t - self.horizon_s:
            then = self._past.popleft()
        if then is not None:
            self._past.appendleft(then)  # the newest one at least horizon_s old serves the next frame too
            self.last_nis = self.nis(then, t, p_cam_ned_m, los_unit_ned)
            if self.last_nis > self.nis_threshold:
                self._inconsistent_until = t + self.hold_s
        self._past.append(est)
        model = f"{est.model}:{est.motion_prior}"
        if self._model is not None and model != self._model:
            self._inconsistent_until = max(self._inconsistent_until, t + self.model_hold_s)
        self._model = model
        if est.observable and t <= self._inconsistent_until:
            self.demoted += 1
            return demote(dataclasses.replace(est, observable=False))
        return est


class ManoeuvreDetector:
    """A CUSUM (Page 1954; Basseville & Nikiforov, *Detection of Abrupt Changes*, 1993, section 2.2) on the
    sliding window's per-frame innovations: the newest bearing's squared standardised residual before its
    incremental step, per axis (``0.5 r^T r``: exponential with mean 1 while the selected model follows the
    target).  ``S_k = max(0, S_{k-1} + min(x_k, clip) - reference)``; it fires when ``S_k`` exceeds
    ``threshold``.

    Why: a stiff model selected over a window the target flew steadily (a racetrack leg, or a turn) is
    confidently wrong as soon as the target changes motion model; the window then slides range to explain
    the new bearings (1 % -> 40 % of range within 4 s at a range sigma of 0.7 %), while the innovations of
    the first frames after the change are already 5-20 per axis.  The mean over the newest 15 frames that
    calls a selection early waits for 15 frames and for the selection period; this test fires after
    2-3 frames of such innovations.  Under the null hypothesis (increments ``x - 2`` with ``x`` ~ Exp(1))
    the threshold 10 is crossed about once in 1e4 frames; ``clip`` keeps one outlier (a wrong detection)
    from firing it alone."""

    def __init__(self, reference: float = 2.0, threshold: float = 10.0, clip: float = 8.0):
        if not (reference > 1.0 and threshold > 0 and clip > reference):
            raise ValueError(f"ManoeuvreDetector: invalid reference {reference}, threshold {threshold}, clip {clip}")
        self.reference = float(reference)
        self.threshold = float(threshold)
        self.clip = float(clip)
        self.statistic = 0.0
        self.fired = 0
        self._rise_t_s = math.inf
        #: the estimated time of the change the last firing detected: the first frame of the statistic's
        #: excursion from 0 that crossed the threshold (Page's change-time estimate); -inf before any
        self.onset_t_s = -math.inf

    def add(self, innovation_per_axis: float, t_s: float) -> bool:
        """One frame's innovation (``0.5 r^T r``) at ``t_s``; True when the statistic crosses the threshold (the
        model no longer explains the bearings; :attr:`onset_t_s` is then set).  A non-finite innovation counts
        as ``clip``."""
        x = float(innovation_per_axis)
        x = min(x, self.clip) if math.isfinite(x) else self.clip
        was_zero = self.statistic <= 0.0
        self.statistic = max(0.0, self.statistic + x - self.reference)
        if self.statistic <= 0.0:
            self._rise_t_s = math.inf
        elif was_zero:
            self._rise_t_s = float(t_s)
        if self.statistic > self.threshold:
            self.fired += 1
            self.onset_t_s = min(self._rise_t_s, float(t_s))
            return True
        return False

    def reset(self) -> None:
        """A new model selection: the statistic starts again from 0 (:attr:`onset_t_s` is kept)."""
        self.statistic = 0.0
        self._rise_t_s = math.inf


class SelectionHistory:
    """Consecutive model selections must agree on the target's range where their windows overlap.

    Why: a window that holds a change of motion model (a racetrack's leg and half of its turn) is followed
    by no single family; a stiff one can explain every bearing at the wrong range (30-50 % short, range
    sigma 2-5 %, adequacy test passed: the bearings cannot tell the two apart), and the selection calls it
    observable.  The selection made a few seconds earlier on a window of one motion model put the same
    frames at another range, confidently.  Two solutions of largely the same bearings that disagree beyond
    their covariances cannot both be right: the posterior over motion models that includes a switch would
    hold both (Bayesian model averaging over the selections: the spread between their means), so neither
    is confident.  Such a selection is demoted (unobservable, with the range floor), and kept: a later
    selection must agree with it too, until the window has slid past their common frames.

    Which of two such selections is wrong is unknown, and the wrong one is wrong over its whole window (it is a
    basin of the solution, not a frame): every frame either holds stays *disputed* until the window has slid
    past it.  A later selection that shares disputed frames is not confirmed by agreeing with what is kept
    there (the other solution may have left the window already), so it is demoted too.  On the racetrack a
    wrong-range selection over a window that held a turn and a leg conflicted with the right one before it; the
    next selections, over the turn alone, fell into the same wrong basin (their warm start), agreed with it
    once the right one's frames had left the window, and were published 30-40 % of range off at a 1 % range
    sigma.

    The test is on range only (the bearings pin the rest of the position in both): at the frames both windows
    hold (sampled every ``sample_s``), ``(u^T (p_new - p_old))^2 > nsigma^2 u^T (P_new + P_old) u`` with ``u``
    the new solution's line of sight.  Both solutions share most of their bearings, so the difference's own
    spread is smaller than the summed covariances: the test errs towards agreement."""

    def __init__(self, nsigma: float = 3.0, sample_s: float = 1.0):
        if not (nsigma > 0 and sample_s > 0):
            raise ValueError(f"SelectionHistory: invalid nsigma {nsigma} or sample_s {sample_s}")
        self.nsigma = float(nsigma)
        self.sample_s = float(sample_s)
        self._t = np.zeros(0)
        self._p = np.zeros((0, 3))
        self._P = np.zeros((0, 3, 3))
        self._disputed = np.zeros(0, dtype=bool)  # per kept row: two selections disagreed on this frame
        self.conflicts = 0
        #: selections demoted for sharing disputed frames, though they agreed with the rows kept there
        self.disputed = 0
        self.last_max_nsigma = math.nan

    def check(self, t_s, p_ned_m, cov_p_ned_m2, p_cam_ned_m, observable: bool) -> bool:
        """Whether a selection's window solution (rows at times ``t_s`` (F,), positions (F, 3), model-averaged
        point covariances (F, 3, 3) before any range floor, cameras (F, 3)) agrees on range with the
        observable selections kept whose frames it holds; an ``observable`` one is kept for the next."""
        t = np.asarray(t_s, dtype=float)
        p = np.asarray(p_ned_m, dtype=float)
        P = np.asarray(cov_p_ned_m2, dtype=float)
        keep = self._t >= t[0]
        self._t, self._p, self._P = self._t[keep], self._p[keep], self._P[keep]
        self._disputed = self._disputed[keep]
        i = np.searchsorted(t, self._t)
        i = np.minimum(i, t.size - 1)
        common = np.abs(t[i] - self._t) <= 1e-9  # the windows' rows are the same kept frames
        agree, conflict = True, False
        self.last_max_nsigma = math.nan
        if np.any(common):
            j = i[common]
            los = p[j] - np.asarray(p_cam_ned_m, dtype=float)[j]
            u = los / np.maximum(np.linalg.norm(los, axis=1), 1e-9)[:, None]
            d = np.einsum("fi,fi->f", u, p[j] - self._p[common])
            var = np.einsum("fi,fij,fj->f", u, P[j] + self._P[common], u)
            z = np.abs(d) / np.sqrt(np.maximum(var, 1e-30))
            self.last_max_nsigma = float(np.max(z))
            conflict = self.last_max_nsigma > self.nsigma
            agree = not conflict
            if conflict:
                self.conflicts += 1
                self._disputed[:] = True  # every row kept within this window: the earlier selections' solutions
            elif np.any(self._disputed[common]):
                agree = False
                self.disputed += 1
        if observable:
            # one row per sample_s bin of absolute time: the next window picks the same frames
            b = np.floor(t / self.sample_s)
            first = np.concatenate([[True], b[1:] != b[:-1]])
            self._t = np.concatenate([self._t, t[first]])
            self._p = np.concatenate([self._p, p[first]])
            self._P = np.concatenate([self._P, P[first]])
            # a conflicting selection's rows are disputed, all of them; not those of a selection demoted only for
            # sharing disputed frames (a chain of those would not end while the window keeps sliding)
            self._disputed = np.concatenate([self._disputed, np.full(int(first.sum()), conflict)])
        return agree

    def reset(self) -> None:
        self._t = np.zeros(0)
        self._p = np.zeros((0, 3))
        self._P = np.zeros((0, 3, 3))
        self._disputed = np.zeros(0, dtype=bool)


def unsteady_evidence_nats(grid_log_evidence: dict[str, list[tuple[float, float]]] | None) -> float:
    """How far (nats of log evidence) the best model of a selection (``MapResult.grid_log_evidence``: per family,
    (q, log evidence) of each intensity solved) is above the best *steady* one: each family at its stiffest
    intensity, a constant velocity, acceleration or turn with next to no process noise.  0 without a selection.

    Why: a target that keeps one motion (a racetrack's leg, or its turn; a circling or a cruising target) is
    explained by a steady model about as well as by a loose one (0-4.2 nats apart on the racetrack's single legs
    and turns, circling targets and synthetic P1/P2 flights under RTK); a window that holds a change of
    motion needs the process noise of a loose intensity to bend through it (17-440 nats once both motions hold a
    few seconds of it).  A single model over such a window can explain the bearings at the wrong range (0.6-0.9
    of it at a 3-5 % range sigma), so beyond ``MapConfig.model_margin_nats`` (the margin within which the
    selection calls models indistinguishable) the window is no ground for a verdict."""
    if not grid_log_evidence:
        return 0.0
    rows = [qe for qes in grid_log_evidence.values() for qe in qes]
    if not rows:
        return 0.0
    best = max(e for _, e in rows)
    steady = max(min(qes, key=lambda qe: qe[0])[1] for qes in grid_log_evidence.values() if qes)
    return float(best - steady)
