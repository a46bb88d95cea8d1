"""Output policy of irtrack.track/2: the line of sight with every pose, positions graded not
gated, #276 only for observable positions; and the camera-mismatch warning fed by the pipeline's residuals."""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np
import pytest

from onboard.app.estimator_worker import ThreadedEstimator
from onboard.app.service import MISMATCH_WARNINGS
from onboard.app.watchdog import Watchdog
from onboard.core.errors import InputError
from onboard.core.frames import CameraMount, PinholeIntrinsics, quat_from_euler, quat_from_rotmat, rotmat_from_quat
from onboard.core.pose import PoseBuffer
from onboard.core.track import (
    TRACK_SCHEMA,
    LineOfSight,
    Track,
    line_of_sight_ned,
    track_from_json,
    track_to_bytes,
    track_to_json,
)
from onboard.estimation.map_estimator import across_range_widened
from onboard.io.mavlink_wire import geo_status_fields
from onboard.pipeline.frame_pipeline import FramePipeline, make_tracker
from tests.fakes import idle_status, positioned_track, single_chain
from tests.onboard.test_pipeline import Rig

LOS_TOL_DEG = 0.05  # centroid error ~0.03 px at f = 765 px is ~0.002 deg; the pointing is exact
SIGMA_REL_TOL = 1e-6
LOS_KEYS = ("los_ned", "los_az_deg", "los_el_deg", "los_sigma_az_deg", "los_sigma_el_deg", "camera_ned_m")


def _az_el_deg(d_ned) -> tuple[float, float]:
    n, e, d = d_ned
    return math.degrees(math.atan2(e, n)), math.degrees(math.atan2(-d, math.hypot(n, e)))


def test_schema_is_version_2():
    assert TRACK_SCHEMA == "irtrack.track/2"


def test_line_of_sight_is_published_with_every_pose_even_without_an_estimate():
    rig = Rig(estimator=None)  # no 3-D at all
    for tr in rig.run(12):
        j = track_to_json(tr)
        assert j["ned_m"] is None and all(j[key] is not None for key in LOS_KEYS)
        ts = (tr.time_boot_us - rig.scene.boot_us0) / 1e6
        p_cam, _ = rig.scene.camera(ts)
        truth = rig.scene.target(ts)[0] - p_cam
        az, el = _az_el_deg(truth)
        assert abs(j["los_az_deg"] - az) < LOS_TOL_DEG and abs(j["los_el_deg"] - el) < LOS_TOL_DEG
        assert el > 0  # the target flies 15 m above the camera: elevation positive up
        assert np.allclose(j["los_ned"], truth / np.linalg.norm(truth), atol=math.radians(LOS_TOL_DEG))
        assert np.allclose(j["camera_ned_m"], p_cam, atol=1e-3)
        back = track_from_json(track_to_bytes(tr))
        assert back.los is not None and back.los.azimuth_deg == pytest.approx(j["los_az_deg"])


def test_no_line_of_sight_without_a_pose():
    rig = Rig(estimator=None)
    tr = rig.pipe.process(rig.scene.frame(0), 0)  # no telemetry fed
    j = track_to_json(tr)
    assert j["u_px"] is not None and not j["pose_valid"] and all(j[key] is None for key in LOS_KEYS)
    assert "los_sigma_bias_deg" in j and j["los_sigma_bias_deg"] is None


@pytest.mark.parametrize("bias_deg", [0.3, 0.0])
def test_each_line_of_sight_states_the_attitude_bias_share_of_its_sigma_as_configured(bias_deg):
    """``los_sigma_bias_deg`` is the daemon's ``estimator.attitude_bias_sigma_deg`` on every frame with a line of
    sight (a fleet fusion takes it as the vehicle's prior), null on one without, and survives the JSON round trip;
    the sigmas hold it (white and bias in quadrature)."""
    config = single_chain()
    config = dataclasses.replace(
        config, estimator=dataclasses.replace(config.estimator, attitude_bias_sigma_deg=bias_deg)
    )
    rig = Rig(estimator=None, config=config)
    assert track_to_json(rig.pipe.process(rig.scene.frame(0), 0))["los_sigma_bias_deg"] is None  # no pose yet
    tracks = rig.run(6, start=1)
    for tr in tracks:
        j = track_to_json(tr)
        assert j["los_sigma_bias_deg"] == pytest.approx(bias_deg, rel=1e-12)
        assert min(j["los_sigma_az_deg"], j["los_sigma_el_deg"]) >= bias_deg
        assert track_from_json(track_to_bytes(tr)).los.sigma_bias_deg == pytest.approx(bias_deg, rel=1e-12)


def test_a_track_without_the_bias_share_reads_as_not_stated_and_a_bad_one_is_refused_by_name():
    j = track_to_json(Rig(estimator=None).run(2)[-1])
    del j["los_sigma_bias_deg"]  # a daemon before the key
    assert track_from_json(j).los is not None and track_from_json(j).los.sigma_bias_deg is None
    for bad in (-0.1, 91.0, "0.1", True):
        with pytest.raises(InputError, match="sigma_bias_deg"):
            track_from_json({**j, "los_sigma_bias_deg": bad})


def test_line_of_sight_sigma_follows_the_documented_formula():
    K = PinholeIntrinsics.vue_pro_640()
    s_px, s_att = 0.3, math.radians(math.hypot(0.05, 0.1))
    # a camera looking north and 30 deg up (camera z forward, y down): the principal point's ray
    q = quat_from_euler(0.0, math.radians(30.0), 0.0)  # body FRD pitched up
    R_body_from_cam = rotmat_from_quat(CameraMount().q_body_from_cam())
    q_ned_from_cam = quat_from_rotmat(rotmat_from_quat(q) @ R_body_from_cam)
    los = line_of_sight_ned((K.cx_px, K.cy_px), K, q_ned_from_cam, (1.0, 2.0, -3.0), s_px, s_att)
    assert los.azimuth_deg == pytest.approx(0.0, abs=1e-9) and los.elevation_deg == pytest.approx(30.0, abs=1e-9)
    s = math.sqrt((s_px / K.fx_px) ** 2 + s_att**2)  # on the axis: isotropic angular noise
    assert los.sigma_elevation_deg == pytest.approx(math.degrees(s), rel=SIGMA_REL_TOL)
    assert los.sigma_azimuth_deg == pytest.approx(math.degrees(s) / math.cos(math.radians(30.0)), rel=SIGMA_REL_TOL)
    # more pixel noise, more sigma; no noise, no sigma
    assert (
        line_of_sight_ned((K.cx_px, K.cy_px), K, q_ned_from_cam, (0, 0, 0), 3.0, s_att).sigma_elevation_deg
        > los.sigma_elevation_deg
    )
    zero = line_of_sight_ned((K.cx_px, K.cy_px), K, q_ned_from_cam, (0, 0, 0), 0.0, 0.0)
    assert zero.sigma_azimuth_deg == 0.0 and zero.sigma_elevation_deg == 0.0


def test_line_of_sight_validation_names_the_field():
    with pytest.raises(Exception, match="unit vector"):
        LineOfSight((1.0, 1.0, 0.0), 45.0, 0.0, 0.1, 0.1, (0.0, 0.0, 0.0))
    los = LineOfSight((1.0, 0.0, 0.0), 0.0, 0.0, 0.1, 0.1, (0.0, 0.0, 0.0))
    with pytest.raises(Exception, match="Track.los needs a pose"):
        Track(vehicle="uav1", seq=1, time_boot_us=1, state="searching", los=los)


def test_positions_are_published_when_finite_with_observable_false():
    rig = Rig(ready_after=1, observable=False)
    tracks = rig.run(4)
    last = tracks[-1]
    assert last.has_position and not last.observable and last.los is not None
    j = track_to_json(last)
    # the fake's diag(4, 9, 1), widened across the line of sight for the range it does not know
    ts = (rig.scene.t_us(3) - rig.scene.boot_us0) / 1e6
    los = np.asarray(j["ned_m"]) - rig.scene.camera(ts)[0]
    r = float(np.linalg.norm(los))
    C = across_range_widened(np.diag([4.0, 9.0, 1.0]), los / r, r)
    assert j["ned_m"] is not None and j["observable"] is False
    np.testing.assert_allclose(j["sigma_ned_m"], np.sqrt(np.diag(C)), rtol=1e-6)
    assert geo_status_fields(last) is None  # #276: not for an unobservable position
    f = geo_status_fields(last, observable_only=False)
    assert f["h_acc_m"] == pytest.approx(math.sqrt(C[0, 0] + C[1, 1])) and f["v_acc_m"] == pytest.approx(
        math.sqrt(C[2, 2])
    )
    assert f["dist_m"] == pytest.approx(j["range_m"])


def _mismatched_rig(pitch_deg: float) -> Rig:
    """Frames and telemetry of the scene's (identity) mount, a pipeline configured with another."""
    rig = Rig(ready_after=5)  # the fake estimator returns the true target: an estimate the frames agree with
    mount = CameraMount.from_euler_deg((0.0, 0.0, 0.0), 0.0, pitch_deg, 0.0)
    rig.pose = PoseBuffer(mount=mount, config=rig.config.pose, origin=rig.scene.origin, counter=rig.counter)
    rig.pipe = FramePipeline(rig.config, rig.pose, make_tracker(rig.config), rig.est, counter=rig.counter)
    return rig


def _watch(rig: Rig, n: int, caplog) -> tuple[Watchdog, list]:
    wd = Watchdog(
        started_s=0.0,
        frame_key="irtrack/uav1/ir/frame",
        zenoh_where="peer",
        mavlink_connection="udpin:x",
        camera_size_px=(640, 512),
    )
    rr = []
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for k in range(n):
            tr = rig.step(k)
            now_s = (tr.time_boot_us - rig.scene.boot_us0) / 1e6  # fake clock: the frames' own
            wd.residual(now_s, tr.residual_rms_norm)
            rr.append(tr.residual_rms_norm)
    return wd, rr


def test_mount_mismatch_triggers_the_camera_warning_exactly_once(caplog):
    wd, rr = _watch(_mismatched_rig(-10.0), 240, caplog)  # 8 s
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "camera_mismatch" in warnings[0].getMessage()
    assert "camera.mount" in warnings[0].getMessage()
    assert [w.code for w in wd.active] == ["camera_mismatch"]
    assert min(r for r in rr if r is not None) > 3


def test_matching_mount_raises_no_camera_warning(caplog):
    wd, rr = _watch(_mismatched_rig(0.0), 240, caplog)
    assert not [r for r in caplog.records if r.levelno == logging.WARNING] and wd.active == ()
    assert max(r for r in rr if r is not None) < 1


def test_while_the_camera_mismatches_no_direction_or_position_goes_out_and_the_residual_still_does(caplog):
    rig = _mismatched_rig(-10.0)
    wd = Watchdog(
        started_s=0.0, frame_key="k", zenoh_where="peer", mavlink_connection="udpin:x", camera_size_px=(640, 512)
    )
    tracks = []
    for k in range(240):  # 8 s; the daemon's order: the warnings set the pipeline, then the frame
        rig.pipe.withheld_because = tuple(w.code for w in wd.active if w.code in MISMATCH_WARNINGS)
        tr = rig.step(k)
        wd.residual((tr.time_boot_us - rig.scene.boot_us0) / 1e6, tr.residual_rms_norm)
        tracks.append(tr)
    first = next(k for k, tr in enumerate(tracks) if tr.los is None)
    assert 0 < first < 240 and rig.pipe.withheld_because == ("camera_mismatch",)
    assert tracks[first - 1].los is not None and tracks[first - 1].has_position  # before the warning: published
    after = tracks[first:]
    assert all(tr.los is None and not tr.has_position and tr.pose_valid for tr in after)
    assert all(tr.u_px is not None and tr.residual_rms_norm is not None for tr in after)  # image fields, residual
    assert [w.code for w in wd.active] == ["camera_mismatch"]  # still judged on the residuals
    n_resets = rig.pipe.estimator_resets
    rig.pipe.withheld_because = ()  # cleared: published again, from a fresh window
    tr = rig.step(240)
    assert tr.los is not None and rig.pipe.estimator_resets == n_resets + 1


def test_the_status_says_whether_geometry_is_withheld_and_why():
    kw = dict(frames_in=1, frames_processed=1, tracks_published=1, estimator="inline")
    unzoomed = {"zoom": None, "frames_withheld_zoom": 0}
    assert idle_status(**kw)["geometry"] == {"output": "published", "withheld_because": [], **unzoomed}
    got = idle_status(**kw, withheld_because=("gimbal_mismatch",))["geometry"]
    assert got == {"output": "withheld", "withheld_because": ["gimbal_mismatch"], **unzoomed}
    got = idle_status(**kw, withheld_because=("zoom_mismatch",), zoom=2.0, frames_withheld_zoom=7)["geometry"]
    assert got == {"output": "withheld", "withheld_because": ["zoom_mismatch"], "zoom": 2.0, "frames_withheld_zoom": 7}


ZOOM_FROM, ZOOM_UNTIL = 20, 40  # frames stating 2x: [ZOOM_FROM, ZOOM_UNTIL)


def test_frames_stating_another_zoom_withhold_direction_and_position_from_the_first_and_not_the_2d_track(caplog):
    """IRF1's zoom field: 2x from frame 20 on (P1-like scene, the daemon's order: the watchdog's warnings set the
    pipeline, then the frame, then the watchdog is fed).  The frame that first states it already goes out without
    a line of sight or a position, the 2-D track goes on, no row reaches the estimator, the warning is raised once
    naming the zoom, and the first frame back at 1.0 is published again from a fresh window."""
    rig = Rig(ready_after=3)
    wd = Watchdog(
        started_s=0.0, frame_key="k", zenoh_where="peer", mavlink_connection="udpin:x", camera_size_px=(640, 512)
    )
    tracks, active = [], []
    with caplog.at_level(logging.INFO, logger="onboard.app.watchdog"):
        for k in range(ZOOM_UNTIL + 10):
            rig.pipe.withheld_because = tuple(w.code for w in wd.active if w.code in MISMATCH_WARNINGS)
            zoom = 2.0 if ZOOM_FROM <= k < ZOOM_UNTIL else 1.0
            rig.feed_until(rig.scene.t_us(k) + 45_000)
            adds = sum(c == "add" for c, _ in rig.est.calls)
            tr = rig.pipe.process(dataclasses.replace(rig.scene.frame(k), zoom=zoom), 0)
            added = sum(c == "add" for c, _ in rig.est.calls) - adds
            wd.zoom((tr.time_boot_us - rig.scene.boot_us0) / 1e6, rig.pipe.last_zoom, rig.pipe.zoom_withheld)
            tracks.append((tr, added, rig.pipe.withheld_because))
            active.append([w.code for w in wd.active])
    before, zoomed, after = tracks[:ZOOM_FROM], tracks[ZOOM_FROM:ZOOM_UNTIL], tracks[ZOOM_UNTIL:]
    assert all(tr.los is not None and added == 1 for tr, added, _ in before) and before[-1][0].has_position
    for tr, added, why in zoomed:
        assert tr.los is None and not tr.has_position and tr.pose_valid and why == ("zoom_mismatch",)
        assert tr.u_px is not None and tr.measurement_valid  # the image chain is zoom-agnostic: tracked on
        assert added == 0  # no ray made with the wrong focal length reaches the estimator
    assert active[ZOOM_FROM - 1] == [] and all(a == ["zoom_mismatch"] for a in active[ZOOM_FROM:ZOOM_UNTIL])
    assert all(a == [] for a in active[ZOOM_UNTIL:])
    assert rig.pipe.frames_withheld_zoom == ZOOM_UNTIL - ZOOM_FROM and rig.pipe.last_zoom == 1.0
    assert all(tr.los is not None and why == () for tr, _, why in after)
    assert sum(c == "reset" for c, _ in rig.est.calls) == 1  # back at 1.0: a fresh window, as a cleared mismatch
    assert after[-1][0].has_position
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name.endswith("watchdog")]
    assert len(warned) == 1 and warned[0].startswith("zoom_mismatch: ")
    for words in ("2x", "camera.intrinsics are for 1.0x", "set the camera's zoom back", "calibrate"):
        assert words in warned[0], words
    assert any(r.getMessage() == "zoom_mismatch cleared" for r in caplog.records)


def test_the_first_frame_back_at_the_calibrated_zoom_starts_the_fresh_window_with_its_own_row(caplog):
    """The estimator starts again before the first frame back at 1.0 is added, not after: its row is the new window's
    first (not dropped with the old window), and the estimator worker is not asked for the old window's estimate,
    as old as the frames withheld, which it withheld as stale after a gap in the frames that never was (counted
    ``estimate_after_gap``).  Before, the frame's row went to the old window, the reset came after it, and the
    daemon logged ``estimate_after_gap`` and "estimator reset: configuration mismatch cleared"."""
    rig = Rig(ready_after=3)
    # the daemon's worker, answering no frame in time (result_wait_s 0): each frame gets the newest estimate carried
    worker = ThreadedEstimator(rig.est, rig.counter, result_wait_s=0.0, max_extrapolation_s=0.3)
    pipe = FramePipeline(rig.config, rig.pose, make_tracker(rig.config), worker, counter=rig.counter)
    try:
        with caplog.at_level(logging.INFO, logger="onboard.pipeline.frame_pipeline"):
            for k in range(ZOOM_UNTIL + 5):
                rig.feed_until(rig.scene.t_us(k) + 45_000)
                zoom = 2.0 if ZOOM_FROM <= k < ZOOM_UNTIL else 1.0
                pipe.process(dataclasses.replace(rig.scene.frame(k), zoom=zoom), 0)
                time.sleep(0.005)  # the worker answers between frames, as the daemon's does
    finally:
        worker.close()
    assert rig.counter["estimate_after_gap"] == 0  # 20 frames (0.67 s) withheld are no gap in the frames
    kinds = [c for c, _ in rig.est.calls]
    assert kinds.count("reset") == 1
    last_zoom_free, back = (rig.scene.t_us(k) / 1e6 for k in (ZOOM_FROM - 1, ZOOM_UNTIL))
    at = kinds.index("reset")
    assert rig.est.calls[at - 1 : at + 2] == [
        ("add", pytest.approx(last_zoom_free)),
        ("reset", pytest.approx(math.nan, nan_ok=True)),
        ("add", pytest.approx(back)),
    ]
    assert "estimator reset: zoom_mismatch cleared" in [r.getMessage() for r in caplog.records]


def test_a_zoom_that_flips_every_frame_is_warned_once_not_at_each_flip(caplog):
    """Two senders on one key (one at 1.0, one at 2x), or a lens encoder at the tolerance's edge: the zoom flips
    every frame, and each flip starts or ends the withholding.  Each zoomed frame is still withheld and each frame
    at 1.0 published, but the pipeline says so once: before, a WARNING every other frame (15 a second at 30 Hz), and
    an INFO "published again" and "estimator reset" between each two."""
    rig = Rig(ready_after=3)
    tracks = []
    with caplog.at_level(logging.DEBUG, logger="onboard.pipeline.frame_pipeline"):
        for k in range(60):
            rig.feed_until(rig.scene.t_us(k) + 45_000)
            zoom = 2.0 if k >= 20 and k % 2 else 1.0
            tracks.append(rig.pipe.process(dataclasses.replace(rig.scene.frame(k), zoom=zoom), 0))
    assert all((tr.los is None) == (k >= 20 and k % 2 == 1) for k, tr in enumerate(tracks))
    assert rig.pipe.frames_withheld_zoom == 20
    pipeline_logs = [r for r in caplog.records if r.name == "onboard.pipeline.frame_pipeline"]
    warned = [r.getMessage() for r in pipeline_logs if r.levelno >= logging.WARNING]
    assert warned == ["line of sight and 3-D positions withheld: zoom_mismatch"]
    told = [r.getMessage() for r in pipeline_logs if r.levelno == logging.INFO]
    assert told.count("line of sight and 3-D positions published again") == 1
    assert told.count("estimator reset: zoom_mismatch cleared") == 1
    # the flips after the first are still in the log, at DEBUG
    flips = [r for r in pipeline_logs if r.levelno == logging.DEBUG and "withheld: zoom_mismatch" in r.getMessage()]
    assert len(flips) == 19


def _eight_frames_stating(zoom: float) -> tuple[Rig, list]:
    """Eight frames of the scene, each stating ``zoom``, and their tracks."""
    rig = Rig(ready_after=3)
    tracks = []
    for k in range(8):
        rig.feed_until(rig.scene.t_us(k) + 45_000)
        tracks.append(rig.pipe.process(dataclasses.replace(rig.scene.frame(k), zoom=zoom), 0))
    return rig, tracks


@pytest.mark.parametrize("zoom", [0.0, 1.0, 1.004])
def test_frames_stating_no_zoom_or_the_calibrated_one_are_published_as_before(zoom):
    rig, tracks = _eight_frames_stating(zoom)
    assert all(tr.los is not None for tr in tracks) and tracks[-1].has_position
    assert rig.pipe.withheld_because == () and rig.pipe.frames_withheld_zoom == 0
    assert rig.pipe.last_zoom == (None if zoom == 0.0 else pytest.approx(zoom))


@pytest.mark.parametrize("zoom", [math.nan, -1.0, math.inf])
def test_a_zoom_no_zoom_can_be_is_counted_and_read_as_not_stated_and_tracking_goes_on(zoom):
    rig, tracks = _eight_frames_stating(zoom)
    assert all(tr.los is not None for tr in tracks) and tracks[-1].has_position
    assert rig.pipe.last_zoom is None and rig.pipe.withheld_because == () and rig.pipe.frames_processed == 8
    assert rig.counter["frame_zoom_invalid"] == 8


def test_utc_time_round_trips_and_is_null_until_known():
    plain = track_to_json(positioned_track())
    assert plain["time_unix_us"] is None and plain["time_unix_sigma_us"] is None
    stamped = positioned_track(time_unix_us=1_800_000_000_000_010, time_unix_sigma_us=312)
    back = track_from_json(track_to_bytes(stamped))
    assert (back.time_unix_us, back.time_unix_sigma_us) == (1_800_000_000_000_010, 312)
    assert track_from_json({**plain, "time_unix_us": 5}).time_unix_sigma_us is None  # a sender without a sigma
    for bad in ({"time_unix_us": 1.8e15}, {"time_unix_us": -1}, {"time_unix_us": True}, {"time_unix_sigma_us": 3}):
        with pytest.raises(InputError, match="time_unix"):
            track_from_json({**plain, **bad})


@pytest.mark.parametrize("unix_us, sigma_us", [(1_800_000_000_000_010, 312), (7, None), (None, None), (np.int64(9), 0)])
def test_a_utc_stamp_gives_the_track_replace_would_and_refuses_what_it_refuses(unix_us, sigma_us):
    for track in (positioned_track(), positioned_track(measurement_valid=False, observable=False)):
        got = track.with_time_unix(unix_us, sigma_us)
        want = dataclasses.replace(track, time_unix_us=unix_us, time_unix_sigma_us=sigma_us)
        assert track_to_bytes(got) == track_to_bytes(want)
        for name in Track.__dataclass_fields__:
            a, b = getattr(got, name), getattr(want, name)
            assert type(a) is type(b) and (np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b), name
        assert track.time_unix_us is None  # the stamped one is a new track
    for bad in ((1.8e15, None), (-1, None), (True, None), (None, 3), (2**63, None), (5, -1)):
        with pytest.raises(InputError, match="time_unix"):
            positioned_track().with_time_unix(*bad)
        with pytest.raises(InputError, match="time_unix"):
            dataclasses.replace(positioned_track(), time_unix_us=bad[0], time_unix_sigma_us=bad[1])
