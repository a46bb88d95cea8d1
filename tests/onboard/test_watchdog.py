"""onboard.app.watchdog: each condition warned once (fake clock), naming what to check; active list follows the condition."""

from __future__ import annotations

import logging
import re

import pytest

from onboard.app.watchdog import Watchdog
from onboard.core.errors import InputError

KEY = "irtrack/uav1/ir/frame"
WHERE = "zenoh mode peer, connect tcp/10.0.0.2:7447, listen none, multicast scouting off"
CONN = "udpin:0.0.0.0:14540"


def _wd(**kw) -> Watchdog:
    return Watchdog(
        started_s=100.0, frame_key=KEY, zenoh_where=WHERE, mavlink_connection=CONN, camera_size_px=(640, 512), **kw
    )


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_no_frames_and_no_mavlink_warn_once_after_5_s(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i in range(49):  # 100.0 .. 104.8 s: quiet
            wd.step(100.0 + 0.1 * i, frames_in=0, mavlink_rx=0)
        assert _warnings(caplog) == [] and wd.active == ()
        for i in range(50, 200):  # 105 .. 120 s
            wd.step(100.0 + 0.1 * i, frames_in=0, mavlink_rx=0)
    msgs = _warnings(caplog)
    assert len(msgs) == 2
    frames = next(m for m in msgs if m.startswith("no_frames"))
    assert KEY in frames and "tcp/10.0.0.2:7447" in frames and "mode peer" in frames
    mav = next(m for m in msgs if m.startswith("no_mavlink"))
    assert CONN in mav
    assert {w.code for w in wd.active} == {"no_frames", "no_mavlink"}


def test_no_mavlink_on_a_connection_that_cannot_open_says_why_not_what_to_check_far_away(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i in range(60):
            wd.step(100.0 + 0.1 * i, frames_in=0, mavlink_rx=0, mavlink_open_error="[Errno 98] Address already in use")
    mav = next(m for m in _warnings(caplog) if m.startswith("no_mavlink"))
    assert CONN in mav and "cannot be opened ([Errno 98] Address already in use)" in mav
    assert "another program" in mav and "mavlink-router sends there" not in mav


def test_no_mavlink_while_signing_refuses_every_packet_says_the_keys_differ(caplog):
    """A sender signing with another key: every packet refused, and 'no_mavlink' was cleared by them (a walkthrough
    of deploy/README's signing: one mavlink_signature_bad line, then 'no_mavlink cleared'). Refused messages are not
    the autopilot heard, and the warning says why nothing is taken."""
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i in range(60):  # 6 s: packets arrive, every one refused by signing
            wd.step(100.0 + 0.1 * i, frames_in=0, mavlink_rx=0, mavlink_refused=10 * i)
    mav = next(m for m in _warnings(caplog) if m.startswith("no_mavlink"))
    assert CONN in mav and "signing refuses every packet" in mav and "key differs" in mav
    assert "no_mavlink" in {w.code for w in wd.active}


def test_inputs_clear_the_warnings_and_a_relapse_is_not_warned_again(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.step(106.0, frames_in=0, mavlink_rx=0)
        wd.step(107.0, frames_in=3, mavlink_rx=10)
        assert wd.active == ()
        wd.step(111.0, frames_in=3, mavlink_rx=10)  # 4 s quiet: fine
        assert wd.active == ()
        wd.step(112.5, frames_in=3, mavlink_rx=10)  # 5.5 s quiet: active again, no second WARNING
    assert {w.code for w in wd.active} == {"no_frames", "no_mavlink"}
    assert len(_warnings(caplog)) == 2
    assert "since the last one" in wd.active[0].message


def test_frames_arriving_in_time_never_warn(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i in range(300):
            wd.step(100.0 + 0.1 * i, frames_in=i + 1, mavlink_rx=2 * i + 1)
    assert _warnings(caplog) == [] and wd.active == ()


def test_frame_size_mismatch_names_both_sizes_once(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i in range(10):
            wd.frame_size(100.0 + i, 320, 256)
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and "320 x 256" in msgs[0] and "640 x 512" in msgs[0]
    assert [w.code for w in wd.active] == ["frame_size"]
    wd.frame_size(111.0, 640, 512)
    assert wd.active == ()


def test_a_zoom_the_pipeline_withheld_frames_for_is_warned_once_naming_it_and_cleared_when_it_stops(caplog):
    """The watchdog says what the pipeline decided (its hysteresis: onboard/pipeline/withholding.py), never a
    second decision of its own: a zoom 0.4 % off that the pipeline still withholds for is warned, a 2x zoom the
    pipeline did not withhold (not decided yet) is not."""
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i, zoom in enumerate([None, 1.0, 1.004]):
            wd.zoom(100.0 + i, zoom, False)
        wd.zoom(103.0, 2.0, False)
        assert wd.active == ()
        for i in range(10):
            wd.zoom(110.0 + i, 2.0, True)
        wd.zoom(121.0, 3.0, True)  # zoomed further: the message follows, no second WARNING
        assert [w.code for w in wd.active] == ["zoom_mismatch"] and "a zoom of 3x" in wd.active[0].message
        wd.zoom(121.5, 1.004, True)  # back within 0.5 % but not yet within 0.25 %: still withheld, still said
        assert [w.code for w in wd.active] == ["zoom_mismatch"] and "a zoom of 1.004x" in wd.active[0].message
        wd.zoom(122.0, 1.0, False)
        assert wd.active == ()
        wd.zoom(123.0, 0.5, True)  # zoomed out: raised again, logged at INFO only
        wd.zoom(124.0, None, False)  # a sender that stops stating it: taken as calibrated, as before the field
        assert wd.active == ()
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and msgs[0].startswith("zoom_mismatch: IR frames state a zoom of 2x")
    assert "camera.intrinsics are for 1.0x" in msgs[0] and "set the camera's zoom back to 1.0" in msgs[0]


@pytest.mark.parametrize(
    "values, warned",
    [
        ([5.0] * 60, True),  # 6 s above 3
        ([5.0] * 40, False),  # 4 s: not yet persistent
        ([5.0] * 30 + [1.0] + [5.0] * 30, False),  # broken run: counts again from the dip
        ([5.0] * 30 + [float("nan"), None] * 5 + [5.0] * 30, True),  # unknowns neither count nor reset
        ([1.0] * 100, False),
    ],
)
def test_camera_mismatch_needs_a_persistent_run(caplog, values, warned):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i, v in enumerate(values):
            wd.residual(100.0 + 0.1 * i, v)
    msgs = [m for m in _warnings(caplog) if m.startswith("camera_mismatch")]
    assert len(msgs) == (1 if warned else 0)


def test_watchdog_refuses_bad_settings():
    with pytest.raises(InputError, match="input_timeout_s"):
        _wd(input_timeout_s=0.0)


def test_gimbal_reports_with_a_fixed_mount_warn_once_naming_the_mount(caplog):
    # the watchdog's own level, not whatever root level an earlier in-process program left behind
    caplog.set_level(logging.WARNING, logger="onboard.app.watchdog")
    wd = _wd()
    wd.gimbal(1.0, gimballed=False, gimbal_reports=0, telemetry_since_s=0.5)
    assert "gimbal_mismatch" not in {w.code for w in wd.active}
    for n in (3, 10, 50):
        wd.gimbal(2.0, gimballed=False, gimbal_reports=n, telemetry_since_s=0.5)
    (w,) = [w for w in wd.active if w.code == "gimbal_mismatch"]
    assert "camera.mount.gimballed is false" in w.message
    assert (
        sum(
            "gimbal_mismatch" in r.getMessage() or "GIMBAL_DEVICE" in r.getMessage()
            for r in caplog.records
            if r.levelname == "WARNING"
        )
        == 1
    )


def test_a_gimballed_mount_without_gimbal_messages_warns_after_the_timeout():
    wd = _wd()
    wd.gimbal(3.0, gimballed=True, gimbal_reports=0, telemetry_since_s=None)  # no telemetry yet: nothing to say
    wd.gimbal(4.0, gimballed=True, gimbal_reports=0, telemetry_since_s=1.0)  # 3 s of telemetry: not yet
    assert "gimbal_mismatch" not in {w.code for w in wd.active}
    wd.gimbal(6.5, gimballed=True, gimbal_reports=0, telemetry_since_s=1.0)
    assert "gimbal_mismatch" in {w.code for w in wd.active}
    wd.gimbal(7.0, gimballed=True, gimbal_reports=4, telemetry_since_s=1.0)  # the gimbal speaks: cleared
    assert "gimbal_mismatch" not in {w.code for w in wd.active}


def test_gnss_dropout_is_named_from_the_frames_position_age_and_cleared_when_position_is_back(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for age_s in (0.0, 0.04, 0.3, None):  # fresh, normal lag, at the limit, a frame without a pose
            wd.navigation(101.0, age_s)
        assert wd.active == () and wd.changes == 0
        wd.navigation(101.5, 0.35)
        assert [w.code for w in wd.active] == ["gnss_dropout"] and wd.changes == 1
        wd.navigation(102.0, 1.2)  # still out: no second warning
        wd.navigation(102.5, 0.02)
    assert wd.active == () and wd.changes == 2
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and "GLOBAL_POSITION_INT" in msgs[0] and "dead-reckoned" in msgs[0]


def _offset(estimate_ms, sigma_ms=3.0, state="confident", compensated_ms=0.0, blocks=3):
    from onboard.estimation.time_offset import TimeOffsetEstimate

    return TimeOffsetEstimate(estimate_ms, sigma_ms, state, compensated_ms, blocks, 300, 0, 5.0)


def test_camera_time_offset_warns_when_confidently_above_the_threshold_and_clears_below(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.camera_time_offset(1.0, None, 20.0)  # estimator off
        wd.camera_time_offset(2.0, _offset(None, None, "unknown"), 20.0)
        wd.camera_time_offset(3.0, _offset(60.0, 30.0, "estimating"), 20.0)  # not beyond by two sigmas: nothing
        wd.camera_time_offset(4.0, _offset(24.0, 3.0), 20.0)  # above, but not by two sigmas
        assert wd.active == ()
        wd.camera_time_offset(5.0, _offset(50.0, 3.0, compensated_ms=50.0), 20.0)
        wd.camera_time_offset(6.0, _offset(-48.0, 3.0), 20.0)  # still active: warned once
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and msgs[0].startswith("camera_time_offset")
    assert "50 +- 3 ms late" in msgs[0] and "compensates 50 ms" in msgs[0]
    assert "zoom" in msgs[0]  # a zoom the sender does not state reads as a clock offset (P1 at 2x: 1312 ms)
    assert [w.code for w in wd.active] == ["camera_time_offset"]
    assert "early" in wd.active[0].message and "not compensated" in wd.active[0].message  # the newest estimate's
    wd.camera_time_offset(7.0, _offset(30.0, 10.0, "estimating"), 20.0)
    assert [w.code for w in wd.active] == ["camera_time_offset"]  # a doubtful estimate neither raises nor clears
    wd.camera_time_offset(8.0, _offset(5.0, 3.0), 20.0)
    assert wd.active == ()


def test_no_attitude_while_frames_and_mavlink_arrive_warns_after_2_s_and_clears_on_the_next_sample(caplog):
    """An autopilot that heartbeats but stopped streaming #31: only counted (pose_attitude_*) before.  The service
    checks every 0.5 s."""
    wd = _wd()
    n = 0

    def at(t_s: float, newest_us, gimballed: bool = False, frames: bool = True) -> list[str]:
        nonlocal n
        n += 1
        wd.step(100.0 + t_s, frames_in=n if frames else None, mavlink_rx=n, rotation=(newest_us, gimballed))
        return [w.code for w in wd.active]

    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        assert [at(0.5 * k, 500_000 * k) for k in range(1, 5)] == [[]] * 4  # new samples: 0.5 .. 2.0 s
        assert [at(0.5 * k, 2_000_000) for k in range(5, 8)] == [[]] * 3  # 0.5 .. 1.5 s without one
        assert at(4.0, 2_000_000) == ["no_attitude"]  # 2 s
        assert at(4.5, 2_000_000, gimballed=True) == ["no_attitude"]
        assert at(5.0, 4_900_000) == []
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and msgs[0].startswith("no_attitude") and "ATTITUDE_QUATERNION (#31) for 2 s" in msgs[0]
    # never any (a gimballed pod): 2 s after frames and MAVLink arrive
    wd2 = _wd()
    for k in range(1, 6):
        wd2.step(100.0 + 0.5 * k, frames_in=k, mavlink_rx=k, rotation=(None, True))
    assert [w.code for w in wd2.active] == ["no_attitude"] and "(#285) for 2 s (since start)" in wd2.active[0].message
    # frames silent: no_frames' business; the 2 s start again when they come back
    wd3 = _wd()
    for k in range(1, 12):
        wd3.step(100.0 + 0.5 * k, frames_in=1 if k < 8 else k, mavlink_rx=k, rotation=(1, False))
        assert "no_attitude" not in [w.code for w in wd3.active], k


def test_camera_clock_apart_warns_while_the_frames_clock_stands_apart_and_clears_when_they_agree(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.camera_clock(1.0, None)
        assert wd.active == ()
        wd.camera_clock(2.0, -2.04)
        wd.camera_clock(3.0, -2.01)  # still active: warned once
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and msgs[0].startswith("camera_clock_apart") and "-2.0 s from the autopilot's" in msgs[0]
    assert [w.code for w in wd.active] == ["camera_clock_apart"] and "no line of sight" in wd.active[0].message
    wd.camera_clock(4.0, None)
    assert wd.active == ()


def test_camera_time_offset_warns_on_a_significant_estimate_before_it_is_confident():
    wd = _wd()
    wd.camera_time_offset(1.0, _offset(50.0, 13.0, "estimating", blocks=2), 20.0)  # two blocks: sigma not trusted
    assert wd.active == ()
    wd.camera_time_offset(2.0, _offset(5.0, 13.0, "estimating", blocks=3), 20.0)  # below: nothing to clear either
    wd.camera_time_offset(3.0, _offset(50.0, 16.0, "estimating", blocks=3), 20.0)  # 50 - 2 x 16 = 18: not beyond
    assert wd.active == ()
    wd.camera_time_offset(4.0, _offset(50.0, 13.0, "estimating", blocks=3), 20.0)  # 50 - 2 x 13 = 24 > 20
    assert [w.code for w in wd.active] == ["camera_time_offset"] and "50 +- 13 ms late" in wd.active[0].message
    wd.camera_time_offset(5.0, _offset(12.0, 13.0, "estimating", blocks=4), 20.0)  # not confident: not cleared
    assert [w.code for w in wd.active] == ["camera_time_offset"]


def test_video_rate_warns_once_when_the_camera_is_off_video_fps_and_clears_when_they_agree(caplog):
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.video_rate(100.0, None, 30.0, 2_000_000)  # not measured yet: nothing said
        wd.video_rate(100.5, 25.0, 30.0, 2_000_000)  # within 20 %
        assert wd.active == ()
        for i in range(4):
            wd.video_rate(101.0 + 0.5 * i, 9.0, 30.0, 2_000_000)
        (w,) = wd.active
        assert w.code == "video_rate"
        assert "9.0 frames/s" in w.message and "video.fps is 30" in w.message and "0.30 x" in w.message
        assert "0.60 of 2.00 Mbit/s" in w.message
        wd.video_rate(104.0, 30.2, 30.0, 2_000_000)
        assert wd.active == ()
        wd.video_rate(104.5, 60.0, 30.0, 2_000_000)  # a faster camera: over the budget, warned again (INFO)
        assert [x.code for x in wd.active] == ["video_rate"] and "2.00 x" in wd.active[0].message
    assert len([m for m in _warnings(caplog) if m.startswith("video_rate")]) == 1


def test_an_autopilot_reboot_is_warned_with_its_count_and_held_30_s(caplog):
    """An autopilot that restarted in flight (its boot clock back: the pose buffer's reboot) was counted and logged,
    never in the status, as a message-by-message telemetry audit found."""
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.autopilot_reboots(100.0, 0)
        assert wd.active == ()
        wd.autopilot_reboots(101.0, 1)
        assert [w.code for w in wd.active] == ["autopilot_rebooted"] and "1 since start" in wd.active[0].message
        wd.autopilot_reboots(125.0, 1)
        assert [w.code for w in wd.active] == ["autopilot_rebooted"]  # held 30 s after the last
        wd.autopilot_reboots(126.0, 2)
        assert "2 since start" in wd.active[0].message
        wd.autopilot_reboots(155.0, 2)
        assert [w.code for w in wd.active] == ["autopilot_rebooted"]
        wd.autopilot_reboots(156.0, 2)
        assert wd.active == ()
    assert len([m for m in _warnings(caplog) if m.startswith("autopilot_rebooted")]) == 1


def test_the_daemons_own_parts_warn_estimator_restarts_a_stopped_or_lost_recording_and_the_liveness_file(caplog):
    """A helper's failure-injection audit: a worker killed, a recording stopped on a full disk or deleted mid-flight,
    the liveness file's folder removed; each showed only in counters or the log, the status's warnings empty."""
    wd = _wd()
    rec = {"stopped": None, "lost_files": [], "current_file": "/r/f.mcap"}
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.components(100.0, estimator_restarts=0, record=rec, health_error=None)
        assert wd.active == ()
        wd.components(101.0, estimator_restarts=1, record=rec)
        assert [w.code for w in wd.active] == ["estimator_restarted"] and "1 since start" in wd.active[0].message
        wd.components(120.0, estimator_restarts=1, record=rec)
        assert [w.code for w in wd.active] == ["estimator_restarted"]  # held 30 s after the last
        wd.components(131.0, estimator_restarts=1, record=rec)
        assert wd.active == ()
        full = {**rec, "stopped": "120 MB free, under record.min_free_mb (200)"}
        wd.components(132.0, record=full, health_error="/run/irtrack/alive: No such file or directory")
        codes = sorted(w.code for w in wd.active)
        assert codes == ["health_file", "record_stopped"]
        assert "120 MB free" in wd.active[[w.code for w in wd.active].index("record_stopped")].message
        lost = {**rec, "lost_files": ["/r/f.mcap"], "current_file": "/r/f.1.mcap"}
        wd.components(133.0, record=lost)
        codes = sorted(w.code for w in wd.active)
        assert codes == ["record_file_lost"]  # the stop was another run's state here; the health file touched again
        assert "/r/f.mcap" in wd.active[0].message and "goes on in /r/f.1.mcap" in wd.active[0].message
    assert len(_warnings(caplog)) == 4  # each code logged once


def test_record_stopped_names_the_file_it_ended_in_and_says_it_does_not_resume(caplog):
    """A helper's storage audit (a tmpfs filled mid-flight, then freed): the warning said why the recording stopped but
    not which file it ended in, where to free space, nor that freeing it brings no recording back in this run."""
    wd = _wd()
    stopped = "a write failed (No space left on device)"
    rec = {"stopped": stopped, "lost_files": [], "current_file": "/media/sd/f.3.mcap"}
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.components(100.0, record=rec)
        wd.components(101.0, record=rec)
    (w,) = wd.active
    assert w.code == "record_stopped"
    assert "No space left on device" in w.message and "/media/sd/f.3.mcap ends there" in w.message
    assert "does not resume in this run" in w.message and "/media/sd," in w.message and "restart" in w.message
    assert len(_warnings(caplog)) == 1


def test_a_recording_stopped_after_its_only_file_was_deleted_names_no_file_and_does_not_say_it_goes_on():
    """The same audit, the folder deleted and not made again: 'the recording goes on in None', and record_stopped named
    the deleted file as where the recording ends."""
    wd = _wd()
    rec = {"stopped": "a rotate failed (/sd/rec: Read-only file system)", "lost_files": ["/sd/rec/f.mcap"]}
    wd.components(100.0, record={**rec, "path": "/sd/rec/f.mcap", "current_file": None})
    msg = {w.code: w.message for w in wd.active}
    assert "None" not in msg["record_file_lost"] and "has stopped" in msg["record_file_lost"]
    assert "ends there" not in msg["record_stopped"] and "no file of it is left" in msg["record_stopped"]
    assert "make writable) /sd/rec," in msg["record_stopped"]
    wd = _wd()  # a disk with no room for the first file's header: no file made, none lost
    wd.components(100.0, record={"stopped": "no room to start it (No space left on device)", "lost_files": [],
                                 "path": "/sd/rec/f.mcap", "current_file": None})  # fmt: skip
    (w,) = wd.active
    assert "nothing of it was written" in w.message and "make writable) /sd/rec," in w.message


def test_stream_rate_low_names_the_message_and_both_rates_once(caplog):
    from onboard.core.stream_rate import REASK_S, StreamRate

    wd = _wd()
    slow = [StreamRate(31, "ATTITUDE_QUATERNION", 100.0, 20.4, 10.0)]
    with caplog.at_level(logging.INFO):
        wd.stream_rates(20.0, slow)
        wd.stream_rates(21.0, [StreamRate(31, "ATTITUDE_QUATERNION", 100.0, 19.8, 10.0)])
    (w,) = wd.active
    assert w.code == "stream_rate_low"
    assert "ATTITUDE_QUATERNION (#31) arrives at 19.8 Hz, 100 Hz requested" in w.message
    assert f"asked again every {REASK_S:g} s while slow" in w.message  # what the link really does, not a copy
    assert sum("stream_rate_low" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records) == 1
    wd.stream_rates(22.0, [])
    assert wd.active == ()


def test_autopilot_duplicate_names_both_addresses_and_the_id_once(caplog):
    from onboard.io.mavlink_peer import DuplicateSender

    wd = _wd()
    dup = DuplicateSender(1, 1, ("10.0.0.5", 14580), ("10.0.0.6", 14580), 20.0)
    with caplog.at_level(logging.INFO):
        for k in range(10):  # raised and held while the second sender is heard, whatever its telemetry does
            wd.autopilot_duplicate(20.0 + k, [dup])
    (w,) = wd.active
    assert w.code == "autopilot_duplicate"
    assert "10.0.0.6:14580 heartbeats as MAVLink system 1 component 1, which 10.0.0.5:14580 is" in w.message
    assert "MAV_SYS_ID" in w.message and "own port" in w.message
    assert sum("autopilot_duplicate" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records) == 1
    wd.autopilot_duplicate(31.0, [])
    assert wd.active == ()


def test_autopilot_duplicate_says_the_followed_one_is_silent():
    """The followed address silent past a missed heartbeat when the second heartbeats: a router restarted on a new
    port reads so; the warning says it beside the two-vehicles advice."""
    from onboard.io.mavlink_peer import DuplicateSender

    wd = _wd()
    wd.autopilot_duplicate(20.0, [DuplicateSender(1, 1, ("127.0.0.1", 42710), ("127.0.0.1", 51633), 20.0, 3.0)])
    (w,) = wd.active
    assert "127.0.0.1:42710 silent for 3.0 s: a router restarted on a new port" in w.message
    assert "mavlink.heartbeat_timeout_s" in w.message and "MAV_SYS_ID" in w.message


def test_frame_size_stays_raised_while_a_second_camera_of_another_size_alternates_with_the_configured_one(caplog):
    """Raised by each 320 x 256 frame and cleared by each 640 x 512 one, it changed 50 times a second: a status
    message and a log line each time.  It clears once FRAME_SIZE_CLEAR_S pass without a frame of another size."""
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for i in range(60):  # two cameras at 30 Hz, interleaved, for a second
            wd.frame_size(100.0 + i / 60, *((320, 256) if i % 2 else (640, 512)))
        changes = wd.changes
        assert [w.code for w in wd.active] == ["frame_size"] and changes == 1
        assert len(caplog.records) == 1  # the warning, no "cleared" / "again" after it
        wd.frame_size(101.5, 640, 512)  # 0.52 s after the last other frame: held
        assert [w.code for w in wd.active] == ["frame_size"]
        wd.frame_size(102.0, 640, 512)
    assert wd.active == () and wd.changes == changes + 1


def test_frames_without_pose_while_the_telemetry_arrives_warn_within_2_s_naming_the_stamps_lead_and_clear():
    """Frames stamped 200 ms ahead of the telemetry (under the clock-step threshold, past the extrapolation): no pose
    on any frame, attitude arriving, and only the pose_* counters said so.  Frames at 30 Hz, the service's step at
    2 Hz."""
    wd = _wd()
    n = 0

    def run(t0_s: float, t1_s: float, *, has_pose: bool, lead_s: float | None, rotation_moves: bool = True):
        nonlocal n
        codes = []
        for k in range(int(round((t1_s - t0_s) * 30))):
            t_s = t0_s + k / 30
            n += 1
            if k % 15 == 0:
                newest_us = int(t_s * 1e6) if rotation_moves else 1
                wd.step(100.0 + t_s, frames_in=n, mavlink_rx=n, rotation=(newest_us, False))
            wd.frame_pose(100.0 + t_s, has_pose, lead_s)
            codes.append([w.code for w in wd.active])
        return codes

    assert run(0.0, 2.0, has_pose=True, lead_s=-0.01) == [[]] * 60
    codes = run(2.0, 6.0, has_pose=False, lead_s=0.196)
    assert codes[:59] == [[]] * 59 and codes[60:] == [["frames_without_pose"]] * 60  # raised at 2 s
    msg = wd.active[0].message
    assert "196 ms ahead of the telemetry" in msg and "clock sync" in msg and "time_offset" in msg, msg
    assert run(6.0, 7.0, has_pose=True, lead_s=0.0) == [[]] * 30  # the first frame with a pose clears it
    # behind: named so
    run(7.0, 9.5, has_pose=False, lead_s=-0.7)
    assert "700 ms behind" in wd.active[0].message
    run(9.5, 10.0, has_pose=True, lead_s=0.0)
    # the rotation streams stopped: no_attitude's business, not this one's
    codes = run(10.0, 14.0, has_pose=False, lead_s=3.0, rotation_moves=False)
    assert all("frames_without_pose" not in c for c in codes) and codes[-1] == ["no_attitude"]
    # another warning that names the cause: this one clears and stays silent
    wd2 = _wd()
    for k in range(90):
        if k % 15 == 0:
            wd2.step(100.0 + k / 30, frames_in=k + 1, mavlink_rx=k + 1, rotation=(k + 1, False))
        wd2.frame_pose(100.0 + k / 30, False, 0.2)
    assert [w.code for w in wd2.active] == ["frames_without_pose"]
    wd2.camera_clock(103.0, 5.0)
    wd2.frame_pose(103.0, False, 5.0)
    assert [w.code for w in wd2.active] == ["camera_clock_apart"]


def test_two_senders_interleaving_on_the_frame_key_are_warned_within_a_second_and_cleared_after_they_stop(caplog):
    """Two cameras alternating their frames on the key (ArrivalGaps.returns growing 60 a second) were warned by
    nothing: raised at the first check that sees them, held while they go on, cleared FRAME_SOURCES_CLEAR_S after;
    a sender restarting (one return, or two with a late frame) is not two senders."""
    from onboard.app.watchdog import FRAME_SOURCES_CLEAR_S

    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        returns = 0
        for i in range(20):  # 10 s of one sender that restarts twice, a late frame of the old numbering each time
            returns += 2 if i in (4, 14) else 0
            wd.frame_sources(100.0 + 0.5 * i, returns)
        assert wd.active == ()
        for i in range(20, 32):  # a second camera: 30 returns each half second
            returns += 30
            wd.frame_sources(100.0 + 0.5 * i, returns)
            assert [w.code for w in wd.active] == ["frame_sources"]
        t_s = 100.0 + 0.5 * 31
        for i in range(1, 40):  # the second camera gone
            wd.frame_sources(t_s + 0.5 * i, returns)
            if 0.5 * i < FRAME_SOURCES_CLEAR_S:
                assert [w.code for w in wd.active] == ["frame_sources"]
        assert wd.active == ()
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and msgs[0].startswith("frame_sources: two or more senders publish frames on " + KEY)
    assert re.search(r"\(\d+ returns to another numbering in [\d.]+ s\)", msgs[0]) and "deploy/" in msgs[0]


def test_frames_before_the_telemetry_starts_do_not_count_towards_frames_without_pose(caplog):
    """The camera up 3 s before the autopilot's link (frames with no telemetry to stand against), then the first
    frames after it gets no pose while the buffer fills: the 2 s ran from the run's first frame, so the first frame
    looked up against telemetry raised frames_without_pose at once, a WARNING at an ordinary start.  The 2 s count
    only frames without a pose while the telemetry arrives and no other warning names the cause."""
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for k in range(90):  # 3 s at 30 Hz: no telemetry yet
            wd.frame_pose(100.0 + k / 30, False, None)
        for k in range(90, 96):  # the telemetry starts; the first six frames still get no pose
            t_s = 100.0 + k / 30
            wd.step(t_s, frames_in=k + 1, mavlink_rx=k - 89, rotation=(int(t_s * 1e6), False))
            wd.frame_pose(t_s, False, 0.05)
        assert "frames_without_pose" not in [w.code for w in wd.active]
        for k in range(96, 200):  # and then none for more than 2 s: raised
            t_s = 100.0 + k / 30
            wd.step(t_s, frames_in=k + 1, mavlink_rx=k - 89, rotation=(int(t_s * 1e6), False))
            wd.frame_pose(t_s, False, 0.2)
        assert "frames_without_pose" in [w.code for w in wd.active]
    (msg,) = _warnings(caplog)
    assert msg.startswith("frames_without_pose: no pose for the last 61 frames (2 s)"), (
        msg
    )  # from the telemetry's start


def test_no_attitude_says_the_samples_arrive_refused_when_the_pose_buffer_rejects_them(caplog):
    """#31 with a quaternion of norm 1.02 arrives at 100 Hz and every one is refused (attitude_not_unit): the
    warning said 'check the autopilot's message rates', the one thing that was fine."""
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.step(100.5, frames_in=1, mavlink_rx=1, rotation=(500_000, False), rejected={"pose_extrapolated": 7})
        for k in range(2, 7):  # 1.0 .. 3.0 s: refused, 50 a step; a normal count grows alongside
            rejected = {"pose_extrapolated": 7 + k, "attitude_not_unit": 50 * (k - 1), "attitude_resumed": 1}
            wd.step(100.0 + 0.5 * k, frames_in=k, mavlink_rx=k, rotation=(500_000, False), rejected=rejected)
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and msgs[0].startswith("no_attitude"), msgs
    assert "refuses" in msgs[0] and "attitude_not_unit 200" in msgs[0], msgs[0]
    assert "pose_extrapolated" not in msgs[0] and "attitude_resumed" not in msgs[0] and "rates" not in msgs[0]


def test_gnss_dropout_says_the_samples_arrive_refused_when_the_pose_buffer_rejects_them(caplog):
    """#33 with its altitude in m where mm go (x1000: 70 km) is refused (position_alt_out_of_range): the warning said
    'check the GNSS', which was fine; refusals before the last fresh position are not named."""
    wd = _wd()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.navigation(101.0, 0.02, rejected={"position_jump": 1})
        wd.navigation(101.2, 0.22, rejected={"position_jump": 1, "position_alt_out_of_range": 5})  # no new sample
        wd.navigation(101.4, 0.35, rejected={"position_jump": 1, "position_alt_out_of_range": 8})
        wd.navigation(101.5, 0.45, rejected={"position_jump": 1, "position_alt_out_of_range": 11})
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and msgs[0].startswith("gnss_dropout"), msgs
    assert "refuses" in msgs[0] and "position_alt_out_of_range 8" in msgs[0] and "position_jump" not in msgs[0]
    assert "position_alt_out_of_range 11" in wd.active[0].message
    wd.navigation(102.0, 0.02, rejected={"position_jump": 1, "position_alt_out_of_range": 11})
    wd.navigation(103.0, 0.5, rejected={"position_jump": 1, "position_alt_out_of_range": 11})  # a silent stream
    assert "refuses" not in wd.active[0].message and "check the GNSS" in wd.active[0].message


def test_a_session_that_dials_and_has_no_router_or_peer_is_warned_after_5_s_and_cleared_by_one(caplog):
    """The router the daemon dials killed mid-flight: the daemon tracked on, its tracks reaching no one, and nothing
    said so (the live-view and zenoh audit)."""
    wd = _wd()
    connect = ("tcp/10.0.0.9:7447",)
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        wd.zenoh_links(100.0, connect, 1)
        for i in range(49):  # 4.8 s with none: not yet
            wd.zenoh_links(101.0 + 0.1 * i, connect, 0)
        assert wd.active == ()
        wd.zenoh_links(106.0, connect, 0)
        (msg,) = _warnings(caplog)
        assert msg.startswith("zenoh_unconnected: no zenoh router or peer for 5 s (connect tcp/10.0.0.9:7447)")
        wd.zenoh_links(107.0, connect, 0)
        assert len(_warnings(caplog)) == 1 and [w.code for w in wd.active] == ["zenoh_unconnected"]
        wd.zenoh_links(107.5, connect, 1)
        assert wd.active == ()
        wd.zenoh_links(108.0, connect, None)  # not known: no warning, ever
        wd.zenoh_links(120.0, (), 0)  # listening only: peers come when they will (no_frames says it)
        assert wd.active == ()


def test_name_clash_is_warned_once_while_another_daemons_status_arrives_and_clears_after_it_stops(caplog):
    from onboard.app.watchdog import NAME_CLASH_CLEAR_S

    wd = _wd()
    key = "irtrack/uav1/status"
    wd.name_clash(10.0, None, key)
    assert wd.active == ()
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for k in range(5):  # its statuses keep coming, each heard just before the check
            wd.name_clash(11.0 + k, (11.0 + k - 0.2, f"its status says up {k} s"), key)
        (w,) = wd.active
        assert w.code == "name_clash"
        assert key in w.message and "up 4 s" in w.message  # the newest status's words
        assert "its own vehicle name" in w.message and "--vehicle" in w.message
        wd.name_clash(14.8 + NAME_CLASH_CLEAR_S - 0.1, (14.8, "its status says up 4 s"), key)
        assert [x.code for x in wd.active] == ["name_clash"]  # held between statuses
        wd.name_clash(14.8 + NAME_CLASH_CLEAR_S + 0.1, (14.8, "its status says up 4 s"), key)
        assert wd.active == ()
    assert sum(m.startswith("name_clash:") for m in _warnings(caplog)) == 1


@pytest.mark.parametrize(
    ("payload", "words"),
    [
        (
            b'{"schema": "irtrack.status/1", "uptime_s": 12.4, "frames": {"in": 300}, "link": {"state": "connected"}}',
            "its status says up 12 s, 300 frames in, MAVLink connected",
        ),
        (b'{"schema": "irtrack.status/1", "uptime_s": "x", "frames": [], "link": 3}', "a status without uptime"),
        (b'{"schema": "other"}', "not an irtrack.status/1"),
        (b"\xff\xfe", "not JSON"),
        (b"[" * 100_000, "not JSON"),
        (b" " * (300 * 1024), "a payload of 307200 bytes"),
        # an integer too large for a float: math.isfinite and the '.0f' format raised OverflowError
        pytest.param(
            b'{"schema": "irtrack.status/1", "uptime_s": 1' + b"0" * 400 + b', "frames": {"in": 3}}',
            "its status says 3 frames in",
            id="uptime_an_integer_too_large_for_a_float",
        ),
    ],
)
def test_another_daemons_status_is_put_in_words_whatever_it_holds(payload, words):
    from onboard.app.status_sections import twin_words

    assert words in twin_words(payload)
