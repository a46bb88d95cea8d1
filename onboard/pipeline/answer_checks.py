"""Checks on a plug-in's answers before the pipeline reads them: :func:`estimate_problem` for a trajectory
estimator's estimate, :func:`tracker_problem` for a tracker's update (the protocols of
:mod:`onboard.pipeline.plugins`).  Each returns what is wrong in words, or None, so that
:class:`~onboard.pipeline.frame_pipeline.FramePipeline` counts and logs a bad answer once instead of
publishing it or raising on it.  Pure: numpy only.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from onboard.core.track import TRACK_STATES

__all__ = ["estimate_problem", "tracker_problem", "frame_shape_hw"]

_REAL = (int, float, np.integer, np.floating)


def _real(x: Any) -> bool:
    return isinstance(x, _REAL) and not isinstance(x, (bool, np.bool_))


def _shape(x: Any) -> tuple[int, ...] | None:
    shape = getattr(x, "shape", None)  # an array's own: np.shape's wrapper costs more, three times a frame
    if shape is not None or isinstance(x, (str, bytes)):
        return shape
    try:
        return np.shape(x)
    except ValueError:  # a ragged sequence
        return None


def estimate_problem(est: Any) -> str | None:
    """What is wrong with an estimator's answer (the protocol's fields, :mod:`onboard.pipeline.plugins`), None when
    nothing: everything the pipeline reads of it, checked once before anything reads it.  A position, velocity,
    position covariance or range that is not finite is wrong too; the velocity covariance is optional (a
    non-finite one goes out as null), its shape is not; an absent range or ``None`` makes no position."""
    try:
        t_s = est.t_s
        if not (_real(t_s) and math.isfinite(t_s)):
            return f"t_s must be a finite number, got {t_s!r}"
        observable = est.observable
        if not isinstance(observable, (bool, np.bool_)):
            return f"observable must be a bool, got {observable!r}"
        frames = est.window_frames
        if (
            isinstance(frames, (bool, np.bool_))
            or not isinstance(frames, (int, np.integer))
            or not 0 <= frames <= 2**31
        ):
            return f"window_frames must be an integer in [0, 2**31], got {frames!r}"
        for name, shape in (("p_ned_m", (3,)), ("v_ned_mps", (3,)), ("cov_p_ned_m2", (3, 3))):
            value = getattr(est, name)
            if _shape(value) != shape:
                return f"{name} must have the shape {shape}, got {_shape(value) or type(value).__name__}"
            if not np.isfinite(value).all():
                return f"{name} is not finite"
        cov_v = getattr(est, "cov_v_ned_m2ps2", None)
        if cov_v is not None and _shape(cov_v) != (3, 3):
            return f"cov_v_ned_m2ps2 must be None or have the shape (3, 3), got {_shape(cov_v)}"
        range_m = getattr(est, "range_m", None)
        if range_m is not None and not (_real(range_m) and math.isfinite(range_m) and range_m >= 0):
            return f"range_m must be None or a finite number >= 0, got {range_m!r}"
        for name in ("range_sigma_ratio", "residual_rms_norm"):  # NaN: unknown
            value = getattr(est, name, None)
            if value is not None and not (_real(value) and not value < 0):
                return f"{name} must be None or a number >= 0, got {value!r}"
        model = getattr(est, "model", None)
        if model is not None and not isinstance(model, str):
            return f"model must be None or a string, got {model!r}"
    except AttributeError as exc:
        return f"no {exc.name or 'field'} (a {type(est).__name__})"
    except TypeError as exc:  # an array of objects: no finiteness to test
        return f"{type(exc).__name__}: {exc}"
    return None


def _finite_real(x: Any) -> bool:
    return _real(x) and math.isfinite(x)


def frame_shape_hw(pixels: Any) -> tuple[int, int] | None:
    """A frame's ``(height, width)`` (None for anything else: the tracker's problem is then judged without it)."""
    shape = getattr(pixels, "shape", None)
    return (int(shape[0]), int(shape[1])) if shape is not None and len(shape) >= 2 else None


def tracker_problem(upd: Any, frame_hw: tuple[int, int] | None = None) -> str | None:
    """What is wrong with a tracker's answer (:class:`onboard.imaging.TrackUpdate`'s fields, as the pipeline reads
    them), None when nothing: a state of ``TRACK_STATES``, a track id None or >= 1, a centre None or finite (required
    by ``measurement_valid``) and, when measured (``measurement_valid``) and given the frame's ``(height, width)``, on
    the frame (0 <= u <= width, 0 <= v <= height: pixel edges, onboard.core.frames' convention; a measurement off the
    frame is a line of sight the camera did not see, where a coasting track's prediction may well be), a box None or
    four finite numbers with a size >= 0."""
    if upd is None:
        return "update returned None"
    try:
        state = upd.state
        if getattr(state, "value", state) not in TRACK_STATES:
            return f"state must be one of {', '.join(TRACK_STATES)}, got {state!r}"
        tid = upd.track_id
        if tid is not None and (isinstance(tid, (bool, np.bool_)) or not isinstance(tid, (int, np.integer)) or tid < 1):
            return f"track_id must be None or an integer >= 1, got {tid!r}"
        valid = upd.measurement_valid
        if not isinstance(valid, (bool, np.bool_)):
            return f"measurement_valid must be a bool, got {valid!r}"
        u, v = upd.u_px, upd.v_px
        if u is None and v is None:
            if valid:
                return "measurement_valid without a centre (u_px, v_px)"
        elif not (_finite_real(u) and _finite_real(v)):
            return f"the centre (u_px, v_px) must be two finite numbers or None, got ({u!r}, {v!r})"
        elif valid and frame_hw is not None and not (0.0 <= u <= frame_hw[1] and 0.0 <= v <= frame_hw[0]):
            return (
                f"a measured centre (u_px, v_px) = ({u!r}, {v!r}) off the {frame_hw[1]} x {frame_hw[0]} frame "
                f"(0 <= u <= width, 0 <= v <= height)"
            )
        box = upd.bbox
        if box is not None:
            if _shape(box) != (4,) or not all(_finite_real(c) for c in box) or box[2] < 0 or box[3] < 0:
                return f"bbox must be None or four finite numbers (x, y, w, h) with w, h >= 0, got {box!r}"
    except AttributeError as exc:
        return f"no {exc.name or 'field'} (a {type(upd).__name__})"
    return None
