"""The pose nouns: a vehicle pose sample, the pose at a frame's time, a look-up's answer.

Pure core.  Frame conventions are those of :mod:`onboard.core.frames` (local NED, body FRD, ``q_a_from_b``
Hamilton, w first); ``time_boot_us`` is integer microseconds on the autopilot's boot clock.
:class:`~onboard.core.pose.PoseBuffer` makes them; the pipeline, the recorder and the replay read them.

:class:`PoseSample`
    One vehicle pose: ``time_boot_us`` (int), ``p_ned_m`` (3,), ``v_ned_mps`` (3,; NaN = unknown),
    ``q_ned_from_body`` (4,).
:class:`PoseAt`
    The answer of :meth:`~onboard.core.pose.PoseBuffer.pose_at`: the interpolated body pose, the camera
    centre ``p_cam_ned_m`` (3,) and attitude ``q_ned_from_cam`` (4,) through the pod mount (and gimbal),
    and how far apart the bracketing samples were.
:class:`PoseLookup`
    The side-effect-free answer of :meth:`~onboard.core.pose.PoseBuffer.lookup`: a pose or the reason
    there is none.

The arrays are read-only float64 copies, validated in ``__post_init__`` (:class:`InputError` naming the
field).  ``from_floats`` builds the same noun from values the buffer computed, without repeating the
array checks when they pass: the buffer makes one per frame, where the checks cost more than the maths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from onboard.core.errors import InputError
from onboard.core.frames import QUAT_NORM_TOL, FrameError, GeodeticOrigin, check_unit_quat, quat_normalize1

__all__ = ["PoseSample", "PoseAt", "PoseLookup", "check_time_us"]


def _frozen_vec(value, shape: tuple[int, ...], what: str, allow_nan: bool = False) -> np.ndarray:
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what} must be numbers of shape {shape}, got {value!r}") from exc
    if a.shape != shape:
        raise InputError(f"{what} must have shape {shape}, got {a.shape}")
    bad = ~np.isfinite(a)
    if allow_nan:
        bad &= ~np.isnan(a)
    if bad.any():
        raise InputError(f"{what} must be finite{' (NaN = unknown allowed)' if allow_nan else ''}, got {a.tolist()}")
    a.setflags(write=False)
    return a


def check_time_us(value, what: str) -> int:
    """``value`` as an int of microseconds >= 0; :class:`InputError` naming ``what`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{what} must be an integer number of microseconds, got {value!r}")
    if value < 0:
        raise InputError(f"{what} must be >= 0, got {value}")
    return int(value)


def _frozen_floats(values) -> np.ndarray:
    """A read-only float64 array of computed, already checked values (what :func:`_frozen_vec` makes)."""
    a = np.array(values, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class PoseSample:
    """Vehicle pose at ``time_boot_us``: ``p_ned_m`` (3,), ``v_ned_mps`` (3,; NaN = unknown), ``q_ned_from_body`` (4,)."""

    time_boot_us: int
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    q_ned_from_body: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "time_boot_us", check_time_us(self.time_boot_us, "PoseSample.time_boot_us"))
        object.__setattr__(self, "p_ned_m", _frozen_vec(self.p_ned_m, (3,), "PoseSample.p_ned_m"))
        object.__setattr__(self, "v_ned_mps", _frozen_vec(self.v_ned_mps, (3,), "PoseSample.v_ned_mps", allow_nan=True))
        try:
            q = check_unit_quat(self.q_ned_from_body, "PoseSample.q_ned_from_body")
        except FrameError as exc:
            raise InputError(str(exc)) from exc
        object.__setattr__(self, "q_ned_from_body", _frozen_vec(q, (4,), "PoseSample.q_ned_from_body"))

    @classmethod
    def from_floats(cls, t: int, p, v, q) -> PoseSample:
        """``PoseSample(t, p, v, q)`` for floats the buffer computed (``t`` an int >= 0; ``p``, ``v`` 3 floats,
        ``q`` 4): the same sample, without repeating :meth:`__post_init__`'s array checks when they pass;
        when they would not, the constructor itself (which raises as it always did)."""
        w, x, y, z = q
        n1 = math.sqrt(w * w + x * x + y * y + z * z)  # check_unit_quat's norm
        if not (
            math.isfinite(p[0] + p[1] + p[2])
            and not (math.isinf(v[0]) or math.isinf(v[1]) or math.isinf(v[2]))
            and abs(n1 - 1.0) <= QUAT_NORM_TOL
        ):
            return cls(t, p, v, q)
        sample = object.__new__(cls)
        object.__setattr__(sample, "time_boot_us", t)
        object.__setattr__(sample, "p_ned_m", _frozen_floats(p))
        object.__setattr__(sample, "v_ned_mps", _frozen_floats(v))
        object.__setattr__(sample, "q_ned_from_body", _frozen_floats(quat_normalize1(q)))  # as check_unit_quat
        return sample


@dataclass(frozen=True, eq=False)
class PoseAt:
    """Pose interpolated at ``body.time_boot_us``.

    ``p_cam_ned_m`` (3,) and ``q_ned_from_cam`` (4,) from :func:`onboard.core.frames.camera_pose_ned`;
    ``q_mount_from_gimbal`` (4,) or None without a gimbal; ``att_span_us`` / ``pos_span_us`` /
    ``gimbal_span_us``: spacing of the bracketing samples (0 when the query hit a sample);
    ``epoch``: number of autopilot reboots seen so far (poses of different epochs share the origin
    only when ``keep_origin_on_reboot``).  ``discontinuities``: number of breaks in the camera's pose
    track seen so far, reboots and position resets (a GNSS step the buffer accepted) alike: camera
    positions of different counts are not on one continuous track, so no estimate may combine rows
    made with both.  ``att_extrapolated_us`` / ``pos_extrapolated_us`` /
    ``gimbal_extrapolated_us``: how far past its newest sample each stream was extrapolated (0 =
    interpolated; the span is then 0 too); ``sigma_extrapolation_rad`` / ``sigma_extrapolation_m``:
    the 1-sigma attitude / position error that extrapolation adds (:mod:`onboard.core.pose`; 0 when
    interpolated).
    """

    body: PoseSample
    p_cam_ned_m: np.ndarray
    q_ned_from_cam: np.ndarray
    q_mount_from_gimbal: np.ndarray | None
    origin: GeodeticOrigin
    att_span_us: int
    pos_span_us: int
    gimbal_span_us: int | None
    epoch: int
    att_extrapolated_us: int = 0
    pos_extrapolated_us: int = 0
    gimbal_extrapolated_us: int | None = None
    sigma_extrapolation_rad: float = 0.0
    sigma_extrapolation_m: float = 0.0
    discontinuities: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "p_cam_ned_m", _frozen_vec(self.p_cam_ned_m, (3,), "PoseAt.p_cam_ned_m"))
        object.__setattr__(self, "q_ned_from_cam", _frozen_vec(self.q_ned_from_cam, (4,), "PoseAt.q_ned_from_cam"))
        if self.q_mount_from_gimbal is not None:
            object.__setattr__(
                self, "q_mount_from_gimbal", _frozen_vec(self.q_mount_from_gimbal, (4,), "PoseAt.q_mount_from_gimbal")
            )

    @classmethod
    def from_floats(cls, body: PoseSample, p_cam, q_nc, q_mg, *rest) -> PoseAt:
        """``PoseAt(body, p_cam, q_nc, q_mg, *rest)`` for floats the buffer computed, as
        :meth:`PoseSample.from_floats`."""
        if not (
            math.isfinite(p_cam[0] + p_cam[1] + p_cam[2])
            and math.isfinite(q_nc[0] + q_nc[1] + q_nc[2] + q_nc[3])
            and (q_mg is None or math.isfinite(q_mg[0] + q_mg[1] + q_mg[2] + q_mg[3]))
        ):
            return cls(body, p_cam, q_nc, q_mg, *rest)
        pose = object.__new__(cls)
        values = (body, _frozen_floats(p_cam), _frozen_floats(q_nc), None if q_mg is None else _frozen_floats(q_mg))
        for name, value in zip(_POSE_AT_FIELDS, values + rest, strict=True):
            object.__setattr__(pose, name, value)
        return pose

    @property
    def time_boot_us(self) -> int:
        return self.body.time_boot_us

    @property
    def extrapolated(self) -> bool:
        return bool(self.att_extrapolated_us or self.pos_extrapolated_us or self.gimbal_extrapolated_us)

    @property
    def mode(self) -> str:
        """``"interpolated"`` (every stream bracketed the time) or ``"extrapolated"``."""
        return "extrapolated" if self.extrapolated else "interpolated"


_POSE_AT_FIELDS = tuple(f.name for f in fields(PoseAt))


@dataclass(frozen=True)
class PoseLookup:
    """Side-effect-free answer of :meth:`~onboard.core.pose.PoseBuffer.lookup`.

    ``pose`` or ``reason``; ``retry`` is True when the query is newer than a stream's last sample
    by less than its ``max_gap`` (the next sample may still bracket it: ask again later).
    """

    pose: PoseAt | None
    reason: str | None = None
    retry: bool = False
