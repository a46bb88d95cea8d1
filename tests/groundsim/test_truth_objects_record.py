"""The simulator's per-object truth in its recording (``groundsim run --record`` with a scene): one
``irtrack.truth_objects/1`` message per frame holding the rows of ``<truth>.objects.csv``, and their boxes as
foxglove.ImageAnnotations, read back by the mcap package's own reader."""

from __future__ import annotations

import csv
import io
import json
import math

import pytest

from groundsim.world.render.scene import ObjectLabel
from groundsim.world.truth import OBJECT_COLUMNS, TRUTH_COLUMNS, TruthRow, object_rows, truth_objects_json
from onboard.io.foxglove_messages import JSON_SCHEMAS, TRUTH_OBJECTS_SCHEMA
from onboard.io.record import TRUTH_ANNOTATIONS_TOPIC, TRUTH_OBJECTS_TOPIC, FlightRecorder, RecordConfig

LABELS = (
    ObjectLabel(0, "target", 320.25, 240.5, (319, 239, 322, 242), "visible", 7.5, 150.0, (10.0, 20.0, -50.0), True),
    ObjectLabel(1, "bird", 100.0, 80.0, (99, 79, 101, 81), "occluded", 2.0, 60.0, (1.0, 2.0, -3.0)),
    ObjectLabel(2, "aircraft", math.nan, math.nan, None, "out_of_frame", 0.0, 900.0),
)


def _row(seq: int) -> TruthRow:
    return TruthRow(**{**{c: 0 for c in TRUTH_COLUMNS}, "seq": seq, "time_boot_us": 1_000_000 + 40_000 * seq})


def test_truth_objects_are_recorded_as_the_csv_rows_with_their_schema(tmp_path):
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from mcap.reader import make_reader

    path = tmp_path / "sim.mcap"
    rec = FlightRecorder(RecordConfig(path=str(path)), recorder="groundsim")
    rec.start()
    for seq in range(3):
        rec.on_truth_objects(truth_objects_json(_row(seq), LABELS))
    rec.close()
    got, anns = [], []
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == TRUTH_OBJECTS_TOPIC:
                assert schema.name == TRUTH_OBJECTS_SCHEMA and schema.encoding == "jsonschema"
                assert json.loads(schema.data) == JSON_SCHEMAS[TRUTH_OBJECTS_SCHEMA]
                got.append((message.sequence, json.loads(message.data)))
            elif channel.topic == TRUTH_ANNOTATIONS_TOPIC:
                ann = ImageAnnotations()
                ann.ParseFromString(message.data)
                anns.append(ann)
    assert [s for s, _ in got] == [0, 1, 2] and len(anns) == 3
    msg = got[2][1]
    assert msg["seq"] == 2 and msg["time_boot_us"] == 1_080_000
    # the same numbers as the objects CSV's lines of that frame
    lines = list(
        csv.DictReader(
            io.StringIO(
                ",".join(OBJECT_COLUMNS) + "\n" + "".join(",".join(r) + "\n" for r in object_rows(_row(2), LABELS))
            )
        )
    )
    assert [o["id"] for o in msg["objects"]] == [int(r["object_id"]) for r in lines] == [0, 1, 2]
    assert [o["warm"] for o in msg["objects"]] == [True, False, False]
    for o, r in zip(msg["objects"], lines):
        assert o["cls"] == r["cls"] and o["visibility"] == r["visibility"]
        if o["box_px"] is None:
            assert r["x0_px"] == "nan" and o["u_px"] is None
            continue
        x, y, w, h = o["box_px"]
        assert (x, y, x + w, y + h) == tuple(int(r[k]) for k in ("x0_px", "y0_px", "x1_px", "y1_px"))
        assert o["u_px"] == float(r["u_px"]) and o["contrast_netd"] == float(r["contrast_netd"])
        assert o["warm"] is (r["warm"] == "1") and r["warm"] in ("0", "1")
        assert o["p_ned_m"] == [float(r["n_m"]), float(r["e_m"]), float(r["d_m"])]
    # annotations: the drawn objects only (the aircraft out of frame has no box), labelled by class and id
    assert [t.text for t in anns[2].texts] == ["target 0", "bird 1"]


@pytest.mark.parametrize(
    ("change", "said"),
    [
        (lambda o: {k: v for k, v in o.items() if k != "id"}, "no field 'id'"),
        (lambda o: {**o, "u_px": "320"}, "'u_px'"),
        (lambda o: {**o, "id": "x"}, "'id'"),
    ],
    ids=["object_without_id", "u_px_a_string", "id_a_string"],
)
def test_a_damaged_truth_object_is_refused_where_the_recording_is_read(tmp_path, change, said):
    """groundsim report's objects.png reads each truth object's id, u_px and v_px
    (groundsim.evaluation.mot.recorded_mot); load_recording, which says it checks every field the report reads,
    checked only that 'objects' was a list, so a damaged object was a KeyError, TypeError or ValueError traceback in the report."""
    from onboard.app.replay import load_recording
    from onboard.core.errors import InputError
    from tests.recording_edits import rewrite_recording

    path, bad = tmp_path / "sim.mcap", tmp_path / "bad.mcap"
    rec = FlightRecorder(RecordConfig(path=str(path)), recorder="groundsim")
    rec.start()
    for seq in range(3):
        rec.on_truth_objects(truth_objects_json(_row(seq), LABELS))
    rec.close()
    assert len(load_recording(str(path)).truth_objects) == 3  # the simulator's own messages pass, null centres too

    def damage(data: bytes) -> bytes:
        msg = json.loads(data)
        msg["objects"][0] = change(msg["objects"][0])
        return json.dumps(msg).encode()

    rewrite_recording(path, bad, lambda topic, i, _s: damage if topic == TRUTH_OBJECTS_TOPIC and i == 1 else None)
    with pytest.raises(InputError, match=f"message 1 on {TRUTH_OBJECTS_TOPIC} .* is damaged: .*{said}"):
        load_recording(str(bad))
