"""Frame admission under CPU starvation, in lockstep (no sockets, no threads): a pipeline stall is not a clock step.

A stall (the pipeline thread starved, e.g. under a CFS quota) changes two things: the frames arrive late in wall
time, and the daemon's bounded frame queue (``input.queue_length``, oldest dropped) hands the pipeline the newest
few frames only, so the stamps it sees jump by the stall. Neither is a clock step: the frames' own sequence numbers
and stamps still agree with the stream's rate. A real step (stamps jumping with the numbering moving by one) still
restarts the estimator once confirmed, as before.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.app.frame_queue import FrameQueue
from onboard.pipeline.admission import APART_CONFIRM_US, SEQ_MOD, TIME_CONFIRM_FRAMES, FrameAdmission
from onboard.pipeline.frame_pipeline import FrameRejected
from tests.onboard.test_pipeline import Rig

FRAME_RATE_HZ = 30.0
STALL_S = 1.5  # longer than input.time_reset_threshold_s (1 s) plus the queue's 4 frames
THRESHOLD_US = 1_000_000  # input.time_reset_threshold_s default
RESTART_COUNT = 5  # input.sequence_restart_count default


def _kinds(rig: Rig) -> list[str]:
    return [c[0] for c in rig.est.calls]


def test_frames_delivered_late_after_a_stall_are_taken_and_keep_the_estimator():
    """All frames kept (a long queue), delivered in one burst 1.5 s late, telemetry already 1.5 s ahead."""
    rig = Rig(ready_after=3)
    rig.run(10)
    n_stall = int(STALL_S * FRAME_RATE_HZ)
    rig.feed_until(rig.scene.t_us(10 + n_stall) + 45_000)  # the MAVLink thread went on meanwhile
    late_ns = 10**12  # one received time for the whole burst: wall time plays no part in admission
    tracks = [rig.pipe.process(rig.scene.frame(k), late_ns) for k in range(10, 10 + n_stall)]
    assert [t.seq for t in tracks] == list(range(10, 10 + n_stall))
    assert rig.counter.total == 0 and rig.pipe.frames_rejected == 0
    assert _kinds(rig) == ["add"] * (10 + n_stall) and rig.pipe.estimator_resets == 0
    assert tracks[-1].has_position


def test_frames_the_queue_dropped_during_a_stall_are_a_gap_not_a_clock_step():
    """The daemon's FrameQueue during a 1.5 s stall: the pipeline then takes the newest frames only."""
    rig = Rig(ready_after=3)
    rig.run(10)
    queue = FrameQueue(rig.config.input.queue_length)
    n_stall = int(STALL_S * FRAME_RATE_HZ)
    dropped = sum(queue.push(rig.scene.frame(k)) for k in range(10, 10 + n_stall))
    assert dropped == n_stall - rig.config.input.queue_length
    rig.feed_until(rig.scene.t_us(10 + n_stall) + 45_000)
    taken = []
    while (frame := queue.pop(0.0)) is not None:
        taken.append(rig.pipe.process(frame, 0))
    first = taken[0]
    assert first.time_boot_us - rig.scene.t_us(9) > THRESHOLD_US  # the stamps the pipeline sees jump by the stall
    assert [t.seq for t in taken] == list(range(10 + dropped, 10 + n_stall))
    assert rig.counter.total == 0 and rig.pipe.frames_rejected == 0
    assert "reset" not in _kinds(rig) and rig.pipe.estimator_resets == 0
    assert all(t.has_position for t in taken)
    assert rig.step(10 + n_stall).seq == 10 + n_stall  # and the stream goes on


def test_a_stamp_step_of_1_2_s_with_the_numbering_moving_by_one_is_a_clock_step():
    """Stamps 1.2 s ahead of the telemetry, each frame numbered next: refused until TIME_CONFIRM_FRAMES agree and,
    as they stand apart from the telemetry too, until they span APART_CONFIRM_US; then a time reset. The telemetry
    runs on at the true time (a stamp in step with it would be a camera pause)."""
    rig = Rig(ready_after=3)
    rig.run(10)
    step_us = 1_200_000
    t0 = rig.scene.t_us(10)
    n_refused = next(i for i in range(1, 100) if rig.scene.t_us(10 + i) - t0 >= APART_CONFIRM_US)
    assert n_refused >= TIME_CONFIRM_FRAMES
    for i in range(n_refused):
        rig.feed_until(rig.scene.t_us(10 + i) + 45_000)  # the telemetry at the true time, 1.155 s behind the stamps
        with pytest.raises(FrameRejected) as ei:
            rig.pipe.process(rig.scene.frame(10 + i, time_boot_us=rig.scene.t_us(10 + i) + step_us))
        assert ei.value.reason == "time_ahead"
    k = 10 + n_refused
    rig.feed_until(rig.scene.t_us(k) + 45_000)
    tr = rig.pipe.process(rig.scene.frame(k, time_boot_us=rig.scene.t_us(k) + step_us))
    assert tr.seq == k and not tr.has_position  # its stamp is where the telemetry has not been yet: no pose
    assert rig.counter.counts == {
        "frame_time_ahead": n_refused,
        "frame_time_reset": 1,
        "pose_clock_apart": 1,
    }
    assert rig.pipe.estimator_resets == 1 and "reset" in _kinds(rig)
    assert rig.pipe.clock_apart_s == pytest.approx(1.2, abs=0.1)


def test_a_camera_pause_during_a_gnss_dropout_is_not_a_clock_standing_apart():
    """The admission's telemetry reference was the newest time attitude and position both cover, which stands still
    through a GNSS dropout: a camera pausing there (numbering on) seemed 1.5 s and more apart from the telemetry,
    its frames had no pose until GNSS came back.  The attitude streams on: its newest time is the reference."""
    rig = Rig(ready_after=3)
    rig.run(10)
    t_drop = rig.scene.t_us(10)
    no_gnss = lambda t: t >= t_drop  # noqa: E731 - positions withheld from here on
    n_pause = int(STALL_S * FRAME_RATE_HZ)
    tracks = []
    for i in range(20):
        k = 10 + n_pause + i
        rig.feed_until(rig.scene.t_us(k) + 45_000, skip_position=no_gnss)
        tracks.append(rig.pipe.process(rig.scene.frame(k, seq=10 + i), 0))
    assert rig.pipe.clock_apart_s is None and rig.counter["pose_clock_apart"] == 0
    assert rig.counter["frame_time_reset"] == 0 and rig.pipe.estimator_resets == 0


def test_a_camera_clock_stepped_back_2_s_gets_no_pose_until_it_agrees_with_the_telemetry_again():
    """The camera's clock steps back 2 s, the telemetry runs on at the true time: once confirmed, the frames' stamps
    lie inside the pose window, where a lookup finds the poses of 2 s before (a helper's audit in the loop: lines of
    sight 3.4-11.6 deg off against a claimed 0.115, published as measured).  They get no pose, so no line of sight and
    no 3-D, counted, until a frame stamped within the threshold of the telemetry (the clock set right) ends it,
    with no restart of the estimator."""
    rig = Rig(ready_after=3)
    rig.run(10)
    waits: list[int] = []
    rig.pipe.pose_wait = waits.append  # the wait for a frame's telemetry: none while no pose is looked up
    step_us = -2_000_000
    accepted = []
    for k in range(10, 40):
        rig.feed_until(rig.scene.t_us(k) + 45_000)
        try:
            accepted.append(rig.pipe.process(rig.scene.frame(k, time_boot_us=rig.scene.t_us(k) + step_us)))
        except FrameRejected as exc:
            assert exc.reason == "time_behind" and not accepted
    assert accepted and rig.counter["frame_time_reset"] == 1
    assert all(t.los is None and not t.has_position for t in accepted)
    assert rig.counter["pose_clock_apart"] == len(accepted) and rig.pipe.clock_apart_s == pytest.approx(-2.0, abs=0.1)
    assert waits == []
    resets = rig.pipe.estimator_resets
    rig.feed_until(rig.scene.t_us(40) + 45_000)
    back = rig.pipe.process(rig.scene.frame(40))  # the camera's clock set right: in step with the telemetry
    assert back.los is not None and rig.pipe.clock_apart_s is None and len(waits) == 1
    assert rig.pipe.estimator_resets == resets


def test_a_camera_pause_with_the_telemetry_running_on_is_a_gap_not_a_clock_step():
    """The camera stops for 1.5 s and numbers its frames on from where it stopped (its rate cannot place them):
    stamps in step with the telemetry are taken at once, with the same estimate."""
    rig = Rig(ready_after=3)
    tracks = rig.run(10)
    n_pause = int(STALL_S * FRAME_RATE_HZ)
    for i in range(5):
        k = 10 + n_pause + i
        rig.feed_until(rig.scene.t_us(k) + 45_000)
        tracks.append(rig.pipe.process(rig.scene.frame(k, seq=10 + i), 0))
    assert [t.seq for t in tracks[10:]] == list(range(10, 15))
    assert rig.counter.total == 0 and rig.pipe.frames_rejected == 0
    assert _kinds(rig) == ["add"] * 15 and rig.pipe.estimator_resets == 0
    assert all(t.has_position for t in tracks[10:])


@settings(max_examples=100, deadline=None)
@given(
    period_us=st.integers(10_000, 100_000),
    pause_us=st.integers(1_000_001, 600_000_000),
    seq_on=st.integers(1, 1000),
    lag_us=st.integers(-999_000, 999_000),
)
def test_a_frame_after_any_pause_in_step_with_the_telemetry_is_taken(period_us, pause_us, seq_on, lag_us):
    """However long the pause and whatever the numbering did (forward), a frame within the threshold of the
    telemetry's newest time is the next one; the same frame with the telemetry unknown waits for a run."""
    adm = FrameAdmission(THRESHOLD_US, RESTART_COUNT)
    for k in range(3):
        assert adm.admit(k, 10**9 + k * period_us).accepted
    t_us = 10**9 + 2 * period_us + pause_us
    blind = FrameAdmission(THRESHOLD_US, RESTART_COUNT)
    for k in range(3):
        blind.admit(k, 10**9 + k * period_us)
    assert blind.admit(2 + seq_on, t_us).reason == "time_ahead"
    v = adm.admit(2 + seq_on, t_us, reference_us=t_us + lag_us)
    assert (v.accepted, v.reason, v.restart) == (True, "", False)
    assert adm.admit(3 + seq_on, t_us + period_us).accepted


def test_a_frame_far_ahead_with_its_numbering_far_ahead_too_is_one_odd_frame():
    """An hour ahead and 100 000 numbers on (36 ms a number: near the stream's rate, yet not where it puts them)."""
    adm = FrameAdmission(THRESHOLD_US, RESTART_COUNT)
    period_us = 33_333
    for k in range(20):
        assert adm.admit(k, k * period_us).accepted
    odd = adm.admit(19 + 100_000, 19 * period_us + 3_600_000_000)
    assert (odd.accepted, odd.reason) == (False, "time_ahead")
    good = adm.admit(20, 20 * period_us)
    assert (good.accepted, good.reason, good.restart) == (True, "", False)


@settings(max_examples=100, deadline=None)
@given(
    period_us=st.integers(10_000, 100_000),
    seq0=st.integers(0, SEQ_MOD - 1),
    steps=st.lists(st.integers(1, 600), min_size=1, max_size=30),
    jitter_us=st.lists(st.integers(-3_000, 3_000), min_size=40, max_size=40),
)
def test_any_frames_missing_from_a_steady_stream_never_refuse_or_restart(period_us, seq0, steps, jitter_us):
    """Frames numbered and stamped at the stream's rate (stamps jittered by 3 ms) with any of them missing (up to
    600 in a row: 6 to 60 s), the numbering wrapping: each frame taken as the next one. The first ten come without
    gaps (the rate is learnt from the frames taken)."""
    adm = FrameAdmission(THRESHOLD_US, RESTART_COUNT)
    ks = list(range(10))
    for s in steps:
        ks.append(ks[-1] + s)
    for i, k in enumerate(ks):
        v = adm.admit((seq0 + k) % SEQ_MOD, 10**9 + k * period_us + jitter_us[i])
        assert (v.accepted, v.reason, v.restart) == (True, "", False), (k, v)


def test_one_frame_stamped_within_the_threshold_ahead_of_the_stream_and_the_telemetry_is_one_odd_frame():
    """A frame 0.9 s ahead (within the 1 s threshold) was taken as the stream's newest: the good frames after it
    were refused as behind it until a run of them restarted the estimator (and its camera-clock compensation).  It
    is refused now, the stream goes on; a frame after a short camera pause, in step with the telemetry, is taken."""
    period_us = 33_333
    adm = FrameAdmission(THRESHOLD_US, RESTART_COUNT)
    for k in range(20):
        t = 10**9 + k * period_us
        assert adm.admit(k, t, reference_us=t - 20_000 if adm.wants_reference(k, t) else None).accepted
    odd_t = 10**9 + 20 * period_us + 900_000
    assert adm.wants_reference(20, odd_t)
    odd = adm.admit(20, odd_t, reference_us=10**9 + 20 * period_us - 20_000)
    assert (odd.accepted, odd.reason) == (False, "time_ahead")
    for k in range(21, 30):
        t = 10**9 + k * period_us
        v = adm.admit(k, t, reference_us=t - 20_000 if adm.wants_reference(k, t) else None)
        assert (v.accepted, v.reason, v.restart) == (True, "", False)
    # a 0.6 s camera pause numbering on from where it stopped, the telemetry running on with it: the next frame
    t = 10**9 + 29 * period_us + 600_000
    assert adm.wants_reference(30, t)
    v = adm.admit(30, t, reference_us=t - 20_000)
    assert (v.accepted, v.reason, v.restart) == (True, "", False)
