"""The terrain's sampling: with ``terrain.full_resolution`` (the default) an edge moved by the camera renders as the
same edge moved (as a camera samples its optical image); the half-resolution look-up aliases (docs/scenes.md)."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.world.render.scene import SceneContent
from groundsim.world.scenario import load_scenario, scenarios_dir
from groundsim.world.sim import GROUND_D_M, SimCore
from onboard.core.frames import rotmat_from_quat, rotmat_from_rotvec

HALF_PX = 16


@pytest.fixture(scope="module")
def c2_pose():
    sc = load_scenario(scenarios_dir() / "C2.yaml")
    core = SimCore(sc, 1, duration_s=8.5)
    i = 250 * core.ticks_per_frame  # the target over roofs: their edges in the square
    c = core.flight.chunk_of(i)
    j = i - c.i0
    return sc, core.renderer(), c.cam_p_ned_m[j], rotmat_from_quat(c.cam_q_ned_from_cam[j])


def _one_pixel_residual(sc, renderer, p, R, full: bool) -> tuple[float, float]:
    """(largest residual, span) of a square near the principal point between the background rendered with
    the camera turned by one pixel's angle about its y axis (seed 1's frame 250) and the first rendering
    moved by that pixel."""
    terrain = dataclasses.replace(sc.scene.terrain, full_resolution=full)
    scene = SceneContent.from_config(dataclasses.replace(sc.scene, terrain=terrain), renderer, 7)
    turn = rotmat_from_rotvec(np.array([0.0, -1.0 / sc.camera.intrinsics.fx_px, 0.0]))  # one pixel near the centre
    bg0 = scene.render_background(p, R, GROUND_D_M).radiance.astype(np.float64)
    bg1 = scene.render_background(p, R @ turn, GROUND_D_M).radiance.astype(np.float64)
    u, v = 300, 258  # 20 px from the principal point: the turn moves the image there by 1.000 px
    sq = np.s_[v - HALF_PX : v + HALF_PX + 1, u - HALF_PX : u + HALF_PX + 1]
    moved = np.s_[v - HALF_PX : v + HALF_PX + 1, u - HALF_PX - 1 : u + HALF_PX]
    a1, a0 = bg1[sq], bg0[moved]
    return float(np.abs(a1 - a0).max()), float(a0.max() - a0.min())


def test_full_resolution_terrain_moves_as_its_edges_do(c2_pose):
    assert c2_pose[0].scene.terrain.full_resolution  # the default, as C2 is loaded
    residual, span = _one_pixel_residual(*c2_pose, full=True)
    assert span > 1.0  # textured ground (roofs, fields) in the square, in radiance units
    assert residual < 0.01 * span


def test_half_resolution_terrain_aliases_as_documented(c2_pose):
    """``full_resolution: false``, the cheaper look-up: why it is not the default (docs/scenes.md's figure)."""
    residual, span = _one_pixel_residual(*c2_pose, full=False)
    assert residual > 0.03 * span


@settings(max_examples=60, deadline=None)
@given(st.integers(4, 40), st.integers(0, 39), st.integers(0, 39))
def test_full_rows_cover_every_row_two_pyrup_steps_reach(n_rows, first, last):
    """The full-resolution rows looked up (``_full_rows``) hold every row where two pyrUp steps of a coarse
    field, non-zero only on a mask's rows, are non-zero: outside them the terrain reads 0 and the far level's
    weight is exactly 0 (the blend then leaves the near level as it is)."""
    import cv2

    from groundsim.world.render.scene import _full_rows

    first, last = sorted((min(first, n_rows - 1), min(last, n_rows - 1)))
    mask = np.zeros((n_rows, 12), bool)
    mask[first : last + 1] = True
    field = np.where(mask, np.float32(1.0), np.float32(0.0))
    full = cv2.pyrUp(cv2.pyrUp(field))
    reached = np.flatnonzero(np.abs(full).max(axis=1) > 0.0)
    rows = _full_rows(mask, full.shape[0])
    assert rows.start <= reached[0] and reached[-1] < rows.stop
    assert not _full_rows(np.zeros((n_rows, 12), bool), full.shape[0]).stop  # nothing to look up
