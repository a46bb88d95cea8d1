"""FOLLOW_TARGET (#144) for an autopilot's follow mode, from the estimator's 3-D track; pure.

common.xml FOLLOW_TARGET (encoded by :class:`onboard.io.mavlink_wire.FollowTarget`): ``timestamp`` (ms
since boot; here the time the position is of on the autopilot's boot clock: the frame's capture time less the
camera's measured latency, ``(Track.time_boot_us - Track.compensated_us) / 1000``),
``est_capabilities`` (bit positions: POS 0, VEL 1, ACCEL 2, ATT + RATES 3: here POS, and VEL when the
estimate's velocity has a covariance), ``lat`` / ``lon`` (degE7), ``alt`` (m AMSL; our altitude is
ellipsoidal = AMSL, see :mod:`onboard.core.frames`), ``vel`` (m/s NED; (0, 0, 0) = unknown, sent
without the VEL bit), ``acc`` (unknown: 0), ``attitude_q`` (unknown: (1, 0, 0, 0)), ``rates`` (unknown:
0), ``position_cov`` ("eph epv": 1-sigma horizontal and vertical position accuracy in m, the same
root-sum-squares of the covariance as #276's ``h_acc`` / ``v_acc``; the third element 0),
``custom_state`` 0.

Only for a track whose position the estimator calls observable
(:func:`onboard.io.mavlink_wire.geo_status_fields` with ``observable_only``): an autopilot chasing an
unobservable range would chase a guess.

Who acts on it: the daemon sends it on the autopilot link from the vehicle's own system id (component
``mavlink.component_id``, 191), as every component of a vehicle does.

* PX4 takes it: its MAVLink receiver's FOLLOW_TARGET handler publishes lat, lon, alt and vel as the
  ``follow_target`` topic without looking at the sender's system id (nor at ``est_capabilities``), and
  the Follow Me mode (``FlightTaskAutoFollowTarget``, through its target estimator) flies after it.
* ArduPilot does not: ``AP_Follow::should_handle_message`` drops every message whose system id is the
  vehicle's own ("skip our own messages") before it looks at FOLLOW_TARGET or GLOBAL_POSITION_INT, so
  its Follow mode ignores ours.  Following with ArduPilot needs a target that is a system of its own
  (``FOLL_SYSID``), which this daemon is not.
"""

from __future__ import annotations

import math

from onboard.core.track import Track
from onboard.io.mavlink_wire import FOLLOW_TARGET_CAP_POS, FOLLOW_TARGET_CAP_VEL, FollowTarget, geo_status_fields

__all__ = ["FOLLOW_TARGET_CAP_POS", "FOLLOW_TARGET_CAP_VEL", "follow_target"]


def follow_target(track: Track | None) -> FollowTarget | None:
    """The FOLLOW_TARGET of ``track``, or None (no observable position, or a non-finite accuracy: an
    unknown accuracy must not go out looking like "exact")."""
    f = geo_status_fields(track, observable_only=True)
    if f is None or track is None:  # no fields without a track
        return None
    pos = (f["lat_deg"], f["lon_deg"], f["alt_m"], f["h_acc_m"], f["v_acc_m"])
    if not all(v is not None and math.isfinite(v) for v in pos):
        return None
    # a velocity without a (finite) covariance is not vouched for: sent as common.xml's "unknown"
    vel_known = track.cov_v_ned_m2ps2 is not None
    return FollowTarget(
        # the position's own time: the track's line of sight and 3-D are of the stamp less the compensation
        time_boot_us=track.time_boot_us - track.compensated_us,
        lat_deg=f["lat_deg"],
        lon_deg=f["lon_deg"],
        alt_m=float(f["alt_m"]),
        v_ned_mps=(f["vel_n_mps"], f["vel_e_mps"], f["vel_d_mps"]) if vel_known else (0.0, 0.0, 0.0),
        h_acc_m=float(f["h_acc_m"]),
        v_acc_m=float(f["v_acc_m"]),
        est_capabilities=FOLLOW_TARGET_CAP_POS | (FOLLOW_TARGET_CAP_VEL if vel_known else 0),
    )
