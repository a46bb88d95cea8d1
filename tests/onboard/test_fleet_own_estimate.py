"""The fleet's association checked against each vehicle's own observable estimate of its object: what the ray
gates cannot tell apart (two vehicles on two objects whose rays cross; a vehicle whose tracker moved to another
object on the same line of sight)."""

from __future__ import annotations

import math

import numpy as np
import pymap3d
import pytest

from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.track import LineOfSight
from onboard.estimation.fleet import (
    OWN_ESTIMATE_GATE_CHI2,
    ClosestApproach,
    FleetConfig,
    Ray,
    closest_approach,
    own_estimate_chi2,
    pair_crossing,
)
from onboard.estimation.fleet_tracker import FleetTracker
from onboard.estimation.map_estimator import NoiseModel
from onboard.io.fleet_wire import TimedTrack, ray_from_track
from tests.fakes import positioned_track

EXACT = NoiseModel()
SIGMA_RAD = 0.5e-3
# all at one altitude: the rays of uav1 on A and of uav2 on B cross at (400, 0, -100), a point neither sees
UAV1, UAV2 = np.array([0.0, -150.0, -100.0]), np.array([0.0, 150.0, -100.0])
A, B = np.array([800.0, 150.0, -100.0]), np.array([800.0, -150.0, -100.0])
GHOST = np.array([400.0, 0.0, -100.0])
ATOL_M = 1e-6  # 1 um: two WGS84 implementations agree to nanometres a kilometre out
OWN_COV = np.diag([25.0, 25.0, 25.0])  # 5 m: a manoeuvring vehicle that ranged its object itself


def _ray(vehicle, cam, p, t_s, object_id=1, rng=None, own=None):
    d = p - cam
    u = d / np.linalg.norm(d)
    if rng is not None:  # bearing noise across the ray
        e1 = np.cross(u, [0.0, 0.0, 1.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        u = u + SIGMA_RAD * (rng.standard_normal() * e1 + rng.standard_normal() * e2)
        u /= np.linalg.norm(u)
    kw = {} if own is None else {"own_p_ned_m": own, "own_cov_ned_m2": OWN_COV}
    return Ray(vehicle, object_id, t_s, cam, u, SIGMA_RAD, SIGMA_RAD, **kw)


def _fly(tracker, uav1_sees, uav2_sees, own1=None, seconds=1.0, t0=0.0, rng_seed=1, id1=1):
    rng = np.random.default_rng(rng_seed)
    for t in np.arange(t0, t0 + seconds, 1 / 30):
        tracker.add(_ray("uav1", UAV1, uav1_sees, t, id1, rng, own1))
        tracker.add(_ray("uav2", UAV2, uav2_sees, t, 2, rng))
        for tid in tracker.targets:
            if tracker.due(tid):
                tracker.solve(tid)


def test_two_vehicles_on_two_objects_make_a_ghost_unless_one_has_ranged_its_own():
    # the limit: bearings alone put the two at the point where their rays cross, observable
    blind = FleetTracker(FleetConfig(), EXACT)
    _fly(blind, A, B)
    (tid,) = blind.targets
    est = blind.solve(tid)
    assert np.linalg.norm(est.p_ned_m - GHOST) < 5.0 and est.observable
    # uav1 has ranged A itself: the crossing 420 m off what it measured is no position of its object
    counter = RejectCounter()
    told = FleetTracker(FleetConfig(), EXACT, counter)
    _fly(told, A, B, own1=A + 3.0)
    assert told.targets == ()
    assert counter["own_estimate_disagrees"] >= 30  # every frame's pairing, kept out


def test_a_vehicle_that_agrees_with_the_fleet_is_fused_as_before():
    counter = RejectCounter()
    tracker = FleetTracker(FleetConfig(), EXACT, counter)
    _fly(tracker, A, A, own1=A + np.array([4.0, -3.0, 2.0]))
    (tid,) = tracker.targets
    est = tracker.solve(tid)
    assert est.observable and np.linalg.norm(est.p_ned_m - A) < 3.0
    assert counter["own_estimate_disagrees"] == 0 and counter["object_left"] == 0


def test_an_object_whose_vehicle_ranged_another_thing_on_the_same_line_leaves_its_target():
    counter = RejectCounter()
    tracker = FleetTracker(FleetConfig(), EXACT, counter)
    _fly(tracker, A, A, own1=A)
    (tid,) = tracker.targets
    assert ("uav1", 1) in tracker.members(tid)
    # uav1's tracker moves, under the same id, to a bird on its line of sight to A, 420 m nearer: its ray is
    # the same, which the ray gate passes; its own range is not
    bird = UAV1 + 0.5 * (A - UAV1)
    _fly(tracker, bird, A, own1=bird, seconds=0.2, t0=1.0)
    assert ("uav1", 1) not in tracker.members(tid)
    assert counter["object_left"] >= 1


def test_the_own_estimate_test_is_chi_square_and_the_crossing_is_weighted():
    p = A + np.array([3.0, 0.0, 0.0])
    ray = _ray("uav1", UAV1, A, 0.0, own=p)
    assert own_estimate_chi2(ray, A, np.zeros((3, 3))) == pytest.approx(9.0 / 25.0)
    assert own_estimate_chi2(ray, A, np.eye(3) * 11.0) == pytest.approx(9.0 / 36.0)
    assert own_estimate_chi2(_ray("uav1", UAV1, A, 0.0), A, np.eye(3)) is None
    far = own_estimate_chi2(ray, A + np.array([0.0, 0.0, 30.0]), np.zeros((3, 3)))
    assert far > OWN_ESTIMATE_GATE_CHI2
    # the crossing's covariance: across each ray its range times the bearing sigma; near-parallel rays leave it huge
    a, b = _ray("uav1", UAV1, A, 0.0), _ray("uav2", UAV2, A, 0.0)
    ca = closest_approach(a, b, EXACT, EXACT)
    x, P = pair_crossing(a, b, ca, EXACT, EXACT)
    np.testing.assert_allclose(x, A, atol=1e-6)  # noiseless rays cross at the object
    vertical = 1.0 / math.hypot(1.0 / (ca.range_a_m * SIGMA_RAD), 1.0 / (ca.range_b_m * SIGMA_RAD))
    assert math.sqrt(P[2, 2]) == pytest.approx(vertical, rel=1e-6)  # level rays: both measure the vertical
    along = (A - UAV1) / np.linalg.norm(A - UAV1)
    sin_cross = float(np.linalg.norm(np.cross(a.los_ned, b.los_ned)))  # 21 deg between the rays
    cos_cross = float(a.los_ned @ b.los_ned)
    # in the level plane each ray informs only across itself, w n n^T with w = 1 / (r s)^2; inverting the 2 x 2
    # sum in ray a's (along, across) basis gives along ray a ((r_b s)^2 + cos^2 (r_a s)^2) / sin^2: ray b's
    # cross-range error over the sine, plus ray a's own cross-range error carried along it by ray b's slant
    sigma_a_m, sigma_b_m = ca.range_a_m * SIGMA_RAD, ca.range_b_m * SIGMA_RAD
    along_sigma_m = math.sqrt(sigma_b_m**2 + (cos_cross * sigma_a_m) ** 2) / sin_cross
    assert math.sqrt(along @ P @ along) == pytest.approx(along_sigma_m, rel=1e-6)
    # rays parallel to within nothing: along them neither measures; the point there is the closest points' midpoint
    # and the variance is left huge, so an own estimate anywhere along them passes
    c, d = (
        _ray("uav1", UAV1, A, 0.0),
        _ray("uav2", UAV1 + np.array([0.0, 10.0, 0.0]), A + np.array([0.0, 10.0, 0.0]), 0.0),
    )
    mid = UAV1 + np.array([400.0, 5.0, 0.0])
    parallel = ClosestApproach(10.0, 1.0, 400.0, 400.0, mid, 100.0)
    x2, P2 = pair_crossing(c, d, parallel, EXACT, EXACT)
    along2 = c.los_ned
    assert along2 @ P2 @ along2 > 1e11 and float(along2 @ (x2 - mid)) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize(
    "own, words",
    [
        (dict(own_p_ned_m=(1.0, 2.0, 3.0)), "go together"),
        (dict(own_cov_ned_m2=np.eye(3)), "go together"),
        (dict(own_p_ned_m=(1.0, 2.0, math.nan), own_cov_ned_m2=np.eye(3)), "own_p_ned_m"),
        (dict(own_p_ned_m=(1.0, 2.0, 3.0), own_cov_ned_m2=np.eye(2)), "3 x 3"),
        (dict(own_p_ned_m=(1.0, 2.0, 3.0), own_cov_ned_m2=-np.eye(3)), "negative variance"),
        (dict(own_p_ned_m=(1.0, 2.0, 3.0), own_cov_ned_m2="x"), "own_cov_ned_m2"),
    ],
)
def test_a_bad_own_estimate_names_its_field(own, words):
    with pytest.raises(InputError, match=words):
        Ray("uav1", 1, 0.0, (0, 0, 0), (1, 0, 0), 1e-3, 1e-3, **own)


def test_a_track_brings_its_own_estimate_into_the_fleet_frame_only_where_observable():
    los = LineOfSight((0.6, 0.0, -0.8), 0.0, 53.13, 0.1, 0.1, (20.0, 0.0, 0.0))
    track = positioned_track(los=los)
    ray = ray_from_track(TimedTrack(track, 1.0, "vehicle"), track.origin)
    np.testing.assert_allclose(ray.own_p_ned_m, track.p_ned_m, atol=1e-9)
    np.testing.assert_allclose(ray.own_cov_ned_m2, track.cov_p_ned_m2, atol=1e-9)
    # a fleet frame about 1 km east: the same points, placed by pymap3d (an independent WGS84 implementation) from
    # the track's frame through geodetic into the fleet's; the frames' axes differ by the meridians' convergence
    # (about 5 mm over the 130 m between camera and object), which a translation alone would miss
    o = track.origin
    east = type(o)(o.lat_deg, o.lon_deg + 1000.0 / 94_500.0, o.alt_m)
    moved = ray_from_track(TimedTrack(track, 1.0, "vehicle"), east)

    def in_east(p_ned_m):
        lat, lon, alt = pymap3d.ned2geodetic(*p_ned_m, o.lat_deg, o.lon_deg, o.alt_m)
        return np.array(pymap3d.geodetic2ned(lat, lon, alt, east.lat_deg, east.lon_deg, east.alt_m))

    np.testing.assert_allclose(moved.own_p_ned_m, in_east(track.p_ned_m), rtol=0, atol=ATOL_M)
    np.testing.assert_allclose(moved.p_cam_ned_m, in_east(los.p_cam_ned_m), rtol=0, atol=ATOL_M)
    unobservable = positioned_track(los=los, observable=False)
    assert ray_from_track(TimedTrack(unobservable, 1.0, "vehicle"), track.origin).own_p_ned_m is None


@pytest.mark.parametrize("far_m", [200.0, 3000.0])
def test_an_honest_own_estimate_passes_the_pairing_test_at_its_rate_whatever_the_ranges(far_m):
    """The crossing is the weighted one: halfway between the closest points carries half the far ray's error, which
    the pairing covariance does not hold, and honest pairs at unequal ranges would be refused far above the rate."""
    rng = np.random.default_rng(7)
    X = np.array([0.0, 0.0, -100.0])
    near_cam, far_cam = np.array([-200.0, 0.0, -100.0]), np.array([0.0, -far_m, -100.0])
    u = (X - near_cam) / np.linalg.norm(X - near_cam)
    across = np.eye(3) - np.outer(u, u)
    own_cov = np.outer(u, u) * 100.0 + across * (200.0 * SIGMA_RAD) ** 2  # 10 m along, the bearing across
    chi2s = []
    for _ in range(400):
        a = _ray("uav1", near_cam, X, 0.0, rng=rng)
        a = Ray(
            "uav1",
            1,
            0.0,
            a.p_cam_ned_m,
            a.los_ned,
            SIGMA_RAD,
            SIGMA_RAD,
            own_p_ned_m=rng.multivariate_normal(X, own_cov),
            own_cov_ned_m2=own_cov,
        )
        b = _ray("uav2", far_cam, X, 0.0, rng=rng)
        ca = closest_approach(a, b, EXACT, EXACT)
        chi2s.append(own_estimate_chi2(a, *pair_crossing(a, b, ca, EXACT, EXACT)))
    assert 2.5 < np.mean(chi2s) < 3.5 and sum(c > OWN_ESTIMATE_GATE_CHI2 for c in chi2s) <= 1
