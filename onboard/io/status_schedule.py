"""When the camera's tracking statuses (#275 / #276) are due, pure: the rate limits and the schedule arithmetic.

No clocks: times (``now_s``) are passed in.  :mod:`onboard.io.camera_protocol` answers the commands that set and
read the intervals (SET_MESSAGE_INTERVAL, GET_MESSAGE_INTERVAL) and sends the statuses.
"""

from __future__ import annotations

__all__ = ["MAX_TRACKING_STATUS_HZ", "MIN_TRACKING_STATUS_INTERVAL_S"]

#: the fastest a ground station may have #275 / #276 sent.  Each describes the newest track, which changes
#: once per IR frame at most (thermal cores deliver 9 to 60 frames/s, most 25 or 30): a faster stream repeats
#: the same track, and it shares a telemetry radio with the autopilot's.  SET_MESSAGE_INTERVAL has no upper
#: rate in common.xml, so a shorter interval is served at this rate, ACCEPTED, and MESSAGE_INTERVAL reports
#: the interval applied.  The configured defaults (``output.tracking_*_status_hz``) are the operator's and
#: are not clamped.
MAX_TRACKING_STATUS_HZ = 50.0
MIN_TRACKING_STATUS_INTERVAL_S = 1.0 / MAX_TRACKING_STATUS_HZ


def _interval_s(hz: float) -> float | None:
    return None if hz <= 0 else 1.0 / hz


def _next_due(due_s: float, every_s: float, now_s: float) -> float:
    """The next due time on the schedule; one that fell behind restarts from now instead of bursting."""
    nxt = due_s + every_s
    return nxt if nxt > now_s else now_s + every_s
