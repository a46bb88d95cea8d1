"""Benchmark of groundsim.world.flight: guidance tracking error and cost of flying with JSBSim.

``python -m bench.flight``.  Prints, for each reference path flown 10 s (defaults: JSBSim at
240 Hz, controller at 120 Hz, truth sampled at 30 Hz):

* RMS / max distance flown-vs-reference (the guidance's own statistic over every control tick,
  and over the 30 Hz truth samples), largest tilt, attitude smoothness (RMS and max body angular
  acceleration between samples);
* cost per simulated second per vehicle: CPU and wall ms with ``step_to`` at every frame and
  with the batch ``step_through``; the ratio to bare JSBSim stepping measured in the same run;
* the P3 pair (observer on the cubic path yawing toward the circling target, plus the target):
  both vehicles' total cost for the 10 s scenario, frame by frame and with ``fly_pair``;
* the set-up cost of one vehicle.

Numbers only: nothing here asserts on time.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from bench import parse_flags, run_benchmark
from groundsim.world.flight import FlownVehicle, fly, fly_pair
from groundsim.world.motion import Circular, Cubic
from onboard.core.frames import GeodeticOrigin, euler_from_quat

ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)  # the reference scenarios' origin
DURATION_S = 10.0
FRAME_RATE_HZ = 30.0

CASES = {
    "(a) cubic accel 0.49 m/s^2 from 4 m/s": Cubic((0.0, 0.0, -60.0), (4.0, 0.0, 0.0), (0.49, 0.0, 0.0)),
    "(b) circle r 40 m at 8 m/s": Circular((0.0, 0.0, -60.0), 40.0, 0.0, 8.0 / 40.0),
    "(c) circle r 40 m at 5 m/s": Circular((0.0, 0.0, -60.0), 40.0, 0.0, 5.0 / 40.0),
    "(d) P3 observer cubic": Cubic((0.0, 0.0, -60.0), (1.0, 8.0, 0.0), (-0.3, -2.0, -0.2), (0.06, 0.4, 0.04)),
}
# P3's target (config/scenarios/P3.yaml): circle r 40 m at 5 m/s about (150, 20, -90), azimuth -90 deg, -0.125 rad/s
P3_TARGET = Circular((150.0, 20.0, -90.0), 40.0, -math.pi / 2, -0.125)
CONFIGS = {
    "default (JSBSim 240 Hz, control 120 Hz)": {},
    "light   (JSBSim 120 Hz, control 60 Hz)": {"dt_s": 1.0 / 120.0, "control_rate_hz": 60.0},
}


def _times() -> np.ndarray:
    return np.arange(int(DURATION_S * FRAME_RATE_HZ) + 1) / FRAME_RATE_HZ


def _timed(fn):
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c0, time.perf_counter() - w0


def _per_frame(reference, **kw):
    v = FlownVehicle(reference, ORIGIN, **kw)
    return [v.step_to(float(t)) for t in _times()]


def _bare_jsbsim_s(dt_s: float) -> float:
    """CPU seconds of JSBSim alone stepping the same airframe for DURATION_S (the baseline)."""
    v = FlownVehicle(Cubic((0.0, 0.0, -60.0)), ORIGIN)
    fdm = v._fdm
    fdm.set_dt(dt_s)
    n = int(round(DURATION_S / dt_s))
    c0 = time.process_time()
    for _ in range(n):
        fdm.run()
    return time.process_time() - c0


def _smoothness(tr) -> tuple[float, float]:
    dw = np.diff(tr.omega_frd_radps, axis=0) * FRAME_RATE_HZ
    mag = np.linalg.norm(dw, axis=1)
    return float(np.sqrt(np.mean(mag**2))), float(mag.max())


def main() -> None:
    print(
        f"groundsim.world.flight benchmark: {DURATION_S:.0f} s per path, truth at {FRAME_RATE_HZ:.0f} Hz, origin {ORIGIN}"
    )
    for cname, kw in CONFIGS.items():
        dt = kw.get("dt_s", 1.0 / 240.0)
        bare = _bare_jsbsim_s(dt)
        print(f"\n{cname}; bare JSBSim stepping: {1e3 * bare / DURATION_S:.1f} ms CPU per simulated s")
        print(
            f"  {'path':40s} {'rms_m':>7s} {'max_m':>7s} {'smp_rms':>7s} {'tilt':>5s} {'wdot_rms':>8s} {'wdot_max':>8s}"
            f" | ms/sim-s: {'frame cpu':>9s} {'wall':>6s} {'batch cpu':>9s} {'wall':>6s} {'x bare':>6s}"
        )
        for name, ref in CASES.items():
            tr, c_b, w_b = _timed(lambda ref=ref, kw=kw: fly(ref, DURATION_S, FRAME_RATE_HZ, origin=ORIGIN, **kw))
            _, c_f, w_f = _timed(lambda ref=ref, kw=kw: _per_frame(ref, **kw))
            err = np.linalg.norm(tr.p_ned_m - ref.state(tr.t_s).p_ned_m, axis=1)
            roll, pitch, _ = euler_from_quat(tr.q_ned_from_body)
            tilt = math.degrees(float(np.max(np.arccos(np.cos(roll) * np.cos(pitch)))))
            s_rms, s_max = _smoothness(tr)
            ms = 1e3 / DURATION_S
            print(
                f"  {name:40s} {tr.tracking.rms_m:7.3f} {tr.tracking.max_m:7.3f} {np.sqrt(np.mean(err**2)):7.3f} {tilt:5.1f}"
                f" {s_rms:8.4f} {s_max:8.4f} |           {c_f * ms:9.1f} {w_f * ms:6.1f} {c_b * ms:9.1f} {w_b * ms:6.1f}"
                f" {c_b / bare:6.1f}"
            )

        # the P3 pair: two vehicles, the observer yawing toward the target every frame
        def pair(kw=kw):
            obs = FlownVehicle(CASES["(d) P3 observer cubic"], ORIGIN, yaw_mode="target", name="observer", **kw)
            tgt = FlownVehicle(P3_TARGET, ORIGIN, name="target", **kw)
            yaw_err = []
            for t in _times():
                s_t = tgt.step_to(float(t))
                s_o = obs.step_to(float(t), s_t.p_ned_m, s_t.v_ned_mps)
                _, _, yaw = euler_from_quat(s_o.q_ned_from_body)
                d = s_t.p_ned_m - s_o.p_ned_m
                yaw_err.append(abs(math.remainder(float(yaw) - math.atan2(d[1], d[0]), 2 * math.pi)))
            return obs, tgt, yaw_err

        (obs, tgt, yaw_err), c_p, w_p = _timed(pair)
        print(
            f"  P3 pair, step_to per frame: observer rms {obs.tracking_error_m.rms_m:.3f} m (yaw to target max err "
            f"{math.degrees(max(yaw_err)):.2f} deg), target rms {tgt.tracking_error_m.rms_m:.3f} m; "
            f"both vehicles, {DURATION_S:.0f} s incl. set-up: {c_p:.3f} s CPU, {w_p:.3f} s wall"
        )
        (o_tr, t_tr), c_p, w_p = _timed(
            lambda kw=kw: fly_pair(CASES["(d) P3 observer cubic"], P3_TARGET, DURATION_S, FRAME_RATE_HZ, ORIGIN, **kw)
        )
        print(
            f"  P3 pair, fly_pair (batch): observer rms {o_tr.tracking.rms_m:.3f} m, target rms {t_tr.tracking.rms_m:.3f} m; "
            f"both vehicles, {DURATION_S:.0f} s incl. set-up: {c_p:.3f} s CPU, {w_p:.3f} s wall"
        )
        _, c_i, w_i = _timed(lambda kw=kw: FlownVehicle(P3_TARGET, ORIGIN, **kw))
        print(
            f"  set-up of one vehicle (load model, trim, spin-up, calibrate): {1e3 * c_i:.1f} ms CPU, {1e3 * w_i:.1f} ms wall"
        )


if __name__ == "__main__":
    parse_flags("python -m bench.flight", __doc__.splitlines()[0])
    sys.exit(run_benchmark("flight", main))
