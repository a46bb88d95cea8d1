"""The track JSON (onboard.core.track.track_to_json) holds to the per-number reference it replaced: the same
bytes for every Track, including infinite ratios (null), missing groups and numpy inputs."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import GeodeticOrigin
from onboard.core.track import TRACK_SCHEMA, LineOfSight, Track, json_number, track_to_bytes, track_to_json
from tests.fakes import positioned_track

#: the keys whose numbers are integers on the wire (json_number would write them as floats)
INTEGER_KEYS = frozenset(
    {
        "seq",
        "time_boot_us",
        "track_id",
        "window_frames",
        "time_unix_us",
        "time_unix_sigma_us",
        "compensated_us",
        "estimate_epoch",
    }
)


def per_number(value, key: str = ""):
    """The encoding before: every number of the object (in lists and nested objects too) through json_number,
    except the integers'."""
    if isinstance(value, dict):
        return {k: per_number(v, k) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [per_number(v, key) for v in value]
    if value is None or isinstance(value, (bool, str)) or key in INTEGER_KEYS:
        return value
    return json_number(value)


def reference_bytes(track: Track) -> bytes:
    return json.dumps(per_number(track_to_json(track)), separators=(",", ":"), allow_nan=False).encode()


finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
positive = st.floats(0.0, 1e6, allow_nan=False, allow_infinity=False)


@st.composite
def tracks(draw) -> Track:
    with_pos = draw(st.booleans())
    with_los = draw(st.booleans())
    u, v = draw(finite), draw(finite)
    kw: dict[str, Any] = dict(
        vehicle="uav1",
        seq=draw(st.integers(0, 2**32 - 1)),
        time_boot_us=draw(st.integers(0, 2**63)),
        state=draw(st.sampled_from(["searching", "tracking", "coasting", "lost"])),
        track_id=draw(st.one_of(st.none(), st.integers(1, 1000))),
        measurement_valid=True,
        u_px=np.float32(u) if draw(st.booleans()) else u,  # a numpy float from the image chain
        v_px=v,
        bbox=draw(st.one_of(st.none(), st.tuples(finite, finite, positive, positive))),
        pose_valid=with_los,
        residual_rms_norm=draw(st.one_of(st.none(), positive, st.just(math.inf))),
        window_frames=draw(st.integers(0, 500)),
        model=draw(st.one_of(st.none(), st.sampled_from(["cv", "ca"]))),
    )
    if with_los:
        n, e, d = draw(st.tuples(finite, finite, finite).filter(lambda x: math.hypot(*x) > 1e-3))
        r = math.sqrt(n * n + e * e + d * d)
        kw["los"] = LineOfSight(
            u_ned=(n / r, e / r, d / r),
            azimuth_deg=draw(st.floats(-180.0, 180.0)),
            elevation_deg=draw(st.floats(-90.0, 90.0)),
            sigma_azimuth_deg=draw(st.floats(0.0, 180.0)),  # a sigma beyond the circle is refused
            sigma_elevation_deg=draw(st.floats(0.0, 180.0)),
            p_cam_ned_m=np.array(draw(st.tuples(finite, finite, finite))),
            sigma_bias_deg=draw(st.one_of(st.none(), st.floats(0.0, 90.0))),
        )
    if with_pos:
        a = np.array(draw(st.lists(finite, min_size=9, max_size=9))).reshape(3, 3) / 1e3
        cov = a @ a.T + np.diag([-1e-300, 0.0, 1.0])  # a round-off negative variance reads as 0
        cov[0, 0] = abs(cov[0, 0])
        kw.update(
            origin=GeodeticOrigin(32.0, 118.8, 10.0),
            lat_deg=draw(st.floats(-90.0, 90.0)),
            lon_deg=draw(st.floats(-180.0, 180.0)),
            alt_m=draw(finite),
            p_ned_m=np.array(draw(st.tuples(finite, finite, finite))),
            v_ned_mps=list(draw(st.tuples(finite, finite, finite))),
            cov_p_ned_m2=cov,
            cov_v_ned_m2ps2=draw(st.one_of(st.none(), st.just(np.eye(3) * 0.25))),
            range_m=draw(positive),
            range_sigma_ratio=draw(st.one_of(st.none(), positive, st.just(math.inf))),
            observable=draw(st.booleans()),
            time_unix_us=draw(st.one_of(st.none(), st.integers(0, 2**62))),
        )
    return Track(**kw)


@settings(max_examples=300, deadline=None)
@given(tracks())
def test_the_json_is_byte_for_byte_the_per_number_reference(track):
    assert track_to_bytes(track) == reference_bytes(track)


def test_a_positioned_track_and_infinite_ratios():
    for track in (
        positioned_track(),
        positioned_track(range_sigma_ratio=math.inf, residual_rms_norm=math.inf),
        positioned_track(cov_v_ned_m2ps2=np.diag([0.5, 0.25, 0.125]), model="cv"),
    ):
        assert track_to_bytes(track) == reference_bytes(track)
    obj = track_to_json(positioned_track(range_sigma_ratio=math.inf))
    assert obj["schema"] == TRACK_SCHEMA and obj["range_sigma_ratio"] is None
    assert obj["cov_ned_m2"] == [[4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 1.0]]
    assert obj["sigma_ned_m"] == [2.0, 2.0, 1.0]
    assert all(type(x) is float for x in obj["ned_m"] + obj["cov_ned_m2"][0])
