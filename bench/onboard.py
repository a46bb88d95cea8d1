"""Benchmark of the onboard daemon's per-frame pipeline and of its loopback latency.

``python -m bench.onboard [--frames N] [--latency-s S] [--no-latency]``.  Prints:

1. Per-frame processing on one core, synthetic 640 x 512 mono8 frames (a Gaussian blob moving on
   a smooth background with 1 grey-level noise; P2-like geometry: observer circling at 8 m/s,
   target 150-170 m away), through ``FramePipeline.process_payload`` = decode + filter + detect +
   track + pose lookup + sliding-window estimator: frames/s from the median and the p10/p90/p99
   per-frame times, with each stage's median measured in the same run (decode, imaging, estimator
   ``add``) and the share of frames hit by the estimator's periodic model re-selection.
2. Loopback latency through the real daemon (``python -m onboard`` as a subprocess on 127.0.0.1):
   a fake autopilot (pymavlink, UDP) sends attitude/position at 50/25 Hz ahead of the frames, a
   zenoh publisher sends frames at 30 Hz; the time from ``put`` of a frame to the arrival of its
   track message, p50/p99/max, plus the daemon's own status numbers.

Numbers only; nothing asserts on time.  :class:`SyntheticScene` is also the test fixture of
``tests/onboard/test_pipeline.py`` and ``test_service.py``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from onboard.frames import (
    CameraMount,
    GeodeticOrigin,
    PinholeIntrinsics,
    geodetic_from_ned,
    quat_conjugate,
    quat_from_rotmat,
    quat_multiply,
    quat_normalize,
    rotmat_from_quat,
)
from onboard.irframe import IrFrame, encode_irframe

__all__ = ["SyntheticScene", "free_udp_port", "free_tcp_port", "main"]

ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)
BOOT_US0 = 20_000_000  # the scene starts 20 s after the autopilot booted


def _look_at(p_cam: np.ndarray, p_aim: np.ndarray) -> np.ndarray:
    """R_ned_from_cam looking from p_cam at p_aim, image x level (same as groundsim.synth.look_at)."""
    z = p_aim - p_cam
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


@dataclass
class SyntheticScene:
    """A deterministic scene: observer, target, camera pose, frames and telemetry on the boot clock.

    Observer: circle of radius 40 m at 8 m/s, 70 m up, about the origin.  Target: straight line at
    5 m/s (north), 150-170 m from the observer, 85 m up.  The camera (fixed pod, identity mount) is
    pointed at the target with a slowly varying error of a few percent of range, so the target moves
    over the image.  Frames: 640 x 512 mono8, background ``90 + 30 v/H + 8 sin(u/90)``, a Gaussian
    blob (``blob_sigma_px``, ``blob_amp_grey``), white noise ``noise_grey`` (a bank of precomputed
    noise frames).  Times: frame ``k`` is captured at ``BOOT_US0 + k / frame_rate_hz``.
    """

    frame_rate_hz: float = 30.0
    intrinsics: PinholeIntrinsics = field(default_factory=PinholeIntrinsics.vue_pro_640)
    origin: GeodeticOrigin = ORIGIN
    blob_sigma_px: float = 1.5
    blob_amp_grey: float = 60.0
    noise_grey: float = 1.0
    pointing_error_frac: tuple[float, float, float] = (0.03, 0.02, 0.015)
    seed: int = 0
    boot_us0: int = BOOT_US0

    def __post_init__(self) -> None:
        K = self.intrinsics
        h, w = K.height_px, K.width_px
        rng = np.random.default_rng(self.seed)
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
        self._bg = 90.0 + 30.0 * vv / h + 8.0 * np.sin(uu / 90.0)
        self._noise = [rng.normal(0.0, self.noise_grey, (h, w)).astype(np.float32) for _ in range(8)]
        self.mount = CameraMount()
        self._q_body_from_cam = self.mount.q_body_from_cam()

    # ------------------------------------------------------------------ truth

    def t_us(self, k: int) -> int:
        return self.boot_us0 + int(round(k * 1e6 / self.frame_rate_hz))

    def observer(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Observer (= camera) position and velocity, NED."""
        w = 8.0 / 40.0
        a = w * t_s
        p = np.array([40.0 * math.cos(a), 40.0 * math.sin(a), -70.0])
        v = np.array([-40.0 * w * math.sin(a), 40.0 * w * math.cos(a), 0.0])
        return p, v

    def target(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        v = np.array([5.0, 0.0, 0.0])
        return np.array([150.0, 30.0, -85.0]) + v * t_s, v

    def camera(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(p_cam_ned_m, q_ned_from_cam) at ``t_s`` (seconds since the scene started)."""
        p_cam, _ = self.observer(t_s)
        p_tgt, _ = self.target(t_s)
        rng_m = float(np.linalg.norm(p_tgt - p_cam))
        frac = np.asarray(self.pointing_error_frac)
        err = rng_m * frac * np.sin(2 * np.pi * t_s / np.array([7.0, 5.0, 3.0]))
        R = _look_at(p_cam, p_tgt + err)
        return p_cam, quat_from_rotmat(R)

    def body(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_body_ned_m, v_ned_mps, q_ned_from_body) consistent with :meth:`camera` through the mount."""
        p_cam, q_nc = self.camera(t_s)
        _, v = self.observer(t_s)
        q_nb = quat_normalize(quat_multiply(q_nc, quat_conjugate(self._q_body_from_cam)))
        return p_cam, v, q_nb

    def uv(self, t_s: float) -> np.ndarray:
        """The target's true pixel."""
        p_cam, q_nc = self.camera(t_s)
        p_tgt, _ = self.target(t_s)
        return self.intrinsics.project(rotmat_from_quat(q_nc).T @ (p_tgt - p_cam))

    # ------------------------------------------------------------------ sensors

    def image(self, k: int, with_target: bool = True) -> np.ndarray:
        t_s = (self.t_us(k) - self.boot_us0) / 1e6
        img = self._bg + self._noise[k % len(self._noise)]
        if with_target:
            u, v = self.uv(t_s)
            r = int(math.ceil(4 * self.blob_sigma_px))
            j0, j1 = max(int(u) - r, 0), min(int(u) + r + 1, img.shape[1])
            i0, i1 = max(int(v) - r, 0), min(int(v) + r + 1, img.shape[0])
            if j1 > j0 and i1 > i0:
                jj, ii = np.meshgrid(np.arange(j0, j1) + 0.5, np.arange(i0, i1) + 0.5)
                img[i0:i1, j0:j1] += self.blob_amp_grey * np.exp(
                    -((jj - u) ** 2 + (ii - v) ** 2) / (2 * self.blob_sigma_px**2)
                )
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def frame(self, k: int, with_target: bool = True, seq: int | None = None, time_boot_us: int | None = None) -> IrFrame:
        return IrFrame(seq=k if seq is None else seq, time_boot_us=self.t_us(k) if time_boot_us is None else time_boot_us,
                       pixels=self.image(k, with_target))

    def payload(self, k: int, **kw) -> bytes:
        return encode_irframe(self.frame(k, **kw))

    def telemetry(self, t0_us: int, t1_us: int, rate_hz: float):
        """Samples ``(time_boot_us, p_body_ned_m, v_ned_mps, q_ned_from_body)`` every 1/rate_hz in [t0, t1]."""
        step = int(round(1e6 / rate_hz))
        t = t0_us + (-(t0_us - self.boot_us0)) % step  # the first sample time >= t0 on the grid
        while t <= t1_us:
            p, v, q = self.body((t - self.boot_us0) / 1e6)
            yield t, p, v, q
            t += step

    def feed(self, pose_buffer, t0_us: int, t1_us: int, att_rate_hz: float = 50.0, pos_rate_hz: float = 25.0) -> None:
        """Add attitude and NED position samples covering [t0, t1] to a PoseBuffer."""
        for t, _, _, q in self.telemetry(t0_us, t1_us, att_rate_hz):
            pose_buffer.add_attitude(t, q)
        for t, p, v, _ in self.telemetry(t0_us, t1_us, pos_rate_hz):
            pose_buffer.add_position_ned(t, p, v)

    def geodetic(self, p_ned_m) -> tuple[float, float, float]:
        lat, lon, alt = geodetic_from_ned(p_ned_m, self.origin)
        return float(lat), float(lon), float(alt)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
