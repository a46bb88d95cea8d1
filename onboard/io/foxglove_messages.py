"""The messages irtrack shows in Foxglove: JSON schemas, foxglove.RawImage and foxglove.LocationFix fields.

One module for the two places that write them, so that a recording (:mod:`onboard.io.record`, MCAP) and
the live view (:mod:`onboard.io.live_view`, Foxglove WebSocket) carry the same schemas and the same
numbers:

* :data:`JSON_SCHEMAS`: the JSON Schema of each irtrack JSON channel, by schema name
  (``irtrack.mavlink_raw/1``, ``irtrack.frame_input/1``, ``irtrack.track/2``, ``irtrack.status/1``,
  ``irtrack.truth/1``; the recorder's module docstring says what each message holds).
* ``foxglove.RawImage`` of an :class:`~onboard.core.irframe.IrFrame`: :func:`rawimage_fields` (a dict of
  the message's fields), :func:`rawimage_pieces` / :func:`rawimage_bytes` (the serialized protobuf, the
  pixels not copied), :func:`irframe_from_rawimage` (back).  ``timestamp`` = capture time on the
  vehicle's boot clock, ``frame_id`` ``ir_camera``, ``encoding`` ``mono8`` or ``mono16``
  (little-endian), ``step`` = width x bytes per pixel.
* ``foxglove.LocationFix``: :func:`location_fix_fields` (a WGS84 position with its NED covariance
  turned into the ENU covariance LocationFix wants), :func:`camera_fix_fields` (a pose's camera centre).
* :func:`file_descriptor_set`: a protobuf message class's schema as MCAP stores it.

Field dicts carry ``timestamp`` as ``(sec, nsec)`` (:func:`stamp_from_us`): the recorder sets it on a
protobuf message, the live view on the SDK's ``Timestamp``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from onboard.core.errors import InputError
from onboard.core.frames import geodetic_from_ned1
from onboard.core.irframe import IrFrame
from onboard.core.pose_types import PoseAt
from onboard.core.status import STATUS_SCHEMA
from onboard.core.track import TRACK_SCHEMA, TRACK_STATES

__all__ = [
    "MAVLINK_RAW_SCHEMA",
    "FRAME_INPUT_SCHEMA",
    "TRUTH_SCHEMA",
    "JSON_SCHEMAS",
    "CAMERA_FRAME_ID",
    "stamp_from_us",
    "rawimage_fields",
    "rawimage_pieces",
    "rawimage_bytes",
    "irframe_from_rawimage",
    "location_fix_fields",
    "camera_fix_fields",
    "file_descriptor_set",
]

MAVLINK_RAW_SCHEMA = "irtrack.mavlink_raw/1"
FRAME_INPUT_SCHEMA = "irtrack.frame_input/1"
TRUTH_SCHEMA = "irtrack.truth/1"
CAMERA_FRAME_ID = "ir_camera"
US_PER_S = 1_000_000
NS_PER_US = 1_000


# --------------------------------------------------------------------------- JSON schemas

_NUM_OR_NULL = {"type": ["number", "null"]}
_VEC3 = {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_FRAME_STAMP = {"seq": {"type": "integer"}, "time_boot_us": {"type": "integer"}}  # which frame, when (boot clock)


def _object_schema(title: str, description: str, properties: dict, required: list[str]) -> dict[str, Any]:
    """The JSON Schema of an object (its keys in the order the recordings have always stored them)."""
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": properties,
        "required": required,
    }


JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    schema["title"]: schema
    for schema in (
        _object_schema(
            MAVLINK_RAW_SCHEMA,
            "Raw MAVLink bytes as read from one link: a UDP datagram or a serial/TCP read, unparsed.",
            {
                "link": {"type": "string", "description": "which link: autopilot | gcs | vehicle (simulator)"},
                "direction": {"type": "string", "enum": ["rx", "tx"]},
                "receive_time_ns": {"type": "integer", "description": "monotonic clock of the recording process, ns"},
                "source": {"type": ["string", "null"], "description": "peer address host:port, when known"},
                "data": {"type": "string", "contentEncoding": "base64", "description": "the bytes"},
            },
            ["link", "direction", "receive_time_ns", "data"],
        ),
        _object_schema(
            FRAME_INPUT_SCHEMA,
            "A frame the pipeline took from its queue, with the pose interpolated at its capture time.",
            {
                **_FRAME_STAMP,
                "received_ns": {"type": "integer"},
                "pose_looked_up": {"type": "boolean"},
                "pose": {
                    "type": ["object", "null"],
                    "properties": {
                        "time_boot_us": {"type": "integer"},
                        "p_ned_m": _VEC3,
                        "v_ned_mps": _VEC3,
                        "q_ned_from_body": {"type": "array", "items": {"type": "number"}},
                        "p_cam_ned_m": _VEC3,
                        "q_ned_from_cam": {"type": "array", "items": {"type": "number"}},
                        "q_mount_from_gimbal": {"type": ["array", "null"], "items": {"type": "number"}},
                        "origin": {"type": "object"},
                        "epoch": {"type": "integer"},
                    },
                },
            },
            ["seq", "time_boot_us", "received_ns", "pose_looked_up", "pose"],
        ),
        _object_schema(
            TRACK_SCHEMA,
            "One processed frame's track and 3-D estimate (full table in onboard/core/track.py).",
            {
                "schema": {"type": "string"},
                "vehicle": {"type": "string"},
                **_FRAME_STAMP,
                "track_id": {"type": ["integer", "null"]},
                "state": {"type": "string", "enum": list(TRACK_STATES)},
                "measurement_valid": {"type": "boolean"},
                "u_px": _NUM_OR_NULL,
                "v_px": _NUM_OR_NULL,
                "bbox": {"type": ["array", "null"], "items": {"type": "number"}},
                "pose_valid": {"type": "boolean"},
                "lat_deg": _NUM_OR_NULL,
                "lon_deg": _NUM_OR_NULL,
                "alt_m": _NUM_OR_NULL,
                "ned_m": _VEC3,
                "vel_ned_mps": _VEC3,
                "sigma_ned_m": _VEC3,
                "range_m": _NUM_OR_NULL,
                "range_sigma_ratio": _NUM_OR_NULL,
                "observable": {"type": "boolean"},
                "window_frames": {"type": "integer"},
                "model": {"type": ["string", "null"]},
            },
            ["schema", "vehicle", "seq", "time_boot_us", "state"],
        ),
        _object_schema(
            STATUS_SCHEMA,
            "The daemon's status (frames in/processed/dropped/rejected, latencies, link, warnings, record).",
            {"schema": {"type": "string"}, "vehicle": {"type": "string"}, "uptime_s": {"type": "number"}},
            ["schema"],
        ),
        _object_schema(
            TRUTH_SCHEMA,
            "The simulator's exact state at one rendered frame (groundsim run --record).",
            {
                **_FRAME_STAMP,
                "t_s": {"type": "number"},
                "target_ned_m": _VEC3,
                "target_vel_ned_mps": _VEC3,
                "camera_ned_m": _VEC3,
                "target_lat_deg": {"type": "number"},
                "target_lon_deg": {"type": "number"},
                "target_alt_m": {"type": "number"},
                "origin": {"type": "object"},
            },
            ["seq", "time_boot_us"],
        ),
    )
}


# --------------------------------------------------------------------------- foxglove.RawImage


def stamp_from_us(t_us: int) -> tuple[int, int]:
    """``(sec, nsec)`` of a time in microseconds (a Foxglove ``Timestamp``)."""
    return t_us // US_PER_S, (t_us % US_PER_S) * NS_PER_US


def rawimage_fields(frame: IrFrame) -> dict[str, Any]:
    """foxglove.RawImage fields of an :class:`~onboard.core.irframe.IrFrame` (timestamp = capture time, boot clock)."""
    px = frame.pixels
    h, w = px.shape
    mono16 = px.dtype == np.uint16
    return {
        "timestamp": stamp_from_us(int(frame.time_boot_us)),
        "frame_id": CAMERA_FRAME_ID,
        "width": int(w),
        "height": int(h),
        "encoding": "mono16" if mono16 else "mono8",
        "step": int(w * (2 if mono16 else 1)),
        "data": np.ascontiguousarray(px, dtype="<u2" if mono16 else np.uint8).tobytes(),
    }


_RAWIMAGE_DATA_TAG = bytes([(6 << 3) | 2])  # foxglove.RawImage field 6 (data), wire type 2 (length-delimited)


def _varint(n: int) -> bytes:
    """``n`` >= 0 as a protobuf base-128 varint."""
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def rawimage_pieces(frame: IrFrame, header_cls: Any = None) -> tuple[bytes, memoryview]:
    """The serialized foxglove.RawImage of an :class:`~onboard.core.irframe.IrFrame` (:func:`rawimage_fields`) as two
    buffers whose concatenation is the message, the pixels not copied: the protobuf library serializes the small
    fields, the ``data`` field's tag and length are appended by hand (first buffer), the pixel buffer itself is the
    second (a memoryview of the frame's array) -- a protobuf parser merges the concatenation into the same
    message (field order is free on the wire).  ``header_cls``: the RawImage class."""
    if header_cls is None:
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage as header_cls
    px = frame.pixels
    h, w = px.shape
    mono16 = px.dtype == np.uint16
    msg = header_cls(
        frame_id=CAMERA_FRAME_ID,
        width=int(w),
        height=int(h),
        encoding="mono16" if mono16 else "mono8",
        step=int(w * (2 if mono16 else 1)),
    )
    msg.timestamp.seconds, msg.timestamp.nanos = stamp_from_us(int(frame.time_boot_us))
    buf = np.ascontiguousarray(px, dtype="<u2" if mono16 else np.uint8).data.cast("B")
    return msg.SerializeToString() + _RAWIMAGE_DATA_TAG + _varint(buf.nbytes), buf


def rawimage_bytes(frame: IrFrame, header_cls: Any = None) -> bytes:
    """:func:`rawimage_pieces` joined: the serialized foxglove.RawImage of a frame, the pixels copied once."""
    return b"".join(rawimage_pieces(frame, header_cls))


def irframe_from_rawimage(seq: int, img: Any, where: str = "frame") -> IrFrame:
    """The :class:`~onboard.core.irframe.IrFrame` of a decoded foxglove.RawImage protobuf (``seq`` from the MCAP message)."""
    enc = img.encoding
    if enc not in ("mono8", "mono16"):
        raise InputError(f"{where}: encoding: expected mono8 or mono16, got {enc!r}")
    dtype = np.dtype("<u2") if enc == "mono16" else np.dtype(np.uint8)
    if img.step != img.width * dtype.itemsize or len(img.data) != img.step * img.height:
        raise InputError(
            f"{where}: {len(img.data)} bytes do not make {img.width} x {img.height} {enc} (step {img.step})"
        )
    px = np.frombuffer(img.data, dtype=dtype).reshape(img.height, img.width)
    if enc == "mono16":
        px = px.astype(np.uint16)  # native order
    t_us = int(img.timestamp.seconds) * US_PER_S + int(img.timestamp.nanos) // NS_PER_US
    return IrFrame(int(seq), t_us, px)


# --------------------------------------------------------------------------- foxglove.LocationFix

_ENU_FROM_NED = (1, 0, 2)  # ENU axis i is NED axis _ENU_FROM_NED[i] times _ENU_SIGN[i]
_ENU_SIGN = (1.0, 1.0, -1.0)


def location_fix_fields(
    lat_deg: float, lon_deg: float, alt_m: float, t_us: int, frame_id: str, cov_ned_m2: Any = None
) -> dict[str, Any]:
    """foxglove.LocationFix fields of a WGS84 position at ``t_us`` (boot clock); with ``cov_ned_m2`` (3 x 3, NED,
    m^2) its ENU covariance, ``position_covariance_type`` 3 (KNOWN)."""
    out: dict[str, Any] = {
        "timestamp": stamp_from_us(t_us),
        "frame_id": frame_id,
        "latitude": float(lat_deg),
        "longitude": float(lon_deg),
        "altitude": float(alt_m),
    }
    if cov_ned_m2 is not None:
        c = np.asarray(cov_ned_m2, dtype=float).reshape(3, 3).tolist()
        # LocationFix wants ENU, row-major 3x3: P C P^T with P = [[0,1,0],[1,0,0],[0,0,-1]] (swap N/E, flip D -> U),
        # written as the permutation and signs it is (+ 0.0: a zero is +0.0, as the matrix product gives it)
        out["position_covariance"] = [
            _ENU_SIGN[i] * _ENU_SIGN[j] * c[_ENU_FROM_NED[i]][_ENU_FROM_NED[j]] + 0.0
            for i in range(3)
            for j in range(3)
        ]
        out["position_covariance_type"] = 3  # KNOWN
    return out


def camera_fix_fields(pose: PoseAt, t_us: int) -> dict[str, Any]:
    """foxglove.LocationFix fields (frame ``camera``) of the camera centre of a
    :class:`~onboard.core.pose_types.PoseAt` (``p_cam_ned_m`` about ``origin``) at ``t_us``."""
    n, e, d = (float(v) for v in pose.p_cam_ned_m)
    lat, lon, alt = geodetic_from_ned1(n, e, d, pose.origin)
    return location_fix_fields(lat, lon, alt, t_us, "camera")


# --------------------------------------------------------------------------- protobuf schemas


def file_descriptor_set(msg_cls: Any) -> bytes:
    """The FileDescriptorSet of a protobuf message class (its file and every dependency), as MCAP wants."""
    from google.protobuf import descriptor_pb2

    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: Any) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        fds.file.append(proto)

    add(msg_cls.DESCRIPTOR.file)
    return fds.SerializeToString()
