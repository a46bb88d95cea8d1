"""The recorder's faster paths (issue 13, recording cost): the hand-appended RawImage data field parses to the same
message as the protobuf library's encoding, the scalar camera-fix geodesy equals onboard.core.frames', and the periodic
sync (fdatasync + page-cache drop) leaves a file the mcap reader reads whole."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.core.frames import GeodeticOrigin, geodetic_from_ned
from onboard.core.irframe import IrFrame
from onboard.io.record import FlightRecorder, RecordSettings, geodetic_from_ned_scalar, rawimage_bytes, rawimage_fields

ATOL_DEG = 1e-11  # ~1 um on the ground
ATOL_M = 1e-6  # 1 um
ORIGIN = GeodeticOrigin(47.397742, 8.545594, 488.0)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_rawimage_bytes_parse_to_the_protobuf_librarys_message(dtype):
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    px = (np.arange(37 * 53) * 977 % (65535 if dtype == np.uint16 else 255)).astype(dtype).reshape(37, 53)
    frame = IrFrame(7, 12_345_678_901, px)
    fields = rawimage_fields(frame)
    sec, nsec = fields.pop("timestamp")
    ref = RawImage(**fields)
    ref.timestamp.seconds, ref.timestamp.nanos = sec, nsec
    ours = RawImage()
    ours.ParseFromString(rawimage_bytes(frame))
    assert ours == ref
    assert ours.data == px.astype("<u2" if dtype == np.uint16 else np.uint8).tobytes()


@pytest.mark.parametrize("p_ned_m", [(0.0, 0.0, 0.0), (1000.0, -2000.0, -500.0), (5e4, 3e4, -9e3), (-3e5, 2e5, 1e4)])
def test_scalar_geodesy_equals_the_frames_module(p_ned_m):
    lat, lon, alt = (float(v) for v in geodetic_from_ned(np.array(p_ned_m), ORIGIN))
    lat2, lon2, alt2 = geodetic_from_ned_scalar(p_ned_m, ORIGIN)
    assert lat2 == pytest.approx(lat, abs=ATOL_DEG) and lon2 == pytest.approx(lon, abs=ATOL_DEG)
    assert alt2 == pytest.approx(alt, abs=ATOL_M)


def test_periodic_sync_keeps_the_file_whole(tmp_path):
    from mcap.reader import make_reader

    path = str(tmp_path / "s.mcap")
    rec = FlightRecorder(RecordSettings(path, sync_bytes=200_000, chunk_bytes=64 * 1024), vehicle="uav1")
    rec.start()
    px = np.full((120, 160), 9, np.uint8)
    for i in range(40):
        rec.on_frame(IrFrame(i, 1_000_000 + i * 33_333, px), 1000 + i)
    rec.close(30.0)
    assert rec.syncs >= 1 and rec.write_errors == 0  # after a batch past sync_bytes and rec.stats()["syncs"] == rec.syncs
    with open(path, "rb") as f:
        msgs = list(make_reader(f).iter_messages())
    assert [m.sequence for _s, _c, m in msgs] == list(range(40))
