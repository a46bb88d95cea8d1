"""The objects chain on a reference scene's own frames, where a synthetic frame does not reproduce what
went wrong: C3 seed 3, where a bird crosses the primary target."""

from __future__ import annotations

import math

import numpy as np

from groundsim.world.scenario import load_scenario, scenarios_dir
from groundsim.world.sim import SimCore
from onboard.core.frames import rotmat_from_quat
from onboard.imaging import ImagingParams
from onboard.imaging.objects import ObjectTracker

ON_TARGET_PX = 3.0


def _truth_rotations(frames) -> np.ndarray:
    return np.array(
        [
            rotmat_from_quat(
                np.array(
                    [
                        f.truth.q_ned_from_cam_w,
                        f.truth.q_ned_from_cam_x,
                        f.truth.q_ned_from_cam_y,
                        f.truth.q_ned_from_cam_z,
                    ]
                )
            )
            for f in frames
        ]
    )


def _primary_over(sc, frames, rotations, from_k: int):
    """The objects chain over ``frames`` given ``rotations``: (the tracker, the primary at frame 120, the primary
    at the end, the primary's distance to the target, px, on each frame from ``from_k``)."""
    tr = ObjectTracker(sc.camera.intrinsics, frame_rate_hz=sc.frame_rate_hz, imaging=ImagingParams(chain="objects"))
    primary, off_px = None, []
    for k, (f, R) in enumerate(zip(frames, rotations)):
        out = tr.update(f.pixels, R)
        if k == 120:
            primary = out.primary_id
        if k >= from_k:
            target = next(lb for lb in f.labels if lb.object_id == 0)
            prim = next(o for o in out.objects if o.object_id == out.primary_id)
            off_px.append(math.hypot(prim.u_px - target.u_px, prim.v_px - target.v_px))
    return tr, primary, out.primary_id, off_px


def _c3_under_rtk(seed: int, n: int):
    """C3's first ``n`` frames of ``seed`` with the attitude the telemetry reports them with (the run's own RTK
    draws, as `bench.imaging --scene` gives them): (scenario, frames, rotations)."""
    from bench.imaging_scenes import reported_rotations

    sc = load_scenario(scenarios_dir() / "C3.yaml")
    duration = n / sc.frame_rate_hz
    core = SimCore(sc, seed, duration_s=duration)
    frames = [core.frame(k) for k in range(core.frame_count)]
    R_rep, case = reported_rotations(sc, seed, duration, _truth_rotations(frames), None)
    assert case == "RTK"
    return sc, frames, R_rep


def test_a_bird_crossing_the_primary_target_does_not_take_its_track():
    """C3 seed 3, frames 155-166: a bird (tracked since frame ~150) passes over the primary target. Their
    images merged on frame 163 nearer the bird's prediction; nearest-first association gave the merged
    image to the bird's track, whose rate then followed the target, and the primary, coasting, took the
    bird's image when they parted on frame 166 and followed the bird from then on, under the target's
    id (on the target 48 % of the run; the 3-D estimate would have followed a bird). A merged image now
    goes to the track with the most hits: the primary stays on its target through and after the crossing."""
    sc = load_scenario(scenarios_dir() / "C3.yaml")
    core = SimCore(sc, 3, duration_s=185 / sc.frame_rate_hz)
    frames = [core.frame(k) for k in range(core.frame_count)]
    tr, primary, last, off_px = _primary_over(sc, frames, _truth_rotations(frames), 150)
    assert primary is not None and last == primary and tr.primary_changes == 1
    assert max(off_px[-15:]) <= ON_TARGET_PX, f"the primary left the target: {[round(d, 1) for d in off_px]}"


def test_the_primary_keeps_its_target_through_the_crossing_under_rtk_attitude_errors():
    """C3 seed 2 with the attitude the telemetry reports (RTK: 0.05 deg white per axis, 0.67 px): the two
    targets' images merge on frames ~130-161. The frame's attitude error moved both predictions by ~1 px, the
    merged image lay over 2 px from the primary's, nearest-first gave it to the second target's track and the
    primary coasted off its target for good (on target 40 % of the run). The frame's common offset, measured on
    the tracks it is unambiguous for (birds), is taken out before association: the primary keeps its target."""
    sc, frames, R_rep = _c3_under_rtk(2, 175)
    _, primary, last, off_px = _primary_over(sc, frames, R_rep, 160)
    assert primary is not None and last == primary
    assert max(off_px) <= ON_TARGET_PX, f"the primary left the target: {[round(d, 1) for d in off_px]}"


def test_the_second_target_is_found_again_after_the_crossing_under_rtk_attitude_errors():
    """C3 seed 5 under RTK: the two targets' images merge on frames ~131-160 and part slowly (3 px apart by
    frame 171). The second target's track coasted through the merge on its filter's rate (each measurement with
    its frame's attitude error), took a noise point 10 px off in its 12 px gate at frame 153 and wandered; the
    target, 2-5 px beside the primary and hidden in its light, was lost for 87 frames (171-257). Coasting on a
    line fitted to its last positions, about predictions with the frame's common offset out, with an aided
    threshold that rises with its gate, and with the primary deblended while a coasting track lies in its
    light, the track finds its target again as the images part, under its own id."""
    n = 200
    sc, frames, R_rep = _c3_under_rtk(5, n)
    tr = ObjectTracker(sc.camera.intrinsics, frame_rate_hz=sc.frame_rate_hz, imaging=ImagingParams(chain="objects"))
    on_second: dict[int, int | None] = {}  # frame -> the confirmed track on the second target (not the primary)
    for k, (f, R) in enumerate(zip(frames, R_rep)):
        out = tr.update(f.pixels, R)
        second = next(lb for lb in f.labels if lb.object_id == 1)
        on_second[k] = next(
            (
                o.object_id
                for o in out.confirmed
                if o.object_id != out.primary_id
                and math.hypot(o.u_px - second.u_px, o.v_px - second.v_px) <= ON_TARGET_PX
            ),
            None,
        )
    before = on_second[110]  # the images 5 px apart
    after = [on_second[k] for k in range(176, n)]
    assert before is not None and before != out.primary_id
    assert sum(i is not None for i in after) >= len(after) - 2, f"the second target's tracks after the merge: {after}"
    assert set(after) - {None} == {before}, f"before the merge {before}, after {after}"
