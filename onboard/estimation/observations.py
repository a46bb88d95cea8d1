"""The input noun of the reconstruction core: timestamped bearing observations from a moving camera.

Frames and units follow ``onboard.core.frames``: the camera centre ``p_cam_ned_m`` in local NED metres,
``q_ned_from_cam`` (w, x, y, z) rotating camera-frame vectors (x right, y down, z forward) into
NED, pixels ``(u_px, v_px)`` with the intrinsics of that instant.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from onboard.core.errors import InputError
from onboard.core.frames import QUAT_NORM_TOL, PinholeIntrinsics, check_unit_quat, rotmat_from_quat

__all__ = ["Observations"]


@dataclass(frozen=True)
class Observations:
    """F observations, arrays over a leading axis of length F, times strictly increasing.

    ``t_s`` (F,), ``uv_px`` (F, 2), ``fx_px, fy_px, cx_px, cy_px`` (F,), ``p_cam_ned_m`` (F, 3),
    ``q_ned_from_cam`` (F, 4).  ``xy_norm`` (F, 2), the ideal normalised image coordinates, is
    derived from the pixels (or given, when the pixels were undistorted upstream).
    """

    t_s: np.ndarray
    uv_px: np.ndarray
    fx_px: np.ndarray
    fy_px: np.ndarray
    cx_px: np.ndarray
    cy_px: np.ndarray
    p_cam_ned_m: np.ndarray
    q_ned_from_cam: np.ndarray
    xy_norm: np.ndarray = field(default=None)  # type: ignore[arg-type]  # None: derived from the pixels here
    R_ned_from_cam: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=float).reshape(-1)
        n = t.shape[0]

        def arr(name, shape):
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape == () and shape == (n,):
                a = np.full(n, float(a))
            if a.shape != shape:
                raise InputError(f"Observations.{name}: expected shape {shape}, got {a.shape}")
            if not np.all(np.isfinite(a)):
                bad = int(np.argwhere(~np.isfinite(a.reshape(n, -1)).all(axis=1))[0][0]) if n else 0
                raise InputError(f"Observations.{name}: row {bad} is not finite")
            return a

        object.__setattr__(self, "t_s", arr("t_s", (n,)))
        if n and np.any(np.diff(t) <= 0):
            bad = int(np.argmax(np.diff(t) <= 0)) + 1
            raise InputError(f"Observations.t_s: row {bad} is not after row {bad - 1} (times must increase)")
        for name, shape in (
            ("uv_px", (n, 2)),
            ("fx_px", (n,)),
            ("fy_px", (n,)),
            ("cx_px", (n,)),
            ("cy_px", (n,)),
            ("p_cam_ned_m", (n, 3)),
            ("q_ned_from_cam", (n, 4)),
        ):
            object.__setattr__(self, name, arr(name, shape))
        if np.any(self.fx_px <= 0) or np.any(self.fy_px <= 0):
            raise InputError("Observations.fx_px/fy_px: focal lengths must be > 0")
        norms = np.linalg.norm(self.q_ned_from_cam, axis=1)
        off_unit = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL)
        if off_unit.size:
            raise InputError(
                f"Observations.q_ned_from_cam: row {int(off_unit[0])} quaternion norm {norms[off_unit[0]]:.6g} "
                f"is not 1 within {QUAT_NORM_TOL}"
            )
        object.__setattr__(self, "q_ned_from_cam", check_unit_quat(self.q_ned_from_cam, "Observations.q_ned_from_cam"))
        if self.xy_norm is None:
            xy = np.stack(
                [(self.uv_px[:, 0] - self.cx_px) / self.fx_px, (self.uv_px[:, 1] - self.cy_px) / self.fy_px], axis=1
            )
        else:
            xy = arr("xy_norm", (n, 2))
        object.__setattr__(self, "xy_norm", xy)
        object.__setattr__(self, "R_ned_from_cam", rotmat_from_quat(self.q_ned_from_cam))

    @classmethod
    def from_checked_rows(
        cls, t_s, uv_px, fx_px, fy_px, cx_px, cy_px, p_cam_ned_m, q_ned_from_cam, R_ned_from_cam
    ) -> Observations:
        """Build without re-validating rows that were validated one by one on arrival (sliding window).

        The caller guarantees what ``__post_init__`` checks: finite values, increasing times, unit
        quaternions and ``R_ned_from_cam == R(q_ned_from_cam)``.
        """
        self = object.__new__(cls)
        fx, fy = np.asarray(fx_px, float), np.asarray(fy_px, float)
        uv = np.asarray(uv_px, float)
        xy = np.stack([(uv[:, 0] - np.asarray(cx_px, float)) / fx, (uv[:, 1] - np.asarray(cy_px, float)) / fy], axis=1)
        for name, value in (
            ("t_s", np.asarray(t_s, float)),
            ("uv_px", uv),
            ("fx_px", fx),
            ("fy_px", fy),
            ("cx_px", np.asarray(cx_px, float)),
            ("cy_px", np.asarray(cy_px, float)),
            ("p_cam_ned_m", np.asarray(p_cam_ned_m, float)),
            ("q_ned_from_cam", np.asarray(q_ned_from_cam, float)),
            ("xy_norm", xy),
            ("R_ned_from_cam", np.asarray(R_ned_from_cam, float)),
        ):
            object.__setattr__(self, name, value)
        return self

    def __len__(self) -> int:
        return self.t_s.shape[0]

    @classmethod
    def from_intrinsics(cls, t_s, uv_px, intrinsics: PinholeIntrinsics, p_cam_ned_m, q_ned_from_cam) -> Observations:
        """Observations sharing one camera model; distortion is removed from the pixels here."""
        uv = np.asarray(uv_px, dtype=float)
        n = uv.shape[0]
        # with distortion, the ideal coordinates are computed here; without, __post_init__ derives them
        given = {"xy_norm": intrinsics.normalized_from_pixel(uv)} if intrinsics.has_distortion else {}
        return cls(
            t_s=t_s,
            uv_px=uv,
            fx_px=np.full(n, intrinsics.fx_px),
            fy_px=np.full(n, intrinsics.fy_px),
            cx_px=np.full(n, intrinsics.cx_px),
            cy_px=np.full(n, intrinsics.cy_px),
            p_cam_ned_m=p_cam_ned_m,
            q_ned_from_cam=q_ned_from_cam,
            **given,
        )

    def bearings_ned(self) -> np.ndarray:
        """Unit line-of-sight vectors in NED (F, 3) from the measured pixels and attitudes."""
        b = np.concatenate([self.xy_norm, np.ones((len(self), 1))], axis=1)
        b = np.einsum("fij,fj->fi", self.R_ned_from_cam, b)
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    def with_camera_positions(self, p_cam_ned_m: np.ndarray) -> Observations:
        """The same observations with other (finite, same-shape) camera positions; nothing is re-derived."""
        p = np.asarray(p_cam_ned_m, dtype=float)
        if p.shape != self.p_cam_ned_m.shape or not np.all(np.isfinite(p)):
            raise InputError(
                f"Observations.with_camera_positions: expected finite {self.p_cam_ned_m.shape}, got {p.shape}"
            )
        out = object.__new__(type(self))
        for name in ("t_s", "uv_px", "fx_px", "fy_px", "cx_px", "cy_px", "q_ned_from_cam", "xy_norm", "R_ned_from_cam"):
            object.__setattr__(out, name, getattr(self, name))
        object.__setattr__(out, "p_cam_ned_m", p)
        return out

    def select(self, index) -> Observations:
        """A subset (slice or index array), keeping order."""
        return Observations(
            t_s=self.t_s[index],
            uv_px=self.uv_px[index],
            fx_px=self.fx_px[index],
            fy_px=self.fy_px[index],
            cx_px=self.cx_px[index],
            cy_px=self.cy_px[index],
            p_cam_ned_m=self.p_cam_ned_m[index],
            q_ned_from_cam=self.q_ned_from_cam[index],
            xy_norm=self.xy_norm[index],
        )
