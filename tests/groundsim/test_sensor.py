"""The camera model (groundsim.world.render.sensor): counts, each artefact, flat-field events, AGC, determinism."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.world.render import IrSettings
from groundsim.world.render.planck import band_radiance
from groundsim.world.render.scene_config import scene_config_from_dict
from groundsim.world.render.sensor import Sensor
from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics

INTR = PinholeIntrinsics.vue_pro_640()
IR = IrSettings()
QUIET = IrSettings(netd_k=0.0)
H, W = 512, 640
SMALL_INTR = PinholeIntrinsics(80.0, 80.0, 40.0, 32.0, 80, 64)  # the property tests' frames: 5120 pixels
COUNT_ATOL = 1.0  # rounding of a count
SIGMA_RTOL = 0.1  # sample standard deviation over hundreds to 300k samples
AGC_MAP_ATOL = 1e-9  # the float map's rounding at its top (measured 3e-14 over 255)


def sensor(cfg: dict, ir: IrSettings = QUIET, seed: int = 1, rate: float = 30.0) -> Sensor:
    raw = {"enabled": True, **cfg}
    return Sensor(scene_config_from_dict({"sensor": raw}).sensor, INTR, ir, seed, rate)


def flat(T_k: float) -> np.ndarray:
    return np.full((H, W), float(band_radiance(T_k, IR.band_um)), np.float32)


def test_counts_are_linear_in_radiance_between_the_two_points():
    s = sensor({"counts_at_t_min": 1000, "counts_at_t_max": 15000})
    assert s.counts(flat(IR.t_min_k), 0.0, 0).astype(float) == pytest.approx(1000.0, abs=COUNT_ATOL)
    assert s.counts(flat(IR.t_max_k), 0.0, 0).astype(float) == pytest.approx(15000.0, abs=COUNT_ATOL)
    L_mid = 0.5 * (band_radiance(IR.t_min_k, IR.band_um) + band_radiance(IR.t_max_k, IR.band_um))
    mid = s.counts(np.full((H, W), L_mid, np.float32), 0.0, 0)
    assert mid.dtype == np.uint16 and mid.astype(float) == pytest.approx(8000.0, abs=COUNT_ATOL)
    hot = s.counts(flat(900.0), 0.0, 0)
    assert np.all(hot == 2**14 - 1)  # saturates at 14 bits, not 16
    with pytest.raises(InputError, match="radiance"):
        s.counts(np.zeros((4, 4)), 0.0, 0)


def test_temporal_noise_is_netd_in_counts():
    s = sensor({}, ir=IR)
    a = s.counts(flat(300.0), 0.0, 0).astype(float)
    b = s.counts(flat(300.0), 0.0, 1).astype(float)
    assert np.std(a - b) / math.sqrt(2.0) == pytest.approx(math.hypot(s.noise_sigma_counts, 0.29), rel=SIGMA_RTOL)
    assert s.noise_sigma_counts > 3.0  # 40 mK at ~150 counts/K


def test_column_stripes():
    s = sensor(
        {
            "fpn": {
                "enabled": True,
                "column_sigma_counts": 10.0,
                "pixel_offset_sigma_counts": 0.0,
                "pixel_gain_sigma": 0.0,
                "dead_pixels": 0,
                "hot_pixels": 0,
                "drift_counts_per_s": 0.0,
            }
        }
    )
    c = s.counts(flat(290.0), 0.0, 0).astype(float)
    assert np.std(c.mean(axis=0)) == pytest.approx(10.0, rel=SIGMA_RTOL)  # one offset per column
    assert np.std(c.mean(axis=1)) < 0.5  # rows all alike
    assert np.all(np.ptp(c, axis=0) <= 1.0)  # constant down each column (noise off)


def test_pixel_gain_and_offset_non_uniformity():
    s = sensor(
        {
            "fpn": {
                "enabled": True,
                "column_sigma_counts": 0.0,
                "pixel_offset_sigma_counts": 5.0,
                "pixel_gain_sigma": 0.03,
                "dead_pixels": 0,
                "hot_pixels": 0,
                "drift_counts_per_s": 0.0,
            }
        }
    )
    lo = s.counts(flat(IR.t_min_k), 0.0, 0).astype(float)
    hi = s.counts(flat(IR.t_max_k), 0.0, 0).astype(float)
    assert np.std(lo) == pytest.approx(5.0, rel=SIGMA_RTOL)  # offsets alone at L(t_min)
    span = hi - lo
    assert np.std(span / span.mean()) == pytest.approx(0.03, rel=SIGMA_RTOL)


def test_dead_and_hot_pixels():
    s = sensor(
        {
            "fpn": {
                "enabled": True,
                "dead_pixels": 7,
                "hot_pixels": 4,
                "column_sigma_counts": 0.0,
                "pixel_offset_sigma_counts": 0.0,
                "pixel_gain_sigma": 0.0,
            }
        }
    )
    c = s.counts(flat(295.0), 0.0, 0)
    assert int(np.sum(c == 0)) == 7 and int(np.sum(c == 2**14 - 1)) == 4
    assert np.array_equal(c == 0, s.counts(flat(250.0), 3.0, 5) == 0)  # stuck wherever the scene is


def test_offset_drift_grows_and_the_flat_field_event_steps_it_back():
    cfg = {
        "fpn": {
            "enabled": True,
            "column_sigma_counts": 0.0,
            "pixel_offset_sigma_counts": 0.0,
            "pixel_gain_sigma": 0.0,
            "dead_pixels": 0,
            "hot_pixels": 0,
            "drift_counts_per_s": 2.0,
        },
        "ffc": {"enabled": True, "period_s": 10.0, "first_s": 10.0, "frames": 3, "mode": "frozen"},
    }
    s = sensor(cfg)
    L = flat(290.0)
    c0 = s.counts(L, 0.0, 0).astype(float)
    c5 = s.counts(L, 5.0, 150).astype(float)
    assert np.std(c5 - c0) == pytest.approx(10.0, rel=SIGMA_RTOL)  # 2 counts/s x 5 s
    before = s.counts(L, 9.9, 297).astype(float)
    after = s.counts(L, 10.0 + 3 / 30.0 + 1e-6, 303).astype(float)  # shutter open again
    assert np.std(before - c0) == pytest.approx(19.8, rel=SIGMA_RTOL)
    assert np.std(after - c0) < 1.0  # the drift restarted: a step of ~20 counts (1 sigma)


def test_ffc_state_counts_the_events_and_the_seconds_since_the_last_one_ended():
    """``(events, seconds since the last event ended, shutter closed)``: the shutter closes for 3 frames (0.1 s)
    every 10 s from 10 s; while it is closed the offsets' drift holds its value at the closing (the time since
    the last opening, or since 0 before the first), and restarts when it opens."""
    s = sensor({"ffc": {"enabled": True, "period_s": 10.0, "first_s": 10.0, "frames": 3}})
    want = {
        5.0: (0, 5.0, False),
        10.05: (1, 10.0, True),  # the first event: 10 s of drift since 0 when the shutter closed
        10.6: (1, 0.5, False),
        20.05: (2, 9.9, True),  # 9.9 s since the first opened (10.1 s)
        25.1: (2, 5.0, False),
    }
    for t_s, (events, since_s, closed) in want.items():
        got = s.ffc_state(t_s)
        assert got[0] == events and got[2] is closed and got[1] == pytest.approx(since_s, abs=1e-9), (t_s, got)


@pytest.mark.parametrize("mode", ["frozen", "dropped"])
def test_flat_field_event_freezes_or_drops_frames(mode):
    s = sensor({"ffc": {"enabled": True, "period_s": 1.0, "first_s": 0.5, "frames": 4, "mode": mode}}, ir=IR)
    outs = [s.apply(flat(280.0 + k), k / 30.0, k) for k in range(40)]
    status = [o.status for o in outs]
    assert status[:15] == ["ok"] * 15 and status[15:19] == [mode] * 4 and status[19:] == ["ok"] * 21
    assert outs[14].ffc_count == 0 and outs[15].ffc_count == 1
    if mode == "frozen":
        assert all(o.counts is outs[14].counts for o in outs[15:19])
    else:
        assert all(o.counts is None and o.mono8 is None for o in outs[15:19])


def test_vignetting_darkens_the_corners():
    s = sensor({"vignetting": {"enabled": True, "corner_gain": 0.8}})
    lo = s.counts(flat(IR.t_min_k), 0.0, 0).astype(float)
    hi = s.counts(flat(IR.t_max_k), 0.0, 0).astype(float)
    span = hi - lo
    assert span[256, 320] / span.max() == pytest.approx(1.0, abs=1e-3)
    assert span[0, 0] / span[256, 320] == pytest.approx(0.8, abs=2e-3)


@functools.cache
def _scene_radiance(hot_box: bool) -> np.ndarray:
    """Sky cold on top, ground warm at the bottom; with ``hot_box`` a warm object over a quarter of the image."""
    T_k = np.linspace(250.0, 290.0, 1001)
    L = band_radiance(T_k, IR.band_um)
    T = np.linspace(290.0, 250.0, H)[:, None] * np.ones((1, W))
    if hot_box:
        T[128:384, 160:480] = 289.0
    out = np.interp(T, T_k, L).astype(np.float32)
    out.flags.writeable = False
    return out


def test_agc_uses_the_8_bit_range_monotonically():
    s = sensor({"agc": {"enabled": True}}, ir=IR)
    out = s.apply(_scene_radiance(False), 0.0, 0)
    assert out.mono8.dtype == np.uint8 and out.mono8.shape == (H, W)
    assert out.mono8.min() <= 5 and out.mono8.max() >= 250
    order = np.argsort(out.counts.ravel(), kind="stable")
    assert np.all(np.diff(out.mono8.ravel()[order].astype(int)) >= 0)  # brighter counts never darker


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    raw_bits=st.sampled_from((12, 14, 16)),
    T_lo_k=st.floats(150.0, 300.0),
    T_span_k=st.floats(0.5, 200.0),
    plateau_fraction=st.floats(0.001, 1.0),
    max_gain=st.floats(0.05, 8.0),
    linear_fraction=st.floats(0.0, 1.0),
)
def test_counts_and_agc_are_monotonic_and_within_their_ranges(
    seed, raw_bits, T_lo_k, T_span_k, plateau_fraction, max_gain, linear_fraction
):
    # noiseless, no fixed pattern: every pixel has the same gain, so a warmer pixel has no fewer counts,
    # the counts stay within 0 .. 2^raw_bits - 1 (not only within the uint16 they are stored in), and the
    # AGC map (whatever its knobs and the scene's histogram) never maps more counts to a darker grey
    full = 2**raw_bits - 1
    raw = {
        "enabled": True,
        "raw_bits": raw_bits,
        "counts_at_t_min": full // 8,
        "counts_at_t_max": full - full // 8,
        "agc": {
            "enabled": True,
            "plateau_fraction": plateau_fraction,
            "max_gain": max_gain,
            "linear_fraction": linear_fraction,
        },
    }
    s = Sensor(scene_config_from_dict({"sensor": raw}).sensor, SMALL_INTR, QUIET, 1, 30.0)
    rng = np.random.default_rng(seed)
    T_k = np.sort(rng.uniform(T_lo_k, T_lo_k + T_span_k, SMALL_INTR.width_px * SMALL_INTR.height_px))
    L = band_radiance(T_k, IR.band_um).astype(np.float32).reshape(SMALL_INTR.height_px, SMALL_INTR.width_px)
    out = s.apply(L, 0.0, 0)
    counts = out.counts.ravel().astype(np.int64)
    assert np.all(np.diff(counts) >= 0)
    assert counts.min() >= 0 and counts.max() <= full
    agc = s.agc_map(out.counts)
    assert np.all(np.diff(agc) >= 0) and agc.min() >= 0.0 and agc.max() <= 255.0 + AGC_MAP_ATOL
    # lut_take casts rint(map) to uint8 without saturating: it must already be in range
    assert np.rint(agc).max() <= 255.0
    assert np.all(np.diff(out.mono8.ravel().astype(np.int64)) >= 0)


def test_agc_gain_follows_the_scene_with_its_time_constant():
    tc = 0.3
    s = sensor({"agc": {"enabled": True, "time_constant_s": tc}})
    for k in range(30):
        before = int(s.apply(_scene_radiance(False), k / 30.0, k).mono8[400, 100])
    probe = []
    for k in range(30, 60):
        probe.append(int(s.apply(_scene_radiance(True), k / 30.0, k).mono8[400, 100]))
    instant = sensor({"agc": {"enabled": True, "time_constant_s": 0.0}})
    settled = int(instant.apply(_scene_radiance(True), 0.0, 0).mono8[400, 100])
    # a warm object enters: the map moves frame by frame, not at once, and settles where an instant AGC is
    assert probe[0] != settled and abs(probe[-1] - settled) <= 1
    steps = np.diff(probe)
    assert np.count_nonzero(steps) >= 5
    n_63 = 1 + int(np.argmax(np.abs(np.array(probe) - before) >= 0.63 * abs(settled - before)))  # frames
    assert n_63 / 30.0 == pytest.approx(tc, abs=1.5 / 30.0)


def test_same_seed_same_bytes():
    cfg = {
        "agc": {"enabled": True},
        "fpn": {"enabled": True},
        "vignetting": {"enabled": True},
        "ffc": {"enabled": True, "period_s": 0.5, "first_s": 0.2},
    }
    runs = []
    for seed in (3, 3, 4):
        s = sensor(cfg, ir=IR, seed=seed)
        b = b""
        for k in range(20):
            o = s.apply(_scene_radiance(k > 10), k / 30.0, k)
            b += (o.counts.tobytes() + o.mono8.tobytes()) if o.counts is not None else b"-"
        runs.append(b)
    assert runs[0] == runs[1] and runs[0] != runs[2]
