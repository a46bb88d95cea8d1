"""The JSON Schemas a recording carries describe the messages beside it: each is made from the key table beside the
message's builder (track, status, truth), and each builder's message, with every optional part present and with
none, conforms to it -- every key declared, every required key present, every value of its declared type
(``tests/json_schema_check.py``: the `jsonschema` package, every object closed to undeclared keys).  Real recorded messages are
checked in test_record_daemon.py and test_objects_output.py."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from groundsim.world.truth import TRUTH_COLUMNS, TruthRow, truth_json, truth_json_schema
from onboard.core.frames import GeodeticOrigin
from onboard.core.status import STATUS_JSON_KEYS, STATUS_SCHEMA
from onboard.core.track import TRACK_JSON_KEYS, TRACK_SCHEMA, LineOfSight, Track, track_to_json
from onboard.core.utc_clock import UtcClock
from onboard.io.foxglove_messages import JSON_SCHEMAS, TRUTH_SCHEMA
from onboard.io.mavlink_link import LinkStatus
from tests.fakes import idle_status, tracking_track
from tests.json_schema_check import check

ORIGIN = GeodeticOrigin(47.397742, 8.545594, 488.0)
SUMMARY = {"n": 0, "p50": None, "p99": None, "max": None}


def _full_track() -> Track:
    los = LineOfSight((1.0, 0.0, 0.0), 0.0, 0.0, 0.1, 0.1, (0.0, 0.0, -100.0), sigma_bias_deg=0.08)
    return Track(
        "uav1", 9, 1_000_000, "tracking", track_id=2, measurement_valid=True, u_px=320.5, v_px=256.25,
        bbox=(310.0, 250.0, 20.0, 12.0), pose_valid=True, los=los, origin=ORIGIN, lat_deg=47.4, lon_deg=8.5,
        alt_m=500.0, p_ned_m=(100.0, 2.0, -12.0), v_ned_mps=(1.0, 0.0, 0.0), cov_p_ned_m2=np.diag([4.0, 9.0, 1.0]),
        cov_v_ned_m2ps2=np.eye(3), range_m=100.5, range_sigma_ratio=math.inf, observable=True,
        residual_rms_norm=1.1, window_frames=30, model="cv", time_unix_us=1_700_000_000_000_000,
        time_unix_sigma_us=900,
    )  # fmt: skip


@pytest.mark.parametrize("track", [_full_track(), Track("uav1", 0, 0, "searching")], ids=["full", "empty"])
def test_track_json_has_exactly_the_schemas_keys_in_order_and_conforms(track):
    obj = track_to_json(track)
    assert list(obj) == [k for k, _ in TRACK_JSON_KEYS]
    assert check(obj, JSON_SCHEMAS[TRACK_SCHEMA]) == []
    assert JSON_SCHEMAS[TRACK_SCHEMA]["required"] == list(obj)  # every key is always written


def test_a_track_value_of_the_wrong_type_is_caught():
    obj = track_to_json(_full_track())
    obj["los_az_deg"] = "north"
    obj["extra"] = 1
    errors = check(obj, JSON_SCHEMAS[TRACK_SCHEMA])
    assert len(errors) == 2, errors
    assert any(e.startswith("$: ") and "'extra'" in e for e in errors), errors
    assert any(e.startswith("los_az_deg: 'north' is not of type") for e in errors), errors


def test_guidance_json_has_exactly_the_schemas_keys_in_order_and_conforms():
    from onboard.estimation.guidance import GUIDANCE_JSON_KEYS, GUIDANCE_SCHEMA, Advice, advice_to_json

    advice = Advice(
        t_s=5.0, valid_until_s=8.0, status="advise", manoeuvre="weave", v_ned_mps=(1.0, 8.0, 0.0), range_m=120.0,
        sigma_range_now_m=60.0, sigma_range_without_m=55.0, sigma_range_with_m=12.0, candidates=(),
    )  # fmt: skip
    obj = advice_to_json(advice, "uav1", 5_000_000, in_loop=True)
    assert list(obj) == [k for k, _ in GUIDANCE_JSON_KEYS]
    assert check(obj, JSON_SCHEMAS[GUIDANCE_SCHEMA]) == []
    obj["v_ned_mps"] = [1.0, 8.0]
    assert check(obj, JSON_SCHEMAS[GUIDANCE_SCHEMA]) != []


@pytest.mark.parametrize(
    "fields",
    [
        {},
        {
            "processing_ms": {"n": 3, "p50": 1.0, "p99": 2.0, "max": 2.5},
            "latency_ms": {"n": 0, "p50": None, "p99": None, "max": None},
            "pose_wait_ms": {"n": 0, "p50": None, "p99": None, "max": None},
            "queue_wait_ms": {"n": 0, "p50": None, "p99": None, "max": None},
            "stages_ms": {"imaging": {"n": 1, "p50": 1.0, "p99": 1.0, "max": 1.0}},
            "link": dataclasses.asdict(
                LinkStatus(
                    state="connected",
                    autopilot_sysid=1,
                    heartbeat_age_s=0.4,
                    rates_confirmed=(31, 33),
                    rates_pending=(),
                    rates_refused=(285,),
                    clock_synced=True,
                    messages_rx=500,
                    link_losses=0,
                    reboots=0,
                    gnss={
                        "fix": "rtk_fixed",
                        "fix_type": 6,
                        "satellites": 14,
                        "hdop": 0.8,
                        "vdop": None,
                        "h_acc_m": 0.028,
                        "v_acc_m": 0.02,
                        "age_s": 0.2,
                        "degraded_s": None,
                    },
                    messages_refused=0,
                    streams={"ATTITUDE_QUATERNION": {"msg_id": 31, "requested_hz": 100.0, "measured_hz": None}},
                )
            ),  # fmt: skip
            "last_track": tracking_track(),
            "warnings": [{"code": "no_frames", "message": "check the camera"}],
            "withheld_because": ["gimbal_mismatch"],
            "camera_time_offset": {
                "estimate_ms": 1.5,
                "sigma_ms": None,
                "state": "estimating",
                "compensated_ms": 0.0,
                "blocks": 1,
                "frames": 40,
                "refused_blocks": 0,
                "excitation_mradps": None,
                "warn_threshold_ms": 20.0,
            },  # fmt: skip
            "rejected": {"frame_bad_magic": 2},
        },
    ],
    ids=["idle", "busy"],
)
def test_status_json_conforms_with_the_sections_the_service_adds(fields):
    status = idle_status(**fields)
    if not fields:  # the statistics of an idle daemon are RollingStats summaries too
        for key in ("processing_ms", "latency_ms", "pose_wait_ms"):
            status[key] = {"n": 0, "p50": None, "p99": None, "max": None}
    assert list(status) == [k for k, _ in STATUS_JSON_KEYS]
    schema = JSON_SCHEMAS[STATUS_SCHEMA]
    assert check(status, schema) == ["$: 'utc' is a required property"]  # the service's: added below
    status["utc"] = UtcClock().status()
    status["cpu"].update(gets_share=0.5, throttled_share=None, needs_share=0.5, throttled_periods=0, quota_cores=2.0)
    assert check(status, schema) == []


def test_the_status_sections_of_their_producers_conform():
    """The sections other components add (utc, camera, live view, ...) were bare objects in the schema a recording
    carries: a reader of the file learnt nothing of their keys (a helper's audit with the mcap reader found seven)."""
    from onboard.io.camera_protocol import MAV_CMD_SET_MESSAGE_INTERVAL, CameraCommand
    from onboard.io.live_view import LiveView, LiveViewConfig
    from tests.onboard.test_camera_protocol import _proto  # a CameraProtocol, the camera section's producer

    status = idle_status(processing_ms=SUMMARY, latency_ms=SUMMARY, pose_wait_ms=SUMMARY)
    status["utc"] = UtcClock().status()
    proto = _proto()  # a link with an interval of its own: link_intervals has an entry
    proto.handle(CameraCommand(MAV_CMD_SET_MESSAGE_INTERVAL, (275, -1, 0, 0, 0, 0, 0), 255, 190, via=(0, None)), 0, 0)
    cam = proto.status()
    assert cam["link_intervals"] == [
        {"link": "(0, None)", "image_status_interval_s": None, "geo_status_interval_s": 0.2}
    ]
    status["camera"] = {
        **cam, "endpoints": ["udpout:127.0.0.1:14550"], "tracker_mode": "auto", "tracker_holding": False,
        "last_selection": {"kind": "point", "accepted": False, "reason": "no tracked object in 40 px of (1,2)"},
    }  # fmt: skip
    status["guidance"] = {
        "in_loop": False, "updates": 3, "advised": 1, "published": 1, "publish_errors": 0, "skipped": {},
        "last_status": "advise", "last_manoeuvre": "weave", "setpoints": {"state": "off",
        "why": "guidance.enabled is false", "resumes": None, "sent": 0, "errors": 0, "stops": {}, "advice_ends": {"answer_no_gain": 1}},
    }  # fmt: skip
    status["live_view"] = LiveView(LiveViewConfig(), port=0).stats()  # not started: no socket
    assert check(status, JSON_SCHEMAS[STATUS_SCHEMA]) == []
    # a section's schema lists its keys: one missing, or one the producer adds that the schema does not declare
    del status["camera"]["tracker_holding"]
    status["utc"]["new_key"] = 1
    assert check(status, JSON_SCHEMAS[STATUS_SCHEMA]) == [
        "camera: 'tracker_holding' is a required property",
        "utc: Additional properties are not allowed ('new_key' was unexpected)",
    ]


def test_truth_json_conforms_to_its_schema_made_from_the_row():
    row = TruthRow(**{**{c: 1 for c in TRUTH_COLUMNS}, "target_u_px": math.nan, "target_v_px": math.nan})
    obj = truth_json(row)
    schema = truth_json_schema(TRUTH_SCHEMA)
    assert set(schema["properties"]) == set(obj) == set(schema["required"])
    assert "origin" not in obj and obj["target_u_px"] is None
    assert check(obj, schema) == []
    assert TRUTH_SCHEMA not in JSON_SCHEMAS  # the simulator hands its own to the recorder
