"""What the camera component says about itself, pure: the sensor (CAMERA_INFORMATION) and its video stream.

:class:`~onboard.io.camera_protocol.CameraProtocol` sends these when a ground station asks (its module docstring
has the commands); here are the values it is built from, checked when they are made, and the fields:

* CAMERA_INFORMATION: vendor/model, ``firmware_version``, focal length (mm) = ``fx_px x pixel
  pitch``, sensor size (mm) = resolution x pixel pitch, resolution (px), flags HAS_VIDEO_STREAM (when
  a stream is configured) | HAS_TRACKING_POINT | HAS_TRACKING_RECTANGLE | HAS_TRACKING_GEO_STATUS,
  ``camera_device_id`` 0 (we are the camera component), ``gimbal_device_id`` the gimbal the camera is
  on (:attr:`~onboard.io.camera_protocol.CameraProtocol.gimbal_device_id`: the gimbal device's component id, or 1-6 for one its
  manager speaks for; 0 for a fixed mount or while the gimbal is not yet known).
* VIDEO_STREAM_INFORMATION / STATUS: stream 1 of 1, type by ``video.transport``
  (:func:`video_stream_type`: ``rtp`` -> RTPUDP 1, ``mpegts`` -> MPEG_TS 3; common.xml, "URI gives
  the port number" for both), ``uri`` the UDP port the ground station listens on (QGC's VideoManager
  opens ``udp://0.0.0.0:<uri>`` as RTP H.264 for RTPUDP, ``mpegts://0.0.0.0:<uri>`` for MPEG_TS),
  flags RUNNING (not THERMAL: :class:`VideoStream`), frame rate, bitrate, resolution, ``hfov`` (deg) = ``2 atan(width / 2 fx)``,
  encoding H264.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from onboard.core.checks import is_positive_number
from onboard.core.errors import InputError

__all__ = ["CameraIdentity", "VideoStream", "video_stream_type", "camera_information"]

# common.xml numbers (a test checks them against pymavlink's dialect; the core does not import it)
CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM = 256
CAMERA_CAP_FLAGS_HAS_TRACKING_POINT = 512
CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE = 1024
CAMERA_CAP_FLAGS_HAS_TRACKING_GEO_STATUS = 2048
VIDEO_STREAM_TYPE_RTPUDP = 1
VIDEO_STREAM_TYPE_MPEG_TS = 3
_STREAM_TYPE_OF_TRANSPORT = {"rtp": VIDEO_STREAM_TYPE_RTPUDP, "mpegts": VIDEO_STREAM_TYPE_MPEG_TS}
VIDEO_STREAM_STATUS_FLAGS_RUNNING = 1
VIDEO_STREAM_STATUS_FLAGS_THERMAL = 2
VIDEO_STREAM_ENCODING_H264 = 1

TRACKING_FLAGS = (
    CAMERA_CAP_FLAGS_HAS_TRACKING_POINT
    | CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE
    | CAMERA_CAP_FLAGS_HAS_TRACKING_GEO_STATUS
)


def _finite_positive(name: str, v) -> float:
    if not is_positive_number(v):
        raise InputError(f"{name} must be a finite number > 0, got {v!r}")
    return float(v)


def int_in(name: str, v, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise InputError(f"{name} must be an integer in {lo}..{hi}, got {v!r}")
    return v


@dataclass(frozen=True)
class CameraIdentity:
    """What CAMERA_INFORMATION says about the sensor.  Lengths in mm, resolution in px.

    ``firmware_version``: uint32 as common.xml lays it out, (dev << 24) | (patch << 16) | (minor << 8) | major;
    0 when unknown (what :meth:`from_intrinsics` sends).
    """

    vendor_name: str
    model_name: str
    firmware_version: int
    focal_length_mm: float
    sensor_size_h_mm: float
    sensor_size_v_mm: float
    resolution_h_px: int
    resolution_v_px: int

    def __post_init__(self) -> None:
        for name in ("vendor_name", "model_name"):
            v = getattr(self, name)
            if not isinstance(v, str) or not v or len(v.encode()) > 32:
                raise InputError(f"CameraIdentity.{name} must be 1..32 bytes of text, got {v!r}")
        int_in("CameraIdentity.firmware_version", self.firmware_version, 0, 2**32 - 1)
        for name in ("focal_length_mm", "sensor_size_h_mm", "sensor_size_v_mm"):
            object.__setattr__(self, name, _finite_positive(f"CameraIdentity.{name}", getattr(self, name)))
        int_in("CameraIdentity.resolution_h_px", self.resolution_h_px, 1, 65535)
        int_in("CameraIdentity.resolution_v_px", self.resolution_v_px, 1, 65535)

    @classmethod
    def from_intrinsics(
        cls,
        fx_px: float,
        width_px: int,
        height_px: int,
        pixel_pitch_um: float,
        vendor_name: str = "irtrack",
        model_name: str = "IR tracker",
        firmware_version: int = 0,
    ) -> CameraIdentity:
        """Focal length and sensor size from the pinhole model and the detector's pixel pitch."""
        pitch_mm = _finite_positive("pixel_pitch_um", pixel_pitch_um) / 1000.0
        return cls(
            vendor_name,
            model_name,
            firmware_version,
            float(fx_px) * pitch_mm,
            width_px * pitch_mm,
            height_px * pitch_mm,
            int(width_px),
            int(height_px),
        )


def video_stream_type(transport: str) -> int:
    """VIDEO_STREAM_TYPE of a ``video.transport``: ``rtp`` -> RTPUDP (1), ``mpegts`` -> MPEG_TS (3)."""
    try:
        return _STREAM_TYPE_OF_TRANSPORT[transport]
    except (KeyError, TypeError):
        raise InputError(
            f"video.transport: expected one of {', '.join(_STREAM_TYPE_OF_TRANSPORT)}, got {transport!r}"
        ) from None


@dataclass(frozen=True)
class VideoStream:
    """The one video stream we advertise (VIDEO_STREAM_INFORMATION).

    ``stream_type``: VIDEO_STREAM_TYPE (RTPUDP 1, MPEG_TS 3); ``uri``: what the ground station opens
    (for UDP types the port number it listens on, e.g. ``"5600"``); ``hfov_deg`` horizontal field of
    view; ``thermal`` sets VIDEO_STREAM_STATUS_FLAGS_THERMAL.

    ``thermal`` is off by default although the stream is thermal imaging: QGroundControl sets up its main video
    only from a stream without that flag (``VideoManager::autoStreamConfigured``) and leaves a thermal stream out
    of its stream list, to overlay it on a main one; flagged, the camera's only stream would open no video at all.
    """

    stream_type: int
    uri: str
    framerate_hz: float
    bitrate_bps: int
    resolution_h_px: int
    resolution_v_px: int
    hfov_deg: float
    name: str = "IR"
    thermal: bool = False
    encoding: int = VIDEO_STREAM_ENCODING_H264

    def __post_init__(self) -> None:
        if self.stream_type not in (VIDEO_STREAM_TYPE_RTPUDP, VIDEO_STREAM_TYPE_MPEG_TS):
            raise InputError(f"VideoStream.stream_type must be RTPUDP (1) or MPEG_TS (3), got {self.stream_type!r}")
        if not isinstance(self.uri, str) or not self.uri or len(self.uri.encode()) > 160:
            raise InputError(f"VideoStream.uri must be 1..160 bytes of text, got {self.uri!r}")
        object.__setattr__(self, "framerate_hz", _finite_positive("VideoStream.framerate_hz", self.framerate_hz))
        int_in("VideoStream.bitrate_bps", self.bitrate_bps, 0, 2**32 - 1)
        int_in("VideoStream.resolution_h_px", self.resolution_h_px, 1, 65535)
        int_in("VideoStream.resolution_v_px", self.resolution_v_px, 1, 65535)
        hfov = _finite_positive("VideoStream.hfov_deg", self.hfov_deg)
        if hfov >= 360.0:
            raise InputError(f"VideoStream.hfov_deg must be below 360, got {hfov}")
        object.__setattr__(self, "hfov_deg", hfov)

    @property
    def flags(self) -> int:
        return VIDEO_STREAM_STATUS_FLAGS_RUNNING | (VIDEO_STREAM_STATUS_FLAGS_THERMAL if self.thermal else 0)


def camera_information(
    identity: CameraIdentity, time_boot_ms: int, has_video: bool, gimbal_device_id: int = 0
) -> dict[str, Any]:
    """CAMERA_INFORMATION (#259) fields (``gimbal_device_id``: the camera's gimbal, 0 = none)."""
    flags = TRACKING_FLAGS | (CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM if has_video else 0)
    return dict(
        time_boot_ms=int(time_boot_ms) % 2**32,
        vendor_name=_pad(identity.vendor_name, 32),
        model_name=_pad(identity.model_name, 32),
        firmware_version=identity.firmware_version,
        focal_length=identity.focal_length_mm,
        sensor_size_h=identity.sensor_size_h_mm,
        sensor_size_v=identity.sensor_size_v_mm,
        resolution_h=identity.resolution_h_px,
        resolution_v=identity.resolution_v_px,
        lens_id=0,
        flags=flags,
        cam_definition_version=0,
        cam_definition_uri=b"",
        gimbal_device_id=int_in("gimbal_device_id", gimbal_device_id, 0, 255),
        camera_device_id=0,
    )


def _pad(text: str, n: int) -> list[int]:
    """A uint8_t[n] char array (pymavlink packs lists of ints for those fields)."""
    b = text.encode()[:n]
    return list(b) + [0] * (n - len(b))
