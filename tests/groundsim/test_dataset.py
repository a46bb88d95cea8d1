"""groundsim.evaluation.dataset: labelled IR sequences, read back by independent readers (pycocotools, TrackEval)."""

from __future__ import annotations

import configparser
import csv
import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.dataset import (
    FORMATS,
    DatasetOptions,
    TargetLabel,
    body_box_corners_frd_m,
    export_dataset,
    target_label,
)
from groundsim.world.scenario import load_scenario, reference_scenario_paths
from onboard.core.errors import ConfigError
from onboard.core.frames import PinholeIntrinsics, rotmat_from_quat

LABEL_ATOL_PX = 0.05  # a label is only useful for training if it sits on the truth pixel (within 0.05 px)
LEVER_ATOL_M = 1e-3  # measured - true camera position = injected error, up to the lever arm's rotation (~um)
DURATION_S = 1.0
SEEDS = (0, 1)


def _scenario(name="P1"):
    return load_scenario(reference_scenario_paths()[name])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds")
    summaries, _ = export_dataset(
        [_scenario()],
        SEEDS,
        out,
        DatasetOptions(duration_s=DURATION_S, formats=("mot", "coco", "obs")),
        workers=2,
        progress=False,
    )
    return out, summaries


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    """Each column as numbers, or as text where it holds words (labels.csv's visibility_state, sensor_status)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))

    def column(k: str) -> np.ndarray:
        try:
            return np.array([float(r[k]) for r in rows])
        except ValueError:
            return np.array([r[k] for r in rows])

    return {k: column(k) for k in rows[0]}


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _independent_pixel(cams: dict, truth: dict, i: int) -> tuple[float, float]:
    """Pinhole projection written here from the files alone (cameras.csv intrinsics + truth.csv 3-D)."""
    p_t = np.array([truth["target_n_m"][i], truth["target_e_m"][i], truth["target_d_m"][i]])
    p_c = np.array([cams["true_n_m"][i], cams["true_e_m"][i], cams["true_d_m"][i]])
    w, x, y, z = (cams[f"true_q{c}"][i] for c in "wxyz")
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )  # R_ned_from_cam
    pc = R.T @ (p_t - p_c)
    return cams["fx_px"][i] * pc[0] / pc[2] + cams["cx_px"][i], cams["fy_px"][i] * pc[1] / pc[2] + cams["cy_px"][i]


def test_layout_and_manifest(dataset):
    out, summaries = dataset
    man = json.loads((out / "manifest.json").read_text())
    assert man["schema"] == "irtrack.dataset/1"
    assert man["seeds"] == list(SEEDS) and man["scenarios"][0]["name"] == "P1" and man["scenarios"][0]["sha256"]
    names = [s["name"] for s in man["sequences"]]
    assert names == ["P1-RTK-s0", "P1-RTK-s1"]
    for s in summaries:
        d = out / s.name
        assert len(list((d / "img1").glob("*.png"))) == s.frames == 30
        for f in ("labels.csv", "cameras.csv", "truth.csv", "seqinfo.ini", "gt/gt.txt"):
            assert (d / f).is_file(), f


def test_coco_loads_in_pycocotools_and_centroids_match_truth(dataset):
    COCO = pytest.importorskip("pycocotools.coco").COCO
    out, summaries = dataset
    coco = COCO(str(out / "coco.json"))
    assert len(coco.getImgIds()) == sum(s.frames for s in summaries)
    ann_ids = coco.getAnnIds(catIds=coco.getCatIds(catNms=["target"]))
    assert len(ann_ids) == sum(s.labelled for s in summaries) > 0
    cams = {s.name: _read_csv(out / s.name / "cameras.csv") for s in summaries}
    truth = {s.name: _read_csv(out / s.name / "truth.csv") for s in summaries}
    worst = 0.0
    for ann in coco.loadAnns(ann_ids):
        img = coco.loadImgs(ann["image_id"])[0]
        i = img["frame_index"] - 1
        u, v = _independent_pixel(cams[img["sequence"]], truth[img["sequence"]], i)
        ku, kv, flag = ann["keypoints"]
        worst = max(worst, abs(ku - u), abs(kv - v))
        x, y, w, h = ann["bbox"]
        assert flag == 2 and x <= ku <= x + w and y <= kv <= y + h  # the centroid inside its box
        assert (out / img["file_name"]).is_file()
        assert coco.annToMask(ann).sum() > 0  # pycocotools rasterises the box
    assert worst < LABEL_ATOL_PX
    # COCO's own evaluator: the ground truth submitted as detections is a perfect score
    from pycocotools.cocoeval import COCOeval

    dets = coco.loadRes(
        [
            dict(image_id=a["image_id"], category_id=a["category_id"], bbox=a["bbox"], score=1.0)
            for a in coco.loadAnns(ann_ids)
        ]
    )
    ev = COCOeval(coco, dets, "bbox")
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    assert ev.stats[0] == pytest.approx(1.0)  # AP at IoU .50:.95


def test_mot_layout_read_by_trackeval(dataset, tmp_path):
    """TrackEval reads each sequence's boxes where the labels put them, and scores a "tracker" that outputs
    the ground truth perfect through the project's own scorer (:func:`groundsim.evaluation.mot.score_mot`,
    which reads ``OUT/mot/{gt,trackers,seqmap.txt}``: here ``gt`` is the dataset itself)."""
    trackeval = pytest.importorskip(
        "trackeval"
    )  # installed with --no-deps (it pins opencv-python, which shadows contrib)
    from groundsim.evaluation.mot import BOX_SIDE_PX, score_mot

    out, summaries = dataset
    mot = tmp_path / "mot"
    mot.mkdir()
    (mot / "gt").symlink_to(out, target_is_directory=True)
    # the dataset's own seqmap, as TrackEval takes it (SEQMAP_FILE), and the copy score_mot reads
    assert (out / "seqmaps" / "irtrack-all.txt").read_text() == "name\n" + "".join(f"{s.name}\n" for s in summaries)
    (mot / "seqmap.txt").write_text((out / "seqmaps" / "irtrack-all.txt").read_text())
    trk = mot / "trackers" / "gt_copy" / "data"
    trk.mkdir(parents=True)
    for s in summaries:  # a "tracker" that outputs the ground truth: TrackEval must score it perfect
        rows = [line.split(",") for line in (out / s.name / "gt" / "gt.txt").read_text().splitlines()]
        (trk / f"{s.name}.txt").write_text("".join(",".join(r[:6] + ["1", "-1", "-1", "-1"]) + "\n" for r in rows))
    ds = trackeval.datasets.MotChallenge2DBox(
        {
            "GT_FOLDER": str(out),
            "TRACKERS_FOLDER": str(mot / "trackers"),
            "SKIP_SPLIT_FOL": True,
            "SEQMAP_FILE": str(out / "seqmaps" / "irtrack-all.txt"),
            "TRACKERS_TO_EVAL": ["gt_copy"],
            "PRINT_CONFIG": False,
        }
    )
    for s in summaries:
        raw = ds.get_raw_seq_data("gt_copy", s.name)
        assert raw["num_timesteps"] == s.frames
        assert sum(len(ids) for ids in raw["gt_ids"]) == s.labelled  # one box per labelled frame, no other
        labels = _read_csv(out / s.name / "labels.csv")
        for t in range(s.frames):
            boxes = raw["gt_dets"][t]
            if labels["in_image"][t]:
                assert boxes.shape == (1, 4) and raw["gt_ids"][t].tolist() == [1]
                # the BOX_SIDE_PX square about the label's centroid, in MOT's 1-based pixel coordinates
                half = BOX_SIDE_PX / 2
                np.testing.assert_allclose(
                    boxes[0],
                    [labels["u_px"][t] - half + 1, labels["v_px"][t] - half + 1, BOX_SIDE_PX, BOX_SIDE_PX],
                    atol=1e-3,
                )
    scores = score_mot(tmp_path, [s.name for s in summaries], tracker="gt_copy")
    assert set(scores) == {s.name for s in summaries}
    for seq, m in scores.items():
        assert m["MOTA"] == pytest.approx(1.0) and m["IDF1"] == pytest.approx(1.0) and m["IDSW"] == 0, (seq, m)
        assert m["HOTA"] == pytest.approx(1.0), (seq, m)


def test_seqinfo_ini_is_what_mot_readers_parse(dataset):
    out, summaries = dataset
    ini = configparser.ConfigParser()
    ini.read(out / summaries[0].name / "seqinfo.ini")
    seq = ini["Sequence"]
    assert (seq["name"], seq["imDir"], int(seq["seqLength"]), int(seq["frameRate"])) == (
        summaries[0].name,
        "img1",
        30,
        30,
    )
    assert (int(seq["imWidth"]), int(seq["imHeight"]), seq["imExt"]) == (640, 512, ".png")


def test_measured_pose_carries_the_injected_navigation_error(dataset):
    out, summaries = dataset
    cams = _read_csv(out / summaries[0].name / "cameras.csv")
    truth = _read_csv(out / summaries[0].name / "truth.csv")
    d = np.stack([cams[f"meas_{c}_m"] - cams[f"true_{c}_m"] for c in "ned"], axis=1)
    err = np.stack([truth[f"nav_p_err_{c}_m"] for c in "ned"], axis=1)
    assert np.abs(err).max() > 0.01  # RTK: a real error, so the check below can fail
    np.testing.assert_allclose(d, err, atol=LEVER_ATOL_M)
    q_t = np.stack([cams[f"true_q{c}"] for c in "wxyz"], axis=1)
    q_m = np.stack([cams[f"meas_q{c}"] for c in "wxyz"], axis=1)
    ang = [
        math.acos(min(1.0, (np.trace(rotmat_from_quat(a) @ rotmat_from_quat(b).T) - 1) / 2)) for a, b in zip(q_m, q_t)
    ]
    want = np.linalg.norm(np.stack([truth[f"nav_att_err_{c}_rad"] for c in "ned"], axis=1), axis=1)
    np.testing.assert_allclose(ang, want, atol=1e-6)


def test_same_seed_identical_files_other_seed_differs(dataset, tmp_path):
    out, _ = dataset
    again = tmp_path / "again"
    export_dataset(
        [_scenario()],
        [0],
        again,
        DatasetOptions(duration_s=DURATION_S, formats=("mot", "coco", "obs")),
        workers=1,
        progress=False,
    )
    a = {k: v for k, v in _tree_digest(out).items() if k.startswith("P1-RTK-s0/")}
    b = {k: v for k, v in _tree_digest(again).items() if k.startswith("P1-RTK-s0/")}
    assert len(a) == 30 + 6 and a == b  # 30 frames; labels, cameras, truth, obs, seqinfo.ini, gt.txt
    other = {k.replace("-s1/", "-s0/"): v for k, v in _tree_digest(out).items() if k.startswith("P1-RTK-s1/img1/")}
    assert sum(other[k] != a[k] for k in other) == 30  # another seed: other render noise in every frame


def test_sixteen_bit_pngs(tmp_path):
    import cv2

    summaries, _ = export_dataset(
        [_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.2, bit_depth=16), progress=False
    )
    img = cv2.imread(str(tmp_path / summaries[0].name / "img1" / "000001.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint16 and img.shape == (512, 640) and img.max() > 255


def test_label_box_clipped_at_the_image_edge():
    K = PinholeIntrinsics(fx_px=500.0, fy_px=500.0, cx_px=320.0, cy_px=256.0, width_px=640, height_px=512)
    corners = body_box_corners_frd_m(_scenario().ir.target_parts)
    R_nc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # camera looking north, x east, y down
    centred = target_label(K, np.zeros(3), R_nc, [20.0, 0.0, 0.0], np.eye(3), corners)
    assert centred.has_box and centred.visibility == 1.0
    assert centred.u_px == pytest.approx(320.0) and centred.x_px < centred.u_px < centred.x_px + centred.w_px
    # east offset so the centre sits 1 px inside the right edge: about half the box is outside
    edge = target_label(K, np.zeros(3), R_nc, [20.0, 319.0 * 20.0 / 500.0, 0.0], np.eye(3), corners)
    assert edge.in_image and 0.3 < edge.visibility < 0.7 and edge.x_px + edge.w_px == pytest.approx(640.0)
    behind = target_label(K, np.zeros(3), R_nc, [-20.0, 0.0, 0.0], np.eye(3), corners)
    assert not behind.in_image and not behind.has_box and math.isnan(behind.u_px)
    with pytest.raises(Exception, match="visibility"):
        TargetLabel(1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.5, True)


def test_a_mot_box_at_the_image_edge_is_the_whole_square_and_visibility_the_drawn_fraction():
    """The MOT gt box is the BOX_SIDE_PX square about the centroid, not clipped (a tracker's square about the same
    centre reaches past the edge alike); its visibility column stays MOT's visible fraction of the object: the
    drawn box's share in the image (labels.csv's), 0 for a target behind a cloud."""
    from groundsim.evaluation.dataset import mot_gt_lines
    from groundsim.evaluation.mot import BOX_SIDE_PX

    edge = TargetLabel(0.6, 100.5, 0.0, 99.0, 2.0, 3.0, 0.5, True)  # drawn box [-2, 2) x [99, 102): half in
    hidden = TargetLabel(300.5, 200.5, 299.0, 199.0, 3.0, 3.0, 1.0, True, occluded=True)
    rows = [line.split(",") for line in mot_gt_lines([(1, edge), (2, hidden)]).splitlines()]
    half = BOX_SIDE_PX / 2
    assert [float(v) for v in rows[0][2:6]] == pytest.approx(
        [0.6 - half + 1, 100.5 - half + 1, BOX_SIDE_PX, BOX_SIDE_PX]
    )
    assert rows[0][6] == "1" and float(rows[0][8]) == pytest.approx(0.5)
    assert rows[1][6] == "0" and float(rows[1][8]) == 0.0


def test_options_refuse_bad_values():
    with pytest.raises(ConfigError, match="--format"):
        DatasetOptions(formats=("yolo",))
    with pytest.raises(ConfigError, match="--bit-depth"):
        DatasetOptions(bit_depth=12)
    with pytest.raises(ConfigError, match="--nav-noise"):
        DatasetOptions(nav_noise="nope")


def test_cli_bad_format_is_one_line(capsys):
    assert cli_main(["dataset", "--format", "yolo"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--format" in err[0]


def test_a_shorter_run_into_the_same_folder_leaves_no_frame_of_the_longer_one(tmp_path):
    opts = DatasetOptions(duration_s=0.3)
    summaries, _ = export_dataset([_scenario()], [0], tmp_path, opts, progress=False)
    img1 = tmp_path / summaries[0].name / "img1"
    assert len(list(img1.glob("*.png"))) == 9
    export_dataset([_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.1), progress=False)
    assert sorted(p.name for p in img1.glob("*.png")) == ["000001.png", "000002.png", "000003.png"]


def test_a_run_into_a_dataset_replaces_its_sequences_whole(tmp_path, caplog):
    """Made again with other formats, a sequence keeps no file of the earlier run's formats (a gt.txt or an
    obs.csv of other frames), nor the dataset a coco.json of the frames it replaced; the seqmap goes with MOT."""
    export_dataset([_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.2, formats=FORMATS), progress=False)
    seq = tmp_path / "P1-RTK-s0"
    assert {"seqinfo.ini", "obs.csv"} <= {p.name for p in seq.iterdir()} and (tmp_path / "coco.json").exists()
    export_dataset([_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.1, formats=("obs",)), progress=False)
    assert not (seq / "gt").exists() and not (seq / "seqinfo.ini").exists()
    assert not (tmp_path / "coco.json").exists() and not (tmp_path / "seqmaps" / "irtrack-all.txt").exists()
    assert any("coco.json removed" in r.getMessage() for r in caplog.records)
    assert len((seq / "obs.csv").read_text().splitlines()) == 1 + 3  # this run's three frames
    export_dataset([_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.1, formats=("mot",)), progress=False)
    assert not (seq / "obs.csv").exists() and (seq / "gt" / "gt.txt").exists()


def test_a_dataset_with_sequences_this_run_does_not_make_is_refused(tmp_path):
    export_dataset([_scenario()], [0, 1], tmp_path, DatasetOptions(duration_s=0.1), progress=False)
    before = _tree_digest(tmp_path)
    with pytest.raises(ConfigError) as err:
        export_dataset([_scenario()], [1], tmp_path, DatasetOptions(duration_s=0.1), progress=False)
    assert str(err.value).startswith(
        f"--out {tmp_path}: holds a dataset with sequences this run does not make (P1-RTK-s0)"
    )
    assert _tree_digest(tmp_path) == before  # nothing touched


def test_an_out_folder_that_cannot_be_written_is_one_line(tmp_path, monkeypatch, capsys):
    """A folder that exists but refuses files (its mode, a read-only mount; root passes the mode test, so the
    refusal is simulated where the probe creates its file)."""
    import tempfile

    def refused(*_a, **_k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    assert cli_main(["dataset", "--duration", "0.1", "--no-progress", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"groundsim dataset: error: --out {tmp_path}: cannot write in the directory: Permission denied"]


def _target_q(core, k: int):
    i = k * core.ticks_per_frame
    c = core.flight.chunk_of(i)
    return c.tgt_q_ned_from_body[i - c.i0]


def test_the_targets_box_holds_it_as_drawn_without_a_scene():
    """P1 has no scene: the renderer's own box of the target it drew joins the body's projection in the label."""
    from groundsim.world.sim import SimCore

    sc = _scenario()
    core = SimCore(sc, 0, 0.1, render=True)
    corners = body_box_corners_frd_m(sc.ir.target_parts)
    for k in range(core.frame_count):
        fr = core.frame(k)
        assert fr.target_box_px is not None
        tr = fr.truth
        args = (
            sc.camera.intrinsics,
            [tr.cam_n_m, tr.cam_e_m, tr.cam_d_m],
            rotmat_from_quat([tr.q_ned_from_cam_w, tr.q_ned_from_cam_x, tr.q_ned_from_cam_y, tr.q_ned_from_cam_z]),
            [tr.target_n_m, tr.target_e_m, tr.target_d_m],
            rotmat_from_quat(_target_q(core, k)),
            corners,
        )
        body, joined = target_label(*args), target_label(*args, fr.target_box_px)
        x0, y0, x1, y1 = fr.target_box_px
        assert joined.x_px <= min(body.x_px, x0) + 1e-9 and joined.y_px <= min(body.y_px, y0) + 1e-9
        assert joined.x_px + joined.w_px >= max(x1, body.x_px + body.w_px) - 1e-9
        assert joined.w_px * joined.h_px > 2.0 * body.w_px * body.h_px  # the blur, not the body, sets it at range


def test_cli_negative_first_seed_names_its_option(capsys):
    assert cli_main(["dataset", "--seed0", "-1"]) == 2
    assert capsys.readouterr().err.strip() == "groundsim dataset: error: --seed0: expected an integer >= 0, got -1"


def test_cli_a_last_seed_beyond_63_bits_names_seed0(tmp_path, capsys):
    """The run seed is a 63-bit integer: --seed0 past it had been reported as --seed, an option dataset has not."""
    out = tmp_path / "ds"
    assert cli_main(["dataset", "--seed0", str(2**63 - 1), "--seeds", "2", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == (
        f"groundsim dataset: error: --seed0: expected an integer in [0, 2^63 - 2] with --seeds 2, got {2**63 - 1}"
    )
    assert not out.exists()


def test_obs_csv_is_reconstructs_input_and_it_reads_it(dataset, tmp_path, capsys):
    """--format obs: each in-image frame's label pixel and the MEASURED camera pose (cameras.csv's meas_*), in
    onboard.reconstruct's columns; the reconstruction reads it and writes one position per row."""
    from onboard.app.reconstruct import OBS_COLUMNS
    from onboard.app.reconstruct import main as reconstruct

    out, summaries = dataset
    seq = out / summaries[0].name
    with open(seq / "obs.csv", newline="") as f:
        assert tuple(next(csv.reader(f))) == OBS_COLUMNS
    obs, lab, cam = _read_csv(seq / "obs.csv"), _read_csv(seq / "labels.csv"), _read_csv(seq / "cameras.csv")
    seen = lab["in_image"] == 1
    assert len(obs["t_s"]) == int(seen.sum()) > 0
    np.testing.assert_array_equal(obs["t_s"], lab["t_s"][seen])
    np.testing.assert_allclose(obs["u_px"], lab["u_px"][seen], atol=1e-9)
    for o, c in (("cam_n_m", "meas_n_m"), ("cam_e_m", "meas_e_m"), ("cam_d_m", "meas_d_m"), ("q_w", "meas_qw")):
        np.testing.assert_allclose(obs[o], cam[c][seen], atol=1e-9)
    result = tmp_path / "out.csv"
    assert reconstruct([str(seq / "obs.csv"), "-o", str(result)]) == 0, capsys.readouterr().err
    rows = _read_csv(result)
    assert len(rows["t_s"]) == len(obs["t_s"]) and np.all(np.isfinite(rows["n_m"]))


def test_a_fleet_scenario_is_refused_naming_it(tmp_path):
    with pytest.raises(ConfigError, match=r"^--scenario: F1 is a fleet scenario"):
        export_dataset([_scenario("F1")], [0], tmp_path / "ds", DatasetOptions(duration_s=0.1), progress=False)
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize(
    "manifest", [None, '{"name": "my web app"}\n'], ids=["no_manifest", "a_manifest_of_something_else"]
)
def test_a_folder_that_is_not_a_datasets_is_refused_untouched(tmp_path, manifest):
    """A run removes coco.json and the seqmap it does not make and writes manifest.json: in a folder of the user's
    (a home folder, their own COCO labels) it is refused in one line before any sequence is flown."""
    (tmp_path / "coco.json").write_text('{"images": []}\n')
    (tmp_path / "seqmaps").mkdir()
    (tmp_path / "seqmaps" / "irtrack-all.txt").write_text("name\nmine\n")
    if manifest is not None:
        (tmp_path / "manifest.json").write_text(manifest)
    before = _tree_digest(tmp_path)
    with pytest.raises(ConfigError) as err:
        export_dataset([_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.1, formats=("obs",)), progress=False)
    assert str(err.value).startswith(f"--out {tmp_path}: ") and "\n" not in str(err.value)
    assert _tree_digest(tmp_path) == before


def test_a_dataset_interrupted_before_its_manifest_is_taken_again(tmp_path):
    """Ctrl-C leaves the finished sequences and no manifest: the same command is run into that folder again."""
    summaries, _ = export_dataset([_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.1), progress=False)
    for f in ("manifest.json", "seqmaps/irtrack-all.txt"):
        (tmp_path / f).unlink()
    (tmp_path / "seqmaps").rmdir()
    export_dataset([_scenario()], [0], tmp_path, DatasetOptions(duration_s=0.1), progress=False)
    assert (tmp_path / "manifest.json").is_file() and (tmp_path / summaries[0].name / "img1").is_dir()


def test_coco_objects_behind_a_cloud_are_ignored_by_cocoeval_as_trackeval_leaves_them_out(tmp_path):
    """An object behind a cloud (the target or another) was an ordinary COCO annotation, which pycocotools counted
    as a miss of a detector that reports only what it can see, where the MOT files' consider 0 leaves it out: it is
    now ``iscrowd`` 1 (the only "ignore" COCOeval reads), with ``visibility_state`` on every annotation."""
    COCO = pytest.importorskip("pycocotools.coco").COCO
    from pycocotools.cocoeval import COCOeval

    from groundsim.evaluation.dataset import TARGET_ID, SequenceSummary, coco_document
    from groundsim.world.render.scene import ObjectLabel

    def target(frame: int, occluded: bool) -> tuple:
        return (frame, TargetLabel(100.5, 80.5, 98.0, 78.0, 5.0, 5.0, 1.0, True, occluded), 1000 * frame)

    def bird(frame: int, visibility: str) -> tuple:
        return (frame, (ObjectLabel(3, "bird", 300.5, 200.5, (298, 198, 303, 203), visibility, 6.0, 500.0),))

    summary = SequenceSummary(
        "S-RTK-s0", "S", 0, "RTK", 4, 4, 640, 512, 30.0, 0.0,
        labels=(target(1, False), target(2, True), target(3, False), target(4, False)),
        objects=(bird(1, "visible"), bird(2, "visible"), bird(3, "occluded"), bird(4, "visible")),
    )  # fmt: skip
    doc = coco_document([summary], "test")
    anns = doc["annotations"]
    assert [(a["category_id"] == TARGET_ID, a["visibility_state"], a["iscrowd"], a["keypoints"][2]) for a in anns] == [
        (True, "visible", 0, 2),
        (False, "visible", 0, 2),
        (True, "occluded", 1, 1),
        (False, "visible", 0, 2),
        (True, "visible", 0, 2),
        (False, "occluded", 1, 1),
        (True, "visible", 0, 2),
        (False, "visible", 0, 2),
    ]
    path = tmp_path / "coco.json"
    path.write_text(json.dumps(doc))
    coco = COCO(str(path))
    # a detector that finds every object it can see, and nothing behind the clouds: a perfect score
    seen = [a for a in anns if a["visibility_state"] == "visible"]
    dets = coco.loadRes(
        [dict(image_id=a["image_id"], category_id=a["category_id"], bbox=a["bbox"], score=1.0) for a in seen]
    )
    ev = COCOeval(coco, dets, "bbox")
    ev.params.areaRng = [[0.0, 1e10]]  # every box is "small" by COCO's areas; one range, all of them
    ev.params.areaRngLbl = ["all"]
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    assert ev.stats[0] == pytest.approx(1.0)


@pytest.mark.parametrize("second", ["P1", "COPY"], ids=["the_same_file", "another_file_of_the_same_name"])
def test_two_scenarios_of_one_name_are_refused_before_out_is_made(tmp_path, capsys, second):
    """Both would be written into one sequence folder at once (PNGs of two writers, rows of both in one CSV, the
    sequence twice in the manifest): refused in one line naming --scenario, before --out is made."""
    copy = tmp_path / "P1.yaml"
    copy.write_text(reference_scenario_paths()["P1"].read_text())
    out = tmp_path / "ds"
    args = ["dataset", "--scenario", "P1", str(copy) if second == "COPY" else second, "--duration", "0.1"]
    assert cli_main([*args, "--no-progress", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("groundsim dataset: error: --scenario: P1 and "), err
    assert ("same file" if second == "P1" else "both scenario 'P1'") in err[0]
    assert not out.exists()
    with pytest.raises(ConfigError, match="^--scenario: P1 given twice"):  # the library's callers too
        export_dataset([_scenario(), load_scenario(copy)], [0], out, DatasetOptions(duration_s=0.1), progress=False)
    assert not out.exists()


def test_an_interrupted_run_into_a_dataset_leaves_no_index_of_frames_it_removed(tmp_path, monkeypatch, capsys):
    """A dataset made again and interrupted mid-sequence: the earlier manifest, coco.json and seqmap listed frames
    the sequence no longer held (its PNGs removed, gt.txt gone); they go before the first sequence is touched, the
    interrupted line names the sequence left unfinished, and the same command takes the folder again."""
    from groundsim.evaluation import dataset as dataset_module

    args = ["dataset", "--seeds", "2", "--duration", "0.5", "--format", "mot", "coco", "--workers", "1"]
    args += ["--no-progress", "--out", str(tmp_path)]
    assert cli_main(args) == 0
    assert (tmp_path / "manifest.json").is_file() and (tmp_path / "coco.json").is_file()
    write_png, written = dataset_module._write_png, []

    def interrupted_after_five_frames(path, pixels):
        if len(written) == 5:
            raise KeyboardInterrupt
        written.append(path)
        write_png(path, pixels)

    monkeypatch.setattr(dataset_module, "_write_png", interrupted_after_five_frames)
    capsys.readouterr()
    assert cli_main(args) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        f"interrupted: 0 of 2 sequences written in {tmp_path}; not finished: P1-RTK-s0, P1-RTK-s1 (no manifest; "
        "their folders are incomplete or an earlier run's)"
    ), err
    for index in ("manifest.json", "coco.json", "seqmaps"):
        assert not (tmp_path / index).exists(), index
    assert len(list((tmp_path / "P1-RTK-s0" / "img1").glob("*.png"))) == 5
    monkeypatch.undo()
    assert cli_main(args) == 0  # the same command again: a folder of sequences alone is the dataset's
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    for seq in manifest["sequences"]:
        assert len(list((tmp_path / seq["name"] / "img1").glob("*.png"))) == seq["frames"]


def test_a_smaller_run_into_an_interrupted_dataset_is_refused_as_into_a_whole_one(tmp_path, capsys):
    """A folder an interrupted run left (sequences, no manifest) is refused to a run that would not make all of its
    sequences again, as a whole dataset is: its manifest would not list the others while their files stayed."""
    export_dataset([_scenario()], [0, 1], tmp_path, DatasetOptions(duration_s=0.1), progress=False)
    for f in ("manifest.json", "seqmaps/irtrack-all.txt"):  # what an interrupted run leaves
        (tmp_path / f).unlink()
    (tmp_path / "seqmaps").rmdir()
    args = ["dataset", "--seeds", "1", "--duration", "0.1", "--no-progress", "--out", str(tmp_path)]
    assert cli_main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "holds sequences of an interrupted run this run does not make (P1-RTK-s1)" in err, err
    assert not (tmp_path / "manifest.json").exists()


def test_a_ctrl_c_while_the_index_is_written_waits_for_it(tmp_path, monkeypatch, capsys):
    """Every sequence written, a Ctrl-C as the index is written: the index is finished (a whole dataset, which the
    same command need not render again), then the command ends as interrupted, naming what it wrote."""
    import signal

    import groundsim.evaluation.dataset as dataset

    real = dataset.coco_document

    def ctrl_c_then_document(*a, **k):
        signal.raise_signal(signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(dataset, "coco_document", ctrl_c_then_document)
    args = ["dataset", "--seeds", "1", "--duration", "0.1", "--format", "mot", "coco", "--no-progress"]
    assert cli_main([*args, "--out", str(tmp_path)]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"interrupted: 1 of 1 sequences written in {tmp_path}: P1-RTK-s0", err
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert [s["name"] for s in manifest["sequences"]] == ["P1-RTK-s0"] and (tmp_path / "coco.json").is_file()


def test_a_mistyped_seed_count_is_one_line_not_a_job_list_of_that_size(tmp_path, capsys):
    from groundsim.evaluation.dataset import MAX_DATASET_SEQUENCES

    out = tmp_path / "ds"
    args = ["dataset", "--scenario", "P1", "P2", "--seeds", str(MAX_DATASET_SEQUENCES), "--out", str(out)]
    assert cli_main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--seeds: at most 10000 sequences in one dataset" in err, err
    assert not out.exists()


DEV_FULL = Path("/dev/full")  # every write to it fails as on a full disk (ENOSPC)
needs_dev_full = pytest.mark.skipif(not DEV_FULL.exists(), reason="needs /dev/full")


@needs_dev_full
def test_a_full_disk_under_a_sequence_is_one_line_naming_out_not_a_traceback(tmp_path, capsys):
    """A sequence's labels.csv on a full disk: its rows are flushed when it is closed, in the middle of the
    run's clean-up, which raised the OSError as a traceback (exit 1)."""
    seq = tmp_path / "P1-RTK-s0"
    (seq / "img1").mkdir(parents=True)  # what an interrupted run leaves, which a run takes again
    (seq / "labels.csv").symlink_to(DEV_FULL)
    code = cli_main(["dataset", "--duration", "0.1", "--workers", "1", "--no-progress", "--out", str(tmp_path)])
    err = [line for line in capsys.readouterr().err.splitlines() if "level=" not in line]
    assert code == 2
    assert err == [f"groundsim dataset: error: --out {tmp_path}: cannot write: No space left on device"]
    assert not (tmp_path / "manifest.json").exists()  # no index of a dataset that is not whole


@needs_dev_full
def test_a_frame_on_a_full_disk_names_the_file_and_the_reason_and_libpng_says_nothing(capfd):
    """cv2.imwrite answered a full disk with False alone, after libpng printed ``libpng error: Write Error`` on
    fd 2 itself: the command's line had no reason and a stray line before it."""
    from groundsim.evaluation.dataset import _write_png

    with pytest.raises(OSError) as err:
        _write_png(DEV_FULL, np.full((64, 80), 7, np.uint8))
    assert (err.value.strerror, err.value.filename) == ("No space left on device", str(DEV_FULL))
    assert capfd.readouterr().err == ""


@needs_dev_full
def test_a_truth_csv_that_cannot_be_written_is_named_without_an_option_dataset_does_not_have(tmp_path, capsys):
    seq = tmp_path / "P1-RTK-s0"
    (seq / "img1").mkdir(parents=True)
    (seq / "truth.csv").symlink_to(DEV_FULL)
    code = cli_main(["dataset", "--duration", "0.1", "--workers", "1", "--no-progress", "--out", str(tmp_path)])
    err = [line for line in capsys.readouterr().err.splitlines() if "level=" not in line]
    assert code == 2
    assert err == [f"groundsim dataset: error: {seq / 'truth.csv'}: cannot write: No space left on device"]
