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


def test_a_bird_crossing_the_primary_target_does_not_take_its_track():
    """C3 seed 3, frames 155-166: a bird (tracked since frame ~150) passes over the primary target. Their
    images merged on frame 163 nearer the bird's prediction; nearest-first association gave the merged
    image to the bird's track, whose rate then followed the target, and the primary, coasting, took the
    bird's image when they parted on frame 166 and followed the bird from then on, under the target's
    id (on the target 48 % of the run; the 3-D estimate would have followed a bird). A merged image now
    goes to the track with the most hits: the primary stays on its target through and after the crossing."""
    sc = load_scenario(scenarios_dir() / "C3.yaml")
    n = 185
    core = SimCore(sc, 3, duration_s=n / sc.frame_rate_hz)
    tr = ObjectTracker(sc.camera.intrinsics, frame_rate_hz=sc.frame_rate_hz, imaging=ImagingParams(chain="objects"))
    primary = None
    off_px = []
    for k in range(core.frame_count):
        f = core.frame(k)
        t = f.truth
        R = rotmat_from_quat(np.array([t.q_ned_from_cam_w, t.q_ned_from_cam_x, t.q_ned_from_cam_y, t.q_ned_from_cam_z]))
        out = tr.update(f.pixels, R)
        if k == 120:
            primary = out.primary_id
        if k >= 150:
            target = next(lb for lb in f.labels if lb.object_id == 0)
            prim = next(o for o in out.objects if o.object_id == out.primary_id)
            off_px.append(math.hypot(prim.u_px - target.u_px, prim.v_px - target.v_px))
    assert primary is not None and out.primary_id == primary and tr.primary_changes == 1
    assert max(off_px[-15:]) <= ON_TARGET_PX, f"the primary left the target: {[round(d, 1) for d in off_px]}"
