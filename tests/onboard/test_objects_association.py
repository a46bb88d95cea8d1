"""The object tracker's association and confirmation where objects come in company or near the threshold
(onboard.imaging.objects): a large object whose image splits into two candidates, two objects flying alongside
on a clear sky, and an object detected on two frames of three."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics
from onboard.imaging.objects import ObjectParams, ObjectTracker
from onboard.imaging.objects_association import (
    OWNED_PX,
    common_shift,
    continue_with,
    in_own_gate,
    owning_tracks,
    track_gate,
)
from onboard.imaging.objects_model import TrackRecord
from onboard.imaging.preprocess import ImagingParams

H_PX, W_PX = 96, 128
K = PinholeIntrinsics(200.0, 200.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
NOISE_GREY = 0.5
AMP_GREY = 30.0
MATCH_PX = 2.0  # a confirmed object this close to a point is on it


def _frame(rng: np.random.Generator, points: list[tuple[float, float]], amp_grey: float = AMP_GREY) -> np.ndarray:
    """A clear sky (a smooth gradient and 0.5 grey of noise) with a warm 0.7 px Gaussian at each point."""
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    img = 60.0 + 20.0 * yy / H_PX + 3.0 * xx / W_PX + rng.normal(0.0, NOISE_GREY, (H_PX, W_PX))
    for u, v in points:
        img += amp_grey * np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * 0.7**2))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _turning_object(k: int) -> tuple[float, float]:
    """Rightwards at 0.6 px/frame until frame 20, then downwards at 1.5 px/frame."""
    if k <= 20:
        return 20.0 + 0.6 * k, 30.0
    return 32.0, 30.0 + 1.5 * (k - 20)


def test_a_confirmed_object_whose_image_splits_keeps_its_id_through_a_turn():
    """On frame 20 the object's image splits in two (a second blob 3 px below it, as a bird's wings do):
    that candidate starts a tentative track, which sits still where the object, turning downwards,
    passes next.  Nearest-first association alone gives the object to that track (its prediction lies
    nearer than the confirmed track's, which still points rightwards): the confirmed track coasts away
    and the object is confirmed again under a new id 15 frames later (C3's bird 2, frames 108-170).
    Served first, the confirmed track keeps it."""
    rng = np.random.default_rng(21)
    tr = ObjectTracker(K)
    ids: list[int] = []
    for k in range(40):
        u, v = _turning_object(k)
        points = [(u, v), (u, v + 3.0)] if k == 20 else [(u, v)]
        out = tr.update(_frame(rng, points), None)
        on = [o.object_id for o in out.confirmed if math.hypot(o.u_px - u, o.v_px - v) <= MATCH_PX]
        if k >= 20:
            assert len(on) <= 1, f"frame {k}: two confirmed tracks on one object {on}"
        ids += on
    assert len(ids) >= 28  # confirmed on frame 11, then on it on every frame
    assert len(set(ids)) == 1, f"the object changed id: {sorted(set(ids))}"


def test_two_objects_alongside_on_a_clear_sky_are_confirmed_though_they_move_alike():
    """Two objects 15 px apart on a clear sky, moving 0.1 px/frame unlike each other: each is the other's
    only neighbour track, and a lone neighbour on a clear sky, not carried by its surroundings, is not a
    fragment of a background to differ from; both are confirmed once their tracks are steady (C3's two
    targets waited 42 frames for 0.15 px/frame of relative motion)."""
    rng = np.random.default_rng(22)
    tr = ObjectTracker(K)
    first: dict[str, int] = {}
    for k in range(25):
        pts = {"a": (40.0 + 0.30 * k, 40.0), "b": (40.0 + 0.40 * k, 55.0)}
        out = tr.update(_frame(rng, list(pts.values())), None)
        for name, (u, v) in pts.items():
            if any(math.hypot(o.u_px - u, o.v_px - v) <= MATCH_PX for o in out.confirmed):
                first.setdefault(name, k)
    # confirm_in_window (12) measured frames at the least: frame 11 is the first that can confirm
    assert set(first) == {"a", "b"}
    assert max(first.values()) <= 14


def test_each_track_is_confirmed_on_its_own_twelfth_measured_frame():
    """The same two objects, the second appearing three frames after the first: each is confirmed on the frame
    its own track has ``confirm_in_window`` (12) measured positions, 11 and 14, not when the first one is (a
    frame's confirmation pass runs once any track is due, and then tests every tentative track on its own)."""
    rng = np.random.default_rng(22)
    tr = ObjectTracker(K)
    first: dict[str, int] = {}
    for k in range(20):
        pts = {"a": (40.0 + 0.30 * k, 40.0)}
        if k >= 3:
            pts["b"] = (40.0 + 0.40 * k, 55.0)
        out = tr.update(_frame(rng, list(pts.values())), None)
        for name, (u, v) in pts.items():
            if any(math.hypot(o.u_px - u, o.v_px - v) <= MATCH_PX for o in out.confirmed):
                first.setdefault(name, k)
    assert first == {"a": 11, "b": 14}


@pytest.mark.parametrize("max_run, confirmed", [(1, True), (0, False)])
def test_a_tentative_track_bridges_single_dim_frames_by_aided_detection(max_run, confirmed):
    """An object above the whole-frame threshold on two frames of three and 5 grey (under it, over the
    aided threshold) on the third: measured on 10 of every 15 frames it never reaches the 12 that confirm
    a track; a tentative track with 5 hits bridging one frame at a time by aided detection is confirmed
    within ~15 frames (C3 seed 1's second target)."""
    rng = np.random.default_rng(23)
    tr = ObjectTracker(K, params=ObjectParams(aided_tentative_max_run=max_run))
    first = None
    for k in range(40):
        uv = (30.0 + 0.5 * k, 40.0)
        img = _frame(rng, [uv], AMP_GREY if k % 3 != 2 else 5.0)
        out = tr.update(img, None)
        if first is None and any(math.hypot(o.u_px - uv[0], o.v_px - uv[1]) <= MATCH_PX for o in out.confirmed):
            first = k
    assert (first is not None and first <= 20) is confirmed, f"first confirmed on frame {first}"


@pytest.mark.parametrize(
    ("start_uv", "chosen"),
    [
        ((W_PX / 2 - 20.0, H_PX / 2 + 8.0), True),  # 0.11 rad off the axis: where the gimbal holds its target
        ((12.0, 10.0), False),  # 0.32 rad, in the corner: C2 seed 1's terrain fragment at (114, 5) of 640 x 512
    ],
)
def test_a_lone_confirmed_object_far_off_the_axis_is_never_made_the_primary(start_uv, chosen):
    """The auto rule's fallback (no steady track about the centre: the nearest one) is bounded by
    ``primary_max_off_axis_rad``: a confirmed object in a corner stays an object, reported, but is not handed
    to the 3-D estimator as the target; the same object near the centre is."""
    rng = np.random.default_rng(31)
    tr = ObjectTracker(K)
    confirmed = primaries = 0
    for k in range(30):
        u, v = start_uv[0] + 0.3 * k, start_uv[1]
        out = tr.update(_frame(rng, [(u, v)]), None)
        confirmed += any(math.hypot(o.u_px - u, o.v_px - v) <= MATCH_PX for o in out.confirmed)
        primaries += out.primary_id is not None
    assert confirmed >= 15  # confirmed in both cases: only the selection differs
    if chosen:
        assert primaries >= 15 and tr.primary_changes == 1
    else:
        assert primaries == 0 and tr.primary_changes == 0


def test_the_daemons_imaging_section_sets_the_primarys_off_axis_bound():
    """``imaging.primary_max_off_axis_rad`` reaches the auto rule: the corner object of the test above, 0.32 rad
    off the axis, becomes the primary under a fixed pod's wider bound (0.5 rad)."""
    rng = np.random.default_rng(31)
    tr = ObjectTracker(K, imaging=ImagingParams(primary_max_off_axis_rad=0.5))
    assert tr.params.primary_max_off_axis_rad == 0.5
    primaries = 0
    for k in range(30):
        out = tr.update(_frame(rng, [(12.0 + 0.3 * k, 10.0)]), None)
        primaries += out.primary_id is not None
    assert primaries >= 15 and tr.primary_changes == 1


def test_a_merged_image_goes_to_the_held_track_with_the_most_hits():
    """Candidate 0 lies within OWNED_PX of held tracks 0 (40 hits) and 1 (12 hits), nearer track 1: only
    track 0 may take it; candidate 1, near track 1 alone, stays its own; a coasting track (2) and a held
    one beyond OWNED_PX (3) claim nothing and lose nothing."""
    from onboard.imaging.objects_association import OWNED_PX, merged_to_the_elder

    pairs = sorted(
        [
            (False, 0.4, 1, 0),  # the younger held track is nearer the merged image
            (False, 0.9, 0, 0),
            (False, 2.5, 1, 1),
            (True, 0.2, 2, 0),  # coasting: not held, served after the held ones as before
            (False, OWNED_PX + 0.5, 3, 0),
        ]
    )
    held = [True, True, False, True]
    hits = [40, 12, 90, 99]
    kept = merged_to_the_elder(pairs, held, hits)
    assert (False, 0.4, 1, 0) not in kept
    assert kept == [q for q in pairs if q != (False, 0.4, 1, 0)]
    # no contest (one held track near each candidate): the pairs as they were
    assert merged_to_the_elder(pairs[1:], held, hits) == pairs[1:]


@pytest.mark.parametrize(
    "speed_pxpf, initiation_gate_px, confirmed",
    [(6.5, 10.0, True), (6.5, 4.0, False), (0.3, 10.0, True), (3.5, 10.0, True), (3.9, 10.0, True)],
)
def test_a_fast_object_is_confirmed_by_two_point_initiation(speed_pxpf, initiation_gate_px, confirmed):
    """An object crossing the frame at 6.5 px a frame (a bird near the camera, C3 seed 1 over 30 s): a new track's
    prediction stays where its one hit was, 6.5 px off on the next frame, beyond the 4 px gate, and every frame
    started a new track that was never confirmed. A track with one hit is now searched within
    ``initiation_gate_px``, and a second hit beyond the 4 px gate sets its velocity (nearer, the filter's update
    as before: a slow object's two-point velocity carries the attitude error's jitter): the object is confirmed
    on the 12th frame that can (frame 11), under one id. A slow object is confirmed as before. At 3.5-3.9 px a
    frame the second hit falls inside the gate and gets the filter's velocity, a fraction of the object's, and the
    third fell just beyond the gate, for a new track every two frames: a tentative track with two hits and nothing
    in its gate is now searched about its two positions' extrapolation."""
    rng = np.random.default_rng(26)
    tr = ObjectTracker(K, params=ObjectParams(initiation_gate_px=initiation_gate_px))
    ids = []
    for k in range(16):
        u, v = 10.0 + speed_pxpf * k, 40.0 + 0.2 * k
        out = tr.update(_frame(rng, [(u, v)]), None)
        ids += [o.object_id for o in out.confirmed if math.hypot(o.u_px - u, o.v_px - v) <= MATCH_PX]
    assert bool(ids) is confirmed, ids
    if confirmed:
        assert len(set(ids)) == 1 and len(ids) >= 4, ids


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(5.0, W_PX - 5.0), st.floats(5.0, H_PX - 5.0), st.floats(-8.0, 8.0), st.floats(-8.0, 8.0)),
        min_size=1,
        max_size=4,
    ),
    st.lists(st.booleans(), min_size=30, max_size=30),
    st.floats(0.0, 2e-3),
    st.integers(0, 2**31 - 1),
)
def test_any_motion_drops_and_attitude_jitter_keep_the_outputs_consistent(objects, kept, jitter_rad, seed):
    """Objects on any course (up to 8 px a frame each way: crossings, fast movers, leaving the frame), frames the
    daemon dropped (their times skipped), and a camera attitude with a white error up to 0.1 deg: every frame's
    output has unique ids, finite pixels, states the module defines, and a primary among its objects."""
    from onboard.core.frames import quat_from_rotvec, rotmat_from_quat
    from onboard.imaging.objects_model import OBJECT_STATES

    rng = np.random.default_rng(seed)
    R_mount = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    tr = ObjectTracker(K)
    for k, keep in enumerate(kept):
        if not keep:
            continue
        points = [(u + du * k, v + dv * k) for u, v, du, dv in objects]
        R = rotmat_from_quat(quat_from_rotvec(rng.normal(0.0, jitter_rad, 3))) @ R_mount
        out = tr.update(_frame(rng, [p for p in points if 0 <= p[0] < W_PX and 0 <= p[1] < H_PX]), R, k * 33_333)
        ids = [o.object_id for o in out.objects]
        assert len(ids) == len(set(ids))
        assert all(o.state in OBJECT_STATES and math.isfinite(o.u_px) and math.isfinite(o.v_px) for o in out.objects)
        assert out.primary_id is None or out.primary_id in ids


def test_a_weak_difference_moves_a_confirmed_track_but_not_its_velocity():
    """A background difference taken only at the near threshold (``PointCandidate.weak``) updates where a confirmed
    track is, not its velocity or the positions its coast is fitted to; an ordinary one updates all three."""
    from onboard.imaging.clutter import PointCandidate

    def confirmed_tracker():
        rng = np.random.default_rng(5)
        tr = ObjectTracker(K)
        for k in range(16):
            tr.update(_frame(rng, [(30.0 + 0.8 * k, 40.0)]), None)
        (t,) = [t for t in tr._tracks if t.confirmed]
        return tr, t

    for weak in (True, False):
        tr, t = confirmed_tracker()
        rate, hist = t.rate.copy(), list(t.history)
        tr._frame_index += 1
        u = 30.0 + 0.8 * 16 + 1.0  # 1 px ahead of the object's course
        tr._associate([PointCandidate(u, 40.0, (int(u) - 1, 39, 2, 2), 4, 2.0, 1.1, weak)], np.eye(3))
        assert t.misses == 0 and t.uv == (u, 40.0)
        if weak:
            np.testing.assert_array_equal(t.rate, rate)
            assert t.history == hist
        else:
            assert not np.array_equal(t.rate, rate)
            assert t.history[-1][2:] == (u, 40.0)


# ---------------------------------------------------------------- the pure rules, on hand-made numbers


def test_a_candidate_in_two_gates_does_not_count_towards_the_common_shift():
    """Track 0 alone sees its candidate unambiguously; tracks 1 and 2 share one (in both gates): with one
    unambiguous track there is no common shift, though each track has exactly one candidate in its gate."""
    puv = np.array([[0.0, 0.0], [10.0, 0.0], [11.0, 0.0]])
    cuv = np.array([[1.0, 0.5], [12.0, 0.5]])
    d = np.hypot(*(cuv[None, :, :] - puv[:, None, :]).transpose(2, 0, 1))
    gate = np.full(3, 3.0)
    assert common_shift(puv, cuv, d, gate, [True, True, True]) is None
    # the shared candidate moved out of track 2's gate: tracks 0 and 1 are unambiguous, their median shift
    cuv[1] = (7.5, 0.5)
    d = np.hypot(*(cuv[None, :, :] - puv[:, None, :]).transpose(2, 0, 1))
    np.testing.assert_allclose(common_shift(puv, cuv, d, gate, [True, True, True]), [-0.75, 0.5])


def test_the_gate_grows_per_coasted_frame_up_to_its_limit():
    p = ObjectParams()
    assert track_gate(p, 0) == p.gate_px and track_gate(p, 2) == p.gate_px + 2 * p.gate_growth_px
    np.testing.assert_array_equal(
        track_gate(p, np.array([0, 4, 1000])), [p.gate_px, p.gate_px + 4 * p.gate_growth_px, p.max_gate_px]
    )


def test_a_candidate_is_owned_within_owned_px_of_a_prediction():
    a, b = (
        TrackRecord(1, np.zeros(3), np.zeros(3), (0.0, 0.0), (0, 0, 1, 1)),
        TrackRecord(2, np.zeros(3), np.zeros(3), (0.0, 0.0), (0, 0, 1, 1)),
    )
    held = [(a, (50.0 + 0.9 * OWNED_PX, 50.0)), (b, (50.0, 50.0 + 1.1 * OWNED_PX))]
    assert owning_tracks(50.0, 50.0, held) == [a]
    # within its own gate, but owned by another track's prediction
    assert in_own_gate(50.0, 50.0, (53.0, 50.0), 4.0, [(50.0 + 1.1 * OWNED_PX, 50.0)])
    assert not in_own_gate(50.0, 50.0, (53.0, 50.0), 4.0, [(50.0 + 0.9 * OWNED_PX, 50.0)])
    assert not in_own_gate(50.0, 50.0, (54.5, 50.0), 4.0, [])


def test_a_coasting_track_continued_by_a_tentative_one_adds_its_hits():
    o = TrackRecord(7, np.zeros(3), np.zeros(3), (1.0, 2.0), (0, 1, 2, 2), hits=30, misses=5, dim_hits=4)
    t = TrackRecord(9, np.ones(3), np.ones(3), (3.0, 4.0), (2, 3, 2, 2), hits=6, dim_hits=2, aided_run=1)
    t.history = [(k, None, 0.0, 0.0) for k in range(10)]
    continue_with(o, t, window=8)
    assert (o.object_id, o.hits, o.misses, o.dim_hits, o.aided_run, o.uv) == (7, 36, 0, 6, 1, (3.0, 4.0))
    assert o.history == t.history[-8:]
