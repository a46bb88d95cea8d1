"""groundsim eval's MOT files (groundsim.evaluation.mot): lines, layout, and TrackEval reading them."""

from __future__ import annotations

import configparser
import math
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.evaluation.mot import BOX_SIDE_PX, HIDDEN_CLASS, gt_rows, seq_name, tracker_rows, write_mot


def _label(oid, u, v, visibility="visible"):
    return SimpleNamespace(object_id=oid, u_px=u, v_px=v, visibility=visibility)


def test_gt_rows_every_object_one_based_with_visibility_flag():
    rows = gt_rows(
        3,
        [
            _label(0, 10.0, 20.0),
            _label(2, 50.5, 60.5, "occluded"),
            _label(4, math.nan, 1.0),
            _label(5, 1, 1, "out_of_frame"),
        ],
    )
    # every object the image plane can place, visible (1) or not (0: occluded, out of frame); none behind the camera
    assert [r.split(",")[:2] for r in rows] == [["3", "1"], ["3", "3"], ["3", "6"]]
    assert [r.split(",")[6] for r in rows] == ["1", "0", "0"]
    # hidden: MOT17's distractor class, whose matched tracker boxes TrackEval drops rather than counts
    assert [r.split(",")[7] for r in rows] == ["1", str(HIDDEN_CLASS), str(HIDDEN_CLASS)] == ["1", "8", "8"]
    f = rows[0].split(",")
    # MOT's 1-based left/top of a BOX_SIDE_PX square about the centre
    assert float(f[2]) == pytest.approx(10.0 - BOX_SIDE_PX / 2 + 1) and float(f[5]) == BOX_SIDE_PX
    assert f[6] == "1" and rows[1].split(",")[6] == "0"
    assert gt_rows(1, (), (5.0, 6.0), True)[0].startswith("1,1,")
    assert gt_rows(1, (), (5.0, 6.0), False)[0].split(",")[6:8] == ["0", "8"]
    assert gt_rows(1, (), (math.nan, 6.0), True) == []


def test_tracker_rows_from_objects_or_the_single_track():
    objs = SimpleNamespace(confirmed=(SimpleNamespace(object_id=7, u_px=100.0, v_px=50.0, score=2.5),))
    assert tracker_rows(4, objs) == [f"4,7,{100 - 2:.3f},{50 - 2:.3f},6.000,6.000,2.500,-1,-1,-1\n"]
    track = SimpleNamespace(state="tracking", u_px=10.0, v_px=10.0, track_id=2)
    assert tracker_rows(4, None, track)[0].startswith("4,2,")
    assert tracker_rows(4, None, SimpleNamespace(state="coasting", u_px=1.0, v_px=1.0, track_id=2)) == []


def test_objects_whose_centre_is_not_finite_are_left_out_of_the_tracker_file_and_counted(tmp_path):
    """A tracker's objects with NaN or infinite centres: the MOT lines hold the finite ones only, the others are
    counted, and TrackEval scores the sequence (a NaN line made it refuse the whole sequence: 'matrix contains
    invalid numeric entries', its HOTA lost)."""
    from groundsim.evaluation.mot import score_mot, unscorable_objects

    def objs(*uv):
        return SimpleNamespace(
            confirmed=tuple(SimpleNamespace(object_id=i + 1, u_px=u, v_px=v, score=1.0) for i, (u, v) in enumerate(uv))
        )

    frame = objs((100.0, 50.0), (math.nan, 50.0), (100.0, math.inf))
    assert [line.split(",")[1] for line in tracker_rows(1, frame)] == ["1"]
    assert unscorable_objects(frame) == 2 and unscorable_objects(objs((1.0, 2.0))) == 0
    pytest.importorskip("trackeval")
    gt = "".join(gt_rows(1, [_label(0, 100.0, 50.0)]) + gt_rows(2, [_label(0, 100.0, 50.0)]))
    trk = "".join(tracker_rows(1, frame) + tracker_rows(2, frame))
    run = SimpleNamespace(scenario="S", nav_noise="RTK", seed=0, frames=2, error=None, mot_gt=gt, mot_tracker=trk)
    seqs = write_mot(tmp_path, [run], {"S": (640, 512, 30.0)})
    assert score_mot(tmp_path, seqs)[seqs[0]]["HOTA"] == pytest.approx(1.0)


def test_write_mot_layout_and_trackeval_scores_a_perfect_tracker(tmp_path, capsys):
    gt = "".join("".join(gt_rows(k, [_label(0, 100.0 + k, 50.0), _label(1, 200.0, 80.0 - k)])) for k in range(1, 31))
    objects = [
        SimpleNamespace(confirmed=(SimpleNamespace(object_id=5, u_px=100.0 + k, v_px=50.0, score=3.0),))
        for k in range(31)
    ]
    trk = "".join("".join(tracker_rows(k, objects[k])) for k in range(1, 31))
    run = SimpleNamespace(scenario="C3", nav_noise="RTK", seed=2, frames=30, error=None, mot_gt=gt, mot_tracker=trk)
    failed = SimpleNamespace(scenario="C3", nav_noise="RTK", seed=3, frames=0, error="boom", mot_gt="", mot_tracker="")
    seqs = write_mot(tmp_path, [run, failed], {"C3": (640, 512, 30.0)})
    assert seqs == [seq_name("C3", "RTK", 2)] == ["C3-RTK-s2"]
    ini = configparser.ConfigParser()
    ini.read(tmp_path / "mot" / "gt" / "C3-RTK-s2" / "seqinfo.ini")
    assert ini["Sequence"]["seqLength"] == "30" and ini["Sequence"]["imWidth"] == "640"
    assert (tmp_path / "mot" / "trackers" / "irtrack" / "data" / "C3-RTK-s2.txt").read_text() == trk
    pytest.importorskip("trackeval")  # installed with --no-deps (it pins opencv-python)
    from groundsim.evaluation.mot import score_mot

    m = score_mot(tmp_path, seqs)["C3-RTK-s2"]
    assert capsys.readouterr().out == ""  # TrackEval's banner is not the command's output
    # one of two objects tracked perfectly, the other missed: DetA 0.5, AssA 1, HOTA sqrt(0.5)
    assert m["DetA"] == pytest.approx(0.5) and m["AssA"] == pytest.approx(1.0)
    assert m["HOTA"] == pytest.approx(math.sqrt(0.5)) and m["IDSW"] == 0


@pytest.mark.parametrize("hidden", ["occluded", "out_of_frame"])
def test_a_track_coasting_on_a_hidden_object_is_neither_a_hit_nor_a_false_positive(tmp_path, hidden):
    """An object visible on frame 1, behind a cloud (or just past the image edge) on frame 2, and a track on it
    both frames: TrackEval scores it perfect.  With the hidden row class 1 (consider 0) TrackEval had left the row
    out but counted the box on it a false positive (HOTA 0.5); PerceptionScore counts it neither way either."""
    pytest.importorskip("trackeval")
    from groundsim.evaluation.mot import PerceptionScore, score_mot

    u = {"occluded": 100.0, "out_of_frame": -1.0}[hidden]
    gt = "".join(gt_rows(1, [_label(0, 100.0, 50.0)]) + gt_rows(2, [_label(0, u, 50.0, hidden)]))
    track = [
        SimpleNamespace(confirmed=(SimpleNamespace(object_id=3, u_px=x, v_px=50.0, score=2.0),)) for x in (100.0, u)
    ]
    trk = "".join(tracker_rows(1, track[0]) + tracker_rows(2, track[1]))
    run = SimpleNamespace(scenario="S", nav_noise="RTK", seed=0, frames=2, error=None, mot_gt=gt, mot_tracker=trk)
    seqs = write_mot(tmp_path, [run], {"S": (640, 512, 30.0)})
    m = score_mot(tmp_path, seqs)[seqs[0]]
    assert m["HOTA"] == pytest.approx(1.0) and m["MOTA"] == pytest.approx(1.0)

    def perception(track_u_when_hidden: float) -> dict:
        """Five frames at 1 Hz: the object visible on two, hidden on three, the track on it while visible."""
        ps = PerceptionScore(frame_rate_hz=1.0)
        for k in range(5):
            visible = k < 2
            obj_u = 100.0 if visible else u
            track_u = 100.0 if visible else track_u_when_hidden
            ps.add([(0, obj_u, 50.0, visible, 10.0)], {3: (track_u, 50.0)}, None)
        return ps.figures()

    on_it, off_it = perception(u), perception(u + 200.0)
    # on the hidden object three frames of five: not a false track; 200 px off it those frames: one
    assert on_it["false_tracks_per_min"] == 0.0 and off_it["false_tracks_per_min"] > 0.0
    # the hidden frames are not counted for the detection probability (the visible one past the 1 s settling is)
    assert on_it["pd_counted"] == 1


def test_perception_score_pd_false_tracks_switches_and_state_accuracy():
    from groundsim.evaluation.mot import PerceptionScore

    ps = PerceptionScore(frame_rate_hz=10.0)  # 1 s settling = 10 frames
    for k in range(40):
        target = (0, 100.0 + k, 50.0, k < 30, 12.0)  # visible for 30 frames, then gone (out of frame, say)
        faint = (1, 300.0, 200.0, True, 2.0)  # under 3 NETD: never counted
        bird = (2, 400.0, 100.0, True, None)  # contrast unknown: counted
        tracks = {}
        if k < 30:
            tracks[7 if k < 20 else 8] = (100.0 + k + 1.0, 50.0)  # on the target, 1 px off; its id changes once
        if k % 2 == 0:
            tracks[9] = (400.0, 102.0)  # the bird every other frame
        tracks[11] = (10.0, 10.0)  # on nothing: a false track
        selected = (100.0 + k + 1.0, 50.0) if k < 30 else (130.0, 50.0) if k < 35 else None
        ps.add([target, faint, bird], tracks, selected)
    f = ps.figures()
    # counted after 1 s: the target frames 10-29 (20, all found), the bird frames 10-39 (30, 15 found)
    assert f["pd_counted"] == 50 and f["pd_pct"] == pytest.approx(100.0 * 35 / 50)
    assert f["false_tracks_per_min"] == pytest.approx(1 / (40 / 10 / 60))  # track 11 only, over 4 s
    assert f["id_switches"] == 1
    # SA: 30 visible frames at IoU(1 px shift of 6 px squares) = 30/42, 5 frames reporting a box on nothing (0),
    # 5 frames with nothing reported while the target is absent (1)
    iou = (5.0 * 6.0) / (2 * 36.0 - 30.0)
    assert f["state_accuracy"] == pytest.approx((30 * iou + 0 + 5) / 40)


def test_perception_score_counts_false_tracks_over_the_frames_processed():
    from groundsim.evaluation.mot import PerceptionScore

    ps = PerceptionScore(frame_rate_hz=10.0)
    for k in range(20):
        done = k < 10  # the second half refused by the pipeline: no track made
        ps.add([(0, 100.0, 50.0, True, 12.0)], {3: (10.0, 10.0)} if done else {}, None, processed=done)
    f = ps.figures()
    assert f["false_tracks_per_min"] == pytest.approx(1 / (10 / 10 / 60))  # one false track in 1 s
    assert f["pd_counted"] == 0  # the target's frames after its first second were all refused: none counted
    assert f["state_accuracy"] == pytest.approx(0.0)  # visible throughout, never a box reported


def _line(frame: int, oid: int, u: float, v: float, visible: bool = True, gt: bool = True) -> str:
    from groundsim.evaluation.mot import gt_line, square_box

    if gt:
        return gt_line(frame, oid, u, v, 1 if visible else None, 1.0)
    return f"{frame},{oid},{square_box(u, v)},1,-1,-1,-1\n"


def test_object_timeline_pairs_each_frames_objects_and_ids_one_to_one_nearest_first():
    from groundsim.evaluation.mot import object_timeline

    gt = _line(1, 1, 100.0, 100.0) + _line(1, 2, 102.0, 100.0) + _line(2, 1, 100.0, 100.0, visible=False)
    # frame 1: id 7 sits on object 2 and within 3 px of object 1 too; id 8 on object 1: each takes its nearest
    trk = (
        _line(1, 7, 101.9, 100.0, gt=False) + _line(1, 8, 100.2, 100.0, gt=False) + _line(2, 7, 100.5, 100.0, gt=False)
    )
    trk += _line(2, 9, 300.0, 40.0, gt=False) + _line(3, 9, 301.0, 40.0, gt=False)
    tl = object_timeline(gt, trk)
    assert tl["objects"] == {1: [(1, True, 8), (2, False, 7)], 2: [(1, True, 7)]}
    assert tl["false"] == {9: [2, 3]}  # (frame 3 has no truth at all: every tracked id there is a false one)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.integers(1, 4), st.integers(1, 5), st.floats(0, 20), st.floats(0, 20), st.booleans())),
    st.lists(st.tuples(st.integers(1, 4), st.integers(1, 5), st.floats(0, 20), st.floats(0, 20))),
)
def test_object_timeline_accounts_for_every_tracked_id_once_a_frame(gts, trks):
    from groundsim.evaluation.mot import MATCH_PX, object_timeline

    gt_by = {(f, i): (u, v, vis) for f, i, u, v, vis in gts}  # (one row per frame and id, as the files hold)
    trk_by = {(f, i): (u, v) for f, i, u, v in trks}
    gt = "".join(_line(f, i, u, v, vis) for (f, i), (u, v, vis) in gt_by.items())
    trk = "".join(_line(f, i, u, v, gt=False) for (f, i), (u, v) in trk_by.items())
    tl = object_timeline(gt, trk)
    for frame in range(1, 5):
        ids = {i for (f, i) in trk_by if f == frame}
        paired = [(g, tid) for g, rows in tl["objects"].items() for f, _, tid in rows if f == frame and tid is not None]
        false = {tid for tid, frames in tl["false"].items() if frame in frames}
        assert len({tid for _, tid in paired}) == len(paired)  # one object per tracked id
        assert {tid for _, tid in paired} | false == ids and not false & {tid for _, tid in paired}
        for g, tid in paired:  # each pair within the radius (the boxes' centres, after the files' 3 decimals)
            gu, gv, _ = gt_by[(frame, g)]
            tu, tv = trk_by[(frame, tid)]
            assert math.hypot(gu - tu, gv - tv) <= MATCH_PX + 0.01
        # an object and an id left unpaired on one frame are farther apart than the radius
        unpaired = {g for g, rows in tl["objects"].items() for f, _, tid in rows if f == frame and tid is None}
        for g in unpaired:
            gu, gv, _ = gt_by[(frame, g)]
            assert all(
                math.hypot(gu - trk_by[(frame, t)][0], gv - trk_by[(frame, t)][1]) > MATCH_PX - 0.01 for t in false
            )


def test_plot_objects_draws_a_png_from_the_mot_files(tmp_path):
    import numpy as np

    from groundsim.evaluation.report_plots import plot_objects

    gt = "".join(_line(k, 1, 50.0 + k, 60.0, visible=k < 20) for k in range(1, 31))
    trk = "".join(_line(k, 3, 50.0 + k, 60.0, gt=False) for k in range(5, 25))
    trk += "".join(_line(k, 4 + k, 200.0, 10.0, gt=False) for k in range(1, 12))  # 11 false ids: a shared row
    path = plot_objects(tmp_path / "o.png", gt, trk, np.arange(30) / 30.0, "t")
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_recorded_mot_numbers_the_simulators_frames_and_counts_the_daemons_confirmed_objects_on_theirs():
    from groundsim.evaluation.mot import object_timeline, recorded_mot

    def label(oid, u, v, visibility="visible"):
        return {"id": oid, "u_px": u, "v_px": v, "visibility": visibility}

    truth = [  # (out of order in the file: numbered in time)
        {"seq": 1, "time_boot_us": 1_033_333, "objects": [label(0, 11.0, 20.0), label(1, None, None, "out_of_frame")]},
        {"seq": 0, "time_boot_us": 1_000_000, "objects": [label(0, 10.0, 20.0), label(1, 50.0, 60.0, "occluded")]},
    ]
    objects = [
        {"time_boot_us": 1_033_333, "frame_index": 1, "objects": [
            {"id": 7, "state": "confirmed", "u_px": 11.2, "v_px": 20.0},
            {"id": 8, "state": "coasting", "u_px": 50.0, "v_px": 60.0},  # a prediction: not a tracked object
        ]},
        {"time_boot_us": 9_999_999, "frame_index": 2, "objects": [  # no truth frame of this time: left out
            {"id": 7, "state": "confirmed", "u_px": 11.0, "v_px": 20.0},
        ]},
    ]  # fmt: skip
    gt, trk, t_s = recorded_mot(truth, objects)
    assert t_s == [0.0, 0.033333]
    assert [line.split(",")[:2] + line.split(",")[6:8] for line in gt.splitlines()] == [
        ["1", "1", "1", "1"],  # frame 1, the target (id + 1), visible, class 1
        ["1", "2", "0", str(HIDDEN_CLASS)],  # the occluded one: consider 0
        ["2", "1", "1", "1"],  # (the object behind the camera has no row)
    ]
    assert [line.split(",")[:2] for line in trk.splitlines()] == [["2", "7"]]
    assert object_timeline(gt, trk)["objects"][1] == [(1, True, None), (2, True, 7)]
