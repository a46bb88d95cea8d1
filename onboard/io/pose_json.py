"""A pose as the flight recording's JSON: :func:`pose_to_json` writes a :class:`~onboard.core.pose_types.PoseAt`
(on the ``frame_input`` and ``imaging_pose`` channels of :mod:`onboard.io.record`), :func:`pose_from_json` reads it
back for replay (:mod:`onboard.app.replay`, :mod:`onboard.app.recorded_messages`).

Floats go out as they are (``json`` prints them by ``repr``), so a recorded pose reads back bit for bit; NaN goes out
as null and comes back as NaN.  Reading checks what replay would otherwise take on trust (the camera's quaternions
unit, its position finite; the times, spans and counts integers >= 0 as written, the gimbal's null or such an integer;
the extrapolation sigmas finite numbers >= 0) and raises :class:`~onboard.core.errors.InputError` naming where and the
field.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin, check_unit_quat
from onboard.core.pose_types import PoseAt, PoseSample
from onboard.core.track import ORIGIN_ALT_RANGE_M

__all__ = ["pose_to_json", "pose_from_json"]


def _vec(v) -> list | None:
    if v is None:
        return None
    return [x if math.isfinite(x) else None for x in np.asarray(v, dtype=float).ravel().tolist()]


def _arr(v) -> np.ndarray:
    # a JSON null (None) becomes NaN; a lone number or null one of shape (1,), which the shape checks refuse (a 0-d
    # array would break check_unit_quat's shape[-1])
    return np.array(v, dtype=float, ndmin=1)


def _count(obj: Mapping[str, Any], key: str, default: Any = None, optional: bool = False) -> Any:
    """``obj[key]`` (``default`` when absent and one is given), an integer >= 0 as :func:`pose_to_json` writes it, or
    null where ``optional``: not coerced, as ``int()`` would (1.5 read as 1, ``true`` as 1, ``"12"`` as 12)."""
    v = obj[key] if default is None or key in obj else default
    if v is None and optional:
        return None
    if type(v) is not int or v < 0:
        raise ValueError(f"{key} must be an integer >= 0{' or null' if optional else ''}, got {v!r}")
    return v


def _sigma(obj: Mapping[str, Any], key: str) -> float:
    """``obj[key]`` (0 when absent): a finite number >= 0, not a string ``float()`` would read (``"nan"``)."""
    v = obj.get(key, 0.0)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise ValueError(f"{key} must be a finite number >= 0, got {v!r}")
    return float(v)


def _origin(o: Mapping[str, Any]) -> GeodeticOrigin:
    """The pose's origin, its altitude within what a track's origin may have (``ORIGIN_ALT_RANGE_M``): a recorded
    origin 1e300 m up made every position of the replay meaningless without a word."""
    origin = GeodeticOrigin(float(o["lat_deg"]), float(o["lon_deg"]), float(o["alt_m"]))
    lo, hi = ORIGIN_ALT_RANGE_M
    if not lo <= origin.alt_m <= hi:
        raise ValueError(f"origin.alt_m must be in [{lo:g}, {hi:g}] m, got {origin.alt_m!r}")
    return origin


def pose_to_json(pose: PoseAt | None) -> dict[str, Any] | None:
    """A :class:`~onboard.core.pose_types.PoseAt` as a JSON-able dict (NaN as null); :func:`pose_from_json` inverts it."""
    if pose is None:
        return None
    b, o = pose.body, pose.origin
    return {
        "time_boot_us": int(b.time_boot_us),
        "p_ned_m": _vec(b.p_ned_m),
        "v_ned_mps": _vec(b.v_ned_mps),
        "q_ned_from_body": _vec(b.q_ned_from_body),
        "p_cam_ned_m": _vec(pose.p_cam_ned_m),
        "q_ned_from_cam": _vec(pose.q_ned_from_cam),
        "q_mount_from_gimbal": _vec(pose.q_mount_from_gimbal),
        "origin": {"lat_deg": float(o.lat_deg), "lon_deg": float(o.lon_deg), "alt_m": float(o.alt_m)},
        "att_span_us": int(pose.att_span_us),
        "pos_span_us": int(pose.pos_span_us),
        "gimbal_span_us": None if pose.gimbal_span_us is None else int(pose.gimbal_span_us),
        "epoch": int(pose.epoch),
        "discontinuities": int(pose.discontinuities),
        "att_extrapolated_us": int(pose.att_extrapolated_us),
        "pos_extrapolated_us": int(pose.pos_extrapolated_us),
        "gimbal_extrapolated_us": None if pose.gimbal_extrapolated_us is None else int(pose.gimbal_extrapolated_us),
        "sigma_extrapolation_rad": float(pose.sigma_extrapolation_rad),
        "sigma_extrapolation_m": float(pose.sigma_extrapolation_m),
    }


def pose_from_json(obj: Mapping[str, Any] | None, where: str = "pose") -> PoseAt | None:
    """The :class:`~onboard.core.pose_types.PoseAt` of :func:`pose_to_json`'s dict (None for None); raises
    :class:`InputError` naming ``where`` and the field on a malformed one."""
    if obj is None:
        return None
    try:
        o = obj["origin"]
        body = PoseSample(
            _count(obj, "time_boot_us"), _arr(obj["p_ned_m"]), _arr(obj["v_ned_mps"]), _arr(obj["q_ned_from_body"])
        )
        # the stored body quaternion was already a checked unit quaternion: keep its exact bits
        object.__setattr__(body, "q_ned_from_body", _frozen(_arr(obj["q_ned_from_body"])))
        g = None if obj.get("q_mount_from_gimbal") is None else _arr(obj["q_mount_from_gimbal"])
        q_cam, p_cam = _arr(obj["q_ned_from_cam"]), _arr(obj["p_cam_ned_m"])
        # checked, not normalised (the recording's exact bits are replayed): a zero or scaled camera quaternion had
        # replayed as a line of sight straight down, or as frames without one, with nothing refused
        check_unit_quat(q_cam, "q_ned_from_cam")
        if g is not None:
            check_unit_quat(g, "q_mount_from_gimbal")
        if p_cam.shape != (3,) or not np.all(np.isfinite(p_cam)):
            raise ValueError(f"p_cam_ned_m must be 3 finite numbers, got {obj['p_cam_ned_m']!r}")
        return PoseAt(
            body=body,
            p_cam_ned_m=p_cam,
            q_ned_from_cam=q_cam,
            q_mount_from_gimbal=g,
            origin=_origin(o),
            att_span_us=_count(obj, "att_span_us"),
            pos_span_us=_count(obj, "pos_span_us"),
            gimbal_span_us=_count(obj, "gimbal_span_us", optional=True) if "gimbal_span_us" in obj else None,
            epoch=_count(obj, "epoch"),
            att_extrapolated_us=_count(obj, "att_extrapolated_us", 0),
            pos_extrapolated_us=_count(obj, "pos_extrapolated_us", 0),
            gimbal_extrapolated_us=_count(obj, "gimbal_extrapolated_us", optional=True)
            if "gimbal_extrapolated_us" in obj
            else None,
            sigma_extrapolation_rad=_sigma(obj, "sigma_extrapolation_rad"),
            sigma_extrapolation_m=_sigma(obj, "sigma_extrapolation_m"),
            # a recording made before position resets were counted: its reboots are its only breaks
            discontinuities=_count(obj, "discontinuities", obj["epoch"]),
        )
    except KeyError as exc:
        raise InputError(f"{where}: missing field {exc.args[0]!r}") from None
    # (OverflowError: an integer too large for a float, an infinity for an integer)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{where}: {exc}") from None


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a
