"""FOLLOW_TARGET (#144) for an autopilot's follow mode, from the estimator's 3-D track; pure.

common.xml FOLLOW_TARGET: ``timestamp`` (ms since boot; here the frame's capture time on the
autopilot's boot clock, ``Track.time_boot_us`` / 1000), ``est_capabilities`` (bit positions: POS 0,
VEL 1, ACCEL 2, ATT + RATES 3), ``lat`` / ``lon`` (degE7), ``alt`` (m AMSL; our altitude is
ellipsoidal = AMSL, see :mod:`onboard.core.frames`), ``vel`` (m/s NED; (0, 0, 0) = unknown), ``acc``
(unknown: 0), ``attitude_q`` (unknown: (1, 0, 0, 0)), ``rates`` (unknown: 0), ``position_cov``
("eph epv": 1-sigma horizontal and vertical position accuracy in m, the same root-sum-squares of the
covariance as #276's ``h_acc`` / ``v_acc``; the third element 0), ``custom_state`` 0.

Only for a track whose position the estimator calls observable (:func:`onboard.core.track.geo_status_fields`
with ``observable_only``): an autopilot chasing an unobservable range would chase a guess.
PX4's follow-target mode consumes this message (``FollowTarget``); ArduPilot's follow mode reads
FOLLOW_TARGET or GLOBAL_POSITION_INT of the followed system.
"""

from __future__ import annotations

import math
from typing import Any

from onboard.core.track import Track, geo_status_fields

__all__ = ["FOLLOW_TARGET_CAP_POS", "FOLLOW_TARGET_CAP_VEL", "follow_target_fields"]

FOLLOW_TARGET_CAP_POS = 1 << 0
FOLLOW_TARGET_CAP_VEL = 1 << 1


def follow_target_fields(track: Track | None) -> dict[str, Any] | None:
    """Keyword arguments of pymavlink's ``follow_target_send`` for ``track``, or None (no observable
    position, or a non-finite accuracy: an unknown accuracy must not go out looking like "exact")."""
    f = geo_status_fields(track, observable_only=True)
    if f is None:
        return None
    pos = (f["lat_deg"], f["lon_deg"], f["alt_m"], f["h_acc_m"], f["v_acc_m"])
    if not all(v is not None and math.isfinite(v) for v in pos):
        return None
    vel = [f["vel_n_mps"], f["vel_e_mps"], f["vel_d_mps"]]  # a Track's velocity is always finite
    return dict(
        timestamp=int(track.time_boot_us // 1000),
        est_capabilities=FOLLOW_TARGET_CAP_POS | FOLLOW_TARGET_CAP_VEL,
        lat=int(round(f["lat_deg"] * 1e7)),
        lon=int(round(f["lon_deg"] * 1e7)),
        alt=float(f["alt_m"]),
        vel=[float(v) for v in vel],
        acc=[0.0, 0.0, 0.0],
        attitude_q=[1.0, 0.0, 0.0, 0.0],
        rates=[0.0, 0.0, 0.0],
        position_cov=[float(f["h_acc_m"]), float(f["v_acc_m"]), 0.0],
        custom_state=0,
    )
