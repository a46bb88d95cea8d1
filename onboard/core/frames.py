"""Every frame convention irtrack uses, in one place.

Frames
------
WGS84
    Geodetic latitude ``lat_deg`` (north positive), longitude ``lon_deg`` (east positive), both
    in degrees, and ``alt_m``: height above the WGS84 ellipsoid in metres.  MAVLink
    ``GLOBAL_POSITION_INT.alt`` is AMSL; irtrack treats AMSL as ellipsoidal height (the geoid
    undulation is a constant offset over a flight and cancels in a local frame).
ECEF
    Earth-centred, earth-fixed, metres (``p_ecef_m``).
Local NED
    North, East, Down in metres about a :class:`GeodeticOrigin` (lat, lon, alt); the tangent
    plane of the WGS84 ellipsoid at the origin (``p_ned_m``, ``v_ned_mps``).
Local level
    The NED axes where the vehicle is: north, east and the ellipsoid's normal at its own latitude and
    longitude.  An autopilot measures gravity and north there, so its attitude (``ATTITUDE_QUATERNION``),
    its velocity (``GLOBAL_POSITION_INT`` vx, vy, vz) and an earth-frame gimbal attitude (#285) are relative
    to the local level, not to the origin's NED.  The two differ by the angle between the two normals, about
    0.009 deg per km from the origin (0.6 px of the default camera at 5 km, a pixel at 8.3 km);
    ``q_ned_from_level(lat_deg, lon_deg, origin)`` turns one into the other, and the pose buffer applies it
    to everything the autopilot reports (:mod:`onboard.core.pose`).  A caller that gives positions in NED
    (``PoseBuffer.add_position_ned``, a flat world such as a test's) gives its attitudes in that NED too.
Body FRD
    Forward, Right, Down, fixed to the airframe.  MAVLink ``ATTITUDE_QUATERNION`` gives
    ``q_ned_from_body``; Euler angles are the aerospace Z-Y-X sequence (yaw, then pitch, then
    roll), so ``R_ned_from_body = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
Mount
    The camera pod's own FRD-like frame: x along the optical axis, y right, z down.  The mount
    is fixed to the body by ``CameraMount``: a lever arm (the camera centre in body FRD metres)
    and ``q_body_from_mount``.  An optional gimbal adds ``q_mount_from_gimbal`` (same axes);
    with no gimbal the gimbal frame equals the mount frame.
Camera (OpenCV)
    x right, y down, z forward (optical axis), metres; origin at the optical centre.  The fixed
    axis permutation from camera to mount is ``R_mount_from_cam`` (cam z -> mount x, cam x ->
    mount y, cam y -> mount z).
Image
    Pixels ``(u_px, v_px)``: u to the right, v down, origin at the top-left pixel's top-left
    corner, so the centre of pixel (i, j) is (j + 0.5, i + 0.5) and the principal point of a
    640 x 512 sensor is (320, 256).
Line of sight (azimuth / elevation)
    A direction ``l`` in local NED as ``az_deg = atan2(l_e, l_n)``: from north towards east,
    (-180, 180]; ``el_deg = atan2(-l_d, hypot(l_n, l_e))``: positive up, [-90, 90].  Used by the
    track's ``los_az_deg`` / ``los_el_deg`` (:func:`onboard.core.track.line_of_sight_ned`).

Quaternions
-----------
Hamilton convention, scalar first ``(w, x, y, z)``, unit norm.  ``q_a_from_b`` rotates vectors
expressed in frame b into frame a: ``v_a = R(q_a_from_b) @ v_b``; composition is
``q_a_from_c = q_a_from_b (x) q_b_from_c``.  ``q`` and ``-q`` are the same rotation.

Small-angle errors
------------------
An attitude error ``phi`` (rotation vector, rad) expressed in NED perturbs the true attitude as
``R_meas = Exp(phi) @ R_true`` (the navigation-frame psi-angle error model of strapdown INS,
Titterton & Weston, Strapdown Inertial Navigation Technology, 2nd ed., ch. 11).

Intrinsics
----------
Pinhole: ``u = fx * x/z + cx``, ``v = fy * y/z + cy`` on distorted normalised coordinates;
radial-tangential (Brown-Conrady, OpenCV order ``k1, k2, p1, p2, k3``) distortion is optional.
The default camera is the FLIR Vue Pro 640: 13 mm lens, 17 um pitch, 640 x 512 pixels, so
``fx = fy = 13e-3 / 17e-6 = 764.7 px`` and the principal point is the image centre.

All functions are pure and vectorised over a leading axis where the docstring says ``(..., 3)``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import pymap3d

from onboard.core.errors import IrtrackError

__all__ = [
    "GeodeticOrigin",
    "CameraMount",
    "PinholeIntrinsics",
    "far_off_image",
    "FrameError",
    "ecef_from_geodetic",
    "geodetic_from_ecef",
    "ned_from_geodetic",
    "geodetic_from_ned",
    "geodetic_from_ned1",
    "q_ned_from_level",
    "q_ned_from_level1",
    "quat_normalize",
    "quat_multiply",
    "quat_conjugate",
    "quat_rotate",
    "rotmat_from_quat",
    "quat_from_rotmat",
    "quat_from_euler",
    "euler_from_quat",
    "quat_from_rotvec",
    "rotvec_from_quat",
    "rotmat_from_rotvec",
    "quat_slerp",
    "Quat",
    "quat_normalize1",
    "quat_multiply1",
    "quat_conjugate1",
    "quat_from_rotvec1",
    "rotvec_from_quat1",
    "quat_slerp1",
    "R_MOUNT_FROM_CAM",
    "camera_pose_ned",
]

QUAT_NORM_TOL = 1e-3  # a MAVLink quaternion whose norm is off by more than this is rejected
VUE_PRO_640_FOCAL_M = 13e-3
VUE_PRO_640_PITCH_M = 17e-6


class FrameError(IrtrackError, ValueError):
    """An input to a frame conversion is not a valid rotation, pose or camera."""


# --------------------------------------------------------------------------- geodesy (WGS84)


@dataclass(frozen=True)
class GeodeticOrigin:
    """Origin of a local NED frame: WGS84 latitude/longitude in degrees, altitude in metres."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("lat_deg", "lon_deg", "alt_m"):
            if not math.isfinite(getattr(self, name)):
                raise FrameError(f"GeodeticOrigin.{name} must be finite, got {getattr(self, name)!r}")
        if not -90.0 <= self.lat_deg <= 90.0:
            raise FrameError(f"GeodeticOrigin.lat_deg must be in [-90, 90], got {self.lat_deg}")
        if not -180.0 <= self.lon_deg <= 360.0:
            raise FrameError(f"GeodeticOrigin.lon_deg must be in [-180, 360], got {self.lon_deg}")


_ELL = pymap3d.Ellipsoid.from_name("wgs84")


_A_M, _B_M = float(_ELL.semimajor_axis), float(_ELL.semiminor_axis)
_E_M = math.sqrt(_A_M**2 - _B_M**2)


def _ecef_from_geodetic1(lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
    """One point: pymap3d.geodetic2ecef's formulas in floats (numpy's call overhead on one point cost
    more than the arithmetic; the daemon converts every position sample and every published point)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n_m = _A_M**2 / math.hypot(_A_M * math.cos(lat), _B_M * math.sin(lat))
    return np.array(
        [
            (n_m + alt_m) * math.cos(lat) * math.cos(lon),
            (n_m + alt_m) * math.cos(lat) * math.sin(lon),
            (n_m * (_B_M / _A_M) ** 2 + alt_m) * math.sin(lat),
        ]
    )


def _geodetic_from_ecef1(x: float, y: float, z: float) -> tuple[float, float, float] | None:
    """One point: pymap3d.ecef2geodetic's closed form (You 2000, eqns 4, 7, 13) in floats; None near the
    polar axis or the centre (pymap3d's special cases), which the caller hands to pymap3d."""
    r = math.sqrt(x**2 + y**2 + z**2)
    u = math.sqrt(0.5 * (r**2 - _E_M**2) + 0.5 * math.hypot(r**2 - _E_M**2, 2 * _E_M * z))
    hxy = math.hypot(x, y)
    if u < 1.0 or hxy < 1.0:
        return None
    hue = math.hypot(u, _E_M)
    beta = math.atan(hue / u * z / hxy)
    beta += ((_B_M * u - _A_M * hue + _E_M**2) * math.sin(beta)) / (
        _A_M * hue * 1 / math.cos(beta) - _E_M**2 * math.cos(beta)
    )
    lat = math.atan(_A_M / _B_M * math.tan(beta))
    alt = math.hypot(z - _B_M * math.sin(beta), hxy - _A_M * math.cos(beta))
    if x**2 / _A_M**2 + y**2 / _A_M**2 + z**2 / _B_M**2 < 1:
        alt = -alt
    return math.degrees(lat), math.degrees(math.atan2(y, x)), alt


def ecef_from_geodetic(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """WGS84 geodetic -> ECEF metres, shape (..., 3)."""
    if all(isinstance(v, (float, int)) for v in (lat_deg, lon_deg, alt_m)):
        return _ecef_from_geodetic1(float(lat_deg), float(lon_deg), float(alt_m))
    x, y, z = pymap3d.geodetic2ecef(lat_deg, lon_deg, alt_m, ell=_ELL, deg=True)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1).astype(float)


def geodetic_from_ecef(p_ecef_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF metres (..., 3) -> (lat_deg, lon_deg, alt_m)."""
    p = np.asarray(p_ecef_m, dtype=float)
    if p.shape == (3,):
        one = _geodetic_from_ecef1(*p.tolist())
        if one is not None:
            return np.asarray(one[0]), np.asarray(one[1]), np.asarray(one[2])
    lat, lon, alt = pymap3d.ecef2geodetic(p[..., 0], p[..., 1], p[..., 2], ell=_ELL, deg=True)
    return np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float)


@functools.lru_cache(maxsize=64)
def _origin_ecef_m(origin: GeodeticOrigin) -> np.ndarray:
    """The origin's ECEF position (cached per origin: conversions are called per telemetry sample)."""
    out = ecef_from_geodetic(origin.lat_deg, origin.lon_deg, origin.alt_m)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=64)
def _R_ned_from_ecef(origin: GeodeticOrigin) -> np.ndarray:
    lat, lon = math.radians(origin.lat_deg), math.radians(origin.lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    R = np.array(
        [
            [-sl * co, -sl * so, cl],
            [-so, co, 0.0],
            [-cl * co, -cl * so, -sl],
        ]
    )
    R.setflags(write=False)
    return R


def ned_from_geodetic(lat_deg, lon_deg, alt_m, origin: GeodeticOrigin) -> np.ndarray:
    """WGS84 geodetic -> local NED metres about ``origin``, shape (..., 3)."""
    d_ecef = ecef_from_geodetic(lat_deg, lon_deg, alt_m) - _origin_ecef_m(origin)
    return d_ecef @ _R_ned_from_ecef(origin).T


def geodetic_from_ned(p_ned_m, origin: GeodeticOrigin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local NED metres (..., 3) about ``origin`` -> WGS84 (lat_deg, lon_deg, alt_m)."""
    p = np.asarray(p_ned_m, dtype=float)
    p_ecef = _origin_ecef_m(origin) + p @ _R_ned_from_ecef(origin)
    return geodetic_from_ecef(p_ecef)


@functools.lru_cache(maxsize=64)
def _ned_frame_floats(origin: GeodeticOrigin) -> tuple[float, ...]:
    """The origin's ECEF position and ``R_ned_from_ecef`` (row-major) as 12 floats."""
    return (*_origin_ecef_m(origin).tolist(), *_R_ned_from_ecef(origin).ravel().tolist())


def geodetic_from_ned1(n_m: float, e_m: float, d_m: float, origin: GeodeticOrigin) -> tuple[float, float, float]:
    """:func:`geodetic_from_ned` of one point, in plain floats: ``p_ecef = p0_ecef + R_ned_from_ecef^T p_ned``,
    then :func:`geodetic_from_ecef`'s closed form (pymap3d itself near the polar axis).  The recorder and
    the live view convert one camera position per frame, where numpy's per-call overhead on three numbers
    cost more than the arithmetic."""
    x0, y0, z0, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _ned_frame_floats(origin)
    x = x0 + (r00 * n_m + r10 * e_m + r20 * d_m)
    y = y0 + (r01 * n_m + r11 * e_m + r21 * d_m)
    z = z0 + (r02 * n_m + r12 * e_m + r22 * d_m)
    one = _geodetic_from_ecef1(x, y, z)
    if one is not None:
        return one
    lat, lon, alt = geodetic_from_ecef(np.array([x, y, z]))
    return float(lat), float(lon), float(alt)


def _q_ned_from_level_halves(lat_deg, lon_deg, origin: GeodeticOrigin):
    """The three half-angles of ``q_ned_from_level``: ``R_ned_from_ecef(origin) R_ned_from_ecef(lat, lon)^T``
    with ``R_ecef_from_ned(lat, lon) = Rz(lon) Ry(-lat - pi/2)``, so ``Ry(lat0 + pi/2) Rz(lon - lon0) Ry(-lat - pi/2)``."""
    a = 0.5 * (math.radians(origin.lat_deg) + 0.5 * math.pi)
    return (
        a,
        0.5 * np.radians(np.asarray(lon_deg, dtype=float) - origin.lon_deg),
        -0.5 * (np.radians(np.asarray(lat_deg, dtype=float)) + 0.5 * math.pi),
    )


def q_ned_from_level(lat_deg, lon_deg, origin: GeodeticOrigin) -> np.ndarray:
    """``q_ned_from_level`` (..., 4): the rotation from the local level at WGS84 ``(lat_deg, lon_deg)`` (the
    NED axes there, module docstring) to the local NED of ``origin``; the identity at the origin.  Exact: the
    product of the two tangent frames' ECEF rotations, ``Ry(lat0 + pi/2) Rz(lon - lon0) Ry(-lat - pi/2)``."""
    a, b, c = _q_ned_from_level_halves(lat_deg, lon_deg, origin)
    ca, sa = math.cos(a), math.sin(a)
    cb, sb, cc, sc = np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    # qy(a) (x) qz(b) (x) qy(c), with qy(t) = (cos t, 0, sin t, 0) and qz(t) = (cos t, 0, 0, sin t)
    w = ca * cb * cc - sa * cb * sc
    x = sa * sb * cc - ca * sb * sc
    y = ca * cb * sc + sa * cb * cc
    z = sa * sb * sc + ca * sb * cc
    return np.stack([w, x, y, z], axis=-1)


def q_ned_from_level1(lat_deg: float, lon_deg: float, origin: GeodeticOrigin) -> Quat:
    """:func:`q_ned_from_level` of one position in plain floats (the pose buffer turns one per telemetry sample,
    where numpy's per-call overhead cost ten times the arithmetic)."""
    a = 0.5 * (math.radians(origin.lat_deg) + 0.5 * math.pi)
    b = 0.5 * math.radians(lon_deg - origin.lon_deg)
    c = -0.5 * (math.radians(lat_deg) + 0.5 * math.pi)
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    return (
        ca * cb * cc - sa * cb * sc,
        sa * sb * cc - ca * sb * sc,
        ca * cb * sc + sa * cb * cc,
        sa * sb * sc + ca * sb * cc,
    )


# --------------------------------------------------------------------------- quaternions


# Single quaternions (shape (4,)) take scalar paths below: the daemon converts one pose per telemetry
# sample and per frame, where numpy's per-call overhead on 4 numbers cost more than the arithmetic
# (moveaxis, stack and reductions were ~30 % of the pipeline thread).  Same formulas, same order of
# operations as the vectorised paths (tests/onboard/test_frames_scalar.py compares them).  The kernels
# of those paths work on Python floats (the ``*1`` functions: one quaternion in, a tuple out); the pose
# buffer calls them directly, without the array round trip.

Quat = tuple[float, float, float, float]


def quat_normalize1(q) -> Quat:
    """:func:`quat_normalize` of one quaternion given as 4 floats (the same FrameError)."""
    w, x, y, z = q
    n1 = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n1) or n1 < 1e-12:
        raise FrameError("quaternion is zero or not finite")
    sgn = -1.0 if w / n1 < 0.0 else 1.0
    return (sgn * (w / n1), sgn * (x / n1), sgn * (y / n1), sgn * (z / n1))


def quat_multiply1(a, b) -> Quat:
    """:func:`quat_multiply` of two quaternions given as 4 floats each."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    )


def quat_conjugate1(q) -> Quat:
    """:func:`quat_conjugate` of one quaternion (its product with (1, -1, -1, -1) is exact negation)."""
    return (q[0], -q[1], -q[2], -q[3])


def quat_from_rotvec1(a: float, b: float, c: float) -> Quat:
    """:func:`quat_from_rotvec` of one rotation vector given as 3 floats."""
    angle1 = math.sqrt(a * a + b * b + c * c)
    k1 = math.sin(0.5 * angle1) / angle1 if angle1 > 1e-8 else 0.5 - angle1**2 / 48.0
    return (math.cos(0.5 * angle1), k1 * a, k1 * b, k1 * c)


def rotvec_from_quat1(q) -> tuple[float, float, float]:
    """:func:`rotvec_from_quat` of one quaternion given as 4 floats: the norm sums the squares in order, as
    numpy's does; the angle is numpy's ``arctan2`` (its own kernel, not libm's ``atan2``)."""
    w, x, y, z = quat_normalize1(q)
    s = math.sqrt(x * x + y * y + z * z)
    angle = 2.0 * float(np.arctan2(s, min(max(w, -1.0), 1.0)))
    k = angle / s if s > 1e-12 else 2.0
    return k * x, k * y, k * z


def quat_slerp1(q0, q1, alpha: float) -> Quat:
    """:func:`quat_slerp` of two quaternions given as 4 floats each and a scalar ``alpha``."""
    l0, l1 = quat_normalize1(q0), quat_normalize1(q1)
    d1 = l0[0] * l1[0] + l0[1] * l1[1] + l0[2] * l1[2] + l0[3] * l1[3]
    if d1 < 0.0:
        l1, d1 = (-l1[0], -l1[1], -l1[2], -l1[3]), -d1
    th = math.acos(min(max(d1, -1.0), 1.0))
    st = math.sin(th)
    w0s, w1s = (1.0 - alpha, alpha) if st < 1e-9 else (math.sin((1.0 - alpha) * th) / st, math.sin(alpha * th) / st)
    return quat_normalize1([w0s * c0 + w1s * c1 for c0, c1 in zip(l0, l1)])


def quat_normalize(q) -> np.ndarray:
    """Unit quaternion(s) (..., 4), sign fixed so that w >= 0.  Zero or non-finite -> FrameError."""
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):
        return np.array(quat_normalize1(q.tolist()))
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(n < 1e-12):
        raise FrameError("quaternion is zero or not finite")
    q = q / n
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_multiply(q1, q2) -> np.ndarray:
    """Hamilton product q1 (x) q2, (w, x, y, z), broadcast over leading axes."""
    q1 = np.asarray(q1, dtype=float)
    q2 = np.asarray(q2, dtype=float)
    if q1.shape == (4,) and q2.shape == (4,):
        return np.array(quat_multiply1(q1.tolist(), q2.tolist()))
    w1, x1, y1, z1 = np.moveaxis(q1, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(q2, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_conjugate(q) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion): q_b_from_a from q_a_from_b."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def rotmat_from_quat(q) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of unit quaternion(s) (..., 4): ``R(q_a_from_b) = R_a_from_b``."""
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):
        w, x, y, z = q.tolist()
        xx, yy, zz = x * x, y * y, z * z
        xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
        return np.array(
            [
                [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
                [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
                [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
            ]
        )
    w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    R = np.stack(
        [
            1 - 2 * (yy + zz),
            2 * (xy - wz),
            2 * (xz + wy),
            2 * (xy + wz),
            1 - 2 * (xx + zz),
            2 * (yz - wx),
            2 * (xz - wy),
            2 * (yz + wx),
            1 - 2 * (xx + yy),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def quat_rotate(q, v) -> np.ndarray:
    """Rotate vector(s) v (..., 3) by q: ``v_a = q_a_from_b * v_b``."""
    R = rotmat_from_quat(q)
    return np.einsum("...ij,...j->...i", R, np.asarray(v, dtype=float))


def quat_from_rotmat(R) -> np.ndarray:
    """Unit quaternion (..., 4), w >= 0, of rotation matrix/matrices (..., 3, 3) (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for k, m in enumerate(flat):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        i = int(np.argmax([tr, m[0, 0], m[1, 1], m[2, 2]]))
        if i == 0:
            s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif i == 1:
            s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif i == 2:
            s = 2.0 * math.sqrt(max(1.0 + m[1, 1] - m[0, 0] - m[2, 2], 0.0))
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * math.sqrt(max(1.0 + m[2, 2] - m[0, 0] - m[1, 1], 0.0))
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        out[k] = q
    return quat_normalize(out).reshape(R.shape[:-2] + (4,))


def quat_from_euler(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """``q_ned_from_body`` from aerospace Z-Y-X Euler angles (yaw, pitch, roll), radians."""
    cr, sr = np.cos(np.asarray(roll_rad) / 2), np.sin(np.asarray(roll_rad) / 2)
    cp, sp = np.cos(np.asarray(pitch_rad) / 2), np.sin(np.asarray(pitch_rad) / 2)
    cy, sy = np.cos(np.asarray(yaw_rad) / 2), np.sin(np.asarray(yaw_rad) / 2)
    q = np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )
    return quat_normalize(q)


def euler_from_quat(q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(roll_rad, pitch_rad, yaw_rad), aerospace Z-Y-X, of ``q_ned_from_body``."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quat_from_rotvec(phi_rad) -> np.ndarray:
    """Exp map: rotation vector (..., 3) in radians -> unit quaternion (..., 4)."""
    phi = np.asarray(phi_rad, dtype=float)
    if phi.shape == (3,):
        return np.array(quat_from_rotvec1(*phi.tolist()))
    angle = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle with its series near zero
    k = np.where(angle > 1e-8, np.sin(half) / np.where(angle > 1e-8, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), k * phi], axis=-1)


def rotvec_from_quat(q) -> np.ndarray:
    """Log map: unit quaternion (..., 4) -> rotation vector (..., 3), angle in [0, pi]."""
    q = quat_normalize(q)
    w = np.clip(q[..., :1], -1.0, 1.0)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, w)
    k = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0)
    return k * q[..., 1:]


def rotmat_from_rotvec(phi_rad) -> np.ndarray:
    """Exp map to a rotation matrix (..., 3, 3)."""
    return rotmat_from_quat(quat_from_rotvec(phi_rad))


def quat_slerp(q0, q1, alpha) -> np.ndarray:
    """Spherical linear interpolation from q0 (alpha = 0) to q1 (alpha = 1), shortest arc."""
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    if q0.shape == (4,) and q1.shape == (4,) and np.ndim(alpha) == 0:
        return np.array(quat_slerp1(q0.tolist(), q1.tolist(), float(alpha)))
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    alpha = np.asarray(alpha, dtype=float)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    small = sin_t < 1e-9
    safe = np.where(small, 1.0, sin_t)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / safe)
    w1 = np.where(small, alpha, np.sin(alpha * theta) / safe)
    return quat_normalize(w0 * q0 + w1 * q1)


def check_unit_quat(q, what: str, tol: float = QUAT_NORM_TOL) -> np.ndarray:
    """Validate a quaternion from outside (wire, file): finite and |norm - 1| <= tol; returns it normalised."""
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):
        n1 = math.sqrt(sum(c * c for c in q.tolist()))
        if not math.isfinite(n1):
            raise FrameError(f"{what}: quaternion must be 4 finite numbers (w, x, y, z)")
        if abs(n1 - 1.0) > tol:
            raise FrameError(f"{what}: quaternion norm {n1:.6g} is not 1 within {tol}")
        return quat_normalize(q)
    if q.ndim == 0 or q.shape[-1] != 4 or not np.all(np.isfinite(q)):  # a lone number has no last axis
        raise FrameError(f"{what}: quaternion must be 4 finite numbers (w, x, y, z)")
    n = np.linalg.norm(q, axis=-1)
    off = np.abs(n - 1.0)
    if np.any(off > tol):
        worst = float(n.flat[int(np.argmax(off))])  # the norm itself: a zero quaternion reads 0, not 2
        raise FrameError(f"{what}: quaternion norm {worst:.6g} is not 1 within {tol}")
    return quat_normalize(q)


# --------------------------------------------------------------------------- camera pod and camera

#: cam z (forward) -> mount x, cam x (right) -> mount y, cam y (down) -> mount z
R_MOUNT_FROM_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
Q_MOUNT_FROM_CAM = np.array([0.5, 0.5, 0.5, 0.5])


@dataclass(frozen=True)
class CameraMount:
    """Where the camera pod sits on the airframe.

    ``lever_arm_frd_m``: optical centre in body FRD metres.  ``q_body_from_mount``: rotation of the
    pod's mount frame (x optical axis, y right, z down) into body FRD.  Identity means the camera
    looks straight ahead; a mount pitched down by ``p`` rad is ``quat_from_euler(0, -p, 0)``.
    """

    lever_arm_frd_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    q_body_from_mount: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    gimballed: bool = False

    def __post_init__(self) -> None:
        arm = np.asarray(self.lever_arm_frd_m, dtype=float)
        if arm.shape != (3,) or not np.all(np.isfinite(arm)):
            raise FrameError(f"CameraMount.lever_arm_frd_m must be 3 finite metres, got {self.lever_arm_frd_m!r}")
        check_unit_quat(self.q_body_from_mount, "CameraMount.q_body_from_mount")

    @classmethod
    def from_euler_deg(cls, lever_arm_frd_m, roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0, gimballed=False) -> CameraMount:
        q = quat_from_euler(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
        lx, ly, lz = (float(a) for a in lever_arm_frd_m)
        qw, qx, qy, qz = (float(c) for c in q)
        return cls((lx, ly, lz), (qw, qx, qy, qz), gimballed)

    def q_body_from_cam(self, q_mount_from_gimbal=None) -> np.ndarray:
        """Camera attitude on the airframe, optionally through a gimbal (..., 4)."""
        q = np.asarray(self.q_body_from_mount, dtype=float)
        if q_mount_from_gimbal is not None:
            q = quat_multiply(q, q_mount_from_gimbal)
        return quat_multiply(q, Q_MOUNT_FROM_CAM)


def camera_pose_ned(p_body_ned_m, q_ned_from_body, mount: CameraMount, q_mount_from_gimbal=None):
    """Camera centre and attitude in local NED from the vehicle's pose and the pod mount.

    ``p_cam_ned_m = p_body_ned_m + R_ned_from_body @ lever_arm_frd_m`` and
    ``q_ned_from_cam = q_ned_from_body (x) q_body_from_mount [(x) q_mount_from_gimbal] (x) q_mount_from_cam``.
    Vectorised over a leading axis.  Returns ``(p_cam_ned_m, q_ned_from_cam)``.
    """
    q_nb = np.asarray(q_ned_from_body, dtype=float)
    p_cam = np.asarray(p_body_ned_m, dtype=float) + quat_rotate(q_nb, np.asarray(mount.lever_arm_frd_m, dtype=float))
    q_nc = quat_normalize(quat_multiply(q_nb, mount.q_body_from_cam(q_mount_from_gimbal)))
    return p_cam, q_nc


#: a pixel's undistortion is trusted when re-distorting it lands this close (well under a centroid's error)
UNDISTORT_TOLERANCE_PX = 0.01
#: points checked along each ray from the principal point to the image's edge
RAY_STEPS = 64
#: Newton's undistortion stops when the model's residual is this small (normalised units: ~1e-10 px)
NEWTON_DONE = 1e-13


def far_off_image(coord_px: float, size_px: float) -> bool:
    """Whether a pixel coordinate lies more than one image ``size_px`` (its width for u, height for v) outside the
    image: no camera sees there, so it is a corrupt measurement (the estimators and the CSV readers refuse it)."""
    return not -size_px <= coord_px <= 2.0 * size_px


@dataclass(frozen=True)
class PinholeIntrinsics:
    """Pinhole camera with optional radial-tangential distortion (OpenCV order k1, k2, p1, p2, k3)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int
    distortion: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        for name in ("fx_px", "fy_px", "cx_px", "cy_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise FrameError(f"PinholeIntrinsics.{name} must be a finite number, got {v!r}")
        if self.fx_px <= 0 or self.fy_px <= 0:
            raise FrameError(f"PinholeIntrinsics focal lengths must be > 0, got fx={self.fx_px}, fy={self.fy_px}")
        if int(self.width_px) <= 0 or int(self.height_px) <= 0:
            raise FrameError(f"PinholeIntrinsics size must be positive, got {self.width_px} x {self.height_px}")
        if len(self.distortion) != 5 or not all(math.isfinite(float(k)) for k in self.distortion):
            raise FrameError(
                f"PinholeIntrinsics.distortion must be 5 finite numbers (k1 k2 p1 p2 k3), got {self.distortion!r}"
            )

    @classmethod
    def vue_pro_640(cls) -> PinholeIntrinsics:
        """FLIR Vue Pro 640: 13 mm, 17 um pitch, 640 x 512, principal point at the centre."""
        f = VUE_PRO_640_FOCAL_M / VUE_PRO_640_PITCH_M
        return cls(f, f, 320.0, 256.0, 640, 512)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(k != 0.0 for k in self.distortion)

    def distort_normalized(self, xy) -> np.ndarray:
        """Ideal normalised coordinates (..., 2) -> distorted normalised coordinates."""
        xy = np.asarray(xy, dtype=float)
        if not self.has_distortion:
            return xy
        xd, yd, _, _ = self._distorted(xy[..., 0], xy[..., 1])
        return np.stack([xd, yd], axis=-1)

    def _distorted(self, x, y):
        """The model at ideal ``x``, ``y``: distorted ``xd``, ``yd`` and the ``r2``, ``radial`` they were made of
        (which the undistortion's Jacobian reuses)."""
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd, r2, radial

    def undistort_normalized(self, xy_d, iterations: int = 20) -> np.ndarray:
        """Distorted normalised coordinates -> ideal ones, by Newton's method on the model's own Jacobian.

        OpenCV's fixed-point iteration converges only where the model bends little: with a wide thermal lens
        (fx 300 px on 640 x 512, 94 deg across, k1 -0.3, k2 0.05) twenty of its steps leave the corners 6 px
        off.  Newton's steps converge wherever the model does not fold, which :meth:`undistortion_failure`
        checks over the image."""
        xy_d = np.asarray(xy_d, dtype=float)
        if not self.has_distortion:
            return xy_d
        k1, k2, p1, p2, k3 = self.distortion
        xy = xy_d.copy()
        for _ in range(iterations):
            x, y = xy[..., 0], xy[..., 1]
            xd, yd, r2, radial = self._distorted(x, y)
            res = xy_d - np.stack([xd, yd], axis=-1)
            if not np.any(np.abs(res) > NEWTON_DONE):  # NaN goes on to the iteration limit, and stays NaN
                break
            d_radial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
            a = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x  # d xd / dx
            b = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y  # d xd / dy = d yd / dx
            d = radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x  # d yd / dy
            with np.errstate(divide="ignore", invalid="ignore"):
                det = a * d - b * b
                step = np.stack(
                    [(d * res[..., 0] - b * res[..., 1]) / det, (a * res[..., 1] - b * res[..., 0]) / det], -1
                )
            xy = xy + step
        return xy

    def undistortion_failure(self, tolerance_px: float = UNDISTORT_TOLERANCE_PX) -> str | None:
        """Where :meth:`normalized_from_pixel` fails inside the image, in words, or None where it holds.

        A lens model holds when each pixel has one ideal point the undistortion finds: along rays
        from the principal point to the image's corners and edge midpoints, the ideal radius grows with the
        pixel's (no fold), and re-distorting the ideal point of each pixel on those rays and on the image's border
        lands within ``tolerance_px`` of the pixel.  Strong
        or mistyped coefficients (a sign or decimal slip) fail one of the two and would turn every pixel near
        the edges into a confidently wrong bearing."""
        if not self.has_distortion:
            return None
        t = np.linspace(1.0 / RAY_STEPS, 1.0, RAY_STEPS)[:, None]
        w, h = float(self.width_px), float(self.height_px)
        centre = np.array([self.cx_px, self.cy_px])
        # every pixel of the border too: a tangential term breaks the rays' symmetry, and a strong model can fail
        # on a few pixels beside a corner that the ray through the corner does not cross
        us, vs = np.arange(0.0, w + 1.0), np.arange(0.0, h + 1.0)
        border = np.concatenate(
            [np.stack([us, np.zeros_like(us)], -1), np.stack([us, np.full_like(us, h)], -1)]
            + [np.stack([np.zeros_like(vs), vs], -1), np.stack([np.full_like(vs, w), vs], -1)]
        )
        err, _ = self._round_trip_px(border)
        if (err > tolerance_px).any():
            i = int(np.argmax(err > tolerance_px))
            return f"pixel ({border[i, 0]:.0f}, {border[i, 1]:.0f}) does not undistort (off by {err[i]:.3g} px)"
        ends = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h), (w / 2, 0.0), (w, h / 2), (w / 2, h), (0.0, h / 2)]
        for end in ends:
            d = np.asarray(end) - centre
            if not d.any():
                continue
            uv = centre + t * d
            err, xy = self._round_trip_px(uv)
            r = np.hypot(xy[:, 0], xy[:, 1])
            where = f"towards pixel ({end[0]:g}, {end[1]:g})"
            bad = err > tolerance_px
            if bad.any():
                i = int(np.argmax(bad))
                return f"pixel ({uv[i, 0]:.0f}, {uv[i, 1]:.0f}) does not undistort (off by {err[i]:.3g} px)"
            if not np.all(np.diff(r) > 0.0):
                i = int(np.argmax(np.diff(r) <= 0.0)) + 1
                return f"the model folds {where}: pixel ({uv[i, 0]:.0f}, {uv[i, 1]:.0f}) maps back towards the centre"
        return None

    def _round_trip_px(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How far (px) each of the pixels ``uv`` (n, 2) lands from itself once undistorted and distorted again
        (inf where either diverges), and the ideal points (n, 2) the undistortion found."""
        with np.errstate(over="ignore", invalid="ignore"):  # a diverging model is what the caller looks for
            xy = self.normalized_from_pixel(uv)
            back = self.distort_normalized(xy)
            back_px = np.stack([self.fx_px * back[:, 0] + self.cx_px, self.fy_px * back[:, 1] + self.cy_px], axis=-1)
            err = np.hypot(*(back_px - uv).T)
        return np.where(np.isfinite(err), err, np.inf), xy

    def project(self, p_cam_m) -> np.ndarray:
        """Camera-frame points (..., 3) -> pixels (..., 2).  Points with z <= 0 give NaN."""
        p = np.asarray(p_cam_m, dtype=float)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.where((z > 0)[..., None], p[..., :2] / z[..., None], np.nan)
        xy = self.distort_normalized(xy)
        return np.stack([self.fx_px * xy[..., 0] + self.cx_px, self.fy_px * xy[..., 1] + self.cy_px], axis=-1)

    def normalized_from_pixel(self, uv_px) -> np.ndarray:
        """Pixels (..., 2) -> ideal normalised coordinates (x/z, y/z)."""
        uv = np.asarray(uv_px, dtype=float)
        xy_d = np.stack([(uv[..., 0] - self.cx_px) / self.fx_px, (uv[..., 1] - self.cy_px) / self.fy_px], axis=-1)
        return self.undistort_normalized(xy_d)

    def bearing_cam_from_pixel(self, uv_px) -> np.ndarray:
        """Pixels (..., 2) -> unit bearing vectors in the camera frame (..., 3)."""
        xy = self.normalized_from_pixel(uv_px)
        b = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return b / np.linalg.norm(b, axis=-1, keepdims=True)

    def bearing_cam_from_uv(self, u_px: float, v_px: float) -> tuple[float, float, float]:
        """One pixel -> its unit bearing in the camera frame: :meth:`bearing_cam_from_pixel`'s, bit for bit, in
        floats for a camera without distortion (the daemon asks it every frame, where numpy's per-call overhead
        on one pixel was most of its cost)."""
        if self.has_distortion:
            b = self.bearing_cam_from_pixel((u_px, v_px))
            return (float(b[0]), float(b[1]), float(b[2]))
        x, y = (u_px - self.cx_px) / self.fx_px, (v_px - self.cy_px) / self.fy_px
        n = math.sqrt(x * x + y * y + 1.0)
        return (x / n, y / n, 1.0 / n)
