"""The IR frame and its wire format (zenoh key ``irtrack/<vehicle>/ir/frame``), pure.

Wire format, version 1: a 32-byte little-endian header, ``struct '<4sHHIIIQf'``

======  ======  =====================================================================
offset  type    field
======  ======  =====================================================================
0       4s      magic ``b"IRF1"``
4       u16     version, 1
6       u16     encoding: 1 = mono8 (uint8), 2 = mono16 (uint16, little-endian)
8       u32     width, pixels
12      u32     height, pixels
16      u32     sequence number (the sender's frame counter; wraps at 2**32)
20      u64     capture time in microseconds on the vehicle's boot clock (the clock of
                MAVLink ``time_boot_ms``), ``time_boot_us``
28      f32     zoom: the optical/digital zoom factor of this frame relative to the zoom
                ``camera.intrinsics`` were calibrated at (1.0 = as calibrated); 0.0 = not
                stated (these bytes were padding, zero on send, before the field existed)
======  ======  =====================================================================

The zoom field keeps version 1 in both directions: every earlier sender wrote zeros there (not
stated, read as before) and an earlier reader ignores it.  A zoom that is not finite, is negative
or lies outside :data:`ZOOM_PLAUSIBLE` (0.01-100x) refuses nothing (a sloppy sender's padding must
not stop tracking): the frame keeps it as sent and :attr:`IrFrame.stated_zoom` reads it as not
stated (:attr:`IrFrame.zoom_invalid`; the pipeline counts it as ``frame_zoom_invalid``).  What a
stated zoom does to the daemon's geometry is :func:`zoom_off_calibration`'s, used by
:mod:`onboard.pipeline.frame_pipeline` and the watchdog: beyond 0.5 % of 1.0 it is off, and stays off until
within half that (hysteresis).

then ``height * width * depth`` bytes of pixels, row-major (row 0 is the top of the image,
see "Image" in :mod:`onboard.core.frames`), nothing after them.

Decoding validates, in this order and without copying the pixels: length against
``max_bytes`` (so a frame 100x too large is refused on its ``len`` alone), header length,
magic, version, encoding, dimensions, then the exact payload size.  Every refusal raises
:class:`IrFrameError` whose ``reason`` is one of :data:`REJECT_REASONS`, so a service can
count rejections by reason.  The monotonic-sequence check needs state and belongs to the
receiver, not to this module.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from onboard.core.errors import InputError

__all__ = [
    "HEADER",
    "MAGIC",
    "VERSION",
    "ENCODING_MONO8",
    "ENCODING_MONO16",
    "DEFAULT_MAX_BYTES",
    "REJECT_REASONS",
    "IrFrame",
    "IrFrameError",
    "encode_irframe",
    "decode_irframe",
    "check_payload_size",
    "ZOOM_NOT_STATED",
    "ZOOM_TOLERANCE",
    "ZOOM_PLAUSIBLE",
    "zoom_off_calibration",
]

HEADER = struct.Struct("<4sHHIIIQf")
if HEADER.size != 32:  # pragma: no cover - a typo in the format string, caught at import
    raise RuntimeError(f"IR frame header must be 32 bytes, struct gives {HEADER.size}")

MAGIC = b"IRF1"
VERSION = 1
ENCODING_MONO8 = 1
ENCODING_MONO16 = 2
#: encoding code -> little-endian numpy dtype of one pixel
_DTYPE_OF_ENCODING: dict[int, np.dtype] = {ENCODING_MONO8: np.dtype("<u1"), ENCODING_MONO16: np.dtype("<u2")}

#: Largest payload (header + pixels) accepted by default: 16 MiB, i.e. a 4096 x 2048 mono16
#: frame; a 640 x 512 mono16 frame is 655 392 bytes.
DEFAULT_MAX_BYTES = 16 * 1024 * 1024

_U32_MAX = 2**32 - 1
_U64_MAX = 2**64 - 1
_F32 = struct.Struct("<f")

#: the zoom field's value for "not stated" (what every sender wrote before the field existed)
ZOOM_NOT_STATED = 0.0
#: a stated zoom this far from 1.0 (relative) or farther is not the zoom ``camera.intrinsics`` were calibrated at:
#: at the edge of a 640 px frame (320 px off centre, fx 765 px) 0.5 % moves a pixel's bearing by 1.6 px, about
#: the line of sight's own 1 sigma there (0.3 px centroid and 0.12 deg attitude: 1.6 px); a zoom stated as 1.0
#: through a float32 or a lens encoder's rounding stays well within it
ZOOM_TOLERANCE = 0.005
#: the zooms a frame may state (relative to the calibrated one): beyond them the field is not a zoom but stray bytes
#: (a sender that leaves the old padding uninitialised), read as not stated and counted (``frame_zoom_invalid``)
ZOOM_PLAUSIBLE = (0.01, 100.0)
_ZOOM_PLAUSIBLE_F32 = tuple(_F32.unpack(_F32.pack(b))[0] for b in ZOOM_PLAUSIBLE)  # as a frame carries them

#: Every value ``IrFrameError.reason`` can take.
REJECT_REASONS = frozenset({"short", "magic", "version", "encoding", "size", "too_large", "dims", "field"})


class IrFrameError(InputError):
    """An IR frame (payload or fields) is invalid.

    ``reason`` is a short code from :data:`REJECT_REASONS`: ``'short'`` (fewer bytes than the
    header), ``'magic'``, ``'version'``, ``'encoding'`` (unknown code or pixel dtype),
    ``'dims'`` (zero width/height or pixels not 2-D), ``'size'`` (payload length differs from
    header + width x height x depth), ``'too_large'`` (above ``max_bytes``), ``'field'``
    (a constructor field out of range: seq, time_boot_us).

    ``seq``: the sequence number of a frame whose header was read whole, its magic and version this reader's
    (``'encoding'``, ``'dims'``, ``'too_large'`` as the header claims it, ``'size'``: a frame cut short or padded on
    the way), None otherwise: the frame arrived, refused, and a receiver counting the frames lost on the way by the
    gaps in their numbers must not count it among them.
    """

    def __init__(self, reason: str, message: str, seq: int | None = None) -> None:
        if reason not in REJECT_REASONS:  # pragma: no cover - programming error
            raise ValueError(f"unknown IrFrameError reason {reason!r}")
        super().__init__(message)
        self.reason = reason
        self.seq = seq


@dataclass(frozen=True)
class IrFrame:
    """One IR image and its capture stamp.

    seq
        Sender's frame counter, 0 .. 2**32 - 1.
    time_boot_us
        Capture time, microseconds on the vehicle's boot clock, 0 .. 2**64 - 1.
    pixels
        ``(H, W)`` numpy array, dtype uint8 (mono8) or native uint16 (mono16), H, W >= 1.
        Stored as a read-only view (the caller's array is not modified, but must not be
        written to afterwards if it is shared).

    zoom
        The zoom field as sent (module docstring): the zoom relative to the calibrated one, 0.0 not
        stated.  Any real number is kept (rounded to float32, as on the wire): a value not finite or
        negative is what a sloppy sender's padding looks like, not a reason to refuse the frame;
        :attr:`stated_zoom` reads it.
    """

    seq: int
    time_boot_us: int
    pixels: np.ndarray
    zoom: float = ZOOM_NOT_STATED

    def __post_init__(self) -> None:
        for name, hi in (("seq", _U32_MAX), ("time_boot_us", _U64_MAX)):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
                raise IrFrameError("field", f"IrFrame.{name} must be an integer, got {type(v).__name__}")
            if not 0 <= int(v) <= hi:
                raise IrFrameError("field", f"IrFrame.{name} must be in [0, {hi}], got {v}")
            object.__setattr__(self, name, int(v))
        z = self.zoom
        if isinstance(z, (bool, np.bool_)) or not isinstance(z, (int, float, np.integer, np.floating)):
            raise IrFrameError("field", f"IrFrame.zoom must be a number, got {type(z).__name__}")
        try:  # what the wire carries: a float32 (so a decoded frame equals the one encoded)
            z32 = _F32.unpack(_F32.pack(float(z)))[0]
        except OverflowError as exc:
            raise IrFrameError("field", f"IrFrame.zoom {z!r} does not fit a float32") from exc
        object.__setattr__(self, "zoom", z32)
        px = self.pixels
        if not isinstance(px, np.ndarray):
            raise IrFrameError("field", f"IrFrame.pixels must be a numpy array, got {type(px).__name__}")
        if px.dtype != np.uint8 and px.dtype != np.uint16:
            raise IrFrameError("encoding", f"IrFrame.pixels dtype must be uint8 or native uint16, got {px.dtype}")
        if px.ndim != 2 or px.shape[0] < 1 or px.shape[1] < 1:
            raise IrFrameError("dims", f"IrFrame.pixels must be 2-D (H, W) with H, W >= 1, got shape {px.shape}")
        if px.shape[0] > _U32_MAX or px.shape[1] > _U32_MAX:  # pragma: no cover - memory bound first
            raise IrFrameError("dims", f"IrFrame.pixels shape {px.shape} exceeds the u32 header fields")
        if px.flags.writeable:
            px = px.view()
            px.flags.writeable = False
            object.__setattr__(self, "pixels", px)

    @property
    def encoding(self) -> int:
        """Wire encoding code: :data:`ENCODING_MONO8` or :data:`ENCODING_MONO16`."""
        return ENCODING_MONO8 if self.pixels.dtype == np.uint8 else ENCODING_MONO16

    @property
    def zoom_invalid(self) -> bool:
        """The zoom field holds a value no camera's zoom is: not finite, negative, or (not 0.0, "not stated") outside
        :data:`ZOOM_PLAUSIBLE` (stray bytes read as a float32 are mostly subnormal or huge): read as not stated."""
        z = self.zoom
        if z == ZOOM_NOT_STATED:
            return False
        return not (math.isfinite(z) and _ZOOM_PLAUSIBLE_F32[0] <= z <= _ZOOM_PLAUSIBLE_F32[1])

    @property
    def stated_zoom(self) -> float | None:
        """The zoom the frame states, relative to the calibrated one; None when not stated (0.0) or invalid."""
        if self.zoom_invalid or self.zoom == ZOOM_NOT_STATED:
            return None
        return self.zoom

    @property
    def height_px(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width_px(self) -> int:
        return int(self.pixels.shape[1])


def encode_irframe(frame: IrFrame) -> bytes:
    """Serialise ``frame`` to the version-1 wire format.

    One copy of the pixels (into the returned ``bytes``); a non-contiguous or big-endian
    array costs one more (made C-contiguous little-endian first).
    """
    if not isinstance(frame, IrFrame):
        raise IrFrameError("field", f"encode_irframe expects an IrFrame, got {type(frame).__name__}")
    px = frame.pixels
    dtype = _DTYPE_OF_ENCODING[frame.encoding]
    px = np.ascontiguousarray(px, dtype=dtype)
    header = HEADER.pack(
        MAGIC, VERSION, frame.encoding, px.shape[1], px.shape[0], frame.seq, frame.time_boot_us, frame.zoom
    )
    return b"".join((header, px.data.cast("B")))


def zoom_off_calibration(stated_zoom: float | None, was_off: bool = False, tolerance: float = ZOOM_TOLERANCE) -> bool:
    """Whether a frame's :attr:`IrFrame.stated_zoom` is not the zoom ``camera.intrinsics`` were calibrated at:
    more than ``tolerance`` (relative) from 1.0, or, ``was_off`` (the last frame's was not), more than half of it: a
    zoom read at the tolerance's edge (a lens encoder's last digit) would otherwise withhold every other frame and
    restart the estimator at each.  Not stated (None) is taken as calibrated, as before the field."""
    return stated_zoom is not None and abs(stated_zoom - 1.0) > (tolerance / 2 if was_off else tolerance)


def check_payload_size(nbytes: int, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
    """Refuse a payload on its length alone, before anything copies it.

    For a transport whose payload object is not a buffer (zenoh ``ZBytes``: call this with
    ``len(sample.payload)`` before ``.to_bytes()``).  Raises :class:`IrFrameError`
    ``'too_large'`` or ``'short'``.
    """
    if nbytes > max_bytes:
        raise IrFrameError("too_large", f"IR frame payload is {nbytes} bytes, above the limit of {max_bytes}")
    if nbytes < HEADER.size:
        raise IrFrameError("short", f"IR frame payload is {nbytes} bytes, shorter than the {HEADER.size}-byte header")


def decode_irframe(payload: bytes | bytearray | memoryview, max_bytes: int = DEFAULT_MAX_BYTES) -> IrFrame:
    """Parse and validate one wire payload; never copies before every check has passed.

    Zero-copy when ``payload`` is immutable (``bytes`` or a read-only memoryview): the pixels
    are a read-only ``np.frombuffer`` view that keeps ``payload`` alive.  A writable buffer
    (``bytearray``, writable memoryview) is copied once, since its owner may reuse it.

    Raises :class:`IrFrameError` (an :class:`~onboard.core.errors.InputError`) with ``reason`` set;
    no other exception for any ``bytes`` input.
    """
    try:
        mv = payload if isinstance(payload, memoryview) else memoryview(payload)
    except TypeError as exc:
        raise IrFrameError("field", f"IR frame payload must be bytes-like, got {type(payload).__name__}") from exc
    if mv.ndim != 1 or mv.itemsize != 1:
        try:
            mv = mv.cast("B")
        except TypeError as exc:
            raise IrFrameError("field", "IR frame payload must be a contiguous byte buffer") from exc
    n = mv.nbytes
    check_payload_size(n, max_bytes)
    magic, version, encoding, width, height, seq, time_boot_us, zoom = HEADER.unpack_from(mv, 0)
    if magic != MAGIC:
        raise IrFrameError("magic", f"IR frame magic is {bytes(magic)!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise IrFrameError("version", f"IR frame version is {version}, this reader supports {VERSION}")
    dtype = _DTYPE_OF_ENCODING.get(encoding)
    if dtype is None:
        raise IrFrameError("encoding", f"IR frame encoding is {encoding}, expected 1 (mono8) or 2 (mono16)", seq=seq)
    if width == 0 or height == 0:
        raise IrFrameError("dims", f"IR frame dimensions {width} x {height} must both be >= 1", seq=seq)
    pixel_bytes = width * height * dtype.itemsize
    if HEADER.size + pixel_bytes > max_bytes:
        raise IrFrameError(
            "too_large",
            f"IR frame header claims {width} x {height} x {dtype.itemsize} bytes, above the limit of {max_bytes}",
            seq=seq,
        )
    if n != HEADER.size + pixel_bytes:
        raise IrFrameError(
            "size",
            f"IR frame payload is {n} bytes, expected {HEADER.size} + {width} x {height} x {dtype.itemsize}"
            f" = {HEADER.size + pixel_bytes}",
            seq=seq,
        )
    pixels = np.frombuffer(mv, dtype=dtype, count=width * height, offset=HEADER.size).reshape(height, width)
    if not mv.readonly:
        pixels = pixels.copy()
    if not pixels.dtype.isnative:  # big-endian host only: one conversion to native order
        pixels = pixels.astype(pixels.dtype.newbyteorder("="))
    return IrFrame(seq=seq, time_boot_us=time_boot_us, pixels=pixels, zoom=zoom)
