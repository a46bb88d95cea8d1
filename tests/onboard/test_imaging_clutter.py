"""The clutter-robust detector (onboard.imaging.clutter) and the object tracker (onboard.imaging.objects)
on small synthetic frames with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics, quat_from_euler, rotmat_from_quat
from onboard.imaging.clutter import (
    ClutterParams,
    DefectMap,
    cfar_threshold,
    column_offsets,
    frame_event,
    isolated_outliers,
    local_contrast,
    local_noise,
    local_noise_coarse,
    point_candidates,
    point_contrast,
    remove_column_offsets,
)
from onboard.imaging.objects import ObjectTracker

H_PX, W_PX = 96, 128
NOISE_GREY = 0.5
CENTRE_TOL_PX = 0.3  # contrast-weighted centre of a symmetric blob on noise
OFFSET_TOL_GREY = 0.15  # column offsets recovered from 24 sampled rows of 0.5 grey noise
FLAT_TOL_GREY = 1e-3  # float32 rounding of box means on a plane
STAIR_FRACTION = 0.1  # of an oblique edge's step left at its rasterised stair corners
STAIR_SLOPE = 0.01  # grey per (grey per 10 px) of slope more there (hypothesis found 0.175 at step 1.5, slope 3.5)


def _blob(img: np.ndarray, u: float, v: float, amp: float, sigma_px: float = 0.7) -> None:
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]].astype(np.float64)
    img += amp * np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * sigma_px**2))


def _sky(rng: np.random.Generator) -> np.ndarray:
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    return 60.0 + 20.0 * yy / H_PX + 3.0 * xx / W_PX + rng.normal(0.0, NOISE_GREY, (H_PX, W_PX))


def test_column_offsets_recovers_known_stripes():
    rng = np.random.default_rng(1)
    stripes = rng.normal(0.0, 2.0, W_PX)
    stripes -= np.median(stripes)
    img = _sky(rng) + stripes[None, :]
    off = column_offsets(img.astype(np.float32), 15)
    # measured against a 15-column running mean: the stripes' column-to-column part is what is found
    # (what a point detector sees); their slow part stays, like any smooth background
    padded = np.pad(stripes, 7, mode="reflect")
    high_pass = stripes - np.convolve(padded, np.ones(15) / 15, mode="valid")
    high_pass -= np.median(high_pass)
    assert np.max(np.abs(off - high_pass)) < OFFSET_TOL_GREY * 4  # the largest of 128 medians of 24 noisy rows
    assert np.median(np.abs(off - high_pass)) < OFFSET_TOL_GREY
    cleaned = remove_column_offsets(img.astype(np.float32), off)
    assert np.std(np.diff(np.median(cleaned, axis=0))) < 0.25 * np.std(np.diff(stripes))


def test_defect_map_finds_hot_and_dead_pixels_not_a_moving_target():
    rng = np.random.default_rng(2)
    hot = [(10, 20), (50, 90), (80, 5)]
    dead = [(30, 60), (70, 110)]
    dm = DefectMap((H_PX, W_PX), frames=10, fraction=0.6)
    for k in range(12):
        img = _sky(rng)
        _blob(img, 40.0 + 2.0 * k, 48.0, 30.0)
        for i, j in hot:
            img[i, j] += 40.0
        for i, j in dead:
            img[i, j] = 0.0
        dm.update(img.astype(np.float32), 4 * NOISE_GREY)
    assert set(zip(*np.nonzero(dm.mask))) == set(hot) | set(dead)
    repaired = dm.repair(img.astype(np.float32))
    for i, j in hot + dead:
        assert abs(repaired[i, j] - np.median(img[i - 1 : i + 2, j - 1 : j + 2])) < 1e-3
    dm.reset()
    assert not dm.mask.any()


def test_isolated_outliers_spares_a_two_pixel_target():
    img = np.full((H_PX, W_PX), 50.0, np.float32)
    img[40:42, 60:62] = 80.0  # a 2 x 2 target: each pixel has a bright neighbour
    img[20, 20] = 80.0
    mask = isolated_outliers(img, 5.0)
    assert list(zip(*np.nonzero(mask))) == [(20, 20)]


@settings(max_examples=40, deadline=None)
@given(
    gx=st.floats(-5.0, 5.0),
    gy=st.floats(-5.0, 5.0),
    step=st.floats(0.0, 50.0),
    angle=st.floats(0.0, math.pi),
)
def test_point_contrast_at_most_a_tenth_of_a_straight_edge_on_a_plane(gx, gy, step, angle):
    """A plane gives <= 0; a rasterised oblique edge leaves one-pixel stair corners, bounded.  (The
    4 px stage alone lets a third of the step through along an edge whose bright side slopes away.)"""
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    img = 100.0 + gx * xx / 10 + gy * yy / 10
    img += step * ((xx - W_PX / 2) * math.cos(angle) + (yy - H_PX / 2) * math.sin(angle) > 0)
    c = point_contrast(img.astype(np.float32), ClutterParams())[
        6:-6, 6:-6
    ]  # the border replicates: a plane stops there
    slope = abs(gx) + abs(gy)  # grey per 10 px
    assert float(c.max()) <= STAIR_FRACTION * step + STAIR_SLOPE * slope + FLAT_TOL_GREY * (1 + slope + step)


@pytest.mark.parametrize("side", ["left", "right", "top", "bottom"])
def test_no_point_contrast_where_the_surround_leaves_the_frame(side):
    """A roof cut by the frame's edge, its surround beyond the edge replicated from itself, is no point: the
    contrast is 0 within guard_px + cell_px // 2 of every edge; a point just inside that band keeps its own."""
    p = ClutterParams()
    band = p.guard_px + p.cell_px // 2
    img = np.full((H_PX, W_PX), 50.0)
    inner = band + 3.0  # px from the edge
    at = {
        "left": (1.5, H_PX / 2),
        "right": (W_PX - 1.5, H_PX / 2),
        "top": (W_PX / 2, 1.5),
        "bottom": (W_PX / 2, H_PX - 1.5),
    }
    inside = {
        "left": (inner, H_PX / 2 + 20),
        "right": (W_PX - inner, H_PX / 2 + 20),
        "top": (W_PX / 2 + 20, inner),
        "bottom": (W_PX / 2 + 20, H_PX - inner),
    }
    _blob(img, *at[side], 30.0)
    _blob(img, *inside[side], 30.0)
    c = point_contrast(img.astype(np.float32), p)
    edge = np.ones_like(c, dtype=bool)
    edge[band:-band, band:-band] = False
    assert np.all(c[edge] == 0.0)
    u, v = inside[side]
    assert c[int(v) - 1 : int(v) + 2, int(u) - 1 : int(u) + 2].max() > 10.0


def test_point_contrast_keeps_a_point_and_drops_a_small_cloud_puff():
    img = np.full((H_PX, W_PX), 50.0)
    img[:, :20] = 70.0  # a warm cloud on the left
    img[40:46, 40:46] = 70.0  # a 6 px puff: narrower than the 4 px surround's reach
    _blob(img, 90.0, 50.0, 8.0)
    c = point_contrast(img.astype(np.float32), ClutterParams())
    assert c[47:52, 87:92].max() > 2.0  # the point beats both surrounds
    assert c[:, :60].max() <= FLAT_TOL_GREY  # the puff beats the 4 px surround, not the 2 px one
    assert local_contrast(img.astype(np.float32), 3, 4)[38:48, 38:48].max() > 2.0


def test_cfar_threshold_follows_the_local_noise_with_a_floor():
    rng = np.random.default_rng(3)
    img = np.full((H_PX, W_PX), 50.0)
    img[:, W_PX // 2 :] += rng.normal(0.0, 4.0, (H_PX, W_PX // 2))  # textured half
    noise = local_noise(img.astype(np.float32), 15)
    thr = cfar_threshold(noise, 5.0, 0.8)
    assert np.all(thr[:, :40] == np.float32(0.8))  # noiseless: the floor
    textured = float(np.median(noise[:, W_PX // 2 + 10 :]))
    assert 0.6 * 4.0 < textured < 1.2 * 4.0  # ~ the texture's sigma (the 3 x 3 mean takes a share)


def test_point_candidates_centres_and_limits():
    rng = np.random.default_rng(4)
    img = _sky(rng)
    truth = [(30.3, 40.6), (100.7, 20.2)]
    for u, v in truth:
        _blob(img, u, v, 25.0)
    img[70:90, 60:80] += 30.0  # too large to be a point
    p = ClutterParams()
    f = img.astype(np.float32)
    cands = point_candidates(point_contrast(f, p), cfar_threshold(local_noise(f), p.threshold_sigma, 0.8), p)
    found = sorted((c.u_px, c.v_px) for c in cands)
    assert len(found) == 2
    for (u, v), (tu, tv) in zip(found, sorted(truth)):
        assert math.hypot(u - tu, v - tv) < CENTRE_TOL_PX
    assert all(c.score >= 1.0 for c in cands)


def test_frame_event_frozen_step_ok():
    a = np.full((H_PX, W_PX), 100, np.uint8)
    assert frame_event(a, None, None, 3.0)[0] == "ok"
    assert frame_event(a, a.copy(), 100.0, 3.0)[0] == "frozen"
    b = a + 5
    assert frame_event(b, a, 100.0, 3.0) == ("step", 105.0)
    assert frame_event(a + 3, a, 100.0, 3.0) == ("ok", 103.0)  # a step is a jump of more than step_lsb
    assert frame_event(a + 4, a, 100.0, 3.0) == ("step", 104.0)
    # one pixel changed is a new frame, on the median's sampling grid (every 8th row and column) or off it
    for i, j in ((0, 0), (3, 5)):
        c = a.copy()
        c[i, j] = 101
        assert frame_event(c, a, 100.0, 3.0)[0] == "ok"


# ---------------------------------------------------------------- object tracker

K = PinholeIntrinsics(200.0, 200.0, W_PX / 2, H_PX / 2, W_PX, H_PX)


def _frame(rng, points, amp=30.0) -> np.ndarray:
    img = _sky(rng)
    for u, v in points:
        _blob(img, u, v, amp)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def test_two_crossing_objects_keep_their_ids():
    rng = np.random.default_rng(5)
    tr = ObjectTracker(K)
    ids_a, ids_b = set(), set()
    for k in range(60):
        a = (20.0 + 1.5 * k, 40.0 + 0.2 * k)  # they cross near frame 30
        b = (110.0 - 1.5 * k, 52.0 - 0.2 * k)
        out = tr.update(_frame(rng, [a, b]), None)
        for o in out.confirmed:
            if math.hypot(o.u_px - a[0], o.v_px - a[1]) < 2.0 and math.hypot(a[0] - b[0], a[1] - b[1]) > 6.0:
                ids_a.add(o.object_id)
            if math.hypot(o.u_px - b[0], o.v_px - b[1]) < 2.0 and math.hypot(a[0] - b[0], a[1] - b[1]) > 6.0:
                ids_b.add(o.object_id)
    assert len(ids_a) == 1 and len(ids_b) == 1 and ids_a != ids_b


def test_camera_rotation_is_compensated_from_the_pose():
    """A world-fixed point while the camera hunts 6 px back and forth each frame (beyond the 4 px gate, and no
    constant image velocity the tracker's two-point initiation could follow) and drifts slowly: one id, confirmed on
    the first frame that can (11); without the pose, never confirmed."""
    rng = np.random.default_rng(6)
    los_ned = np.array([1.0, 0.0, 0.0])
    R_mount = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # cam z = north, x = east, y = down
    for pose in (True, False):
        tr = ObjectTracker(K)
        ids, first = set(), None
        for k in range(30):
            yaw = -0.03 * (k % 2) - 0.002 * k  # rad: 6 px one way, then back, 0.4 px a frame of drift
            R = rotmat_from_quat(quat_from_euler(0.0, 0.0, yaw)) @ R_mount
            c = R.T @ los_ned
            u, v = K.fx_px * c[0] / c[2] + K.cx_px, K.fy_px * c[1] / c[2] + K.cy_px
            out = tr.update(_frame(rng, [(u - 30.0, v)]), R if pose else None)
            ids |= {o.object_id for o in out.confirmed}
            if first is None and out.confirmed:
                first = k
        if pose:
            assert len(ids) == 1 and first == 11
        else:
            assert not ids  # without the pose the gate cannot follow the camera's motion


def _near_far(k: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """Two objects drifting apart (each other's only neighbour: they must move unlike each other to be
    confirmed, see ObjectParams): one near the image centre, one near a corner."""
    return (W_PX / 2 + 3 + 0.1 * k, H_PX / 2 - 2), (20.0, 20.0 + 0.3 * k)


def test_primary_is_the_steady_object_nearest_the_centre_and_a_change_is_reported():
    rng = np.random.default_rng(7)
    tr = ObjectTracker(K)
    changes = []
    primary_uv = None
    for k in range(24):
        near, far = _near_far(k)
        out = tr.update(_frame(rng, [near, far]), None)
        changes.append(out.primary_changed)
        if out.primary is not None:
            primary_uv = (out.primary.u_px, out.primary.v_px)
    assert primary_uv is not None and math.hypot(primary_uv[0] - near[0], primary_uv[1] - near[1]) < CENTRE_TOL_PX
    assert sum(changes) == 1
    first = tr.update(_frame(rng, list(_near_far(24))), None).primary_id
    for k in range(tr.params.coast_frames + 2):  # the primary disappears for good
        out = tr.update(_frame(rng, [_near_far(25 + k)[1]]), None)
    # the change is reported; the far object, in the corner (0.24 rad off the axis), is not taken in its place
    assert first is not None and out.primary_id is None and any(o.object_id != first for o in out.confirmed)
    assert tr.primary_changes == 2


def test_frozen_frames_measure_nothing_and_lose_nothing():
    rng = np.random.default_rng(8)
    tr = ObjectTracker(K)
    for _ in range(8):
        img = _frame(rng, [(60.0, 50.0)])
        out = tr.update(img, None)
    ids = {o.object_id for o in out.confirmed}
    for _ in range(tr.params.coast_frames + 5):
        out = tr.update(img, None)  # the shutter is closed: the same frame again
        assert out.event == "frozen" and not out.confirmed
    out = tr.update(_frame(rng, [(60.0, 50.0)]), None)
    assert {o.object_id for o in out.confirmed} == ids
    assert tr.frozen_frames == tr.params.coast_frames + 5


def test_bad_pose_is_refused():
    tr = ObjectTracker(K)
    with pytest.raises(Exception, match="R_ned_from_cam"):
        tr.update(np.zeros((H_PX, W_PX), np.uint8), np.full((3, 3), np.nan))


def test_object_chain_reports_the_primary_as_the_track_and_a_new_id_on_a_change():
    from onboard.imaging import TrackState
    from onboard.imaging.objects_chain import ObjectChain

    rng = np.random.default_rng(9)
    chain = ObjectChain(K)
    for k in range(20):
        near, far = _near_far(k)
        upd = chain.update(_frame(rng, [near, far]), np.eye(3))
    assert upd.state is TrackState.TRACKING and upd.measurement_valid
    assert math.hypot(upd.u_px - near[0], upd.v_px - near[1]) < CENTRE_TOL_PX
    first = upd.track_id
    sel = chain.select_point(_frame(rng, [near, far]), far[0], far[1], 5.0)
    assert sel is not None and sel.track_id != first and not sel.measurement_valid
    upd = chain.update(_frame(rng, [near, far]))  # no pose this frame: the last one is kept
    assert upd.track_id == sel.track_id and math.hypot(upd.u_px - far[0], upd.v_px - far[1]) < CENTRE_TOL_PX
    assert chain.select_point(_frame(rng, [near, far]), 100.0, 80.0, 5.0) is None  # nothing there
    chain.stop()
    upd = chain.update(_frame(rng, [near, far]))
    assert upd.state in (TrackState.LOST, TrackState.SEARCHING) and upd.track_id is None


def test_a_box_selects_only_an_object_inside_it():
    """A box selects what is in it: the object nearest its centre was taken within half its diagonal, so a long
    thin box beside an object (its centre close to the object, the object outside it) selected that object."""
    from onboard.imaging.objects_chain import ObjectChain

    rng = np.random.default_rng(9)
    chain = ObjectChain(K)
    for k in range(20):
        near, far = _near_far(k)
        upd = chain.update(_frame(rng, [near, far]), np.eye(3))
    first = upd.track_id
    x, y = far
    beside = (x - 40.0, y - 8.0, x + 40.0, y - 3.0)  # 80 x 5 px, 3 px above the far object: its centre 5.5 px off
    assert chain.select_rectangle(_frame(rng, [near, far]), beside) is None
    assert chain.update(_frame(rng, [near, far])).track_id == first  # the selection unchanged
    around = (x - 40.0, y - 8.0, x + 40.0, y + 3.0)
    sel = chain.select_rectangle(_frame(rng, [near, far]), around)
    assert sel is not None and sel.track_id != first


def test_object_chain_selections_on_one_frame_measure_it_once_and_a_stop_in_auto_mode_is_said_to_hold():
    """Two selections decided on one frame (a double click within a frame period) measured the frame twice: the
    second pass read as a frozen frame, every track coasted and the frame count jumped by two.  The selection frame
    is reported from the object's track (measured before it was selected: not fit for 3-D, a TrackUpdate without
    a detection, hence coasting).  After a stop in auto mode the chain holds (no automatic choice until the next selection), which the status reads as ``holding``."""
    from types import SimpleNamespace

    from onboard.app.config import build_config
    from onboard.app.status_sections import camera_section
    from onboard.imaging.objects_chain import ObjectChain

    rng = np.random.default_rng(9)
    chain = ObjectChain(K)
    for k in range(20):
        near, far = _near_far(k)
        upd = chain.update(_frame(rng, [near, far]), np.eye(3))
    first, index = upd.track_id, chain.last_objects.frame_index
    frame = _frame(rng, [near, far])
    sel = chain.select_point(frame, far[0], far[1], 5.0, R_ned_from_cam=np.eye(3))
    assert sel is not None and sel.track_id != first
    assert not sel.measurement_valid
    again = chain.select_point(frame, near[0], near[1], 5.0, R_ned_from_cam=np.eye(3))  # the same frame
    assert again is not None and again.track_id == first
    assert chain.last_objects.frame_index == index + 1
    assert {o.state for o in chain.last_objects.objects} == {"confirmed"}  # nothing coasted

    assert not chain.holding
    chain.stop()
    upd = chain.update(_frame(rng, [near, far]), np.eye(3))
    assert chain.holding and upd.track_id is None
    pipeline = SimpleNamespace(tracker=chain, last_selection=None)
    status = camera_section(SimpleNamespace(status=dict), build_config({}), pipeline)
    assert status["tracker_mode"] == "auto" and status["tracker_holding"] is True
    assert chain.select_point(_frame(rng, [near, far]), far[0], far[1], 5.0, R_ned_from_cam=np.eye(3)) is not None
    assert not chain.holding  # a selection ends the hold
    assert not ObjectChain(K, mode="operator").holding  # operator mode waits by design: no hold to report


PAN_RAD_PER_FRAME = 0.002  # a gimbal following its target at 3.4 deg/s (30 frames/s)
GAP_FRAMES = 63  # a router restart: 2.1 s without telemetry, the frames going on
LOS_TOL_RAD = 2e-3  # the gap's last frame taken at the first rotation after it: one frame's pan, plus a centroid


def _panned(k: int) -> np.ndarray:
    """R_ned_from_cam of a camera looking north, level, panned right by ``PAN_RAD_PER_FRAME`` a frame."""
    c, s = math.cos(PAN_RAD_PER_FRAME * k), math.sin(PAN_RAD_PER_FRAME * k)
    yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return yaw @ np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns: camera x, y, z in NED


def test_a_gap_in_the_rotations_keeps_the_primary_and_its_lines_of_sight():
    """Frames without a rotation (the telemetry stopped for 2.1 s) while the gimbal goes on following its target:
    the chain takes the camera as still over them, so its tracks hold lines of sight of the last rotation.  The
    first rotation after the gap was handed over as it was, a turn of 7 deg in one frame period: the primary's
    prediction fell 25 px off its object, it coasted out and the object was chosen again under a new id (the
    pipeline restarts the 3-D estimate on it).  Kept now, measured on the first frame after the gap, and its
    line of sight there is the camera's, in local NED."""
    from onboard.imaging import TrackState
    from onboard.imaging.objects_chain import ObjectChain

    rng = np.random.default_rng(11)
    chain = ObjectChain(K)

    def target(k: int) -> tuple[float, float]:  # near the centre, drifting as a gimbal's pointing error does
        return W_PX / 2 + 3 + 0.05 * k, H_PX / 2 - 2

    ids, states = [], []
    for k in range(60 + GAP_FRAMES + 60):  # a track coasts 45 frames (coast_frames)
        R = None if 60 <= k < 60 + GAP_FRAMES else _panned(k)
        upd = chain.update(_frame(rng, [target(k)]), R)
        ids.append(upd.track_id)
        states.append(upd.state)
        if k >= 60 + GAP_FRAMES and upd.measurement_valid:
            (prim,) = [o for o in chain.last_objects.objects if o.object_id == upd.track_id]
            truth = _panned(k) @ K.bearing_cam_from_pixel(target(k))
            angle = math.acos(min(float(np.dot(prim.los_ned, truth / np.linalg.norm(truth))), 1.0))
            assert angle < LOS_TOL_RAD, (k, angle)
    assert states[59] is TrackState.TRACKING
    assert set(ids[59:]) == {ids[59]}  # one object, one id: through the gap and after it
    assert all(s is TrackState.TRACKING for s in states[60 + GAP_FRAMES :])


def test_a_click_selects_a_coasting_object_where_it_is_shown_not_where_it_was_last_measured():
    """A coasting object is published (and drawn by the ground station) at its prediction; the click was matched
    against its last measured pixel, 30 px behind it here: a click on the drawn object was refused, and one on
    the empty sky where it had been selected it."""
    from onboard.imaging.objects_model import TrackRecord, los_from_pixel

    tr = ObjectTracker(K, mode="operator")
    R = np.eye(3)
    # a confirmed track last measured at (100, 100), predicted now at (130, 100) after 10 frames unseen
    rec = TrackRecord(
        7,
        los_from_pixel(K, 130.0, 100.0, R),
        np.zeros(3),
        (100.0, 100.0),
        (99, 99, 2, 2),
        hits=30,
        misses=10,
        age=40,
        confirmed=True,
    )
    tr._tracks = [rec]
    out = tr._output(np.zeros((H_PX, W_PX), np.uint8), R, "normal", measured=set(), changed=False)
    (shown,) = out.objects
    assert shown.state == "coasting" and math.hypot(shown.u_px - 130.0, shown.v_px - 100.0) < 1e-6
    assert tr.select_point(100.0, 100.0, 20.0) is None  # where it was: empty sky now
    assert tr.select_point(130.0, 100.0, 20.0) == 7  # where it is drawn


def test_objects_message_carries_every_confirmed_object_as_json():
    import json

    from onboard.imaging.objects import objects_message

    rng = np.random.default_rng(10)
    tr = ObjectTracker(K)
    for k in range(20):
        out = tr.update(_frame(rng, list(_near_far(k))), np.eye(3))
    msg = json.loads(json.dumps(objects_message(out, 123456)))
    assert msg["schema"] == "irtrack.objects/1" and msg["time_boot_us"] == 123456
    assert len(msg["objects"]) == 2 and sum(o["primary"] for o in msg["objects"]) == 1
    for o in msg["objects"]:
        los = np.array(o["los_ned"])
        assert abs(np.linalg.norm(los) - 1.0) < 1e-6
        # with R = I the line of sight is the camera ray through the centre
        assert abs(los[0] / los[2] * K.fx_px + K.cx_px - o["u_px"]) < 1e-3
        assert o["state"] == "confirmed" and o["score"] >= 1.0
        assert o["los_sigma_rad"] == pytest.approx(1.0 / K.fx_px)  # the chain's 1 px, no attitude error given
    # the frames go on without either object: drawn where predicted, coasting, with no line of sight (a sigma grown
    # by a pixel a frame said a few degrees where a prediction over a gap went tens off)
    out = tr.update(_frame(rng, []), np.eye(3))
    msg = json.loads(json.dumps(objects_message(out, 123489, attitude_sigma_rad=0.002)))
    assert [o["state"] for o in msg["objects"]] == ["coasting", "coasting"]
    assert all(o["u_px"] is not None and o["los_ned"] is None and o["los_sigma_rad"] is None for o in msg["objects"])


def test_pipeline_runs_the_objects_chain_with_the_pose():
    from onboard.app.config import build_config
    from onboard.imaging.objects_chain import ObjectChain
    from tests.onboard.test_pipeline import Rig

    rig = Rig(config=build_config({"imaging": {"chain": "objects"}}))
    assert isinstance(rig.pipe.tracker, ObjectChain)
    tracks = rig.run(30)  # confirmation takes confirm_in_window (12) of the first frames
    tracking = [t for t in tracks if t.state == "tracking"]
    assert len(tracking) >= 12 and len({t.track_id for t in tracking}) == 1
    assert rig.pipe.tracker._R is not None  # the pose's rotation reached the chain
    assert (
        rig.pipe.tracker.last_objects is not None and rig.pipe.tracker.last_objects.primary_id == tracking[0].track_id
    )


def test_point_candidates_components_match_opencv_stats():
    """The sparse statistics (area, box, centre) agree with OpenCV's own component statistics."""
    import cv2

    rng = np.random.default_rng(11)
    img = _sky(rng)
    for u, v in ((30.3, 40.6), (100.7, 20.2), (64.0, 70.0), (10.0, 85.0)):
        _blob(img, u, v, 25.0, sigma_px=1.2)
    p = ClutterParams()
    f = img.astype(np.float32)
    contrast = point_contrast(f, p)
    thr = cfar_threshold(local_noise(f), p.threshold_sigma, 0.8)
    cands = point_candidates(contrast, thr, p)
    mask = (contrast >= thr).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    assert len(cands) == n - 1 == 4
    for c in cands:
        lab = labels[c.bbox[1] + c.bbox[3] // 2, c.bbox[0] + c.bbox[2] // 2]
        lab = lab if lab else labels[int(c.v_px), int(c.u_px)]
        assert tuple(int(x) for x in stats[lab, :4]) == c.bbox and int(stats[lab, 4]) == c.area_px
        w = np.where(labels == lab, contrast, 0.0)
        jj, ii = np.meshgrid(np.arange(W_PX) + 0.5, np.arange(H_PX) + 0.5)
        assert abs(c.u_px - (w * jj).sum() / w.sum()) < 1e-4 and abs(c.v_px - (w * ii).sum() / w.sum()) < 1e-4


def test_local_noise_coarse_follows_the_full_size_estimate():
    rng = np.random.default_rng(12)
    img = np.full((H_PX, W_PX), 50.0)
    img[:, W_PX // 2 :] += rng.normal(0.0, 4.0, (H_PX, W_PX // 2))
    f = img.astype(np.float32)
    full, coarse = local_noise(f, 31), local_noise_coarse(f, 31)
    # away from the step between the halves (both are window means there, of slightly different windows)
    for sl in (np.s_[:, : W_PX // 2 - 20], np.s_[:, W_PX // 2 + 20 :]):
        assert np.median(np.abs(coarse[sl] - full[sl])) < 0.1 * max(float(np.median(full[sl])), 0.1)


GROUND_SPOTS = ((30.0, 60.0), (45.0, 90.0), (15.0, 110.0))  # (u, v) on the ground texture, before its scroll


def _textured_scene(k: int, target: tuple[float, float]) -> np.ndarray:
    """A frame whose left half is terrain-like texture with three warm spots on it (roofs), all
    scrolling down at 0.5 px per frame, the right half clear sky, and a target moving across."""
    import cv2

    rng = np.random.default_rng(13)
    big = cv2.blur(rng.normal(0.0, 12.0, (H_PX + 80, W_PX)), (5, 5))
    for u, v in GROUND_SPOTS:
        _blob(big, u, v, 25.0)
    m = np.float32([[1, 0, 0], [0, 1, 0.5 * k - 40.0]])
    tex = cv2.warpAffine(big.astype(np.float32), m, (W_PX, H_PX), flags=cv2.INTER_LINEAR)
    img = _sky(np.random.default_rng(100 + k))
    img[:, : W_PX // 2] += tex[:, : W_PX // 2]
    _blob(img, target[0], target[1], 30.0)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def test_points_moving_with_their_background_are_not_confirmed_and_a_target_is():
    """Warm spots on scrolling terrain move together (each other's background); a target crossing
    them moves unlike them."""
    tr = ObjectTracker(K)
    spots_confirmed, target_confirmed = 0, 0
    for k in range(40):
        target = (15.0 + 0.6 * k, 70.0)
        out = tr.update(_textured_scene(k, target), np.eye(3))
        spots = [(u, v - 40.0 + 0.5 * k) for u, v in GROUND_SPOTS]
        for o in out.confirmed:
            spots_confirmed += any(math.hypot(o.u_px - u, o.v_px - v) < 3.0 for u, v in spots)
            target_confirmed += math.hypot(o.u_px - target[0], o.v_px - target[1]) < 3.0
    assert target_confirmed >= 20  # confirmed within ~15 frames, then measured on every frame
    assert spots_confirmed == 0


@pytest.mark.parametrize("factor, measured", [(0.35, 10), (1.0, 0)])
def test_track_aided_detection_bridges_a_dim_spell_of_a_confirmed_object(factor, measured):
    """A confirmed object dims to 4 grey (below the whole-frame threshold) for 10 frames: the lower
    threshold inside its gate keeps it measured; without it (factor 1) it is not.  A point of the same
    4 grey elsewhere, with no track, never starts one."""
    from onboard.imaging.objects import ObjectParams

    rng = np.random.default_rng(14)
    tr = ObjectTracker(K, params=ObjectParams(aided_threshold_factor=factor))
    seen = 0
    for k in range(34):
        uv = (30.0 + 0.5 * k, 40.0)
        if k < 24:
            out = tr.update(_frame(rng, [uv], 30.0), None)
            continue
        img = _sky(rng)
        _blob(img, uv[0], uv[1], 4.0)
        _blob(img, 100.0, 70.0, 4.0)  # as dim, nothing known there
        out = tr.update(np.clip(np.round(img), 0, 255).astype(np.uint8), None)
        seen += any(math.hypot(o.u_px - uv[0], o.v_px - uv[1]) < 2.0 for o in out.confirmed)
        assert all(math.hypot(o.u_px - 100.0, o.v_px - 70.0) > 5.0 for o in out.objects)
    assert seen == measured


@pytest.mark.parametrize(
    "kwargs", [dict(confirm_in_window=16), dict(confirm_in_window=2), dict(aided_threshold_factor=0.0)]
)
def test_object_params_refuse_inconsistent_confirmation_settings(kwargs):
    from onboard.imaging.objects import ObjectParams

    with pytest.raises(Exception, match="ObjectParams"):
        ObjectParams(**kwargs)
