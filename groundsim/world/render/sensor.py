"""The thermal camera as it behaves: raw counts, fixed-pattern noise, vignetting, flat-field events, AGC.

Public API::

    sensor = Sensor(sensor_config, renderer.intrinsics, renderer.settings, seed, frame_rate_hz)
    out = sensor.apply(radiance, t_s, frame_index)   # SensorFrame(counts, mono8, status)

``radiance``: (H, W) W m^-2 sr^-1 at the aperture, no noise (``SceneFrame.radiance`` or
``IrRenderer.render_radiance``).  Model, per pixel ``(i, j)`` (``groundsim.world.render.scene_config``
names the knobs)::

    counts = c_min + G_ij v_ij g (L - L(t_min_k)) + O_ij(t) + n,     g = (c_max - c_min) / (L(t_max_k) - L(t_min_k))

``G_ij`` the per-pixel gain (1 + N(0, pixel_gain_sigma)), ``v_ij`` vignetting (``1 - (1 - corner_gain) r^2``),
``n`` temporal noise of ``g * netd_k * dL/dT(netd_reference_k)`` counts (1 sigma), ``O_ij(t)`` the offset
pattern: per-column and per-pixel Gaussian offsets (``residual_fraction`` of them) plus a drift pattern
that grows by ``drift_counts_per_s`` (1 sigma) per second since the last flat-field correction (FFC).
Then rounding, saturation at ``2^raw_bits - 1``, dead pixels (0) and hot pixels (full scale): ``counts``,
uint16.  Column and pixel patterns are AR-free, fixed draws (the static part of El Gamal et al.'s FPN
model, Proc. SPIE 3301, 1998); the drift is one more fixed pattern scaled with time, as an uncooled
core's offsets follow its temperature between shutter events.

FFC (``ffc``): at ``first_s + k period_s`` the shutter closes for ``frames`` frames, which are
``frozen`` (the last output repeated, status ``"frozen"``) or ``dropped`` (``counts`` and ``mono8`` None,
status ``"dropped"``); then the drift restarts from zero: a step in the offsets.

AGC (``agc``): plateau histogram equalisation (as FLIR Boson and Lepton cores ship it): the
histogram of the counts (every second pixel of every second row), each bin clipped at
``plateau_fraction`` of the samples and at the count that gives a slope of ``max_gain`` levels per
count, accumulated into a map to 0..255, mixed with a linear map between the 0.1 % and 99.9 % points by
``linear_fraction``; the map moves towards each frame's with time constant ``time_constant_s``
(the frame-to-frame gain changes of a real core).  ``mono8 = map[counts]``.

Deterministic: the noise of frame ``frame_index`` is a window into a noise bank chosen by
``(seed, frame_index)``; the AGC map and the frozen frame are the only state (same calls, same bytes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from groundsim.world.render.kernels import agc_map, lut_take, sensor_counts
from groundsim.world.render.planck import band_radiance, band_radiance_derivative
from groundsim.world.render.scene import section_rng
from groundsim.world.render.scene_config import SensorConfig
from groundsim.world.render.settings import IrSettings
from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics

__all__ = ["Sensor", "SensorFrame", "STATUSES", "NOISE_BANK_FRAMES"]

STATUSES = ("ok", "frozen", "dropped")
NOISE_BANK_FRAMES = 2
AGC_TAIL = 0.001  # the linear part of the AGC maps the 0.1 % .. 99.9 % points to 0 .. 255


@dataclass(frozen=True)
class SensorFrame:
    """One camera output: ``counts`` (H, W) uint16 raw counts, ``mono8`` (H, W) uint8 AGC output (None when
    the AGC is off), ``status`` ``ok`` / ``frozen`` / ``dropped`` (then both images are None), and
    ``ffc_count`` flat-field events so far."""

    counts: np.ndarray | None
    mono8: np.ndarray | None
    status: str
    ffc_count: int


class Sensor:
    """Radiance -> counts (-> AGC mono8); see the module docstring.  Not thread-safe (AGC state)."""

    def __init__(
        self,
        config: SensorConfig,
        intrinsics: PinholeIntrinsics,
        settings: IrSettings,
        seed: int = 0,
        frame_rate_hz: float = 30.0,
    ):
        if not isinstance(config, SensorConfig):
            raise InputError(f"config: expected a SensorConfig, got {type(config).__name__}")
        if not (isinstance(frame_rate_hz, (int, float)) and math.isfinite(frame_rate_hz) and frame_rate_hz > 0):
            raise InputError(f"frame_rate_hz: expected a number > 0, got {frame_rate_hz!r}")
        self.config = c = config
        self.settings = s = settings
        self.frame_rate_hz = float(frame_rate_hz)
        self._H, self._W = H, W = int(intrinsics.height_px), int(intrinsics.width_px)
        self.full_scale = 2**c.raw_bits - 1
        L_min = float(band_radiance(s.t_min_k, s.band_um))
        L_max = float(band_radiance(s.t_max_k, s.band_um))
        self.counts_per_radiance = (c.counts_at_t_max - c.counts_at_t_min) / (L_max - L_min)
        self._L_min = L_min
        netd_L = float(s.netd_k) * float(band_radiance_derivative(s.netd_reference_k, s.band_um))
        self.noise_sigma_counts = netd_L * self.counts_per_radiance
        rng = section_rng(seed, "sensor", c.seed)
        gain = np.full((H, W), self.counts_per_radiance, np.float64)
        f = c.fpn
        if f.enabled:
            gain *= 1.0 + f.pixel_gain_sigma * rng.standard_normal((H, W))
        if c.vignetting.enabled:
            v = np.arange(H) + 0.5 - intrinsics.cy_px
            u = np.arange(W) + 0.5 - intrinsics.cx_px
            r2 = v[:, None] ** 2 + u[None, :] ** 2
            gain *= 1.0 - (1.0 - c.vignetting.corner_gain) * r2 / r2.max()
        self._gain = gain.astype(np.float32)
        offset = np.full((H, W), float(c.counts_at_t_min), np.float64)
        drift = np.zeros((H, W), np.float64)
        self._dead = self._hot = np.zeros(0, np.intp)
        if f.enabled:
            static = f.column_sigma_counts * rng.standard_normal(W)[None, :] + f.pixel_offset_sigma_counts * (
                rng.standard_normal((H, W))
            )
            offset += f.residual_fraction * static
            # drift: half column structure, half pixel, unit variance per second of drift rate
            drift = (rng.standard_normal(W)[None, :] + rng.standard_normal((H, W))) / math.sqrt(2.0)
            drift *= f.drift_counts_per_s
            n_bad = min(f.dead_pixels + f.hot_pixels, H * W)
            bad = rng.choice(H * W, size=n_bad, replace=False)
            self._dead, self._hot = bad[: f.dead_pixels], bad[f.dead_pixels :]
        self._offset_at_zero = (offset - L_min * gain).astype(np.float32)  # counts = gain L + this
        self._drift = drift.astype(np.float32) if f.enabled and f.drift_counts_per_s > 0.0 else None
        n = H * W
        self._noise = (rng.standard_normal(n * NOISE_BANK_FRAMES, dtype=np.float32)) * np.float32(
            self.noise_sigma_counts
        )
        self._noise_offsets = n * (NOISE_BANK_FRAMES - 1) + 1
        self._seed = int(seed)
        self._offset_now = np.empty((H, W), np.float32)
        self._lut: np.ndarray | None = None
        self._last: SensorFrame | None = None

    # ------------------------------------------------------------------ flat-field events

    def ffc_state(self, t_s: float) -> tuple[int, float, bool]:
        """``(events so far, seconds since the last one ended, shutter closed now)`` at ``t_s``; before the first
        event the seconds are since 0, and while the shutter is closed they hold their value at its closing."""
        ffc = self.config.ffc
        if not ffc.enabled or t_s < ffc.first_s:
            return 0, max(float(t_s), 0.0), False
        k = int(math.floor((t_s - ffc.first_s) / ffc.period_s))
        start = ffc.first_s + k * ffc.period_s
        closed_s = ffc.frames / self.frame_rate_hz
        if t_s < start + closed_s - 1e-9:
            since = (start - ffc.period_s + closed_s) if k > 0 else 0.0  # before the first: since time 0
            return k + 1, max(start - since, 0.0), True
        return k + 1, float(t_s) - (start + closed_s), False

    # ------------------------------------------------------------------ a frame

    def counts(self, radiance, t_s: float, frame_index: int) -> np.ndarray:
        """Raw counts (H, W) uint16 of ``radiance`` at ``t_s`` (no FFC freezing, no AGC)."""
        L = np.asarray(radiance, dtype=np.float32)
        if L.shape != (self._H, self._W):
            raise InputError(f"radiance: expected shape {(self._H, self._W)}, got {L.shape}")
        _, since_s, _ = self.ffc_state(t_s)
        # per-frame scratch images (the counts below are a new array: the caller keeps them)
        offset = (
            self._offset_at_zero
            if self._drift is None
            else cv2.scaleAdd(self._drift, since_s, self._offset_at_zero, dst=self._offset_now)
        )
        n = self._H * self._W
        off = int(np.random.default_rng([self._seed, int(frame_index)]).integers(self._noise_offsets))
        noise = self._noise[off : off + n].reshape(self._H, self._W)
        out = np.empty((self._H, self._W), np.uint16)
        # one pass: gain, offset, noise, then cv2.add(..., dtype=CV_16U)'s rounding and saturation and the
        # raw full scale (the numpy/OpenCV formulation, in tests/groundsim/test_render_kernels.py, is bit for bit)
        sensor_counts(np.ascontiguousarray(L), self._gain, offset, noise, self.full_scale, out)
        flat = out.reshape(-1)
        flat[self._dead] = 0
        flat[self._hot] = self.full_scale
        return out

    def agc_map(self, counts: np.ndarray) -> np.ndarray:
        """This frame's AGC map (float, ``2^raw_bits`` entries, 0..255) before the temporal smoothing."""
        a = self.config.agc
        return agc_map(
            counts,
            self.full_scale + 1,
            float(a.plateau_fraction),
            float(a.max_gain),
            float(a.linear_fraction),
            AGC_TAIL,
        )

    def apply(self, radiance, t_s: float, frame_index: int) -> SensorFrame:
        """One frame through the camera: a :class:`SensorFrame` (see the module docstring)."""
        events, _, closed = self.ffc_state(float(t_s))
        if closed:
            if self.config.ffc.mode == "dropped" or self._last is None:
                return SensorFrame(None, None, "dropped", events)
            last = self._last
            return SensorFrame(last.counts, last.mono8, "frozen", events)
        counts = self.counts(radiance, t_s, frame_index)
        mono8 = None
        if self.config.agc.enabled:
            new = self.agc_map(counts)
            tc = self.config.agc.time_constant_s
            if self._lut is None or tc <= 0.0:
                self._lut = new
            else:
                self._lut = self._lut + (1.0 - math.exp(-1.0 / (self.frame_rate_hz * tc))) * (new - self._lut)
            mono8 = np.empty(counts.shape, np.uint8)
            lut_take(self._lut, counts, mono8)
        frame = SensorFrame(counts, mono8, "ok", events)
        self._last = frame
        return frame
