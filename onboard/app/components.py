"""The daemon's parts that are built from its configuration alone: the MAVLink camera component
(:func:`make_camera_protocol`) and the words that say where zenoh looks for frames (:func:`zenoh_where`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from onboard.app.config import OnboardConfig
from onboard.core.frames import PinholeIntrinsics

if TYPE_CHECKING:
    from onboard.core.counters import RejectCounter
    from onboard.io.camera_protocol import CameraProtocol

__all__ = ["make_camera_protocol", "zenoh_where", "zenoh_unreachable_hint"]


def make_camera_protocol(
    config: OnboardConfig, intrinsics: PinholeIntrinsics, counter: RejectCounter | None = None
) -> CameraProtocol:
    """The :class:`~onboard.io.camera_protocol.CameraProtocol` of ``config`` (gcs, output rates, camera), counting
    the commands it refuses in ``counter`` (the daemon's)."""
    from onboard.io.camera_description import CameraIdentity, VideoStream, video_stream_type
    from onboard.io.camera_protocol import CameraProtocol

    g, o, v = config.gcs, config.output, config.video
    identity = CameraIdentity.from_intrinsics(
        intrinsics.fx_px, intrinsics.width_px, intrinsics.height_px, g.pixel_pitch_um, g.vendor_name, g.model_name
    )
    stream = None
    if v.destination:  # the ground station listens on the destination's port (QGC: udp://0.0.0.0:PORT)
        hfov_deg = math.degrees(2.0 * math.atan(intrinsics.width_px / (2.0 * intrinsics.fx_px)))
        stream = VideoStream(
            video_stream_type(v.transport),
            v.destination.rpartition(":")[2],
            v.fps,
            v.bitrate_bps,
            intrinsics.width_px,
            intrinsics.height_px,
            hfov_deg,
        )
    return CameraProtocol(
        identity,
        intrinsics.width_px,
        intrinsics.height_px,
        component_id=g.component_id,
        stream=stream,
        image_status_hz=o.tracking_image_status_hz,
        geo_status_hz=o.tracking_geo_status_hz,
        observable_only=not o.geo_status_unobservable,
        heartbeat_interval_s=g.heartbeat_interval_s,
        track_request_timeout_s=g.track_request_timeout_s,
        target_rendered=stream is not None and v.overlay,
        counter=counter,
    )


def zenoh_where(config: OnboardConfig) -> str:
    """The zenoh session's endpoints and mode in words, for the no-frames warning."""
    z = config.zenoh
    parts = [f"zenoh mode as {z.config_file} sets it (peer by default)" if z.config_file else "zenoh mode peer"]
    # with a config file, its own endpoints come first: 'none' would hide a file that connects over TLS
    for name, given in (("connect", z.connect), ("listen", z.listen)):
        if z.config_file:
            extra = f" and {', '.join(given)}" if given else ""
            parts.append(f"{name} as {z.config_file} sets it{extra}")
        else:
            parts.append(f"{name} " + (", ".join(given) if given else f"none (--zenoh-{name})"))
    scout = {True: "on", False: "off", None: "as the config file says"}[z.multicast_scouting]
    parts.append(f"multicast scouting {scout}")
    gossip = {True: "on", False: "off", None: "as the config file says"}[z.gossip_autoconnect]
    parts.append(f"dialing gossiped peers {gossip}")
    return "; ".join(parts)


def zenoh_unreachable_hint(config: OnboardConfig) -> str | None:
    """A warning for a session no peer that a router introduces can meet: it connects (to a router, say), listens
    nowhere and dials no gossiped peer, and no config file may say otherwise.  A zenoh 1.10 router does not relay
    between peers, so a camera or simulator connected to the same router never reaches it.  None when it can."""
    z = config.zenoh
    if not z.connect or z.listen or z.config_file is not None or z.gossip_autoconnect is not False:
        return None
    return (
        f"zenoh: this peer connects to {', '.join(z.connect)} and listens nowhere, dialing no peer that gossip names "
        "(zenoh.gossip_autoconnect false): if its frames come through a zenoh router from another peer, they can "
        "never reach it; listen (zenoh.listen, e.g. tcp/127.0.0.1:0, which the router's gossip then names), or set "
        "zenoh.gossip_autoconnect true, or run as a client of the router (zenoh.config_file)"
    )
