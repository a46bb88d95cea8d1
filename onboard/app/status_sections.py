"""Sections of the daemon's status that read one component each (:meth:`OnboardService.status` puts them
together): kept apart so that the service stays the wiring."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from onboard.app.config import OnboardConfig
    from onboard.io.camera_protocol import CameraProtocol
    from onboard.pipeline.frame_pipeline import FramePipeline

__all__ = ["camera_section", "estimator_label", "time_offset_section"]


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
