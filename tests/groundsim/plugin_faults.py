"""Misbehaving plug-ins and pool jobs for the tests of the evaluation's fault handling: each does one wrong thing
a foreign estimator or job could do (leave the process, raise now and then), importable by name in a worker."""

from __future__ import annotations

import os
import sys
import time

from onboard.pipeline.plugins import build


def pool_job(x):
    """``x * 10``; ``"exit"`` calls sys.exit(3), ``"os_exit"`` leaves the process at once (os._exit(4)),
    ``"hang"`` sleeps 30 s (a plug-in that hangs)."""
    if x == "hang":
        time.sleep(30.0)
    if x == "exit":
        sys.exit(3)
    if x == "os_exit":
        os._exit(4)
    return x * 10


class _Wrap:
    """Our ``paper`` estimator underneath, so that what the wrapper does not spoil is a real estimate."""

    def __init__(self) -> None:
        from onboard.app.config import OnboardConfig

        self.inner = build("paper", OnboardConfig())
        self.n_add = 0

    def reset(self) -> None:
        self.inner.reset()

    def add(self, *args):
        self.n_add += 1
        return self.inner.add(*args)

    def predict(self, t_s, p_cam_ned_m=None):
        return self.inner.predict(t_s, p_cam_ned_m)


class ExitsOnAdd(_Wrap):
    def add(self, *args):
        sys.exit(3)


class LeavesOnAdd(_Wrap):
    """Leaves its process at once (os._exit(4)) on the first ``add``: a crash no exception handler sees."""

    def add(self, *args):
        os._exit(4)


class RaisesSometimes(_Wrap):
    """Every third ``add`` raises ValueError."""

    def add(self, *args):
        if (self.n_add + 1) % 3 == 0:
            self.n_add += 1
            raise ValueError(f"RaisesSometimes: add #{self.n_add} fails")
        return super().add(*args)


class WritesInputs(_Wrap):
    """Moves the pixel and the camera position it is given by 1000 (where it can) before estimating; records
    whether each camera position it got was writable (``seen_writable``, per instance, the last one built in
    ``instances[-1]``)."""

    instances: list[WritesInputs] = []

    def __init__(self) -> None:
        super().__init__()
        self.seen_writable: list[bool] = []
        WritesInputs.instances.append(self)

    def add(self, t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        self.seen_writable.append(bool(getattr(p_cam_ned_m, "flags", None) and p_cam_ned_m.flags.writeable))
        for a in (uv_px, p_cam_ned_m):
            try:
                a[0] += 1000.0
            except (TypeError, ValueError):  # a tuple, a read-only array: as it should be
                pass
        return super().add(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)


class NanPosition(_Wrap):
    """Its estimates, when it has one, with a NaN position."""

    def add(self, *args):
        from types import SimpleNamespace

        e = super().add(*args)
        return None if e is None else SimpleNamespace(**{**vars(e), "p_ned_m": [float("nan")] * 3})
