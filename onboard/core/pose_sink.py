"""What a telemetry adapter needs of the pose store it feeds: :class:`PoseSink`.

:class:`onboard.core.pose.PoseBuffer` is one; the daemon passes the MAVLink link a
:class:`onboard.app.shared_pose.SharedPoseBuffer` (the same buffer behind a lock, shared with the
pipeline thread), which is another.
"""

from __future__ import annotations

from typing import Any, Protocol

from onboard.core.frames import CameraMount
from onboard.core.pose import GimbalReference

__all__ = ["PoseSink"]


class PoseSink(Protocol):
    """The writer's side of a pose buffer: samples in, with the mount and the reboot count to read.

    Every ``add_*`` returns True when the sample was stored (a refused one is counted, never raised)."""

    @property
    def mount(self) -> CameraMount: ...

    @property
    def reboots(self) -> int: ...

    def add_attitude(self, time_boot_us: int, q_ned_from_body: Any, omega_frd_rps: Any = None) -> bool: ...

    def add_position(
        self, time_boot_us: int, lat_deg: float, lon_deg: float, alt_m: float, v_ned_mps: Any = None
    ) -> bool: ...

    def add_gimbal_status(
        self, time_boot_us: int, q_ref_from_gimbal: Any, reference: GimbalReference, omega_ref_rps: Any = None
    ) -> bool: ...
