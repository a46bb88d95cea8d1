"""The camera poses at the frames' own stamps, kept over the 3-D window, to make the window's rows again at another
camera-clock compensation without a new window (:mod:`onboard.pipeline.frame_pipeline`, step 7).

The pose buffer keeps seconds of telemetry, the 3-D window tens of seconds: the rows' poses at ``t - c_new`` come
from the poses the pipeline looked up at every frame's stamp ``t`` (30 Hz), interpolated (slerp for the attitude,
linear for the position).  At 50 ms the new time falls between the stamps of the two frames before; the
interpolation over one frame period (33 ms) of a camera turning at 0.1 rad/s / s bends the attitude by micro-radians,
far under its 0.9 mrad white noise, and averages the two samples' noise instead of taking one.
"""

from __future__ import annotations

import collections

import numpy as np

from onboard.core.frames import quat_slerp

__all__ = ["StampPoseHistory"]


class StampPoseHistory:
    """``append(t_us, q_ned_from_cam, p_cam_ned_m)`` once per frame with a pose at its stamp, times increasing;
    :meth:`poses_at` interpolates them.  Keeps the last ``span_s``; a time that does not increase starts it over
    (the stream restarted).  A bracket wider than ``max_gap_s`` is no pose (frames without telemetry between)."""

    def __init__(self, span_s: float, max_gap_s: float = 0.2) -> None:
        self.span_us = int(round(float(span_s) * 1e6))
        self.max_gap_us = int(round(float(max_gap_s) * 1e6))
        self._rows: collections.deque[tuple[int, np.ndarray, np.ndarray]] = collections.deque()

    def __len__(self) -> int:
        return len(self._rows)

    def clear(self) -> None:
        self._rows.clear()

    def append(self, t_us: int, q_ned_from_cam, p_cam_ned_m) -> None:
        t = int(t_us)
        if self._rows and t <= self._rows[-1][0]:
            self._rows.clear()
        self._rows.append((t, np.asarray(q_ned_from_cam, dtype=float), np.asarray(p_cam_ned_m, dtype=float)))
        while self._rows[0][0] < t - self.span_us:
            self._rows.popleft()

    def poses_at(self, t_us) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times (N,) in microseconds -> ``q_ned_from_cam`` (N, 4), ``p_cam_ned_m`` (N, 3) and ``ok`` (N,): False
        (and NaN rows) outside the history or across a gap."""
        want = np.asarray(t_us, dtype=np.int64).reshape(-1)
        q = np.full((want.size, 4), np.nan)
        p = np.full((want.size, 3), np.nan)
        ok = np.zeros(want.size, dtype=bool)
        if len(self._rows) < 2 or want.size == 0:
            return q, p, ok
        ts = np.fromiter((r[0] for r in self._rows), dtype=np.int64, count=len(self._rows))
        qs = np.array([r[1] for r in self._rows])
        ps = np.array([r[2] for r in self._rows])
        hi = np.searchsorted(ts, want, side="left")
        exact = (hi < ts.size) & (ts[np.minimum(hi, ts.size - 1)] == want)
        inside = (hi > 0) & (hi < ts.size)
        hi_c = np.clip(hi, 1, ts.size - 1)
        lo_c = hi_c - 1
        span = ts[hi_c] - ts[lo_c]
        inside &= span <= self.max_gap_us
        if inside.any():
            i = np.flatnonzero(inside)
            alpha = (want[i] - ts[lo_c[i]]) / span[i]
            q[i] = quat_slerp(qs[lo_c[i]], qs[hi_c[i]], alpha)
            p[i] = ps[lo_c[i]] + alpha[:, None] * (ps[hi_c[i]] - ps[lo_c[i]])
        if exact.any():
            j = np.flatnonzero(exact)
            q[j], p[j] = qs[hi[j]], ps[hi[j]]
        ok = inside | exact
        return q, p, ok
