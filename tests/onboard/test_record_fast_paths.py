"""The recorder's faster paths: the hand-appended RawImage data field parses to the same message as the protobuf
library's encoding, the camera fix is the camera centre in WGS84 (onboard.core.frames' conversion), and the periodic
sync (fdatasync + page-cache drop) leaves a file the mcap reader reads whole, the raw MAVLink JSON made from cached parts is
json.dumps' (hypothesis), the LocationFix covariance's permutation equals the NED -> ENU matrix product."""

from __future__ import annotations

import math
import time

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import GeodeticOrigin, geodetic_from_ned
from onboard.core.irframe import IrFrame
from onboard.io.foxglove_messages import camera_fix_fields, location_fix_fields, rawimage_bytes, rawimage_fields
from onboard.io.record import FlightRecorder, RecordConfig

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
def test_camera_fix_is_the_camera_centre_in_wgs84(p_ned_m):
    from types import SimpleNamespace

    lat, lon, alt = (float(v) for v in geodetic_from_ned(np.array(p_ned_m), ORIGIN))
    f = camera_fix_fields(SimpleNamespace(p_cam_ned_m=np.array(p_ned_m), origin=ORIGIN), 12_345_678)
    assert f["latitude"] == pytest.approx(lat, abs=ATOL_DEG) and f["longitude"] == pytest.approx(lon, abs=ATOL_DEG)
    assert f["altitude"] == pytest.approx(alt, abs=ATOL_M)
    assert f["timestamp"] == (12, 345_678_000) and f["frame_id"] == "camera" and "position_covariance" not in f


def test_periodic_sync_keeps_the_file_whole(tmp_path):
    from mcap.reader import make_reader

    path = str(tmp_path / "s.mcap")
    rec = FlightRecorder(RecordConfig(path=path, sync_mb=0.2, chunk_kb=64), vehicle="uav1")
    rec.start()
    px = np.full((120, 160), 9, np.uint8)
    for i in range(40):
        rec.on_frame(IrFrame(i, 1_000_000 + i * 33_333, px), 1000 + i)
    # the writer's own turns sync (a closing writer finishes the file without one): wait for them to write it all
    t_end = time.monotonic() + 30.0
    while rec.messages_written < 40 and time.monotonic() < t_end:
        time.sleep(0.01)
    rec.close(30.0)
    assert (
        rec.syncs >= 1 and rec.write_errors == 0
    )  # after a batch past sync_bytes and rec.stats()["syncs"] == rec.syncs
    with open(path, "rb") as f:
        msgs = list(make_reader(f).iter_messages())
    assert [m.sequence for _s, _c, m in msgs] == list(range(40))


@settings(max_examples=200, deadline=None)
@given(
    data=st.binary(max_size=300),
    link=st.sampled_from(["autopilot", "gcs", "vehicle", 'l\u00e9"\\']),
    source=st.one_of(
        st.none(), st.tuples(st.sampled_from(["127.0.0.1", "::1"]), st.integers(0, 65535)), st.text(max_size=12)
    ),
    direction=st.sampled_from(["rx", "tx"]),
    now=st.integers(0, 2**63 - 1),
)
def test_mavlink_json_is_json_dumps_of_the_documented_object(data, link, source, direction, now):
    import base64
    import json

    rec = FlightRecorder(RecordConfig(path="/nonexistent/never_opened.mcap"), vehicle="uav1")
    src = None if source is None else (f"{source[0]}:{source[1]}" if isinstance(source, tuple) else str(source))
    ref = json.dumps(
        {
            "link": link,
            "direction": direction,
            "receive_time_ns": now,
            "source": src,
            "data": base64.b64encode(data).decode(),
        },
        separators=(",", ":"),
    ).encode()
    assert rec._mavlink_json(data, link, source, direction, now) == ref
    assert rec._mavlink_json(data, link, source, direction, now) == ref  # from the cached parts


@settings(max_examples=200, deadline=None)
@given(c=hnp.arrays(np.float64, (3, 3), elements=st.floats(-1e6, 1e6, allow_nan=False)))
def test_location_fix_covariance_is_the_ned_to_enu_similarity(c):
    P = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    got = location_fix_fields(1.0, 2.0, 3.0, 4, "target", c)["position_covariance"]
    assert got == (P @ c @ P.T).ravel().tolist()  # equal values (a zero's sign aside: +0.0 here)
    assert all(math.copysign(1.0, x) > 0 for x in got if x == 0.0)
