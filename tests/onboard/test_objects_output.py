"""Every object of the objects image chain in the outputs: the MCAP recording (read back by the mcap package's
own reader: JSON with its JSON schema, and foxglove.ImageAnnotations decoded by the Foxglove schema classes), the
replay (the same objects, bit for bit), and the video overlay (decoded by an independent decoder, PyAV's FFmpeg:
each object's box drawn where it is, the selected target brighter)."""

from __future__ import annotations

import dataclasses
import io
import json

import numpy as np
import pytest

from onboard.app.config import build_config
from onboard.app.observers import FrameResult, RecorderTap, frame_objects, recording_metadata
from onboard.io.foxglove_messages import (
    JSON_SCHEMAS,
    MIN_DRAWN_BOX_PX,
    OBJECTS_SCHEMA,
    drawn_box,
    objects_annotations,
    truth_objects_annotations,
)
from onboard.io.record import OBJECT_ANNOTATIONS_TOPIC, FlightRecorder, RecordingPoseSource
from tests.onboard.test_pipeline import Rig
from tests.udp_capture import UdpCapture

N_FRAMES = 40
STATIC_UV = (120, 90)  # a second warm object, still in the image
BOX_TOL_PX = 1e-9
TELEMETRY_LATE_US = 30_000  # the telemetry before the wait ends this long before the frame's capture time
TELEMETRY_AFTER_WAIT_US = 45_000


def _record(path, n: int = N_FRAMES, zoom_of=lambda k: 0.0, withheld_of=lambda k: ()):
    """The service's frame loop over a synthetic scene with the objects chain and a recorder tap (no sockets):
    (config, the objects messages the frames gave, tracks).  ``zoom_of(k)``: the zoom frame ``k`` states (IRF1);
    ``withheld_of(k)``: the daemon's warnings that withhold frame ``k``'s geometry (as its watchdog sets them)."""
    config = build_config(
        {"imaging": {"chain": "objects"}, "estimator": {"enabled": False}, "record": {"path": str(path)}}
    )
    rig = Rig(estimator=None, config=config)
    memo = RecordingPoseSource(rig.pose)
    rig.pipe.pose_source = memo
    # as in the daemon: the frame's telemetry arrives during the pipeline's wait, after the image chain looked up
    # its pose (extrapolated then), so the chain's pose and the frame's differ
    rig.pipe.pose_wait = lambda t_us: rig.feed_until(t_us + TELEMETRY_AFTER_WAIT_US)
    tap = RecorderTap(FlightRecorder(config.record, vehicle=config.vehicle, metadata=recording_metadata(config)), path)
    tap.start()
    sent, tracks = [], []
    try:
        for k in range(n):
            rig.feed_until(rig.scene.t_us(k) - TELEMETRY_LATE_US)
            frame = rig.scene.frame(k)
            px = frame.pixels.copy()
            u, v = STATIC_UV
            px[v : v + 2, u : u + 2] = np.minimum(px[v : v + 2, u : u + 2].astype(int) + 60, 255)
            frame = dataclasses.replace(frame, pixels=px, zoom=zoom_of(k))
            rx_ns = 1_000_000_000 + k * 33_000_000
            tap.on_received(frame, rx_ns)
            rig.pipe.withheld_because = withheld_of(k)
            track = rig.pipe.process(frame, rx_ns)
            objects = frame_objects(rig.pipe, track)
            looked_up, pose, imaging_pose = memo.take_lookups()
            result = FrameResult(rx_ns, looked_up, pose, track, None, objects, imaging_pose, rig.pipe.last_withheld)
            tap.on_frame(frame, result)
            sent.append(objects)
            tracks.append(track)
    finally:
        tap.close(5.0)
    return config, sent, tracks


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("objects") / "flight.mcap"
    config, sent, tracks = _record(path)
    return path, config, sent, tracks


def test_the_recording_holds_every_frames_objects_with_their_schema_read_by_the_mcap_reader(recorded):
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from mcap.reader import make_reader

    path, config, sent, _ = recorded
    objects, annotations = [], []
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == f"irtrack/{config.vehicle}/objects":
                assert schema.name == OBJECTS_SCHEMA and schema.encoding == "jsonschema"
                assert channel.message_encoding == "json"
                assert json.loads(schema.data) == JSON_SCHEMAS[OBJECTS_SCHEMA]
                objects.append((message.sequence, json.loads(message.data)))
            elif channel.topic == OBJECT_ANNOTATIONS_TOPIC:
                assert schema.name == "foxglove.ImageAnnotations" and schema.encoding == "protobuf"
                ann = ImageAnnotations()
                ann.ParseFromString(message.data)
                annotations.append(ann)
    assert [m for _, m in objects] == sent  # every frame, in order, the values as made
    assert [seq for seq, _ in objects] == list(range(N_FRAMES))
    confirmed = [m for m in sent if m["objects"]]
    assert len(confirmed) >= N_FRAMES // 2
    last = sent[-1]
    assert len(last["objects"]) == 2 and sum(o["primary"] for o in last["objects"]) == 1  # target and still object
    still = next(o for o in last["objects"] if not o["primary"])
    assert abs(still["u_px"] - (STATIC_UV[0] + 1)) < 0.5 and abs(still["v_px"] - (STATIC_UV[1] + 1)) < 0.5
    # the annotations: one box and one label per object, the frame's capture time as their stamp
    assert len(annotations) == N_FRAMES
    ann, msg = annotations[-1], sent[-1]
    assert len(ann.points) == len(msg["objects"]) == len(ann.texts)
    for pa, ta, o in zip(ann.points, ann.texts, msg["objects"]):
        x, y, w, h = drawn_box(*o["box_px"])
        corners = [c for p in pa.points for c in (p.x, p.y)]
        assert corners == pytest.approx([x, y, x + w, y, x + w, y + h, x, y + h], abs=BOX_TOL_PX)
        assert pa.timestamp.seconds * 1_000_000 + pa.timestamp.nanos // 1000 == msg["time_boot_us"]
        assert ta.text == (f"{o['id']} target" if o["primary"] else str(o["id"]))
        assert pa.thickness == (2.0 if o["primary"] else 1.0)


def test_replay_reads_the_objects_back_and_makes_the_same_ones(recorded):
    from onboard.app.replay import config_of, load_recording, replay
    from onboard.app.replay_compare import compare_objects

    path, _, sent, tracks = recorded
    rec = load_recording(str(path))
    assert rec.objects == sent
    res = replay(rec, config_of(rec), jobs=2)  # the objects chain needs the poses: runs in this process
    assert res.objects == sent
    assert compare_objects(rec.objects, res.objects) == (N_FRAMES, N_FRAMES, 0)
    changed = [dict(m) for m in sent]
    changed[-1] = {**changed[-1], "primary_id": None}
    assert compare_objects(changed, res.objects) == (N_FRAMES, N_FRAMES - 1, 0)
    assert [t["track_id"] for t in res.tracks] == [t.track_id for t in tracks]
    # the image chain's own poses were recorded (/onboard/imaging_pose) and are what makes it bit for bit: the
    # frames' poses alone give the chain other rotations
    assert sum(len(v) for v in rec.imaging_poses.values()) == N_FRAMES
    alone = replay(dataclasses.replace(load_recording(str(path)), imaging_poses={}), config_of(rec))
    assert compare_objects(rec.objects, alone.objects)[1] < N_FRAMES


def test_a_replay_states_each_frames_recorded_zoom_and_withholds_the_same_lines_of_sight(tmp_path):
    """The recording keeps the frame as a foxglove.RawImage, which has no zoom: frame_input carries IRF1's zoom, so a
    replay of frames that stated 2x withholds their lines of sight as the flight did (it published them all)."""
    from onboard.app.replay import config_of, load_recording, replay

    zoomed = range(20, 30)
    path = tmp_path / "zoomed.mcap"
    _, _, tracks = _record(path, zoom_of=lambda k: 2.0 if k in zoomed else 1.0)
    rec = load_recording(str(path))
    assert [inp["zoom"] for inp in rec.inputs] == [2.0 if k in zoomed else 1.0 for k in range(N_FRAMES)]
    flown = [tr.los is not None for tr in tracks]
    assert not any(flown[k] for k in zoomed) and any(flown[: zoomed.start]) and any(flown[zoomed.stop :])
    res = replay(rec, config_of(rec))
    assert [t["los_ned"] is not None for t in res.tracks] == flown


def test_a_replay_withholds_the_lines_of_sight_the_daemon_withheld_for_its_warnings(tmp_path):
    """The daemon withholds a frame's line of sight and 3-D position while its watchdog holds a mismatch (a camera or
    gimbal unlike the configuration, two senders on the frame key, a clock offset left uncompensated): decided from
    its links and clocks, which a replay does not have.  frame_input carries the codes that withheld each frame, so a
    replay withholds the same frames (before, it published a line of sight for every one of them) and restarts its
    estimate where the flight's did."""
    from onboard.app.replay import config_of, load_recording, replay

    mismatched = range(15, 25)
    path = tmp_path / "mismatched.mcap"
    _, _, tracks = _record(path, withheld_of=lambda k: ("camera_mismatch",) if k in mismatched else ())
    rec = load_recording(str(path))
    assert [inp["withheld_because"] for inp in rec.inputs] == [
        ["camera_mismatch"] if k in mismatched else [] for k in range(N_FRAMES)
    ]
    flown = [tr.los is not None for tr in tracks]
    assert not any(flown[k] for k in mismatched) and any(flown[: mismatched.start]) and any(flown[mismatched.stop :])
    res = replay(rec, config_of(rec))
    assert [t["los_ned"] is not None for t in res.tracks] == flown
    # a recording from before the field: the frames are replayed as before, none withheld for the daemon's warnings
    older = dataclasses.replace(
        rec, inputs=[{k: v for k, v in i.items() if k != "withheld_because"} for i in rec.inputs]
    )
    assert all(
        t["los_ned"] is not None for t in replay(older, config_of(rec)).tracks[mismatched.start : mismatched.stop]
    )


def test_annotations_draw_small_boxes_at_least_min_size_and_truth_labels():
    msg = {
        "time_boot_us": 2_500_000,
        "objects": [
            {"id": 3, "state": "confirmed", "box_px": [10.0, 20.0, 2.0, 2.0], "primary": True},
            {"id": 7, "state": "coasting", "box_px": [100.0, 50.0, 20.0, 12.0], "primary": False},
        ],
    }
    ann = objects_annotations(msg)
    small = [c for p in ann.points[0].points for c in (p.x, p.y)]
    lo, hi = 11 - MIN_DRAWN_BOX_PX / 2, 11 + MIN_DRAWN_BOX_PX / 2
    assert small == pytest.approx([lo, lo + 10, hi, lo + 10, hi, hi + 10, lo, hi + 10])
    big = [c for p in ann.points[1].points for c in (p.x, p.y)]
    assert big == pytest.approx([100, 50, 120, 50, 120, 62, 100, 62])
    assert ann.points[1].outline_color.r == 1.0 and ann.points[1].outline_color.b < 0.5  # coasting: amber
    assert (ann.points[0].timestamp.seconds, ann.points[0].timestamp.nanos) == (2, 500_000_000)
    truth = {
        "seq": 1,
        "time_boot_us": 5,
        "objects": [
            {"id": 0, "cls": "target", "box_px": [4.0, 5.0, 3.0, 3.0]},
            {"id": 2, "cls": "bird", "box_px": None},  # not drawn on this frame: left out
        ],
    }
    t_ann = truth_objects_annotations(truth)
    assert len(t_ann.points) == 1 and t_ann.texts[0].text == "target 0"


# --------------------------------------------------------------------------- video overlay

W_PX, H_PX = 320, 240


def _objects_msg() -> dict:
    return {
        "schema": OBJECTS_SCHEMA,
        "time_boot_us": 1,
        "frame_index": 0,
        "primary_id": 4,
        "objects": [
            {
                "id": 4,
                "state": "confirmed",
                "u_px": 80.0,
                "v_px": 60.0,
                "box_px": [70.0, 50.0, 20.0, 20.0],
                "primary": True,
            },
            {
                "id": 9,
                "state": "confirmed",
                "u_px": 220.0,
                "v_px": 160.0,
                "box_px": [210.0, 150.0, 20.0, 20.0],
                "primary": False,
            },
            {
                "id": 12,
                "state": "confirmed",
                "u_px": 161.0,
                "v_px": 121.0,
                "box_px": [160.0, 120.0, 2.0, 2.0],
                "primary": False,
            },
        ],
    }


def test_overlay_draws_every_object_the_target_brighter_and_frames_point_targets():
    from onboard.io.video import OBJECT_GREY, draw_overlay

    img = np.full((H_PX, W_PX), 40, np.uint8)
    img[120:122, 160:162] = 90  # the point target of object 12
    out = draw_overlay(img, None, _objects_msg())
    assert out[50, 70:91].min() == OBJECT_GREY["primary"] and out[60, 90] == OBJECT_GREY["primary"]
    assert out[150, 210:231].min() == OBJECT_GREY["confirmed"] and out[160, 230] == OBJECT_GREY["confirmed"]
    assert out[60, 80] == 40 and out[160, 220] == 40  # inside the boxes: the image
    assert np.all(out[120:122, 160:162] == 90)  # a point target is framed, not covered
    x, y, w, h = drawn_box(160.0, 120.0, 2.0, 2.0)
    assert out[int(round(y)), int(round(x)) : int(round(x + w)) + 1].min() == OBJECT_GREY["confirmed"]
    assert np.all(img[50, 70:91] == 40)  # the input untouched
    assert np.array_equal(draw_overlay(img, None, None), img)


def test_overlay_boxes_survive_h264_decoded_by_pyav():
    av = pytest.importorskip("av")
    from onboard.io.video import H264TsEncoder, draw_overlay

    buf = io.BytesIO()
    enc = H264TsEncoder(buf, W_PX, H_PX, fps=30.0, gop_frames=30)
    img = np.full((H_PX, W_PX), 40, np.uint8)
    n = 5
    for _ in range(n):
        enc.encode(draw_overlay(img, None, _objects_msg()))
    enc.close()
    c = av.open(io.BytesIO(buf.getvalue()), format="mpegts")
    try:
        frames = [f.to_ndarray(format="gray") for f in c.decode(video=0)]
    finally:
        c.close()
    assert len(frames) == n
    dec = frames[-1].astype(int)
    # each box's top edge decoded bright against the grey 40 sky; the primary brighter than the others
    primary_edge = dec[50, 72:89].mean()
    other_edge = dec[150, 212:229].mean()
    assert primary_edge > 240 and 150 < other_edge < primary_edge - 20
    sky = dec[100, 40]  # far from any box (the decoder maps the encoder's luma range: 40 reads about 28)
    assert sky < 60 and abs(dec[60, 80] - sky) <= 3  # inside a box: the sky too


# --------------------------------------------------------------------------- live view


@pytest.mark.integration
def test_the_live_view_serves_the_objects_and_their_annotations():
    import asyncio

    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

    from onboard.io.live_view import LiveView, LiveViewConfig
    from tests.onboard.test_live_view import _watch

    lv = LiveView(LiveViewConfig(), port=0, vehicle="uav1")
    lv.start()
    try:
        msg = _objects_msg()
        topics = {lv.objects_topic, OBJECT_ANNOTATIONS_TOPIC}
        got = asyncio.run(
            _watch(f"ws://127.0.0.1:{lv.port}", topics, {t: 1 for t in topics}, lambda: lv.on_objects(msg))
        )
    finally:
        lv.close()
    adv = got["advertised"]
    assert adv[lv.objects_topic]["schemaName"] == OBJECTS_SCHEMA and adv[lv.objects_topic]["encoding"] == "json"
    assert adv[OBJECT_ANNOTATIONS_TOPIC]["schemaName"] == "foxglove.ImageAnnotations"
    assert json.loads(got["messages"][lv.objects_topic][0]) == msg
    ann = ImageAnnotations()
    ann.ParseFromString(got["messages"][OBJECT_ANNOTATIONS_TOPIC][0])
    assert [t.text for t in ann.texts] == ["4 target", "9", "12"]


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_the_video_tap_streams_the_objects_drawn():
    """The daemon's video tap: FrameResult.objects -> VideoStreamer (AGC, overlay, H.264 in MPEG-TS over UDP on
    127.0.0.1) -> PyAV decodes the datagrams: the boxes are in the picture."""
    import time

    av = pytest.importorskip("av")
    from onboard.app.observers import VideoTap
    from onboard.core.irframe import IrFrame
    from onboard.core.track import Track

    rx = UdpCapture()
    config = build_config(
        {
            "camera": {"intrinsics": {"width_px": W_PX, "height_px": H_PX, "fx_px": 300.0, "fy_px": 300.0}},
            "video": {"destination": f"127.0.0.1:{rx.port}", "transport": "mpegts", "queue_length": 16},
        }
    )
    tap = VideoTap(config, config.camera.pinhole())
    n = 12
    sky = np.full((H_PX, W_PX), 1000, np.uint16) + (np.arange(W_PX, dtype=np.uint16) % 7)[None, :]
    try:
        tap.start()
        for k in range(n):
            track = Track(vehicle="uav1", seq=k, time_boot_us=k * 33_333, state="searching")
            tap.on_frame(IrFrame(k, k * 33_333, sky), FrameResult(0, True, None, track, None, _objects_msg()))
            time.sleep(0.02)
        deadline = time.monotonic() + 20.0
        while tap.streamer.frames_encoded < n and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        tap.close(2.0)
        rx.close()
    c = av.open(io.BytesIO(b"".join(rx.chunks)), format="mpegts")
    try:
        frames = [f.to_ndarray(format="gray").astype(int) for f in c.decode(video=0)]
    finally:
        c.close()
    assert len(frames) >= n - 3  # MPEG-TS holds the last picture or two back until the next
    dec = frames[-1]
    sky_grey = np.median(dec)
    assert dec[50, 72:89].mean() > sky_grey + 100 and dec[150, 212:229].mean() > sky_grey + 60


def test_every_json_message_of_the_recording_conforms_to_its_embedded_schema(recorded):
    # objects, frame inputs, the image chain's poses and tracks: each key declared, each required one present, each
    # value of its type; the annotations numbered as the frames their objects came from
    from mcap.reader import make_reader

    from tests.json_schema_check import check

    path, config, _sent, _ = recorded
    seen, annotated, objects_seqs = set(), [], []
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding == "json":
                errors = check(json.loads(message.data), json.loads(schema.data))
                assert not errors, (channel.topic, errors[:5])
                seen.add(schema.name)
            if channel.topic == OBJECT_ANNOTATIONS_TOPIC:
                annotated.append(message.sequence)
            elif channel.topic == f"irtrack/{config.vehicle}/objects":
                objects_seqs.append(message.sequence)
    assert {"irtrack.objects/1", "irtrack.frame_input/1", "irtrack.track/2"} <= seen
    assert annotated == objects_seqs == list(range(N_FRAMES))


def test_the_objects_rays_are_withheld_with_the_tracks_and_say_their_compensation():
    """While the daemon withholds the geometry (a camera or gimbal mismatch) the track had no line of sight but every
    object kept its los_ned (a direction the daemon itself called wrong); and the objects' rays, looked up at the
    frame's time less the camera's compensation, did not say so, as the track does (compensated_us)."""
    config = build_config({"imaging": {"chain": "objects"}, "estimator": {"enabled": False}})
    rig = Rig(estimator=None, config=config)
    rays = []
    for k in range(30):
        if k == 20:
            rig.pipe.withheld_because = ("camera_mismatch",)
        track = rig.step(k)
        msg = frame_objects(rig.pipe, track)
        assert msg is not None and msg["compensated_us"] == track.compensated_us
        rays.append(([o["los_ned"] for o in msg["objects"]], [o["los_sigma_rad"] for o in msg["objects"]], track))
    before = [r for r in rays[10:20] if r[0]]
    assert before and all(los is not None for los_list, _, _ in before for los in los_list)
    after = rays[20:]
    assert any(los_list for los_list, _, _ in after)  # the objects are still there, their pixels published
    assert all(los is None for los_list, _, _ in after for los in los_list)
    assert all(s is None for _, sigmas, _ in after for s in sigmas)
    assert all(track.los is None for _, _, track in after)


def test_the_objects_line_of_sight_sigma_counts_the_attitude_error_as_the_tracks_does():
    """The objects message gave each ray the chain's pixel sigma alone (1 px over fx), while the track's line of sight
    of the same primary on the same frame counts the camera attitude's error too: 0.65 of the track's sigma under
    RTK (an audit). Now the attitude's sigma is in quadrature: never below the track's elevation sigma."""
    import math

    config = build_config({"imaging": {"chain": "objects"}, "estimator": {"enabled": False}})
    rig = Rig(estimator=None, config=config)
    compared = 0
    for k in range(25):
        track = rig.step(k)
        msg = frame_objects(rig.pipe, track)
        prim = [o for o in msg["objects"] if o["primary"] and o["state"] == "confirmed"] if msg else []
        if not prim or track.los is None:
            continue
        s_el_rad = math.radians(track.los.sigma_elevation_deg)
        assert prim[0]["los_sigma_rad"] >= s_el_rad
        assert prim[0]["los_sigma_rad"] >= rig.pipe.attitude_sigma_rad > 0
        compared += 1
    assert compared >= 10


def test_the_objects_message_states_the_tracks_run_and_no_key_without_one():
    """A restarted daemon's object ids start again, as its track ids: the objects say its run as the track does."""
    config = build_config({"imaging": {"chain": "objects"}, "estimator": {"enabled": False}})
    rig = Rig(estimator=None, config=config)
    rig.pipe.run_id = "0123456789abcdef"
    msgs = [frame_objects(rig.pipe, rig.step(k)) for k in range(15)]
    assert msgs and all(m["run_id"] == "0123456789abcdef" for m in msgs if m is not None)
    rig.pipe.run_id = None  # (a replay of a recording older than run ids: the key absent, as in the recording)
    msg = frame_objects(rig.pipe, rig.step(15))
    assert msg is not None and "run_id" not in msg
