"""``rpekf``: a range-parameterised extended Kalman filter bank with an RTS smoother (bearings-only tracking).

Written only against the :class:`onboard.pipeline.plugins.TrajectoryEstimator` protocol, with numpy and nothing
else of irtrack (its intrinsics argument is used through ``fx_px, fy_px, cx_px, cy_px`` only, the
quaternion is converted here): the kind of filter a user would bring from a tracking library, plugged
in without a change to irtrack (registered as an entry point in irtrack's ``pyproject.toml`` like
any outside package would register it in its own).

Model.  State ``x = [p_ned_m (3), v_ned_mps (3)]``, constant velocity with white acceleration of
spectral density ``accel_psd_m2ps3``: ``F = [[I, dt I], [0, I]]``, ``Q = q [[dt^3/3 I, dt^2/2 I],
[dt^2/2 I, dt I]]``.  Measurement: ideal normalised image coordinates ``z = (x_c / z_c, y_c / z_c)``
of ``p_c = R_ned_from_cam^T (p - p_cam)``, noise ``sigma_z^2 = (pixel_sigma_px / f)^2 +
attitude_sigma_rad^2`` per axis; EKF linearisation at the prediction.

Range parameterisation (Peach, "Bearings-only tracking using a set of range-parameterised extended
Kalman filters", IEE Proc. Control Theory Appl. 142(1), 1995): at the first bearing, ``n_filters``
EKFs start at ranges ``r_i = r_min rho^i`` (``rho = (r_max / r_min)^(1 / (n - 1))``) along it, each
with radial sigma ``r_i (rho - 1) / sqrt(12)`` (so the hypotheses tile the range interval) and
cross-range sigma ``r_i sigma_z``; velocity ``N(0, speed_sigma_mps^2 I)``.  Weights are updated with
each filter's innovation likelihood; the reported estimate is the Gaussian-mixture mean and
covariance (spread of the filters included).  ``observable`` when the mixture's radial sigma / range
is below ``observable_sigma_ratio`` (3 %; irtrack's MAP estimator uses 5.5 %, its own calibration).

Smoother.  :meth:`RangeParameterisedEkf.smoothed` runs the Rauch-Tung-Striebel backward pass
(Rauch, Tung & Striebel 1965) over each filter's stored history and mixes the smoothed tracks with
the final weights: the whole-flight trajectory after the fact (not used by the online pipeline).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from onboard.estimation.sliding import TrackEstimate

__all__ = ["RpEkfConfig", "RpEkfEstimate", "RangeParameterisedEkf"]


@dataclass(frozen=True)
class RpEkfConfig:
    n_filters: int = 8
    r_min_m: float = 20.0
    r_max_m: float = 2000.0
    speed_sigma_mps: float = 15.0
    accel_psd_m2ps3: float = 1.0
    pixel_sigma_px: float = 0.3
    attitude_sigma_rad: float = 0.0
    observable_sigma_ratio: float = 0.03
    max_history: int = 2000

    def __post_init__(self) -> None:
        if not (
            self.n_filters >= 2
            and 0 < self.r_min_m < self.r_max_m
            and self.speed_sigma_mps > 0
            and self.accel_psd_m2ps3 > 0
            and self.pixel_sigma_px > 0
            and self.attitude_sigma_rad >= 0
            and self.observable_sigma_ratio > 0
            and self.max_history >= 2
        ):
            raise ValueError(f"RpEkfConfig: invalid values {self}")


@dataclass(frozen=True)
class RpEkfEstimate(TrackEstimate):
    """The estimate of the plug-in protocol (:class:`onboard.estimation.sliding.TrackEstimate`, see
    :mod:`onboard.pipeline.plugins`), plus the filters' weights."""

    model: str = "rpekf"
    weights: tuple = field(default=())


def _R_ned_from_cam(q) -> np.ndarray:
    w, x, y, z = (float(a) for a in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _transition(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    I3 = np.eye(3)
    F = np.block([[I3, dt * I3], [np.zeros((3, 3)), I3]])
    Q = q * np.block([[dt**3 / 3 * I3, dt**2 / 2 * I3], [dt**2 / 2 * I3, dt * I3]])
    return F, Q


class RangeParameterisedEkf:
    """A bank of EKFs over range hypotheses (module docstring).  Step methods of the plug-in protocol."""

    def __init__(self, config: RpEkfConfig | None = None) -> None:
        self.config = config or RpEkfConfig()
        self.reset()

    @classmethod
    def from_config(cls, config) -> RangeParameterisedEkf:
        """From irtrack's OnboardConfig: the pixel and white attitude noise its estimator assumes."""
        noise = config.estimator.noise_model()
        # the filter has no bias state: the attitude bias the estimator models is folded into white noise
        att = math.hypot(
            float(getattr(noise, "attitude_white_sigma_rad", 0.0)),
            float(getattr(noise, "attitude_bias_sigma_rad", 0.0)),
        )
        return cls(RpEkfConfig(pixel_sigma_px=float(getattr(noise, "pixel_sigma_px", 0.3)), attitude_sigma_rad=att))

    def reset(self) -> None:
        self._x: np.ndarray | None = None  # (n, 6)
        self._P: np.ndarray | None = None  # (n, 6, 6)
        self._logw: np.ndarray | None = None
        self._t: float | None = None
        self._frames = 0
        self._history: list = []  # per step: (t, F, x_pred, P_pred, x_filt, P_filt)

    # ----------------------------------------------------------------- protocol

    def add(self, t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        c = self.config
        t = float(t_s)
        u, v = (float(a) for a in uv_px)
        z = np.array([(u - intrinsics.cx_px) / intrinsics.fx_px, (v - intrinsics.cy_px) / intrinsics.fy_px])
        sigma_z2 = (c.pixel_sigma_px / math.sqrt(intrinsics.fx_px * intrinsics.fy_px)) ** 2 + c.attitude_sigma_rad**2
        p_cam = np.asarray(p_cam_ned_m, dtype=float)
        R_nc = _R_ned_from_cam(q_ned_from_cam)
        if self._x is None:
            self._init(t, z, sigma_z2, p_cam, R_nc)
            return self._mixture(t, p_cam)
        F, Q = _transition(t - self._t, c.accel_psd_m2ps3)
        x_pred = self._x @ F.T
        P_pred = F @ self._P @ F.T + Q
        x_new, P_new, logw = x_pred.copy(), P_pred.copy(), self._logw.copy()
        Rm = sigma_z2 * np.eye(2)
        for i in range(len(x_pred)):
            pc = R_nc.T @ (x_pred[i, :3] - p_cam)
            if pc[2] <= 1e-6:  # hypothesis behind the camera: it cannot explain the bearing
                logw[i] = -np.inf
                continue
            h = pc[:2] / pc[2]
            J = np.array([[1 / pc[2], 0, -pc[0] / pc[2] ** 2], [0, 1 / pc[2], -pc[1] / pc[2] ** 2]]) @ R_nc.T
            H = np.hstack([J, np.zeros((2, 3))])
            S = H @ P_pred[i] @ H.T + Rm
            nu = z - h
            Sinv = np.linalg.inv(S)
            K = P_pred[i] @ H.T @ Sinv
            x_new[i] = x_pred[i] + K @ nu
            IKH = np.eye(6) - K @ H
            P_new[i] = IKH @ P_pred[i] @ IKH.T + K @ Rm @ K.T  # Joseph form
            logw[i] += -0.5 * (nu @ Sinv @ nu) - 0.5 * math.log(np.linalg.det(2 * math.pi * S))
        if not np.isfinite(logw).any():
            self.reset()
            return None
        logw -= np.max(logw)
        self._x, self._P, self._logw, self._t = x_new, P_new, logw, t
        self._frames += 1
        self._history.append((t, F, x_pred, P_pred, x_new.copy(), P_new.copy()))
        del self._history[: -c.max_history]
        return self._mixture(t, p_cam)

    def predict(self, t_s, p_cam_ned_m=None):
        if self._x is None:
            return None
        F, Q = _transition(float(t_s) - self._t, self.config.accel_psd_m2ps3)
        x = self._x @ F.T
        P = F @ self._P @ F.T + Q
        return self._mix(float(t_s), x, P, self._logw, p_cam_ned_m)

    # ----------------------------------------------------------------- internals

    def _init(self, t, z, sigma_z2, p_cam, R_nc) -> None:
        c = self.config
        rho = (c.r_max_m / c.r_min_m) ** (1.0 / (c.n_filters - 1))
        ranges = c.r_min_m * rho ** np.arange(c.n_filters)
        d = R_nc @ np.array([z[0], z[1], 1.0])
        d /= np.linalg.norm(d)
        x = np.zeros((c.n_filters, 6))
        P = np.zeros((c.n_filters, 6, 6))
        proj_perp = np.eye(3) - np.outer(d, d)
        for i, r in enumerate(ranges):
            x[i, :3] = p_cam + r * d
            s_rad = r * (rho - 1.0) / math.sqrt(12.0)
            P[i, :3, :3] = s_rad**2 * np.outer(d, d) + r * r * sigma_z2 * proj_perp
            P[i, 3:, 3:] = c.speed_sigma_mps**2 * np.eye(3)
        self._x, self._P, self._logw, self._t = x, P, np.zeros(c.n_filters), t
        self._frames = 1
        self._history = [(t, np.eye(6), x.copy(), P.copy(), x.copy(), P.copy())]

    def _mixture(self, t, p_cam):
        return self._mix(t, self._x, self._P, self._logw, p_cam)

    def _mix(self, t, x, P, logw, p_cam):
        w = np.exp(logw - np.max(logw))
        w /= w.sum()
        mean = w @ x
        dx = x - mean
        cov = np.einsum("i,ijk->jk", w, P) + np.einsum("i,ij,ik->jk", w, dx, dx)
        cam = np.asarray(p_cam, dtype=float) if p_cam is not None else mean[:3]
        los = mean[:3] - cam
        rng = float(np.linalg.norm(los))
        ratio = float(math.sqrt(max((los / rng) @ cov[:3, :3] @ (los / rng), 0.0)) / rng) if rng > 0 else math.inf
        return RpEkfEstimate(
            t_s=t,
            p_ned_m=mean[:3],
            v_ned_mps=mean[3:],
            cov_p_ned_m2=cov[:3, :3],
            cov_v_ned_m2ps2=cov[3:, 3:],
            observable=bool(ratio < self.config.observable_sigma_ratio),
            range_m=rng,
            range_sigma_ratio=ratio,
            window_frames=self._frames,
            weights=tuple(float(a) for a in w),
        )

    def smoothed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RTS-smoothed trajectory over the stored history: ``(t_s (N,), p_ned_m (N, 3), cov_p_ned_m2 (N, 3, 3))``,
        each filter smoothed alone, then mixed with the final weights."""
        if not self._history:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3))
        h = self._history
        n = len(h)
        xs = [h[-1][4].copy()]
        Ps = [h[-1][5].copy()]
        for k in range(n - 2, -1, -1):
            _, F1, xp1, Pp1, _, _ = h[k + 1]
            _, _, _, _, xf, Pf = h[k]
            x_next, P_next = xs[0], Ps[0]
            xk, Pk = np.empty_like(xf), np.empty_like(Pf)
            for i in range(len(xf)):
                G = Pf[i] @ F1.T @ np.linalg.pinv(Pp1[i])
                xk[i] = xf[i] + G @ (x_next[i] - xp1[i])
                Pk[i] = Pf[i] + G @ (P_next[i] - Pp1[i]) @ G.T
            xs.insert(0, xk)
            Ps.insert(0, Pk)
        w = np.exp(self._logw - np.max(self._logw))
        w /= w.sum()
        t = np.array([s[0] for s in h])
        p = np.stack([w @ x[:, :3] for x in xs])
        cov = np.stack(
            [
                np.einsum("i,ijk->jk", w, P[:, :3, :3]) + np.einsum("i,ij,ik->jk", w, x[:, :3] - pm, x[:, :3] - pm)
                for x, P, pm in zip(xs, Ps, p)
            ]
        )
        return t, p, cov
