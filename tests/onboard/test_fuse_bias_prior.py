"""The fusion takes each vehicle's attitude-bias prior from its tracks (``los_sigma_bias_deg``), unless
``--vehicle-noise NAME:attitude_bias_deg=..`` names the vehicle; a track without the key (an older daemon) takes
``--attitude-bias-deg`` as before.  Two synthetic vehicles 300 m apart on a target at 500-650 m, 0.5 s at 30 Hz, fed
to the fusion's step logic as :func:`onboard.app.fuse.main` builds it from its options."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
from scipy.stats import chi2

from groundsim.evaluation.fleet_synth import SynthTarget, SynthVehicle, measure, track_payload
from onboard.app.fuse import Fusion, build_parser
from onboard.app.fuse_noise import bias_named, noise_models
from onboard.core.counters import RejectCounter
from onboard.core.frames import GeodeticOrigin
from onboard.estimation.fleet import FleetConfig
from onboard.estimation.fleet_tracker import FleetTracker
from onboard.io.fleet_wire import ClockConsistency, CommonClock, fleet_track_key

ORIGIN = GeodeticOrigin(32.0, 118.8, 20.0)
T0_UNIX_S = 1_800_000_000.0
WHITE_RAD = 0.3e-3  # the rays' white bearing noise
FRAMES = 15  # 0.5 s at 30 Hz: the scatter test (10 rays a vehicle) acts on the later solves only
TRIALS = 100


def fusion_of(argv: list[str]) -> Fusion:
    """The fusion ``python -m onboard.fuse`` builds from ``argv`` (its noise and its --vehicle-noise names)."""
    args = build_parser().parse_args(argv)
    counter = RejectCounter(log_interval_s=3600.0)
    return Fusion(
        FleetTracker(FleetConfig(), noise_models(args), counter),
        CommonClock(),
        counter=counter,
        bias_named=bias_named(args.vehicle_noise),
        clock_check=ClockConsistency(judging_max_s=0.0),  # no wait for a clock verdict: the clocks are not the subject
    )


def fly(fusion: Fusion, rng, bias_deg: float, stated_deg: float | None, first_frame: int = 0) -> list[float]:
    """One geometry: both vehicles' attitudes off by a draw of ``bias_deg`` per axis, their sigmas holding it, their
    tracks stating ``stated_deg`` (None: not at all), from frame ``first_frame`` on; the NEES of each two-vehicle
    fleet track."""
    tgt = SynthTarget(tuple(rng.uniform([500, -150, -150], [650, 150, -100])), tuple(rng.uniform(-8, 8, 3)))
    vehicles = [
        SynthVehicle(
            n, (0.0, y, -100.0), (10, 0, 0), attitude_error_rad=tuple(rng.normal(0, math.radians(bias_deg), 3))
        )
        for n, y in (("uav1", -150.0), ("uav2", 150.0))
    ]
    stated_rad = None if stated_deg is None else math.radians(stated_deg)
    nees = []
    for k in range(first_frame, first_frame + FRAMES):
        t = k / 30
        for v in vehicles:
            los = measure(v, tgt, t, rng, WHITE_RAD, math.radians(bias_deg))
            obj = track_payload(
                v.name,
                k,
                int(1e6 + t * 1e6),
                los,
                ORIGIN,
                time_unix_us=int(round((T0_UNIX_S + t) * 1e6)),
                bias_sigma_rad=stated_rad,
            )
            fusion.receive(f"irtrack/{v.name}/track", json.dumps(obj).encode(), T0_UNIX_S + t + 0.005)
        for key, msg in fusion.flush():
            if key == fleet_track_key() and len(msg["vehicles"]) == 2:
                e = np.asarray(msg["ned_m"]) - tgt.p_ned_m(msg["time_unix_us"] / 1e6 - T0_UNIX_S)
                nees.append(float(e @ np.linalg.solve(np.asarray(msg["cov_ned_m2"]), e)))
    return nees


def test_vehicles_whose_tracks_state_their_bias_are_fused_honestly_without_any_vehicle_noise():
    """Both vehicles' attitudes off by 0.3 deg (1 sigma), their tracks stating 0.3 deg, the fusion's
    --attitude-bias-deg left at 0.1: each vehicle's prior is its tracks' 0.3 deg, the fused points honest (mean NEES
    2.83 over 100 geometries, as with a per-vehicle model) and nobody named beyond its prior.  Before, the excess was
    taken for white noise and averaged away over the rays until the scatter test caught it (from 10 rays a vehicle):
    mean NEES 4.98, both vehicles named in all 100."""
    rng = np.random.default_rng(7)
    per_trial = []
    for _ in range(TRIALS):
        fusion = fusion_of([])
        nees = fly(fusion, rng, 0.3, 0.3)
        assert len(nees) >= FRAMES - 1
        per_trial.append(np.mean(nees))
        st = fusion.status(T0_UNIX_S + FRAMES / 30)
        assert st["attitude_bias_prior"] == {
            v: {"deg": 0.3, "source": "track", "stated_deg": pytest.approx(0.3)} for v in ("uav1", "uav2")
        }
        assert st["attitude_bias_deg"] == {} and "attitude_bias_above_prior" not in st["events"]
    # a trial's points share its draw: their mean varies no more than one NEES, chi-square 3 dof (conservative)
    lo, hi = chi2.ppf([0.0005, 0.9995], 3 * TRIALS) / TRIALS
    assert lo <= np.mean(per_trial) <= hi, np.mean(per_trial)


def _records(caplog, level: int, words: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.levelno == level and words in r.getMessage()]


def test_an_explicit_vehicle_noise_wins_over_the_tracks_and_their_disagreement_is_warned_once(caplog):
    """uav2's tracks state 0.3 deg, ``--vehicle-noise uav2:attitude_bias_deg=0.1`` says 0.1: the option's is used
    (its rays then show the bias beyond it: named by the scatter test, as before), and the disagreement is warned once,
    naming both; uav1 takes its tracks'.  Each vehicle's prior is said once at INFO, not per track."""
    fusion = fusion_of(["--vehicle-noise", "uav2:attitude_bias_deg=0.1"])
    with caplog.at_level(logging.INFO, logger="onboard"):
        fly(fusion, np.random.default_rng(3), 0.3, 0.3)
    st = fusion.status(T0_UNIX_S + FRAMES / 30)
    assert st["attitude_bias_prior"] == {
        "uav1": {"deg": 0.3, "source": "track", "stated_deg": pytest.approx(0.3)},
        "uav2": {"deg": 0.1, "source": "vehicle_noise", "stated_deg": pytest.approx(0.3)},
    }
    assert fusion.tracker.noise["uav2"].attitude_bias_sigma_rad == pytest.approx(math.radians(0.1))
    assert fusion.tracker.noise["uav1"].attitude_bias_sigma_rad == pytest.approx(math.radians(0.3))
    assert list(st["attitude_bias_deg"]) == ["uav2"]
    (warned,) = _records(caplog, logging.WARNING, "attitude-bias sigma of")
    text = warned.getMessage()
    assert "uav2" in text and "0.3 deg" in text and "--vehicle-noise uav2:attitude_bias_deg=0.1" in text
    assert len(_records(caplog, logging.INFO, "uav1: attitude-bias prior 0.3 deg, stated by its tracks")) == 1
    assert len(_records(caplog, logging.INFO, "uav2: attitude-bias prior 0.1 deg, from --vehicle-noise")) == 1


def test_an_explicit_vehicle_noise_within_the_factor_of_the_tracks_is_not_warned(caplog):
    fusion = fusion_of(["--vehicle-noise", "uav2:attitude_bias_deg=0.25"])
    with caplog.at_level(logging.INFO, logger="onboard"):
        fly(fusion, np.random.default_rng(3), 0.3, 0.3)
    assert fusion.status(T0_UNIX_S + 1.0)["attitude_bias_prior"]["uav2"]["source"] == "vehicle_noise"
    assert _records(caplog, logging.WARNING, "attitude-bias sigma of") == []


def test_a_track_without_the_key_takes_the_attitude_bias_option_as_before_and_a_later_one_with_it_its_own(caplog):
    """An older daemon's tracks state no bias: the prior is --attitude-bias-deg's 0.1 deg, and the 0.3 deg its rays
    have beyond it is found by the scatter test as before (both named).  The same vehicles restarted on a daemon that
    states 0.3 deg: their tracks' prior from then on."""
    fusion = fusion_of([])
    configured = fusion.tracker.configured_noise
    rng = np.random.default_rng(5)
    with caplog.at_level(logging.INFO, logger="onboard"):
        fly(fusion, rng, 0.3, None)
    st = fusion.status(T0_UNIX_S + FRAMES / 30)
    assert st["attitude_bias_prior"] == {
        v: {"deg": 0.1, "source": "attitude_bias_deg", "stated_deg": None} for v in ("uav1", "uav2")
    }
    assert fusion.tracker.noise is configured  # nobody's own model: exactly the options' noise, as before
    assert sorted(st["attitude_bias_deg"]) == ["uav1", "uav2"]
    assert len(_records(caplog, logging.INFO, "from --attitude-bias-deg (its tracks state none")) == 2

    later = fusion_of([])
    fly(later, rng, 0.3, None)
    fly(later, rng, 0.3, 0.3, first_frame=FRAMES)  # the daemons restarted with the key: their newer tracks
    prior = later.status(T0_UNIX_S + 2 * FRAMES / 30)["attitude_bias_prior"]
    assert {v: (p["deg"], p["source"]) for v, p in prior.items()} == {"uav1": (0.3, "track"), "uav2": (0.3, "track")}
