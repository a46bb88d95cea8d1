"""A coasting vehicle's lines of sight are not measurements: while a daemon's tracker coasts (its blob lost) it
publishes a line of sight to the centre it predicts, with ``measurement_valid`` false.  Two synthetic vehicles on a
target that accelerates sideways while one of them coasts, driven through :class:`~onboard.app.fuse.Fusion`."""

from __future__ import annotations

import json
import math

import numpy as np

from groundsim.evaluation.fleet_synth import SynthTarget, SynthVehicle, measure, track_payload
from onboard.app.fuse import Fusion, build_parser
from onboard.app.fuse_noise import noise_models
from onboard.core.counters import RejectCounter
from onboard.core.frames import GeodeticOrigin
from onboard.estimation.fleet import FleetConfig
from onboard.estimation.fleet_tracker import FleetTracker
from onboard.io.fleet_wire import CommonClock, fleet_track_key

ORIGIN = GeodeticOrigin(32.0, 118.8, 20.0)
T0_UNIX_S = 1_800_000_000.0
FRAME_S = 1 / 30
WHITE_RAD = 0.3e-3
BIAS_PRIOR_RAD = math.radians(0.1)  # the fusion's default attitude-bias prior, and each vehicle's drawn bias
NEES_MAX = 16.3  # chi-square(3) at 0.999
COAST_S = (4.0, 5.5)  # uav2's tracker coasts: 45 frames, the objects chain's coast_frames
ACCEL_NED_MPS2 = np.array([0.0, 6.0, 0.0])  # from the coast's start, across the lines of sight
CRUISE = SynthTarget((592.0, -20.0, -120.0), (0.0, 20.0, 0.0))  # what a coasting tracker predicts


class Manoeuvre(SynthTarget):
    """``CRUISE`` until ``COAST_S[0]``, then accelerating at ``ACCEL_NED_MPS2``."""

    def p_ned_m(self, t_s: float) -> np.ndarray:
        dt = max(t_s - COAST_S[0], 0.0)
        return super().p_ned_m(t_s) + 0.5 * ACCEL_NED_MPS2 * dt * dt


TARGET = Manoeuvre(CRUISE.p0_ned_m, CRUISE.v_ned_mps)


def test_a_coasting_vehicles_predicted_lines_of_sight_are_refused_not_fused():
    """uav2 coasts 1.5 s while the target pulls 6 m/s^2 sideways: its predicted rays were fused as measurements and
    held the fused point to the prediction, every one of 45 tracks called observable, NEES up to 55."""
    rng = np.random.default_rng(7)
    vehicles = [
        SynthVehicle(v.name, v.p0_ned_m, v.v_ned_mps, (0.0, 0.0, 0.0), rng.normal(0.0, BIAS_PRIOR_RAD, 3))
        for v in (
            SynthVehicle("uav1", (0.0, -145.0, -100.0), (3.0, 0.0, 0.0)),
            SynthVehicle("uav2", (0.0, 145.0, -100.0), (3.0, 0.0, 0.0)),
        )
    ]
    fusion = Fusion(
        FleetTracker(FleetConfig(), noise_models(build_parser().parse_args([])), RejectCounter()), CommonClock()
    )
    out = []
    coasting_frames = 0
    for k in range(round(7.0 / FRAME_S)):
        t = k * FRAME_S
        for v in vehicles:
            coasting = v.name == "uav2" and COAST_S[0] <= t < COAST_S[1]
            los = measure(v, CRUISE if coasting else TARGET, t, rng, WHITE_RAD, BIAS_PRIOR_RAD)
            obj = track_payload(
                v.name, k, int(round((1.0 + t) * 1e6)), los, ORIGIN, time_unix_us=int(round((T0_UNIX_S + t) * 1e6))
            )
            if coasting:
                obj.update(state="coasting", measurement_valid=False)
                coasting_frames += 1
            fusion.receive(f"irtrack/{v.name}/track", json.dumps(obj).encode(), T0_UNIX_S + t + 0.005)
        out += [p for key, p in fusion.flush() if key == fleet_track_key()]
    assert fusion.counter["ray_not_measured"] == coasting_frames == 45
    st = fusion.status(T0_UNIX_S + 7.0)
    assert st["rejected"]["ray_not_measured"] == 45 and st["name_clash"] == [] and st["clock_inconsistent"] == []
    during = [p for p in out if COAST_S[0] <= p["time_unix_us"] / 1e6 - T0_UNIX_S < COAST_S[1] and p["observable"]]
    for p in during:
        e = np.asarray(p["ned_m"]) - TARGET.p_ned_m(p["time_unix_us"] / 1e6 - T0_UNIX_S)
        assert float(e @ np.linalg.solve(np.asarray(p["cov_ned_m2"]), e)) < NEES_MAX
    # and uav2 is fused again once it measures
    last = out[-1]
    assert sorted(c["vehicle"] for c in last["vehicles"]) == ["uav1", "uav2"] and last["observable"]
