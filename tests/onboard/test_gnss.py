"""GPS_RAW_INT (#24) end to end without sockets: the wire class round trip (hypothesis over its fields), the pure
GnssState, the watchdog's ``gnss_degraded`` raised and cleared, and the status's ``link.gnss`` section.
The decoding through a real UDP socket is in test_mavlink_link.py."""

from __future__ import annotations

import json
import logging
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mav

from onboard.app.watchdog import Watchdog
from onboard.core.errors import InputError
from onboard.core.gnss import FIX_3D, GPS_FIX_NAMES, GnssState
from onboard.io.mavlink_wire import GpsRawInt, wire_roundtrip
from tests.fakes import idle_status, quiet_link_status
from tests.fuzz_budget import fuzz_settings

DOP = st.one_of(st.just(math.nan), st.floats(0.0, 655.34))
ACC_M = st.one_of(st.just(math.nan), st.floats(0.001, 4_000_000.0))


def _same(a: float, b: float, tol: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


@fuzz_settings(200)
@given(
    st.integers(0, 2**64 - 1),
    st.integers(0, 255),
    st.one_of(st.none(), st.integers(0, 254)),
    DOP,
    DOP,
    ACC_M,
    ACC_M,
)
def test_gps_raw_int_round_trip(t_us, fix, sats, hdop, vdop, h_acc_m, v_acc_m):
    sent = GpsRawInt(t_us, fix, sats, hdop, vdop, h_acc_m, v_acc_m)
    msg = wire_roundtrip(sent.to_message())
    back = GpsRawInt.from_message(msg)
    assert (back.time_usec, back.fix_type, back.satellites_visible) == (t_us, fix, sats)
    assert _same(back.hdop, hdop, 0.005 + 1e-9) and _same(back.vdop, vdop, 0.005 + 1e-9)  # DOP * 100 on the wire
    assert _same(back.h_acc_m, h_acc_m, 0.0005 + 1e-9) and _same(back.v_acc_m, v_acc_m, 0.0005 + 1e-9)  # mm
    # the position is #33's: never sent here; unknown speed and course as common.xml says
    assert (msg.lat, msg.lon, msg.alt, msg.vel, msg.cog) == (0, 0, 0, 65535, 65535)


def test_gps_raw_int_unknowns_on_the_wire():
    msg = wire_roundtrip(GpsRawInt(5, mav.GPS_FIX_TYPE_NO_FIX).to_message())
    assert (msg.eph, msg.epv, msg.satellites_visible, msg.h_acc, msg.v_acc) == (65535, 65535, 255, 0, 0)
    # a sender's numbers as they are: HDOP 0.8 (eph 80), 0.5 m / 0.8 m (mm), 14 satellites
    raw = mav.MAVLink_gps_raw_int_message(7, 3, 0, 0, 0, 80, 120, 0, 0, 14, 0, 500, 800, 0, 0, 0)
    g = GpsRawInt.from_message(wire_roundtrip(raw))
    assert (g.fix_type, g.satellites_visible, g.hdop, g.vdop, g.h_acc_m, g.v_acc_m) == (3, 14, 0.8, 1.2, 0.5, 0.8)


def test_gps_raw_int_accuracy_below_a_millimetre_goes_out_as_one_not_as_unknown():
    """0.5 mm rounds to 0 mm, which the wire reads as unknown: it goes out as 1 mm, the smallest it can say."""
    msg = wire_roundtrip(GpsRawInt(5, mav.GPS_FIX_TYPE_RTK_FIXED, 20, 0.6, 0.9, 0.0005, 0.0005).to_message())
    assert (msg.h_acc, msg.v_acc) == (1, 1)
    back = GpsRawInt.from_message(msg)
    assert (back.h_acc_m, back.v_acc_m) == (0.001, 0.001)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(fix_type=256), "fix_type"),
        (dict(fix_type=True), "fix_type"),
        (dict(time_usec=-1), "time_usec"),
        (dict(satellites_visible=255), "satellites_visible"),
        (dict(hdop=-0.1), "dop"),
        (dict(vdop=math.inf), "dop"),
        (dict(h_acc_m=0.0), "acc_m"),  # 0 mm is "unknown" on the wire: NaN says so
    ],
)
def test_gps_raw_int_refuses_bad_values_by_name(kwargs, field):
    with pytest.raises(InputError, match=rf"GPS_RAW_INT\.{field}"):
        GpsRawInt(**{"time_usec": 0, "fix_type": 3, **kwargs}).to_message()


def test_fix_names_follow_common_xml():
    assert GPS_FIX_NAMES[mav.GPS_FIX_TYPE_NO_GPS] == "no_gps" and GPS_FIX_NAMES[mav.GPS_FIX_TYPE_2D_FIX] == "2d"
    assert GPS_FIX_NAMES[mav.GPS_FIX_TYPE_RTK_FIXED] == "rtk_fixed" and GPS_FIX_NAMES[mav.GPS_FIX_TYPE_PPP] == "ppp"
    assert FIX_3D == mav.GPS_FIX_TYPE_3D_FIX and len(GPS_FIX_NAMES) == 9


def test_gnss_state_keeps_when_the_degraded_run_began():
    g = GnssState.updated(None, 10.0, 3, 14, 0.8, 1.2, 0.5, 0.8)
    assert g.degraded_since_s is None and g.has_3d_fix
    g = GnssState.updated(g, 10.2, 2, 5)
    g = GnssState.updated(g, 10.4, 1, 0)
    assert (g.fix, g.degraded_since_s, g.received_s, g.satellites) == ("no_fix", 10.2, 10.4, 0)
    s = g.summary(11.0)
    assert s["age_s"] == pytest.approx(0.6) and s["degraded_s"] == pytest.approx(0.8)
    assert s["hdop"] is None and s["h_acc_m"] is None and s["fix_type"] == 1  # NaN -> null
    g = GnssState.updated(g, 10.6, 6, 20)
    assert g.degraded_since_s is None and g.summary(10.6)["degraded_s"] is None
    with pytest.raises(ValueError, match="fix_type 9"):
        GnssState.updated(g, 11.0, 9)


def _wd() -> Watchdog:
    return Watchdog(
        started_s=0.0, frame_key="k", zenoh_where="w", mavlink_connection="udpin:0.0.0.0:14540", camera_size_px=(1, 1)
    )


def test_gnss_degraded_after_a_second_below_3d_and_cleared_by_a_3d_fix(caplog):
    wd = _wd()
    g = None
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.gnss(0.0, None)  # no GPS_RAW_INT yet
        g = GnssState.updated(g, 1.0, 3, 14)
        wd.gnss(1.0, g)
        g = GnssState.updated(g, 2.0, 1, 0)
        for t in (2.0, 2.5, 3.0):  # a glitch of up to a second is not a warning
            wd.gnss(t, g)
        assert wd.active == () and wd.changes == 0
        g = GnssState.updated(g, 3.2, 0, None)  # still degraded: the run began at 2.0
        wd.gnss(3.5, g)
        assert [w.code for w in wd.active] == ["gnss_degraded"] and wd.changes == 1
        wd.gnss(4.0, g)  # held: no second warning
        g = GnssState.updated(g, 4.2, 4, 12)  # DGPS: a 3-D fix
        wd.gnss(4.5, g)
        assert wd.active == () and wd.changes == 2
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1
    assert "no_gps" in warned[0] and "unknown satellites" in warned[0] and "1.5 s" in warned[0]
    assert "dead-reckons" in warned[0] and "gnss_dropout" in warned[0]


def test_a_fix_that_comes_and_goes_in_short_runs_is_degraded_too(caplog):
    """GPS_RAW_INT's fix_type flapping 3 <-> 1 every second (a telemetry audit): each run without a fix under the
    second gnss_degraded waits for, never warned.  Three losses within 10 s are; one loss (a dropout that ended) is
    not; the warning clears once the window holds fewer and the fix is there."""
    wd = _wd()
    g = None
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for k in range(6):  # 0.8 s with a fix, 0.7 s without, the watchdog's turn every 0.5 s
            g = GnssState.updated(g, 1.5 * k, 3, 14)
            wd.gnss(1.5 * k + 0.4, g)
            g = GnssState.updated(g, 1.5 * k + 0.8, 1, 0)
            wd.gnss(1.5 * k + 0.9, g)
            if k < 2:
                assert wd.active == ()
        assert g.fix_losses == 6
        assert [w.code for w in wd.active] == ["gnss_degraded"] and "comes and goes" in wd.active[0].message
        g = GnssState.updated(g, 9.1, 3, 14)
        wd.gnss(12.0, g)  # a fix, but the window still holds the losses
        assert [w.code for w in wd.active] == ["gnss_degraded"]
        wd.gnss(19.5, g)
        assert wd.active == ()
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1


def test_one_loss_of_the_fix_that_ends_clears_at_the_fix_as_before():
    wd = _wd()
    g = GnssState.updated(None, 0.0, 3, 14)
    wd.gnss(0.0, g)
    g = GnssState.updated(g, 1.0, 1, 0)
    wd.gnss(3.0, g)  # 2 s without: degraded
    assert [w.code for w in wd.active] == ["gnss_degraded"] and "comes and goes" not in wd.active[0].message
    g = GnssState.updated(g, 3.2, 3, 14)
    wd.gnss(3.5, g)
    assert wd.active == () and g.fix_losses == 1


def test_gnss_degraded_and_gnss_dropout_are_listed_together():
    wd = _wd()
    g = GnssState.updated(GnssState.updated(None, 0.0, 2, 4), 2.0, 2, 4)
    wd.gnss(2.0, g)
    wd.navigation(2.0, 1.5)
    assert [w.code for w in wd.active] == ["gnss_degraded", "gnss_dropout"]
    assert "2d (GPS_RAW_INT #24, 4 satellites)" in wd.active[0].message


def test_status_shows_the_gnss_section_in_the_link():
    def status(gnss):
        st = quiet_link_status("connected", 1, 10)
        link = {k: getattr(st, k) for k in st.__dataclass_fields__}  # as the service makes it
        link["gnss"] = gnss
        empty = {"n": 0, "p50": None, "p99": None, "max": None}
        return idle_status(processing_ms=empty, latency_ms=empty, pose_wait_ms=empty, link=link, estimator="ekf")

    assert quiet_link_status("waiting", None, 0).gnss is None and status(None)["link"]["gnss"] is None
    g = GnssState.updated(None, 5.0, 1, 3, math.nan, 2.5, 12.0, math.nan)
    s = json.loads(json.dumps(status(g.summary(5.25))))
    assert s["link"]["gnss"] == {
        "fix": "no_fix",
        "fix_type": 1,
        "satellites": 3,
        "hdop": None,
        "vdop": 2.5,
        "h_acc_m": 12.0,
        "v_acc_m": None,
        "age_s": 0.25,
        "degraded_s": 0.25,
    }
