"""Test doubles shared by several test files: the fake clock, the fake autopilot (groundsim's scripted one), and
valid tracks and status documents to hand to the code that consumes them."""

from __future__ import annotations

import dataclasses
import socket
from typing import Any

import numpy as np

from groundsim.io.scripted_autopilot import ScriptedAutopilot
from onboard.app.config import OnboardConfig
from onboard.core.frames import GeodeticOrigin
from onboard.core.status import build_status
from onboard.core.track import Track
from onboard.io.mavlink_link import LinkStatus


class FakeClock:
    """The tests' one fake clock: monotonic seconds that move only when the test sets or adds to ``t_s``,
    or when the code under test calls :meth:`sleep` (which advances it and records the request in ``sleeps``).

    Every clock interface the code takes: callable (seconds; ``OnboardService``, ``PoseBuffer``,
    ``MavlinkLink``), ``ns()`` (``OnboardService``), ``now_s()`` and ``sleep(s)`` (the simulator's paced loop,
    the interface of ``groundsim.app.run.SystemClock``)."""

    def __init__(self, t_s: float = 1000.0) -> None:
        self.t_s = t_s
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t_s

    def ns(self) -> int:
        return int(self.t_s * 1e9)

    def now_s(self) -> float:
        return self.t_s

    def sleep(self, s: float) -> None:
        """Advance by ``s`` seconds at once; a sleep of zero or less is a bug of the caller (it raises)."""
        if not s > 0:
            raise AssertionError(f"FakeClock.sleep({s!r}): the caller must not sleep for zero or less")
        self.sleeps.append(s)
        self.t_s += s


# the one fake autopilot of the tests (and of bench.onboard, which cannot import tests/): scripted, call by call
FakeAutopilot = ScriptedAutopilot


def quiet_link_status(state: str, autopilot_sysid: int | None, messages_rx: int) -> LinkStatus:
    """The LinkStatus of a MAVLink link with no heartbeat age, no message-rate requests, no clock sync, no losses
    and no reboots (what a fake link's ``status()`` returns)."""
    return LinkStatus(
        state=state,
        autopilot_sysid=autopilot_sysid,
        heartbeat_age_s=None,
        rates_confirmed=(),
        rates_pending=(),
        rates_refused=(),
        clock_synced=False,
        messages_rx=messages_rx,
        link_losses=0,
        reboots=0,
    )


def tracking_track(**fields) -> Track:
    """A valid ``tracking`` Track of uav1 (seq 1 at 10 us): a measurement at the centre of a 640 x 512 image in a
    20 px box, a pose, the origin (32, 118.8, 0), no position.  ``fields`` replace any of them."""
    kw = dict(
        vehicle="uav1",
        seq=1,
        time_boot_us=10,
        state="tracking",
        track_id=1,
        measurement_valid=True,
        u_px=320.0,
        v_px=256.0,
        bbox=(310.0, 246.0, 20.0, 20.0),
        pose_valid=True,
        origin=GeodeticOrigin(32.0, 118.8, 0.0),
    )
    kw.update(fields)
    return Track(**kw)


def positioned_track(**fields) -> Track:
    """:func:`tracking_track` with an observable position: 100 m north, 80 m up, 130 m away, moving 1 m/s north,
    sigma 2 m horizontal and 1 m vertical, from a 60-frame window.  ``fields`` replace any field."""
    kw = dict(
        lat_deg=32.001,
        lon_deg=118.8,
        alt_m=80.0,
        p_ned_m=(100.0, 0.0, -80.0),
        v_ned_mps=(1.0, 0.0, 0.0),
        cov_p_ned_m2=np.diag([4.0, 4.0, 1.0]),
        range_m=130.0,
        observable=True,
        window_frames=60,
    )
    kw.update(fields)
    return tracking_track(**kw)


def idle_status(**fields) -> dict[str, Any]:
    """:func:`onboard.core.status.build_status` of a daemon that has seen nothing yet: no frames, no statistics, no
    link, no track.  ``fields`` replace any argument (for a test about one part of the document)."""
    kw: dict[str, Any] = dict(
        vehicle="uav1",
        uptime_s=1.0,
        frames_in=0,
        frames_processed=0,
        frames_dropped=0,
        frames_rejected=0,
        tracks_published=0,
        processing_ms={},
        latency_ms={},
        pose_wait_ms={},
        capture_to_track_ms=None,
        rejected={},
        link=None,
        cpu_share=None,
        pipeline_cpu_share=None,
        last_track=None,
        estimator="map",
        queue_length=0,
    )
    kw.update(fields)
    return build_status(**kw)


def single_chain(config: OnboardConfig | None = None) -> OnboardConfig:
    """``config`` (default: the built-in one) with ``imaging.chain: single``.

    For tests of what surrounds the image chain (frame admission, clocks, the estimator hand-off, the
    track's fields) that count frames from the first: the single chain tracks a target on the frame it
    first sees it, while the default objects chain confirms an object over several frames first.  The
    objects chain behind the same pipeline has its own tests (test_objects_output and the eval's).
    """
    config = config or OnboardConfig()
    return dataclasses.replace(config, imaging=dataclasses.replace(config.imaging, chain="single"))


def silent_tcp_server(wait_s: float) -> tuple[socket.socket, socket.socket]:
    """(server, filler): a listening TCP socket on 127.0.0.1 whose accept queue a never-accepted connection fills,
    so that its host drops the next connection's packets, as a host that does not answer would (the caller closes
    both)."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(0)
    return server, socket.create_connection(server.getsockname(), timeout=wait_s)
