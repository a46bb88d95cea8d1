"""Operator selection (click-to-track): a ground station's request in pixels, and the pipeline's answer.

The MAVLink side (:mod:`onboard.io.camera_protocol`) turns MAV_CMD_CAMERA_TRACK_POINT / _RECTANGLE /
STOP_TRACKING into a :class:`TrackRequest`; the pipeline (:meth:`onboard.pipeline.frame_pipeline.FramePipeline.request_track`)
answers with a :class:`TrackResult`, which becomes the COMMAND_ACK."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from onboard.core.errors import InputError

__all__ = ["TrackRequest", "TrackResult"]


@dataclass(frozen=True)
class TrackRequest:
    """An operator's tracking command for the pipeline, in pixels of the camera image.

    ``kind``: ``"point"`` (``u_px, v_px`` and ``radius_px``), ``"rectangle"`` (``rect_px`` =
    ``(x0, y0, x1, y1)``, top-left and bottom-right) or ``"stop"``.  ``request_id`` matches the answer.

    One side decides it: the pipeline that applies it or the camera that gives up waiting, whichever
    :meth:`claim` s it first (the two run on different threads); the other leaves it alone, so a ground station
    told it was rejected never sees it carried out later.
    """

    request_id: int
    kind: str
    u_px: float = math.nan
    v_px: float = math.nan
    radius_px: float = math.nan
    rect_px: tuple[float, float, float, float] | None = None
    _unclaimed: list = field(default_factory=lambda: [True], init=False, repr=False, compare=False)

    def claim(self) -> bool:
        """True for the first caller only (``list.pop`` is one atomic step under the interpreter lock)."""
        try:
            return self._unclaimed.pop()
        except IndexError:
            return False

    def __post_init__(self) -> None:
        if self.kind not in ("point", "rectangle", "stop"):
            raise InputError(f"TrackRequest.kind must be point, rectangle or stop, got {self.kind!r}")


@dataclass(frozen=True)
class TrackResult:
    """The pipeline's answer to a :class:`TrackRequest`: ``accepted`` and, when not, ``reason`` (text);
    ``u_px, v_px`` the selected object's centre and ``track_id`` its track when accepted."""

    request_id: int
    accepted: bool
    reason: str = ""
    u_px: float | None = None
    v_px: float | None = None
    track_id: int | None = None
