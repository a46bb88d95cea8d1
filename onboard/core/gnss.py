"""The autopilot's GNSS receiver as GPS_RAW_INT (#24) reports it: fix, satellites, accuracy, since when degraded.

Pure: the MAVLink adapter decodes each report into :meth:`GnssState.updated` with its receipt time (monotonic s);
the status shows :meth:`GnssState.summary` (``link.gnss``) and the watchdog warns ``gnss_degraded`` from
``degraded_since_s``.  The daemon's position is #33, the autopilot's estimate; this is why that estimate may
be drifting: below a 3-D fix the autopilot dead-reckons (or stops #33, the daemon's ``gnss_dropout``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from onboard.core.track import json_number

__all__ = ["GPS_FIX_NAMES", "FIX_3D", "GnssState"]

#: GPS_FIX_TYPE (common.xml, values 0..8 in this order) -> the name the status shows; another value is out of range
GPS_FIX_NAMES = dict(enumerate(("no_gps", "no_fix", "2d", "3d", "dgps", "rtk_float", "rtk_fixed", "static", "ppp")))
#: GPS_FIX_TYPE_3D_FIX: every value from it on carries a 3-D position (DGPS, RTK, static, PPP refine it)
FIX_3D = 3


@dataclass(frozen=True)
class GnssState:
    """The latest GPS_RAW_INT: ``fix_type`` (a key of :data:`GPS_FIX_NAMES`), ``satellites`` (None: unknown),
    ``hdop``/``vdop`` (NaN: unknown), ``h_acc_m``/``v_acc_m`` (NaN: unknown), ``received_s`` (monotonic s);
    ``degraded_since_s``: receipt of the first report of the current run below a 3-D fix (None: 3-D now);
    ``fix_losses``: how many times so far a report fell below a 3-D fix after one with it (a fix that comes and goes
    in runs each shorter than the watchdog's second: ``gnss_degraded``)."""

    fix_type: int
    satellites: int | None
    hdop: float
    vdop: float
    h_acc_m: float
    v_acc_m: float
    received_s: float
    degraded_since_s: float | None
    fix_losses: int = 0

    @property
    def fix(self) -> str:
        return GPS_FIX_NAMES[self.fix_type]

    @property
    def has_3d_fix(self) -> bool:
        return self.fix_type >= FIX_3D

    @classmethod
    def updated(
        cls,
        prev: GnssState | None,
        now_s: float,
        fix_type: int,
        satellites: int | None = None,
        hdop: float = math.nan,
        vdop: float = math.nan,
        h_acc_m: float = math.nan,
        v_acc_m: float = math.nan,
    ) -> GnssState:
        """The state after a report received at ``now_s``; ``fix_type`` must be a key of :data:`GPS_FIX_NAMES`."""
        if fix_type not in GPS_FIX_NAMES:
            raise ValueError(f"fix_type {fix_type!r} is not a GPS_FIX_TYPE (0..8)")
        since = None
        losses = 0 if prev is None else prev.fix_losses
        if fix_type < FIX_3D:  # a run of degraded reports keeps the time it began
            since = prev.degraded_since_s if prev is not None and prev.degraded_since_s is not None else now_s
            if prev is not None and prev.has_3d_fix:
                losses += 1
        return cls(fix_type, satellites, hdop, vdop, h_acc_m, v_acc_m, float(now_s), since, losses)

    def summary(self, now_s: float) -> dict[str, Any]:
        """``{fix, fix_type, satellites, hdop, vdop, h_acc_m, v_acc_m, age_s, degraded_s}`` (unknown: null;
        ``degraded_s``: how long below a 3-D fix, null when 3-D)."""
        return {
            "fix": self.fix,
            "fix_type": self.fix_type,
            "satellites": self.satellites,
            "hdop": json_number(self.hdop),
            "vdop": json_number(self.vdop),
            "h_acc_m": json_number(self.h_acc_m),
            "v_acc_m": json_number(self.v_acc_m),
            "age_s": json_number(now_s - self.received_s),
            "degraded_s": None if self.degraded_since_s is None else json_number(now_s - self.degraded_since_s),
        }
