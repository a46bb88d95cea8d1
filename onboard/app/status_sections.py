"""Sections of the daemon's status that read one component each (:meth:`OnboardService.status` puts them
together): kept apart so that the service stays the wiring."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from onboard.core.status import STATUS_SCHEMA

if TYPE_CHECKING:
    from onboard.app.config import OnboardConfig
    from onboard.io.camera_protocol import CameraProtocol
    from onboard.pipeline.frame_pipeline import FramePipeline

__all__ = ["camera_section", "estimator_label", "time_offset_section", "twin_words", "TWIN_STATUS_MAX_BYTES"]


def estimator_label(kind: str, estimator: Any) -> str:
    """``estimator``: what estimates the 3-D position (``kind``, e.g. ``sliding window (process)``), and, while its
    worker process is being spawned (the daemon serves before the first is there; a replacement after a crash),
    that it is starting: until then the frames' estimates are carried, and a first position comes later."""
    if getattr(estimator, "starting", False):
        return f"{kind}, worker starting"
    return kind


def time_offset_section(pipeline: FramePipeline, config: OnboardConfig) -> dict[str, Any] | None:
    """``camera_time_offset``: the camera clock's offset estimate with the threshold it is warned at; None
    while the estimator is off."""
    est = pipeline.time_offset_estimate  # a frozen snapshot: safe to read from the status thread
    if est is None:
        return None
    return {**est.as_dict(), "warn_threshold_ms": config.time_offset.warn_threshold_ms}


def camera_section(camera: CameraProtocol, config: OnboardConfig, pipeline: FramePipeline) -> dict[str, Any]:
    """``camera``: the MAVLink camera's state, where it talks, and what the operator's selection did."""
    st = camera.status()
    st["endpoints"] = list(config.gcs.endpoints)
    st["tracker_mode"] = config.gcs.tracker_mode
    st["tracker_holding"] = bool(getattr(pipeline.tracker, "holding", False))
    st["last_selection"] = pipeline.last_selection
    return st


#: a status larger than this from another daemon is not parsed (the daemon's own are a few KiB): only its size is said
TWIN_STATUS_MAX_BYTES = 256 * 1024


def twin_words(payload: bytes) -> str:
    """What another daemon's status (``irtrack.status/1``, on this vehicle's key) says of it, in words for the
    ``name_clash`` warning: its uptime, frames received and MAVLink link state.  Any peer may publish on the key, so
    whatever it sent gives words and never an exception."""
    if len(payload) > TWIN_STATUS_MAX_BYTES:
        return f"a payload of {len(payload)} bytes"
    try:
        obj = json.loads(payload)
    except (ValueError, RecursionError):  # (RecursionError: nested too deep)
        return f"{len(payload)} bytes that are not JSON"
    if not isinstance(obj, dict) or obj.get("schema") != STATUS_SCHEMA:
        return f"{len(payload)} bytes that are not an irtrack.status/1"
    words = []
    up = obj.get("uptime_s")
    # (abs() and not math.isfinite: an integer too large for a float, 1e400 written out, raised OverflowError there and
    # in the format; no daemon is up 1e15 s)
    if isinstance(up, (int, float)) and not isinstance(up, bool) and abs(up) < 1e15:
        words.append(f"up {up:.0f} s")
    frames = obj.get("frames")
    n = frames.get("in") if isinstance(frames, dict) else None
    if isinstance(n, int) and not isinstance(n, bool):
        words.append(f"{n} frames in")
    link = obj.get("link")
    state = link.get("state") if isinstance(link, dict) else None
    if isinstance(state, str):
        words.append(f"MAVLink {state[:40]}")
    return "its status says " + ", ".join(words) if words else "a status without uptime, frames or link"
