"""The objects chain's cost cuts change nothing: arrays reused from frame to frame and shared by
intermediates (:class:`onboard.imaging.clutter.Scratch`), the background motion measured only when asked for
(:class:`onboard.imaging.objects_detection.ObjectDetector`) and the column offsets' medians from sorted
columns give the figures of fresh arrays, of a motion measured on every frame and of ``np.median``, bit
for bit; and the stage timing the benchmark reads."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.frames import PinholeIntrinsics, quat_from_euler, rotmat_from_quat
from onboard.imaging.clutter import (
    ClutterParams,
    DefectMap,
    Scratch,
    cfar_threshold,
    column_offsets,
    isolated_outliers,
    local_noise_coarse,
    median_window_noise,
    noise_cells,
    point_candidates,
    point_contrast,
)
from onboard.imaging.objects import ObjectParams, ObjectTracker
from onboard.imaging.objects_detection import ObjectDetector

W_PX, H_PX = 256, 192
K = PinholeIntrinsics(300.0, 300.0, W_PX / 2, H_PX / 2, W_PX, H_PX)
SCROLL_PXPF = 0.5  # the terrain's own image motion, straight down
YAW_RAD_PER_FRAME = 0.002  # the camera's pan: 0.6 px/frame at the centre, removed from the measured motion
N_FRAMES = 30
MOTION_TOL_PXPF = 0.15  # 64 x 48 px phase correlations scattering by 0.2-0.3 px/frame, averaged over 12-15 frames


def _terrain() -> np.ndarray:
    rng = np.random.default_rng(13)
    return cv2.GaussianBlur(rng.normal(0.0, 30.0, (H_PX + 80, W_PX + 80)), (0, 0), 6.0).astype(np.float32)


def _frame(terrain: np.ndarray, k: int) -> np.ndarray:
    """Terrain scrolling down by SCROLL_PXPF and right by the pan's share, a warm point, noise, mono8."""
    pan_px = K.fx_px * math.tan(YAW_RAD_PER_FRAME * k)
    m = np.float32([[1, 0, -40.0 - pan_px], [0, 1, SCROLL_PXPF * k - 40.0]])
    img = 80.0 + cv2.warpAffine(terrain, m, (W_PX, H_PX), flags=cv2.INTER_LINEAR).astype(np.float64)
    img += np.random.default_rng(100 + k).normal(0.0, 0.5, img.shape)
    img[90:92, 100 + k : 102 + k] += 25.0
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _pose(k: int) -> np.ndarray:
    # camera yawing right (about the NED down axis) while looking north, level: OpenCV camera axes
    R_ned_from_level_cam = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    return rotmat_from_quat(quat_from_euler(0.0, 0.0, YAW_RAD_PER_FRAME * k)) @ R_ned_from_level_cam


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    terrain = _terrain()
    return [_frame(terrain, k) for k in range(N_FRAMES)]


def test_scratch_arrays_give_the_fresh_arrays_figures_frame_after_frame(frames):
    p = ClutterParams()
    scratch = Scratch()
    for img8 in frames[:3]:
        img = img8.astype(np.float32)
        fresh_contrast = point_contrast(img, p)
        fresh_noise = local_noise_coarse(img, p.noise_window_px, 4, full=False)
        fresh_thr = cv2.resize(fresh_noise * np.float32(5.0), (W_PX, H_PX))
        contrast = point_contrast(img, p, scratch=scratch)
        noise = local_noise_coarse(img, p.noise_window_px, 4, full=False, scratch=scratch)
        assert np.array_equal(contrast, fresh_contrast)
        assert np.array_equal(noise, fresh_noise)
        assert point_candidates(contrast, fresh_thr, p, scratch) == point_candidates(fresh_contrast, fresh_thr, p)
        assert np.array_equal(isolated_outliers(img, 3.0, scratch), isolated_outliers(img, 3.0))
    # the next frame's call writes over the last one's result (documented: valid until then)
    again = point_contrast(frames[5].astype(np.float32), p, scratch=scratch)
    assert again is contrast


def test_defect_repair_into_its_own_frame_equals_the_copy(frames):
    dm = DefectMap((H_PX, W_PX), frames=4, fraction=0.5)
    hot = [(10, 20), (50, 90), (1, 1), (H_PX - 2, 7)]  # the border replicated: a pixel there is its own neighbour
    for img8 in frames[:6]:
        img = img8.astype(np.float32)
        for i, j in hot:
            img[i, j] = 255.0
        dm.update(img, 8.0)
    assert set(zip(*np.nonzero(dm.mask))) == set(hot)
    copy = dm.repair(img)
    assert copy is not img and img[10, 20] == 255.0  # the input untouched
    in_place = dm.repair(img, out=img)
    assert in_place is img and np.array_equal(in_place, copy)
    assert all(copy[i, j] < 200.0 for i, j in hot)


def test_defect_map_in_a_shared_scratch_equals_its_own(frames):
    # the detector's intermediates overwrite the shared arrays between two updates
    p = ClutterParams()
    shared = Scratch()
    own, in_shared = DefectMap((H_PX, W_PX), 4, 0.5), DefectMap((H_PX, W_PX), 4, 0.5, shared)
    for k, img8 in enumerate(frames[:8]):
        img = img8.astype(np.float32)
        img[30, 40] = 250.0  # a hot pixel
        if k % 3 == 0:
            img[60, 100] = 0.0  # a pixel that is an outlier on every third frame: never a defect
        own.update(img, 6.0)
        in_shared.update(img, 6.0)
        point_contrast(img, p, scratch=shared)
        local_noise_coarse(img, p.noise_window_px, 4, full=False, scratch=shared)
        assert np.array_equal(in_shared.mask, own.mask)
        assert np.array_equal(in_shared.repair(img), own.repair(img))
    assert in_shared.mask[30, 40] and not in_shared.mask[60, 100]


@pytest.mark.parametrize("acquiring", [False, True])
def test_detector_results_equal_the_functions_on_fresh_arrays(frames, acquiring):
    # its contrast, threshold and candidates survive the intermediates that share its arrays (while
    # acquiring, the threshold's noise near the axis is at most the window's quietest block's)
    p = ClutterParams()
    det = ObjectDetector(K, ObjectParams(), p)
    det.acquiring = acquiring
    for k, img in enumerate(frames[:6]):
        cands = det.detect(img, k)
        assert det.clean is not None and det.contrast is not None and det.threshold is not None
        clean = det.clean.copy()
        assert np.array_equal(det.contrast, point_contrast(clean, p))
        mean = local_noise_coarse(clean, p.noise_window_px, 4, full=False)
        cells, window_cells = noise_cells(clean, 4), p.noise_window_px // 4 | 1
        noise = np.clip(median_window_noise(cells, window_cells), mean * np.float32(p.median_noise_floor), mean)
        if acquiring:
            noise = det._quiet_noise(cells, noise, window_cells)
        threshold = cfar_threshold(noise, p.threshold_sigma, p.min_threshold_lsb)
        assert np.array_equal(det.threshold, cv2.resize(threshold, (W_PX, H_PX), interpolation=cv2.INTER_LINEAR))
        assert cands == point_candidates(det.contrast, det.threshold, p)
        assert any(abs(c.v_px - 91.0) < 1.5 and abs(c.u_px - (101.0 + k)) < 1.5 for c in cands)  # the warm point


def _detector_run(frames, ask_every_frame: bool, skip: frozenset = frozenset()):
    det = ObjectDetector(K, ObjectParams(), ClutterParams())
    seen = []
    for k, img in enumerate(frames):
        if k in skip:  # a frozen frame: the tracker neither detects nor registers it
            continue
        det.detect(img, k)
        det.background_motion(_pose(k))
        if ask_every_frame:
            seen.append(det.background_pxpf)
    return det, seen


@pytest.mark.parametrize("skip", [frozenset(), frozenset({12, 13, 20})])
def test_background_motion_asked_late_equals_the_motion_measured_every_frame(frames, skip):
    eager, per_frame = _detector_run(frames, True, skip)
    lazy, _ = _detector_run(frames, False, skip)
    assert lazy.background_over_window() == eager.background_over_window()
    assert lazy.background_pxpf == eager.background_pxpf == per_frame[-1]
    # and the figure is the terrain's own motion, the camera's pan removed
    bg = lazy.background_over_window()
    assert bg is not None
    assert abs(bg[0]) < MOTION_TOL_PXPF and abs(bg[1] - SCROLL_PXPF) < MOTION_TOL_PXPF
    assert per_frame[0] is None  # the first frame has nothing to be compared with


def test_tracker_output_does_not_depend_on_who_asked_for_the_background(frames):
    """Reading the background motion on every frame (as a debugger would) changes no output."""

    def run(ask: bool):
        tr = ObjectTracker(K)
        outs = []
        for k, img in enumerate(frames):
            outs.append(tr.update(img, _pose(k)))
            if ask:
                tr.detector.background_over_window()
        return outs

    assert repr(run(True)) == repr(run(False))


def test_stage_times_charge_every_tick_of_the_clock_to_one_stage(frames):
    """A clock that advances one second per reading: each lap charges the time since the last one, so the
    stages of a frame add up to every reading but the first; without a clock nothing is recorded."""
    ticks = iter(range(10_000))
    tr = ObjectTracker(K, stage_clock=lambda: float(next(ticks)))
    for k, img in enumerate(frames[:3]):
        before = next(ticks)
        tr.update(img, _pose(k))
        readings = next(ticks) - before - 1
        assert sum(tr.stages.seconds.values()) == readings - 1
    assert list(tr.stages.seconds) == [
        "frame event",
        "fixed pattern",
        "point contrast",
        "noise, threshold",
        "candidates",
        "deblending",
        "track-before-detect",
        "aided detection",
        "association, confirmation",
        "primary, output",
    ]
    assert all(s == 1.0 for s in tr.stages.seconds.values())
    untimed = ObjectTracker(K)
    untimed.update(frames[0], _pose(0))
    assert untimed.stages.seconds == {}


@settings(max_examples=40, deadline=None)
@given(
    st.integers(8, 40),
    st.integers(16, 64),
    st.sampled_from([1, 2, 4]),
    st.sampled_from([np.uint8, np.uint16]),
    st.integers(0, 2**31),
)
def test_column_offsets_are_numpys_median_of_each_column(rows, cols, row_step, dtype, seed):
    """The offsets from sorted columns equal ``np.median`` down the columns, odd and even row counts, ties
    (few grey levels) included."""
    rng = np.random.default_rng(seed)
    top = 6 if seed % 2 else int(np.iinfo(dtype).max)
    image = rng.integers(0, top + 1, (rows, cols)).astype(dtype)
    sampled = np.asarray(image[::row_step], dtype=np.float32)
    hmean = cv2.blur(sampled, (15, 1), borderType=cv2.BORDER_REFLECT)
    ref = np.median(sampled - hmean, axis=0).astype(np.float32)
    ref -= np.float32(np.median(ref))
    assert np.array_equal(column_offsets(image, 15, row_step), ref)
