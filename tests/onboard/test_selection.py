"""Click-to-track: the tracker's operator selection, the pipeline's request queue, the service's
camera step (command in -> pipeline -> COMMAND_ACK out), with synthetic frames and a fake clock."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from onboard.app.config import build_config
from onboard.core.irframe import IrFrame
from onboard.core.track import Track
from onboard.imaging import TargetTracker
from onboard.imaging.preprocess import ImagingParams
from onboard.io.camera_protocol import CameraCommand, TrackRequest
from onboard.pipeline.frame_pipeline import FramePipeline
from tests.fakes import FakeClock, positioned_track, quiet_link_status, single_chain  # noqa: E402

W, H = 640, 512
HOT = (200.0, 150.0)  # the two warm objects' true centres, px
WARM = (450.0, 380.0)
CENTRE_TOL_PX = 0.5


def _frame(k: int, objects=(HOT, WARM), amps=(80.0, 50.0), shift_px: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(k)
    img = 100.0 + rng.normal(0.0, 1.0, (H, W))
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    for (u, v), a in zip(objects, amps):
        img += a * np.exp(-((jj - u - shift_px * k) ** 2 + (ii - v) ** 2) / (2 * 1.5**2))
    return np.clip(img, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- tracker


def test_auto_mode_acquires_the_strongest_operator_mode_waits():
    auto = TargetTracker(ImagingParams())
    upd = auto.update(_frame(0))
    assert upd.state.value == "tracking" and math.hypot(upd.u_px - HOT[0], upd.v_px - HOT[1]) < CENTRE_TOL_PX
    op = TargetTracker(ImagingParams(), mode="operator")
    for k in range(5):
        assert op.update(_frame(k)).state.value == "searching"


def test_select_point_takes_the_object_nearest_the_click_within_the_radius():
    tr = TargetTracker(ImagingParams(), mode="operator")
    assert tr.select_point(_frame(0), 300.0, 300.0, 20.0) is None  # empty sky: nothing, nothing changed
    assert tr.update(_frame(1)).state.value == "searching"
    upd = tr.select_point(_frame(2), WARM[0] + 12.0, WARM[1] - 5.0, 20.0)
    assert upd is not None and upd.track_id == 1 and upd.measurement_valid
    assert math.hypot(upd.u_px - WARM[0], upd.v_px - WARM[1]) < CENTRE_TOL_PX  # the weaker one, as clicked
    for k in range(3, 10):  # it stays on it, not on the stronger one
        upd = tr.update(_frame(k))
        assert upd.track_id == 1 and math.hypot(upd.u_px - WARM[0], upd.v_px - WARM[1]) < CENTRE_TOL_PX


def test_select_rectangle_and_a_new_selection_starts_a_new_track():
    tr = TargetTracker(ImagingParams())
    first = tr.update(_frame(0))
    assert first.track_id == 1
    upd = tr.select_rectangle(_frame(1), (400.0, 330.0, 500.0, 430.0))
    assert upd.track_id == 2 and math.hypot(upd.u_px - WARM[0], upd.v_px - WARM[1]) < CENTRE_TOL_PX
    assert tr.select_rectangle(_frame(2), (0.0, 0.0, 50.0, 50.0)) is None
    assert tr.update(_frame(3)).track_id == 2  # a refused selection leaves the track alone


def test_stop_holds_even_auto_mode_until_the_next_selection():
    tr = TargetTracker(ImagingParams())
    assert tr.update(_frame(0)).state.value == "tracking"
    tr.stop()
    assert tr.holding
    for k in range(1, 5):
        assert tr.update(_frame(k)).state.value == "searching"
    assert tr.select_point(_frame(5), *HOT, 10.0).state.value == "tracking" and not tr.holding


def test_operator_track_is_not_handed_to_another_object_when_it_vanishes():
    p = ImagingParams()
    tr = TargetTracker(p, mode="operator")
    tr.select_point(_frame(0), *WARM, 10.0)
    ids = set()
    for k in range(1, p.lost_frames + 5):
        upd = tr.update(_frame(k, objects=(HOT,), amps=(80.0,)))  # the selected object is gone
        ids.add(upd.track_id)
        assert upd.u_px is None or math.hypot(upd.u_px - HOT[0], upd.v_px - HOT[1]) > 50
    assert upd.state.value in ("lost", "searching") and ids <= {1, None}


def test_bad_mode_is_refused():
    with pytest.raises(Exception, match="tracker mode"):
        TargetTracker(ImagingParams(), mode="manual")


# --------------------------------------------------------------------------- pipeline


class _CountingEstimator:
    def __init__(self) -> None:
        self.resets = 0
        self.adds = 0

    def add(self, *a, **k):
        self.adds += 1
        return None

    def predict(self, *a, **k):
        return None

    def reset(self) -> None:
        self.resets += 1


class _Pose:
    """The same pose for every frame: what the pipeline reads of a :class:`~onboard.core.pose.PoseAt`."""

    def pose_at(self, t_us):
        from types import SimpleNamespace

        from onboard.core.frames import GeodeticOrigin

        return SimpleNamespace(
            p_cam_ned_m=np.zeros(3),
            q_ned_from_cam=np.array([1.0, 0.0, 0.0, 0.0]),
            origin=GeodeticOrigin(32.0, 118.8, 0.0),
            epoch=0,
            body=SimpleNamespace(v_ned_mps=np.zeros(3)),  # still: the camera clock's offset estimator reads it
        )


def _pipeline(mode="auto"):
    """A pipeline on the single chain (``TargetTracker``: it tracks the hot object from the first frame)."""
    cfg = single_chain(build_config({"gcs": {"tracker_mode": mode}, "estimator": {"enabled": False}}))
    est = _CountingEstimator()
    return FramePipeline(cfg, None, TargetTracker(cfg.imaging, mode=mode), est), est


def _ir(k: int, **kw) -> IrFrame:
    return IrFrame(seq=k, time_boot_us=1_000_000 + k * 33_333, pixels=_frame(k, **kw))


def test_pipeline_decides_queued_requests_on_the_next_frame_and_answers_each():
    pipe, _ = _pipeline("operator")
    results = []
    assert pipe.process(_ir(0)).state == "searching"
    pipe.request_selection(TrackRequest(1, "point", u_px=300.0, v_px=300.0, radius_px=20.0), results.append)
    tr = pipe.process(_ir(1))
    assert tr.state == "searching" and len(results) == 1 and not results[0].accepted
    assert "no warm object" in results[0].reason and pipe.last_selection["accepted"] is False
    pipe.request_selection(TrackRequest(2, "point", u_px=HOT[0] + 3, v_px=HOT[1], radius_px=20.0), results.append)
    tr = pipe.process(_ir(2))
    assert results[-1].accepted and results[-1].request_id == 2
    assert tr.state == "tracking" and math.hypot(tr.u_px - HOT[0], tr.v_px - HOT[1]) < CENTRE_TOL_PX
    pipe.request_selection(TrackRequest(3, "stop"), results.append)
    assert pipe.process(_ir(3)).state == "searching" and results[-1].accepted
    assert pipe.process(_ir(4)).state == "searching"


def test_a_new_selection_restarts_the_estimate():
    # the single chain: with objects any new primary restarts the estimate, which would hide what is tested here
    cfg = single_chain(build_config({"estimator": {"enabled": False, "reset_on_new_track": False}}))
    est = _CountingEstimator()
    pipe = FramePipeline(cfg, _Pose(), TargetTracker(cfg.imaging), est)
    before = [pipe.process(_ir(k)) for k in range(5)]
    assert est.adds == 5 and est.resets == 0 and {t.estimate_epoch for t in before} == {0}
    pipe.request_selection(TrackRequest(1, "rectangle", rect_px=(400.0, 330.0, 500.0, 430.0)), lambda r: None)
    tr = pipe.process(_ir(5))
    assert est.resets == 1 and tr.track_id == 2  # reset although reset_on_new_track is off: the operator chose
    assert tr.estimate_epoch == 1  # and the track says its estimate started again


class _IdSequenceTracker:
    """An image chain whose primary's id follows ``ids``, one per frame, centred, fit for 3-D."""

    def __init__(self, ids) -> None:
        self._ids = iter(ids)

    def update(self, pixels, *args):
        from onboard.imaging import TrackState
        from onboard.imaging.detect import Detection
        from onboard.imaging.tracker import TrackUpdate

        det = Detection(320.0, 256.0, 4, 40.0, 160.0, (319, 255, 2, 2), 140.0, 20.0)
        return TrackUpdate(
            TrackState.TRACKING, 320.0, 256.0, (310.0, 246.0, 20.0, 20.0), det, True, next(self._ids), 0, 0
        )


@pytest.mark.parametrize("chain, resets", [("objects", 1), ("single", 0)])
def test_the_objects_chain_never_hands_the_estimate_to_another_object(chain, resets):
    """With reset_on_new_track off, the single chain's new id (its target re-found) keeps the estimate; the
    objects chain's ids name objects, so its primary moving to another id restarts it and the track says so."""
    cfg = build_config({"imaging": {"chain": chain}, "estimator": {"enabled": False, "reset_on_new_track": False}})
    est = _CountingEstimator()
    pipe = FramePipeline(cfg, _Pose(), _IdSequenceTracker([7] * 5 + [1] * 3), est)
    tracks = [pipe.process(_ir(k)) for k in range(8)]
    assert [t.track_id for t in tracks] == [7] * 5 + [1] * 3
    assert est.resets == resets and tracks[-1].estimate_epoch == resets


class _SelectableIdTracker(_IdSequenceTracker):
    """:class:`_IdSequenceTracker` whose selections name object ``selected`` (a click on it)."""

    def __init__(self, ids, selected: int) -> None:
        super().__init__(ids)
        self.selected = selected

    def select_point(self, pixels, u_px, v_px, radius_px, **pose):
        import itertools
        from dataclasses import replace

        self._ids = itertools.repeat(self.selected)  # the selected object is the primary from now on
        return replace(self.update(pixels), track_id=self.selected)


@pytest.mark.parametrize("selected, resets", [(7, 0), (9, 1)])
def test_selecting_the_object_the_estimate_follows_keeps_the_estimate(selected, resets):
    """With the objects chain, a click on the primary it already follows (the box QGC draws; or a command resent
    because its ACK was lost) is accepted and keeps the 3-D estimate; a click on another object restarts it."""
    cfg = build_config({"imaging": {"chain": "objects"}, "estimator": {"enabled": False}})
    est = _CountingEstimator()
    pipe = FramePipeline(cfg, _Pose(), _SelectableIdTracker([7] * 10, selected), est)
    for k in range(5):
        pipe.process(_ir(k))
    results = []
    pipe.request_selection(TrackRequest(1, "point", u_px=320.0, v_px=256.0, radius_px=20.0), results.append)
    tr = pipe.process(_ir(5))
    assert results[0].accepted and tr.track_id == selected
    tracks = [tr] + [pipe.process(_ir(k)) for k in (6, 7)]
    assert est.resets == resets and {t.estimate_epoch for t in tracks} == {resets}


# --------------------------------------------------------------------------- service camera step


class _FakeGcs:
    def __init__(self) -> None:
        self.inbox: list[CameraCommand] = []
        self.sent = []
        self.system_id = None

    def set_system_id(self, sysid: int) -> None:
        self.system_id = sysid

    def poll(self):
        out, self.inbox = self.inbox, []
        return out

    def send(self, out) -> int:
        self.sent.append(out)
        return 1

    def links(self) -> list:
        return [None]  # one link, every endpoint: what CameraProtocol.tick assumes without links

    def close(self) -> None:
        pass


class _FakeLink:
    autopilot_sysid = 7
    open_error = None

    def status(self):
        return quiet_link_status("connected", autopilot_sysid=7, messages_rx=1)


def _service(mode="auto", gimballed=False, chain="objects"):
    from onboard.app.service import OnboardService

    cfg = build_config(
        {
            "imaging": {"chain": chain},
            "estimator": {"enabled": False},
            "output": {"health_file": None},
            "gcs": {"endpoints": ["udpout:127.0.0.1:14550"], "tracker_mode": mode},
            "mavlink": {"connection": "udpin:0.0.0.0:14999", "autopilot_sysid": None},
            "camera": {"mount": {"gimballed": gimballed}},
        }
    )
    clock = FakeClock()
    svc = OnboardService(cfg, clock=clock, clock_ns=clock.ns)
    svc.gcs = _FakeGcs()
    return svc, clock


def _acks(sent):
    return [o.fields for o in sent if o.msg == "command_ack"]


def test_camera_is_silent_until_the_autopilot_is_known_then_speaks_as_its_system():
    svc, clock = _service()
    assert svc.camera_step(clock()) == 0
    svc.link = _FakeLink()
    assert svc.camera_step(clock()) >= 1 and svc.gcs.system_id == 7
    assert svc.gcs.sent[0].msg == "heartbeat" and svc.gcs.sent[0].fields["type"] == mav.MAV_TYPE_CAMERA


def test_a_command_read_before_the_autopilot_is_known_is_dropped_and_counted_not_carried_out_later():
    """Without a system id the camera cannot answer: a command left waiting in the socket would be carried out when
    the autopilot appears, seconds or minutes after its sender gave up on it (ACK timeout, 3 tries)."""
    svc, clock = _service("operator")
    for _ in range(3):  # a ground station broadcasting (target 0/0) to a camera whose vehicle is not heard yet
        svc.gcs.inbox.append(CameraCommand(mav.MAV_CMD_CAMERA_TRACK_POINT, (0.5, 0.5, 0.05, 0, 0, 0, 0), 255, 190))
        assert svc.camera_step(clock()) == 0
    assert svc.gcs.inbox == [] and svc.gcs.sent == []
    assert svc.counter.counts["gcs_command_before_system_id"] == 3
    svc.link = _FakeLink()
    clock.t_s += 10.0
    svc.camera_step(clock())
    assert _acks(svc.gcs.sent) == [] and svc.camera.pending_requests() == 0
    assert svc.camera.counters.get("cmd_camera_track_point", 0) == 0


@pytest.mark.parametrize("gimballed, followed, expected", [(True, 154, 154), (True, None, 0), (False, 154, 0)])
def test_camera_information_names_the_gimbal_the_link_follows(gimballed, followed, expected):
    """common.xml CAMERA_INFORMATION.gimbal_device_id: the gimbal's component id (or 1-6), 0 when none is
    associated: a fixed mount, or a gimballed one whose gimbal has not been heard yet."""
    svc, clock = _service(gimballed=gimballed)
    svc.link = _FakeLink()
    svc.link.gimbal_device_id = followed
    svc.gcs.inbox.append(CameraCommand(mav.MAV_CMD_REQUEST_MESSAGE, (259, 0, 0, 0, 0, 0, 0), 255, 190))
    svc.camera_step(clock())
    (info,) = [o.fields for o in svc.gcs.sent if o.msg == "camera_information"]
    assert info["gimbal_device_id"] == expected


@pytest.mark.parametrize("chain, seen", [("single", 1), ("objects", 12)])
def test_click_to_track_through_the_service_acked_after_the_pipeline_frame(chain, seen):
    """``seen``: frames before the click; the objects chain selects only an object it has confirmed (11 frames)."""
    svc, clock = _service("operator", chain=chain)
    svc.link = _FakeLink()
    for k in range(seen):
        svc.pipeline.process(_ir(k))
    svc.gcs.inbox.append(
        CameraCommand(mav.MAV_CMD_CAMERA_TRACK_POINT, (HOT[0] / W, HOT[1] / H, 20 / W, 0, 0, 0, 0), 255, 190)
    )
    svc.camera_step(clock())
    assert _acks(svc.gcs.sent) == []  # decided by the pipeline thread on its next frame
    tr = svc.pipeline.process(_ir(seen))
    svc.newest.value = (tr, clock())
    clock.t_s += 0.01
    svc.camera_step(clock())
    acks = _acks(svc.gcs.sent)
    assert [(a["command"], a["result"]) for a in acks] == [(mav.MAV_CMD_CAMERA_TRACK_POINT, mav.MAV_RESULT_ACCEPTED)]
    img = [o.fields for o in svc.gcs.sent if o.msg == "camera_tracking_image_status"][-1]
    assert img["tracking_mode"] == mav.CAMERA_TRACKING_MODE_POINT
    assert abs(img["point_x"] - HOT[0] / W) < 0.01 and abs(img["point_y"] - HOT[1] / H) < 0.01
    st = svc.status(clock())["camera"]
    assert st["selection_mode"] == "point" and st["last_selection"]["accepted"] is True
    # a click on empty sky: FAILED, the status says why
    svc.gcs.inbox.append(CameraCommand(mav.MAV_CMD_CAMERA_TRACK_POINT, (0.5, 0.9, 20 / W, 0, 0, 0, 0), 255, 190))
    svc.camera_step(clock())
    svc.pipeline.process(_ir(seen + 1))
    svc.camera_step(clock())
    assert _acks(svc.gcs.sent)[-1]["result"] == mav.MAV_RESULT_FAILED
    refusal = svc.status(clock())["camera"]["last_refusal"]
    assert ("no tracked object" if chain == "objects" else "no warm object") in refusal
    # the usual refusal fits one STATUSTEXT with the camera's prefix (a longer text arrives in chunks, which simple
    # tools show in pieces: 'no confirmed object within 13 px of (32, ' then '26) px')
    (text,) = [o.fields["text"] for o in svc.gcs.sent if o.msg == "statustext"][-1:]
    assert len(text.rstrip(b"\0")) <= 50 and text.rstrip(b"\0").endswith(b")"), text


def test_276_only_for_observable_positions_through_the_camera():

    def track(observable: bool) -> Track:
        return positioned_track(
            u_px=300.0, v_px=200.0, bbox=None, cov_p_ned_m2=np.diag([400.0, 400.0, 100.0]), observable=observable
        )

    svc, clock = _service()
    svc.link = _FakeLink()
    svc.newest.value = (track(False), clock())
    for _ in range(20):
        clock.t_s += 0.05
        svc.newest.value = (svc.newest.value[0], clock())
        svc.camera_step(clock())
    assert not any(o.msg == "camera_tracking_geo_status" for o in svc.gcs.sent)
    svc.newest.value = (track(True), clock())
    clock.t_s += 0.5
    svc.newest.value = (svc.newest.value[0], clock())
    svc.camera_step(clock())
    geo = [o.fields for o in svc.gcs.sent if o.msg == "camera_tracking_geo_status"]
    assert geo and geo[-1]["h_acc"] == pytest.approx(math.sqrt(800.0)) and geo[-1]["dist"] == 130.0


def test_a_request_the_camera_gave_up_on_is_not_carried_out_by_a_later_frame():
    """The camera answers TEMPORARILY_REJECTED when no frame came within its timeout; the request must then not
    be applied by the first frame that does come (a STOP seconds later left the target untracked for the whole
    flight).  Whichever claims a request first decides it."""
    pipe, _ = _pipeline("auto")
    assert pipe.process(_ir(0)).state == "tracking"  # auto mode: the hot target from the first frame
    req = TrackRequest(7, "stop")
    results = []
    pipe.request_selection(req, results.append)
    assert req.claim()  # the camera's timeout took it first
    tr = pipe.process(_ir(1))
    assert tr.state == "tracking" and results == [] and pipe.counter["selection_expired"] == 1
    other = TrackRequest(8, "stop")
    pipe.request_selection(other, results.append)
    assert pipe.process(_ir(2)).state == "searching" and results[-1].accepted
    assert not other.claim()  # the pipeline took it: the camera's timeout leaves it alone


def test_requests_the_camera_decided_without_a_frame_are_counted_not_warned(caplog):
    """Timed out (the camera answered and counted it) or replaced by a newer command (never answered): the frame that
    comes later skips them quietly.  A ground station that resent a click every 5 ms to a camera without frames
    queued thousands, and the first frame logged a WARNING saying each had been answered as rejected."""
    pipe, _ = _pipeline("auto")
    assert pipe.process(_ir(0)).state == "tracking"
    results = []
    for k in range(50):
        req = TrackRequest(k + 1, "point", u_px=300.0, v_px=300.0, radius_px=20.0)
        pipe.request_selection(req, results.append)
        assert req.claim()  # replaced by the next one, or timed out: the camera's
    # the counter's own logger: another test in this process may have set its level (an entry point's logging set-up)
    with caplog.at_level(logging.DEBUG, logger=pipe.counter._log.name):
        assert pipe.process(_ir(1)).state == "tracking"
    assert results == [] and pipe.counter["selection_expired"] == 50
    expired = [r for r in caplog.records if "selection_expired" in r.getMessage()]
    assert expired and {r.levelno for r in expired} == {logging.DEBUG}
    assert "answered" not in expired[0].getMessage()


def test_requests_waiting_without_frames_are_bounded():
    """With no frames nothing takes the queued requests: a ground station resending every 5 ms grew it without end
    (3 MB per 5000, a fault-injection audit). At most MAX_QUEUED_SELECTIONS wait, the newest; the camera answers the
    others when they time out, as it answers any that waited too long."""
    from onboard.pipeline.frame_pipeline import MAX_QUEUED_SELECTIONS

    pipe, _ = _pipeline("auto")
    assert pipe.process(_ir(0)).state == "tracking"
    results = []
    reqs = [TrackRequest(k + 1, "point", u_px=300.0, v_px=300.0, radius_px=20.0) for k in range(1000)]
    for req in reqs:
        pipe.request_selection(req, results.append)
    assert len(pipe._selections) == MAX_QUEUED_SELECTIONS
    assert pipe.counter["selection_dropped"] == 1000 - MAX_QUEUED_SELECTIONS
    pipe.process(_ir(1))
    assert len(results) == MAX_QUEUED_SELECTIONS and not pipe._selections  # the newest ones, each answered
    assert reqs[0].claim()  # the oldest never reached the pipeline: the camera's timeout decides it
