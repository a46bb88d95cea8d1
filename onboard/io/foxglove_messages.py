"""The messages irtrack shows in Foxglove: JSON schemas, foxglove.RawImage, LocationFix and ImageAnnotations.

One module for the two places that write them, so that a recording (:mod:`onboard.io.record`, MCAP) and
the live view (:mod:`onboard.io.live_view`, Foxglove WebSocket) carry the same schemas and the same
numbers:

* :data:`JSON_SCHEMAS`: the JSON Schema of each irtrack JSON channel, by schema name
  (``irtrack.mavlink_raw/1``, ``irtrack.frame_input/1``, ``irtrack.track/2``, ``irtrack.status/1``,
  ``irtrack.objects/1``, ``irtrack.truth_objects/1``, ``irtrack.imaging_pose/1``; the recorder's module docstring
  says what each message holds).  The track's and the status's are made from the key tables beside their
  builders (:data:`onboard.core.track.TRACK_JSON_KEYS`, :data:`onboard.core.status.STATUS_JSON_KEYS`);
  ``irtrack.truth/1`` is the simulator's (:func:`groundsim.world.truth.truth_json_schema`, handed to the recorder
  by ``groundsim run``).  Every key a message has is declared, and every key it always has is required.
* ``foxglove.RawImage`` of an :class:`~onboard.core.irframe.IrFrame`: :func:`rawimage_fields` (a dict of
  the message's fields), :func:`rawimage_pieces` / :func:`rawimage_bytes` (the serialized protobuf, the
  pixels not copied), :func:`irframe_from_rawimage` (back).  ``timestamp`` = capture time on the
  vehicle's boot clock, ``frame_id`` ``ir_camera``, ``encoding`` ``mono8`` or ``mono16``
  (little-endian), ``step`` = width x bytes per pixel.
* ``foxglove.LocationFix``: :func:`location_fix_fields` (a WGS84 position with its NED covariance
  turned into the ENU covariance LocationFix wants), :func:`camera_fix_fields` (a pose's camera centre).
* ``foxglove.ImageAnnotations``: :func:`objects_annotations` (every object of an ``irtrack.objects/1``
  message: a box and its id, the primary target highlighted) and :func:`truth_objects_annotations` (the
  simulator's labels), drawn by Foxglove's Image panel over the frame of the same ``timestamp``.
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
from onboard.core.status import status_json_schema
from onboard.core.track import track_json_schema
from onboard.estimation.guidance import guidance_json_schema

__all__ = [
    "MAVLINK_RAW_SCHEMA",
    "FRAME_INPUT_SCHEMA",
    "TRUTH_SCHEMA",
    "OBJECTS_SCHEMA",
    "TRUTH_OBJECTS_SCHEMA",
    "IMAGING_POSE_SCHEMA",
    "JSON_SCHEMAS",
    "CAMERA_FRAME_ID",
    "stamp_from_us",
    "rawimage_fields",
    "rawimage_pieces",
    "rawimage_bytes",
    "irframe_from_rawimage",
    "location_fix_fields",
    "camera_fix_fields",
    "MIN_DRAWN_BOX_PX",
    "ANNOTATION_STYLES",
    "drawn_box",
    "objects_annotations",
    "truth_objects_annotations",
    "file_descriptor_set",
]

MAVLINK_RAW_SCHEMA = "irtrack.mavlink_raw/1"
FRAME_INPUT_SCHEMA = "irtrack.frame_input/1"
TRUTH_SCHEMA = "irtrack.truth/1"
IMAGING_POSE_SCHEMA = "irtrack.imaging_pose/1"
OBJECTS_SCHEMA = "irtrack.objects/1"  # the zenoh key irtrack/<v>/objects (onboard.io.zenoh_session, the same name)
TRUTH_OBJECTS_SCHEMA = "irtrack.truth_objects/1"
CAMERA_FRAME_ID = "ir_camera"
US_PER_S = 1_000_000
NS_PER_US = 1_000


# --------------------------------------------------------------------------- JSON schemas

_NUM_OR_NULL = {"type": ["number", "null"]}
_VEC3 = {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_BOX = {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4, "description": "x, y, w, h px"}
_FRAME_STAMP = {"seq": {"type": "integer"}, "time_boot_us": {"type": "integer"}}  # which frame, when (boot clock)


_QUAT = {"type": "array", "items": {"type": ["number", "null"]}, "minItems": 4, "maxItems": 4}
_INT_OR_NULL = {"type": ["integer", "null"]}
_VEC3_NULLS = {**_VEC3, "items": {"type": ["number", "null"]}}  # a non-finite component written as null
#: a pose as :func:`onboard.io.pose_json.pose_to_json` writes it (null where it was not looked up or not known)
_POSE = {
    "type": ["object", "null"],
    "properties": {
        "time_boot_us": {"type": "integer"},
        "p_ned_m": _VEC3_NULLS,
        "v_ned_mps": _VEC3_NULLS,
        "q_ned_from_body": _QUAT,
        "p_cam_ned_m": _VEC3_NULLS,
        "q_ned_from_cam": _QUAT,
        "q_mount_from_gimbal": {**_QUAT, "type": ["array", "null"]},
        "origin": {
            "type": "object",
            "properties": {"lat_deg": {"type": "number"}, "lon_deg": {"type": "number"}, "alt_m": {"type": "number"}},
            "required": ["lat_deg", "lon_deg", "alt_m"],
        },
        "att_span_us": {"type": "integer"},
        "pos_span_us": {"type": "integer"},
        "gimbal_span_us": _INT_OR_NULL,
        "epoch": {"type": "integer"},
        "discontinuities": {"type": "integer"},
        "att_extrapolated_us": {"type": "integer"},
        "pos_extrapolated_us": {"type": "integer"},
        "gimbal_extrapolated_us": _INT_OR_NULL,
        "sigma_extrapolation_rad": {"type": "number"},
        "sigma_extrapolation_m": {"type": "number"},
    },
    "required": [
        "time_boot_us",
        "p_ned_m",
        "v_ned_mps",
        "q_ned_from_body",
        "p_cam_ned_m",
        "q_ned_from_cam",
        "q_mount_from_gimbal",
        "origin",
        "att_span_us",
        "pos_span_us",
        "gimbal_span_us",
        "epoch",
        "discontinuities",
        "att_extrapolated_us",
        "pos_extrapolated_us",
        "gimbal_extrapolated_us",
        "sigma_extrapolation_rad",
        "sigma_extrapolation_m",
    ],
}


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
                "pose": _POSE,
                "zoom": {
                    "type": ["number", "null"],
                    "description": "the frame's IRF1 zoom field (relative to the calibrated zoom; 0: not stated; null: "
                    "not finite); absent before the field",
                },
                "withheld_because": {
                    "type": "array",
                    "items": {"type": "string"},
                    "description": "the codes that withheld the frame's line of sight and 3-D position (empty: "
                    "published); absent before the field",
                },
            },
            ["seq", "time_boot_us", "received_ns", "pose_looked_up", "pose"],
        ),
        track_json_schema(),
        status_json_schema(),
        guidance_json_schema(),
        _object_schema(
            IMAGING_POSE_SCHEMA,
            "The pose the image chain got for a frame before the telemetry wait (image chain objects).",
            {**_FRAME_STAMP, "pose": _POSE},
            ["seq", "time_boot_us", "pose"],
        ),
        _object_schema(
            OBJECTS_SCHEMA,
            "Every confirmed or coasting object of one frame (image chain objects), as published on "
            "irtrack/<vehicle>/objects.",
            {
                "schema": {"type": "string", "const": OBJECTS_SCHEMA},
                "time_boot_us": {"type": "integer"},
                "time_unix_us": {"type": ["integer", "null"], "description": "the frame's UTC, us; null until mapped"},
                "time_unix_sigma_us": {"type": ["integer", "null"], "description": "1-sigma of time_unix_us, us"},
                "compensated_us": {
                    "type": "integer",
                    "description": "the lines of sight are of time_boot_us minus this (the camera's latency), us",
                },
                "frame_index": {"type": "integer", "description": "the image chain's frame count, from 0"},
                "primary_id": {"type": ["integer", "null"], "description": "the selected target's id"},
                "run_id": {
                    "type": "string",
                    "description": "the daemon's run, as the track's (optional: absent when not stated)",
                },
                "objects": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "properties": {
                            "id": {"type": "integer"},
                            "state": {"type": "string", "enum": ["confirmed", "coasting"]},
                            "u_px": {"type": "number", "description": "centre, pixels, 3 decimals"},
                            "v_px": {"type": "number", "description": "centre, pixels, 3 decimals"},
                            "box_px": {**_BOX, "description": "x, y, w, h px, 2 decimals"},
                            "los_ned": {
                                **_VEC3,
                                "description": "unit line of sight, local NED, 7 decimals; null without a pose or "
                                "while the geometry is withheld",
                            },
                            "los_sigma_rad": {"type": ["number", "null"], "description": "its 1-sigma, rad"},
                            "score": {"type": "number", "description": "contrast over the local threshold, 3 decimals"},
                            "primary": {"type": "boolean"},
                        },
                        "required": [
                            "id",
                            "state",
                            "u_px",
                            "v_px",
                            "box_px",
                            "los_ned",
                            "los_sigma_rad",
                            "score",
                            "primary",
                        ],
                    },
                },
            },
            [
                "schema",
                "time_boot_us",
                "time_unix_us",
                "time_unix_sigma_us",
                "compensated_us",
                "frame_index",
                "primary_id",
                "objects",
            ],
        ),
        _object_schema(
            TRUTH_OBJECTS_SCHEMA,
            "The simulator's label of every object of a scene at one rendered frame (groundsim run --record).",
            {
                **_FRAME_STAMP,
                "t_s": {"type": "number"},
                "objects": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "properties": {
                            "id": {"type": "integer", "description": "0 is the target of irtrack.truth/1"},
                            "cls": {"type": "string", "enum": ["target", "bird", "aircraft", "glint"]},
                            "u_px": _NUM_OR_NULL,
                            "v_px": _NUM_OR_NULL,
                            "box_px": {**_BOX, "type": ["array", "null"]},
                            "visibility": {"type": "string", "enum": ["visible", "occluded", "out_of_frame"]},
                            "contrast_netd": {"type": "number"},
                            "warm": {"type": "boolean"},
                            "range_m": {"type": "number"},
                            "p_ned_m": _VEC3,
                        },
                        "required": ["id", "cls", "u_px", "v_px", "box_px", "visibility"],
                    },
                },
            },
            ["seq", "time_boot_us", "objects"],
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


# --------------------------------------------------------------------------- foxglove.ImageAnnotations

#: the least side of a drawn box: a point target's box of 2 x 2 px is drawn as a square of this side about its
#: centre, which frames the object instead of covering it (and stays visible when the image is zoomed out)
MIN_DRAWN_BOX_PX = 8.0
#: (r, g, b, a) and line thickness (px) of each kind of object drawn
ANNOTATION_STYLES: dict[str, tuple[tuple[float, float, float, float], float]] = {
    "primary": ((0.2, 1.0, 0.3, 1.0), 2.0),  # the selected target
    "confirmed": ((0.3, 0.8, 1.0, 1.0), 1.0),
    "coasting": ((1.0, 0.8, 0.1, 1.0), 1.0),
    "truth": ((1.0, 0.3, 1.0, 1.0), 1.0),  # the simulator's labels
}
ANNOTATION_FONT_PX = 10.0


def drawn_box(x: float, y: float, w: float, h: float, min_side_px: float = MIN_DRAWN_BOX_PX) -> tuple[float, ...]:
    """The box (x, y, w, h) as drawn: each side at least ``min_side_px``, about the same centre."""
    cx, cy = x + w / 2, y + h / 2
    w, h = max(w, min_side_px), max(h, min_side_px)
    return cx - w / 2, cy - h / 2, w, h


def _box_annotations(t_us: int, boxes: list[tuple[tuple[float, ...], str, str]], cls: Any = None) -> Any:
    """A foxglove.ImageAnnotations protobuf of ``boxes`` (``(box_px (x, y, w, h), label, style)``, style a key of
    :data:`ANNOTATION_STYLES`): each box a line loop (:func:`drawn_box`), its label above its top-left corner."""
    if cls is None:
        from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations as cls
    msg = cls()
    sec, nsec = stamp_from_us(int(t_us))
    for box, label, style in boxes:
        rgba, thickness = ANNOTATION_STYLES[style]
        x, y, w, h = drawn_box(*box)
        pa = msg.points.add()
        pa.timestamp.seconds, pa.timestamp.nanos = sec, nsec
        pa.type = 2  # LINE_LOOP
        pa.thickness = thickness
        pa.outline_color.r, pa.outline_color.g, pa.outline_color.b, pa.outline_color.a = rgba
        for px, py in ((x, y), (x + w, y), (x + w, y + h), (x, y + h)):
            pt = pa.points.add()
            pt.x, pt.y = float(px), float(py)
        ta = msg.texts.add()
        ta.timestamp.seconds, ta.timestamp.nanos = sec, nsec
        ta.position.x, ta.position.y = float(x), float(y) - 2.0
        ta.text = label
        ta.font_size = ANNOTATION_FONT_PX
        ta.text_color.r, ta.text_color.g, ta.text_color.b, ta.text_color.a = rgba
        ta.background_color.a = 0.0
    return msg


def objects_annotations(message: dict[str, Any], cls: Any = None) -> Any:
    """foxglove.ImageAnnotations (protobuf; ``cls`` the class) of an ``irtrack.objects/1`` message: every
    object's box labelled with its id, the primary target's green and thicker (label ``<id> target``),
    coasting ones amber, the others blue; stamped with the frame's capture time (``time_boot_us``), as its
    foxglove.RawImage is, so the Image panel draws them over that frame."""
    boxes = []
    for o in message.get("objects", ()):
        style = "primary" if o.get("primary") else ("coasting" if o.get("state") == "coasting" else "confirmed")
        label = f"{o['id']} target" if style == "primary" else str(o["id"])
        boxes.append((tuple(o["box_px"]), label, style))
    return _box_annotations(int(message["time_boot_us"]), boxes, cls)


def truth_objects_annotations(message: dict[str, Any], cls: Any = None) -> Any:
    """foxglove.ImageAnnotations of an ``irtrack.truth_objects/1`` message: each drawn object's box (magenta)
    labelled ``<cls> <id>`` (objects not drawn on the frame -- no box -- are left out)."""
    boxes = [
        (tuple(o["box_px"]), f"{o['cls']} {o['id']}", "truth")
        for o in message.get("objects", ())
        if o.get("box_px") is not None
    ]
    return _box_annotations(int(message["time_boot_us"]), boxes, cls)


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
