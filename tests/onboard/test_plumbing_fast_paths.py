"""The per-frame plumbing's fast paths give what the general paths gave: a Track's checks on values already of the
checked types, the status percentiles, the usual frame's admission, the worker's pipe framing."""

from __future__ import annotations

import math
import multiprocessing as mp
import pickle
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.app.estimator_wire import recv_msg, send_msg
from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin
from onboard.core.status import RollingStats
from onboard.core.track import LineOfSight, Track, track_to_bytes
from onboard.pipeline.admission import Admission, FrameAdmission

FINITE = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
POSITIVE = st.floats(0.0, 1e6, allow_nan=False, allow_infinity=False)


def _fields(track: Track) -> dict:
    out = {}
    for name, value in vars(track).items():
        if isinstance(value, np.ndarray):
            out[name] = (value.dtype, value.shape, value.tobytes(), value.flags.writeable)
        elif isinstance(value, LineOfSight):
            out[name] = {k: (type(v), v) for k, v in vars(value).items()}
        else:
            out[name] = (type(value), value)
    return out


@settings(max_examples=150, deadline=None)
@given(
    st.tuples(FINITE, FINITE),
    st.tuples(FINITE, FINITE, POSITIVE, POSITIVE),
    st.tuples(FINITE, FINITE, FINITE),
    st.tuples(FINITE, FINITE, FINITE),
    POSITIVE,
    st.one_of(POSITIVE, st.just(math.inf)),
    st.integers(1, 2**31),
)
def test_a_track_of_python_values_equals_one_of_numpy_values(uv, bbox, p, v, rng_m, ratio, seq):
    """Checked values of the right types are kept as they are; numpy scalars, arrays and lists are converted to
    the very same values: the two Tracks have the same fields (types included) and the same JSON."""
    cov = np.diag([1.0, 2.0, 3.0])
    los_kw = dict(azimuth_deg=10.0, elevation_deg=-5.0, sigma_azimuth_deg=0.1, sigma_elevation_deg=0.2)
    common = dict(vehicle="uav1", state="tracking", measurement_valid=True, pose_valid=True, observable=True)
    common.update(origin=GeodeticOrigin(32.0, 118.8, 10.0), lat_deg=32.001, lon_deg=118.8, alt_m=50.0, model="cv")
    plain = Track(
        **common,
        seq=seq,
        time_boot_us=seq * 1000,
        track_id=3,
        u_px=uv[0],
        v_px=uv[1],
        bbox=bbox,
        los=LineOfSight(u_ned=(0.6, 0.8, 0.0), p_cam_ned_m=p, **los_kw),
        p_ned_m=p,
        v_ned_mps=v,
        cov_p_ned_m2=cov,
        range_m=rng_m,
        range_sigma_ratio=ratio,
        residual_rms_norm=1.5,
        window_frames=300,
    )
    numpyish = Track(
        **common,
        seq=np.uint32(seq),
        time_boot_us=np.int64(seq * 1000),
        track_id=np.int64(3),
        u_px=np.float64(uv[0]),
        v_px=uv[1],
        bbox=list(bbox),
        los=LineOfSight(u_ned=np.array([0.6, 0.8, 0.0]), p_cam_ned_m=list(p), **los_kw),
        p_ned_m=np.array(p),
        v_ned_mps=list(v),
        cov_p_ned_m2=cov.tolist(),
        range_m=np.float64(rng_m),
        range_sigma_ratio=np.float64(ratio),
        residual_rms_norm=np.float32(1.5),
        window_frames=np.int32(300),
    )
    assert _fields(plain) == _fields(numpyish)
    assert track_to_bytes(plain) == track_to_bytes(numpyish)


@pytest.mark.parametrize("bad", [math.inf, -math.inf, math.nan])
def test_a_tuple_with_a_non_finite_number_is_still_refused(bad):
    with pytest.raises(InputError, match="Track.bbox must be 4 finite numbers"):
        Track(vehicle="uav1", seq=1, time_boot_us=1, state="tracking", bbox=(1.0, 2.0, bad, 4.0))
    with pytest.raises(InputError, match="Track.u_px must be a finite number"):
        Track(vehicle="uav1", seq=1, time_boot_us=1, state="tracking", u_px=bad, v_px=1.0)
    with pytest.raises(InputError, match="los.u_ned must be 3 finite numbers"):
        LineOfSight((bad, 0.0, 1.0), 0.0, 0.0, 0.1, 0.1, (0.0, 0.0, 0.0))


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.one_of(st.floats(0.0, 1e4, allow_nan=False), st.sampled_from([0.0, 1.0, 2.5]), st.just(math.inf)),
        min_size=1,
        max_size=300,
    ),
    st.booleans(),
)
def test_the_status_percentiles_are_numpys(values, with_nan):
    if with_nan:
        values = [*values, math.nan]
    stats = RollingStats(250)
    for x in values:
        stats.add(x)
    kept = np.array(values[-250:])
    with np.errstate(invalid="ignore"):  # numpy's interpolation between infinities, here and in the summary
        p50, p99 = np.percentile(kept, [50, 99])
        top = kept.max()
        summary = stats.summary()
    finite_or_none = [None if not math.isfinite(x) else float(x) for x in (p50, p99, top)]
    assert summary == {
        "n": kept.size,
        "p50": finite_or_none[0],
        "p99": finite_or_none[1],
        "max": finite_or_none[2],
    }


def test_the_usual_frame_is_admitted_without_a_message_and_a_step_still_says_what_happened():
    adm = FrameAdmission(1_000_000, 5)
    verdicts = [adm.admit(100 + k, 1_000_000 + 33_333 * k) for k in range(10)]
    assert all(v.accepted and v.reason == "" and v.message == "" and not v.restart for v in verdicts)
    v = adm.admit(7, 1_000_000 + 33_333 * 10)  # seq back while time moved on: the sender restarted
    assert v.accepted and v.reason == "sequence_reset" and "the sender restarted" in v.message
    dup = adm.admit(7, 1_000_000 + 33_333 * 10)
    assert not dup.accepted and dup.reason == "duplicate" and "again" in dup.message


@pytest.mark.parametrize("size", [0, 10, 70_000, 1_000_000])
def test_the_worker_pipe_framing_is_connections(size):
    """Messages written on the descriptor read back through Connection.recv_bytes and the other way round,
    a message longer than the pipe's buffer (a snapshot) included; a closed writer reads as EOFError."""
    a, b = mp.Pipe()
    msg = ("snapshot", 1.5, b"x" * size)
    writer = threading.Thread(target=send_msg, args=(a, msg))
    writer.start()
    assert pickle.loads(b.recv_bytes()) == msg
    writer.join()
    writer = threading.Thread(target=b.send_bytes, args=(pickle.dumps(msg),))
    writer.start()
    assert recv_msg(a) == msg
    writer.join()
    b.close()
    with pytest.raises(EOFError):
        recv_msg(a)
    a.close()


def test_a_repeated_sequence_number_with_time_moving_on_is_named_so_not_a_restart():
    """The last frame's seq again, a new capture time (a sender that did not move its counter on): taken, as
    before, but counted as a sender restart (frame_sequence_reset), which it is not."""
    adm = FrameAdmission(1_000_000, 5)
    for k in range(5):
        adm.admit(100 + k, 1_000_000 + 33_333 * k)
    v = adm.admit(104, 1_000_000 + 33_333 * 5)
    assert v.accepted and v.reason == "sequence_repeated" and "seq 104 again" in v.message and not v.restart
    assert adm.admit(105, 1_000_000 + 33_333 * 6) == Admission(True, "")
