"""A batch MAP reconstruction of a long span, solved in windows.

The MAP problem over a span (:class:`~onboard.estimation.map_estimator.MapEstimator`) is dense in its spline's
controls, so a span of minutes costs minutes of CPU and gigabytes.  :func:`plan_windows` cuts the rows into
problems of at most ``window_s``, one every half window, each row taken from the window whose middle is nearest it;
:func:`solve_in_windows` solves them and stitches the rows taken into one per-row solution.  A span of at most
``window_s`` is one problem, solved as :meth:`MapEstimator.solve` solves it.  The online sliding window
(:mod:`onboard.estimation.sliding`) bounds its own problem and does not use this.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from onboard.estimation.map_estimator import EstimationError, MapResult
from onboard.estimation.observations import Observations

__all__ = [
    "DEFAULT_WINDOW_S",
    "Window",
    "WindowingError",
    "WindowedSolution",
    "plan_windows",
    "solvable_rows",
    "solve_in_windows",
    "stitch",
]


#: The longest span solved as one problem by default.  The MAP problem over a span is dense in its spline's
#: controls (two a second per axis), so its time and memory grow with the span cubed whatever the rows
#: (docs/performance.md, "Long files offline"); 60 s keeps every shipped scenario's flight, at its own duration,
#: one problem as before
DEFAULT_WINDOW_S = 60.0


@dataclass(frozen=True)
class Window:
    """One MAP problem of a windowed reconstruction: rows ``first:stop`` (those in ``t_start_s .. t_end_s``) solved
    together, rows ``take_first:take_stop`` (within them) taken from its solution."""

    first: int
    stop: int
    take_first: int
    take_stop: int
    t_start_s: float
    t_end_s: float


class WindowingError(EstimationError):
    """Rows that a windowed reconstruction cannot solve (too few of them in a window or apart from the others)."""


def plan_windows(t_s: np.ndarray, window_s: float, min_rows: int) -> list[Window]:
    """The MAP problems for rows at times ``t_s`` (strictly increasing): one over every row when the rows span at
    most ``window_s`` (or ``window_s`` is 0); otherwise the rows are cut into stretches at gaps longer than half a
    window, and a stretch longer than a window into windows ``window_s`` long, starting every half window and the
    last one ending at the stretch's last row, each row taken from the window whose middle is nearest it (so at
    least a quarter window from that window's ends, but at the stretch's own ends).

    Raises :class:`WindowingError` naming the times when a problem would have fewer than ``min_rows`` rows."""
    if not (math.isfinite(window_s) and window_s >= 0):
        raise ValueError(f"window_s must be a finite number >= 0, got {window_s!r}")
    t = np.asarray(t_s, dtype=float)
    n = t.size
    stretches = _stretches(t, window_s)
    if stretches is None:
        return [Window(0, n, 0, n, float(t[0]) if n else math.nan, float(t[-1]) if n else math.nan)]
    half = window_s / 2.0
    windows: list[Window] = []
    for a, b in stretches:
        if b - a < min_rows:
            raise WindowingError(
                f"{b - a} row(s) at t_s {t[a]:.3f}..{t[b - 1]:.3f} s lie over {half:g} s (half a {window_s:g} s"
                f" window) from the other rows, so they are solved apart, which needs at least {min_rows} rows"
            )
        t0, t1 = t[a], t[b - 1]
        if t1 - t0 <= window_s:
            windows.append(Window(a, b, a, b, float(t0), float(t1)))
            continue
        starts = [float(t0 + k * half) for k in range(int(math.ceil((t1 - t0 - window_s) / half)))]
        starts.append(float(t1 - window_s))
        middles = np.asarray(starts) + half
        # the window of each row: the nearest middle (the earlier one on a tie), between the midpoints of the
        # sorted middles; and each window's rows, before anything is solved
        owner_bounds = a + np.searchsorted(t[a:b], (middles[:-1] + middles[1:]) / 2.0, side="right")
        take_bounds = [a, *owner_bounds.tolist(), b]
        firsts = a + np.searchsorted(t[a:b], np.asarray(starts), side="left")
        # the last window ends at the stretch's last row itself: its start plus window_s, (t1 - window_s) + window_s,
        # can round an ulp below t1 and leave out the very row it takes
        ends = np.asarray(starts) + window_s
        ends[-1] = t1
        stops = a + np.searchsorted(t[a:b], ends, side="right")
        for k, start in enumerate(starts):
            take_first, take_stop = take_bounds[k], take_bounds[k + 1]
            if take_stop <= take_first:
                continue
            first, stop = int(firsts[k]), int(stops[k])
            if stop - first < min_rows:
                raise WindowingError(
                    f"{stop - first} row(s) at t_s {start:.3f}..{ends[k]:.3f} s, one of the {window_s:g} s"
                    f" windows a long span is solved in; each needs at least {min_rows} rows (longer windows take in"
                    " more)"
                )
            windows.append(Window(first, stop, int(take_first), int(take_stop), start, float(ends[k])))
    return windows


def solvable_rows(t_s: np.ndarray, window_s: float, min_rows: int) -> np.ndarray:
    """Which rows :func:`plan_windows` can solve apart from the others: False for the rows of a stretch (rows
    over half a window from the rest, in a span longer than a window) of fewer than ``min_rows``, which it would
    refuse; a caller that may leave such rows without an estimate (an evaluation's batch) drops them first."""
    t = np.asarray(t_s, dtype=float)
    keep = np.ones(t.size, dtype=bool)
    for a, b in _stretches(t, window_s) or ():
        if b - a < min_rows:
            keep[a:b] = False
    return keep


def _stretches(t: np.ndarray, window_s: float) -> list[tuple[int, int]] | None:
    """The rows ``(first, stop)`` of each stretch :func:`plan_windows` solves apart (cut at gaps longer than half a
    window); None when the rows are one problem (no rows, ``window_s`` 0, or a span of at most ``window_s``)."""
    if t.size == 0 or window_s == 0 or t[-1] - t[0] <= window_s:
        return None
    bounds = [0, *(np.flatnonzero(np.diff(t) > window_s / 2.0) + 1).tolist(), t.size]
    return list(zip(bounds[:-1], bounds[1:]))


def stitch(windows: list[Window] | tuple[Window, ...], per_window: list[np.ndarray], n_rows: int) -> np.ndarray:
    """One array over all ``n_rows`` rows from arrays over each window's rows (leading axis), each row taken from
    the window that takes it."""
    out = np.empty((n_rows, *np.shape(per_window[0])[1:]))
    for w, a in zip(windows, per_window):
        out[w.take_first : w.take_stop] = np.asarray(a)[w.take_first - w.first : w.take_stop - w.first]
    return out


@dataclass(frozen=True, eq=False)
class WindowedSolution:
    """:func:`solve_in_windows`' answer: each window, its :class:`MapResult` and solve time (ms); the stitched
    positions and covariances, one per row.  With one window, ``results[0]`` is :meth:`MapEstimator.solve`'s
    answer over every row."""

    windows: tuple[Window, ...]
    results: tuple[MapResult, ...]
    solve_ms: tuple[float, ...]
    p_ned_m: np.ndarray
    cov_p_ned_m2: np.ndarray

    @property
    def sigma_ned_m(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.einsum("fii->fi", self.cov_p_ned_m2), 0.0))

    @property
    def observable(self) -> bool:
        """Every window observable."""
        return all(r.observable for r in self.results)

    @property
    def observable_rows_fraction(self) -> float:
        taken = sum(w.take_stop - w.take_first for w, r in zip(self.windows, self.results) if r.observable)
        return taken / len(self.p_ned_m)

    @property
    def range_sigma_ratio(self) -> float:
        """The largest window's (nan when any is not finite)."""
        ratios = [r.range_sigma_ratio for r in self.results]
        return max(ratios) if all(math.isfinite(x) for x in ratios) else math.nan

    @property
    def model(self) -> str | None:
        """The windows' common motion family; None when they chose different ones."""
        models = {r.model or r.prior.family for r in self.results}
        return models.pop() if len(models) == 1 else None


def solve_in_windows(
    solve: Callable[[Observations], MapResult],
    obs: Observations,
    window_s: float,
    min_rows: int,
    progress: Callable[[int, int, float, float], None] | None = None,
) -> WindowedSolution:
    """``solve`` (a :meth:`MapEstimator.solve`, or one guarding it) over each of :func:`plan_windows`' windows of
    ``obs``; ``progress(k, n, t_first_s, t_last_s)`` before the k-th (from 1) of n.  Raises
    :class:`WindowingError` before any solve when the rows cannot be windowed, and what ``solve`` raises."""
    n = len(obs)
    windows = plan_windows(obs.t_s, window_s, min_rows)
    results: list[MapResult] = []
    times: list[float] = []
    for k, w in enumerate(windows, 1):
        if progress is not None:
            progress(k, len(windows), float(obs.t_s[w.first]), float(obs.t_s[w.stop - 1]))
        part = obs if (w.first, w.stop) == (0, n) else obs.select(slice(w.first, w.stop))
        t0 = time.perf_counter()
        results.append(solve(part))
        times.append((time.perf_counter() - t0) * 1e3)
    if len(windows) == 1:
        p, cov = results[0].p_ned_m, results[0].cov_p_ned_m2
    else:
        p = stitch(windows, [r.p_ned_m for r in results], n)
        cov = stitch(windows, [r.cov_p_ned_m2 for r in results], n)
    return WindowedSolution(tuple(windows), tuple(results), tuple(times), p, cov)
