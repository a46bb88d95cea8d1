r"""Fleet triangulation: one target's 3-D track from several vehicles' lines of sight at once.

Pure core: no zenoh, no clocks, no wire format.  The adapter (:mod:`onboard.io.fleet_wire`) turns each
vehicle's ``irtrack.track/2`` into a :class:`Ray` in ONE local NED frame (the fleet's origin) on ONE clock
(seconds, UTC in practice); :class:`~onboard.estimation.fleet_tracker.FleetTracker` associates the rays of several vehicles with targets
and :func:`triangulate` estimates each target from all its rays together.

Measurement model
-----------------
Ray i (vehicle ``k(i)``, capture time ``t_i``) has origin ``c_i`` (the camera, NED m), unit direction
``u_i`` (NED) and the 1-sigma of its azimuth and elevation as the daemon publishes them
(:func:`onboard.core.track.line_of_sight_ned`: pixel noise plus the attitude's white noise and bias).
Across the ray, ``B_i = [e_az; e_el]`` (2 x 3, orthonormal, both perpendicular to ``u_i``:
``e_az = (-sin az, cos az, 0)``, ``e_el = du/d el``).  With the target at ``p(t)``, the camera-position
error ``beta_k`` (measured minus true) and the attitude error ``phi_k`` (NED rotation vector, the psi-angle
model of :mod:`onboard.core.frames`), the true ray passes through the target:

    B_i (p(t_i) - c_i + beta_k) - r_i B_i [u_i]x phi_k  =  n_i,   n_i ~ N(0, S_i)

(``u_meas = Exp(phi) u_true`` to first order gives ``B d = -r B (phi x u)``), with ``r_i = u_i . (p(t_i) -
c_i)`` the range and the white noise per axis

    S_i = diag((r_i cos(el_i) s_az,i)^2, (r_i s_el,i)^2) + (s_cw^2 + q |t_i - t_0|^3 / 3) I_2.

``s_az, s_el`` are the published sigmas with the attitude bias ``s_b`` taken out (it is the nuisance
``phi_k``, common to all of a vehicle's rays, not white): ``s^2 - s_b^2``, at least a tenth of ``s^2``.
``s_cw`` is the camera position's white noise.  The motion model is constant velocity about the newest
ray's time ``t_0``: ``p(t) = p_0 + v (t - t_0)``; white acceleration of PSD ``q`` (m^2/s^3) makes the
prediction err by ``q |dt|^3 / 3`` per axis, added to each ray's noise (an approximation: it neglects that
this error is correlated between rays; exact for a constant-velocity target).

MAP / weighted least squares
----------------------------
Unknowns ``x = (p_0, v, beta_1, phi_1, ..., beta_K, phi_K)`` (a nuisance only where its prior sigma in the
vehicle's :class:`~onboard.estimation.map_estimator.NoiseModel` is non-zero:
``camera_position_offset_sigma_m``, ``attitude_bias_sigma_rad``).  Dividing the measurement equation by the
distance along the ray ``rho_i = u_i . d_i`` (``d_i = p_0 + v dt_i - c_i + beta_k``) makes it angular, as the
single-vehicle estimator's residuals are; the cost is

    J(x) = sum_i |S_i^-1/2 (B_i d_i / rho_i - B_i [u_i]x phi_k)|^2
           + |p_0 - p_prior|^2 / s_p^2 + |v - v_prior|^2 / s_v^2 + sum_k (|beta_k|^2 / s_o^2 + |phi_k|^2 / s_b^2)

with ``S_i = diag(s_az^2 cos^2 el, s_el^2) + (s_cw^2 + q |dt_i|^3 / 3) / rho_i^2 I`` and weak priors ``s_p``
(``MapConfig.position_prior_sigma_m``, 1 km, about a previous estimate or the pair's closest approach) and
``s_v`` (``MapConfig.velocity_prior_sigma_mps``).  Angular rather than metric residuals: a metric cost
weighted by the last iterate's range slides towards the camera, where every ray's metric miss is small
(the collapse of bearing-only estimation); the angular one is flat along a single camera's scaled
trajectories and the prior holds it there.  Gauss-Newton from the prior's centre with step halving while
the cost grows (Bjorck, Numerical Methods for Least Squares Problems, 1996, ch. 9), ``rho`` clamped at
``min_range_m``.  The covariance is
the inverse Gauss-Newton normal matrix ``H^-1`` at the solution (Laplace); ``J(x_hat) ~ chi2(d)`` when
the model holds (the nuisances' prior rows count as observations), which the verdict tests, with ``d = 2N - 6 +
sum_j w_j (H^-1)_jj`` over the six weak-prior rows ``w_j`` of ``(p, v)``: the residual degrees of freedom of a
regularised fit (the trace of the hat matrix's complement; Hastie, Tibshirani and Friedman, The Elements of
Statistical Learning, 2nd ed., sec. 7.6).  A direction only the prior holds gives its row back: two rays taken at
one time fix the position with one row to spare (their gap) and leave the velocity to its prior, ``d = 1``
(where ``2N - 6`` says -2); three rays at two or three times keep about one too, the velocity along the lines of
sight being the prior's.

Time: a ray's capture time is known to ``time_sigma_s`` (the track's ``time_unix_sigma_us``); over it the target
moves by ``v s_t``, a miss across the ray of ``B v s_t``, added to the ray's white noise with the target's last
estimated velocity (``max_speed_mps`` in every direction before there is one), to the pairing gate with
``max_speed_mps`` and to the association gate with the last velocity.

A bias the prior leaves out: a vehicle whose published sigma holds an attitude bias larger than its prior here (a
daemon that states no ``los_sigma_bias_deg`` configured for a worse attitude than the fusion's
``--attitude-bias-deg``, or a ``--vehicle-noise`` below what its daemon states) has the excess taken for white
noise, which its rays average away: overconfident.  White noise of that size would scatter the vehicle's rays about
their own mean; a bias moves them together.  So after the solve each vehicle with at least
:data:`BIAS_SCATTER_MIN_RAYS` rays in the window has the scatter of its whitened residuals about their mean,
``q = sum |r_i - mean r|^2 / (2 (n - 1))``, compared with 1: below :data:`BIAS_SCATTER_RATIO_MAX`, what of each ray's
published variance is not seen as scatter (``s^2 - q s_w^2``, the median over its rays and axes) is constant, and
where its root exceeds the configured prior by :data:`BIAS_ABOVE_PRIOR_FACTOR` the solve is run again with it as that
vehicle's bias prior (:attr:`Triangulation.bias_above_prior` names the vehicle and the value).  A bias larger than
the published sigma holds (the daemon as wrong as the fusion) is out of reach with two vehicles: its component in the
plane of the two rays moves their crossing along them and leaves no residual, and the component across it is one
chi-square degree of freedom per window, independent of the first (docs/fleet.md, "Per-vehicle noise", measured).

Verdict (the single-vehicle estimator's discipline, :mod:`onboard.estimation.map_estimator`, with its
thresholds from :class:`~onboard.estimation.map_estimator.MapConfig`): ``observable`` when at least two
vehicles contribute, the range sigma seen from each contributing vehicle's newest camera position is below
``observability_max_sigma_range_ratio`` of its range (2 % in :attr:`FleetConfig.verdict`, tighter than the single
vehicle's 5.5 %; ``range_sigma_ratio`` is the worst of them),
the residuals pass ``chi2.sf(J, d) >= adequacy_p_min`` with at least ``MIN_RESIDUAL_DOF`` (0.5) residual degrees
of freedom to test (a solution that fits any rays exactly is never observable, whatever its covariance says) and
the covariance is
positive definite (ranges and range sigmas along each vehicle's newest measured line of sight).  An
unobservable estimate (one vehicle, parallel rays, rays that disagree) keeps its position with its range
sigma raised, along every contributing vehicle's line of sight, to ``MapEstimator.range_floor`` (at least
50 % and 150 m; the position prior's 1 km for one vehicle's own rays and for an estimate collapsed within
twice ``min_range_m`` of a camera), and across it by the bearing's sigma times the far end of that range
interval: never a confident wrong point.  Alone, a vehicle's bearings would let the estimate collapse onto its own camera
track (a target flying with the camera explains every bearing); the tracker therefore carries the last
estimate several vehicles made at constant velocity and corrects it across the lone vehicle's newest ray
(:func:`carried_with_bearing`): the bearing holds the cross-range, the range uncertainty grows.

Two vehicles with bearing noise ``s`` at range ``r`` and a baseline ``B`` across the line of sight give a
range sigma of about ``sqrt(2) s r^2 / B`` from one frame each (each bearing fixes the point across its own
ray; the ``s r^2 / B`` of the usual rule of thumb is one noisy bearing against a perfect one): 0.5 mrad,
1 km, 200 m -> 3.5 m (2.5 m by the rule).

The association of rays with targets, and the tracker that runs it all per ray, are in
:mod:`onboard.estimation.fleet_tracker`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from scipy.special import gammaincc

from onboard.core.checks import is_nonnegative_number, is_positive_int, is_positive_number, require_each
from onboard.core.errors import ConfigError, InputError
from onboard.estimation.map_estimator import MapConfig, NoiseModel, range_floor
from onboard.estimation.state_estimate import StateEstimate

__all__ = [
    "CLOSEST_APPROACH_GATE_CHI2",
    "MIN_BEARING_SIGMA_RAD",
    "MIN_RESIDUAL_DOF",
    "BIAS_SCATTER_RATIO_MAX",
    "BIAS_SCATTER_MIN_RAYS",
    "BIAS_ABOVE_PRIOR_FACTOR",
    "VehicleNoise",
    "white_variance_rad2",
    "modelled_cross_sigma_rad",
    "Ray",
    "FleetConfig",
    "ClosestApproach",
    "closest_approach",
    "Triangulation",
    "triangulate",
    "Contribution",
    "FleetEstimate",
    "fleet_verdict",
    "carried_with_bearing",
    "ray_gate_chi2",
    "OWN_ESTIMATE_GATE_CHI2",
    "own_estimate_chi2",
    "pair_crossing",
    "noise_for",
]

#: chi-square(1 dof) at 1e-4: two rays whose closest approach is farther than this (in its sigmas) do not pair
CLOSEST_APPROACH_GATE_CHI2 = 15.137
#: chi-square(3 dof) at 1e-4: a vehicle's own observable position of its object farther than this (in the sigmas of
#: both) from a fleet position is of another object
OWN_ESTIMATE_GATE_CHI2 = 21.108
#: no camera and attitude solution measures a bearing better than this (1 urad, 0.2 arcsec: a 640-pixel imager
#: over a 1-degree field is 27 urad a pixel, a navigation-grade attitude ~50 urad); a smaller published sigma is
#: a broken publisher, and its weight would be unbounded
MIN_BEARING_SIGMA_RAD = 1e-6
#: the residual test needs redundancy: a solution with fewer effective residual degrees of freedom than this
#: (module docstring, "Verdict") fits any rays, right or wrong, and is never called observable
MIN_RESIDUAL_DOF = 0.5
#: a vehicle's rays scatter about their own mean (within one solve's window) by less than this fraction of the
#: white variance modelled for them: the rest of its published variance is constant, an attitude bias beyond the
#: fusion's prior (module docstring, "A bias the prior leaves out"); chance alone gives below a quarter at 10 rays
#: with probability ~6e-4 (chi-square, 18 dof, below 4.5: 5.5e-4; more where the solve fits part of the scatter)
BIAS_SCATTER_RATIO_MAX = 0.25
#: the scatter test needs this many of a vehicle's rays in the window
BIAS_SCATTER_MIN_RAYS = 10
#: ... and names a vehicle only where the bias it suggests exceeds its configured prior by this factor (the white
#: floor of a tenth of the published variance makes the nominal rays scatter at ~0.3 of their modelled white noise,
#: with no bias beyond the prior in them)
BIAS_ABOVE_PRIOR_FACTOR = 1.5
_UNIT_TOL = 1e-6
_WHITE_FLOOR_FRACTION = 0.1  # the white part of a bearing's variance is at least this fraction of it


def white_variance_rad2(sigma_rad, bias_sigma_rad) -> np.ndarray:
    """The white part of a published bearing variance ``sigma_rad**2`` (any shape) when the attitude bias
    ``bias_sigma_rad`` is a per-vehicle nuisance of the solve: ``sigma^2 - s_b^2``, floored at a tenth of
    ``sigma^2`` and at :data:`MIN_BEARING_SIGMA_RAD` squared.  With the nuisance's prior the ray's modelled
    variance ``white + s_b^2`` is never below the published ``sigma^2`` (a bias larger than the published sigma
    makes the ray less trusted, never more)."""
    var = np.asarray(sigma_rad, dtype=float) ** 2
    bias_var = np.asarray(bias_sigma_rad, dtype=float) ** 2
    return np.maximum(np.maximum(var - bias_var, _WHITE_FLOOR_FRACTION * var), MIN_BEARING_SIGMA_RAD**2)


class VehicleNoise(Mapping[str, NoiseModel]):
    """One :class:`NoiseModel` per vehicle name with a default for every other vehicle (the fusion's
    ``--vehicle-noise`` over its global noise options).  A mapping: :func:`triangulate` and
    :class:`~onboard.estimation.fleet_tracker.FleetTracker` take it where they take a dict of models."""

    def __init__(self, default: NoiseModel, per_vehicle: Mapping[str, NoiseModel] | None = None) -> None:
        if not isinstance(default, NoiseModel):
            raise ConfigError(f"VehicleNoise.default: expected a NoiseModel, got {type(default).__name__}")
        self.default = default
        self.per_vehicle = dict(per_vehicle or {})
        for name, m in self.per_vehicle.items():
            if not isinstance(m, NoiseModel):
                raise ConfigError(f"VehicleNoise[{name!r}]: expected a NoiseModel, got {type(m).__name__}")

    def __getitem__(self, vehicle: str) -> NoiseModel:
        return self.per_vehicle.get(vehicle, self.default)

    def __contains__(self, vehicle: object) -> bool:
        return isinstance(vehicle, str)

    def __iter__(self):
        return iter(self.per_vehicle)

    def __len__(self) -> int:
        return len(self.per_vehicle)


def _vec3(v, what: str) -> np.ndarray:
    try:
        a = np.array(v, dtype=float).reshape(3)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be 3 finite numbers, got {v!r}") from None
    if not np.isfinite(a).all():
        raise InputError(f"{what} must be 3 finite numbers, got {a.tolist()}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Ray:
    """One vehicle's line of sight to one of its objects at one time, in the fleet's frame and clock.

    ``t_s``: capture time on the fleet's common clock, s.  ``p_cam_ned_m`` (3,): the camera, fleet NED, m.
    ``los_ned`` (3,): unit direction camera -> object, fleet NED.  ``sigma_az_rad`` / ``sigma_el_rad``: the
    1-sigma of its azimuth / elevation as published (white attitude noise and bias included).
    ``object_id``: the vehicle's own association (its track id).  ``time_sigma_s``: the 1-sigma of ``t_s``
    (the vehicle's UTC mapping; 0: taken as exact, module docstring "Time").  ``own_p_ned_m`` (3,) and
    ``own_cov_ned_m2`` (3, 3), both or neither: the vehicle's own estimate of the object's position at ``t_s``,
    fleet NED, where its estimator called it observable (the association's check that a fleet position is of the
    object this vehicle sees, :func:`own_estimate_chi2`).  Derived (not init): ``basis_ned`` (2, 3),
    the rows ``e_az``, ``e_el`` across the ray, and ``sigma_cross_rad`` (2,), the angular sigma along them
    (``cos(el) sigma_az``, ``sigma_el``)."""

    vehicle: str
    object_id: int
    t_s: float
    p_cam_ned_m: np.ndarray
    los_ned: np.ndarray
    sigma_az_rad: float
    sigma_el_rad: float
    time_sigma_s: float = 0.0
    own_p_ned_m: np.ndarray | None = None
    own_cov_ned_m2: np.ndarray | None = None
    basis_ned: np.ndarray = field(init=False, repr=False)
    sigma_cross_rad: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.vehicle, str) or not self.vehicle:
            raise InputError(f"Ray.vehicle must be a non-empty string, got {self.vehicle!r}")
        if isinstance(self.object_id, bool) or not isinstance(self.object_id, (int, np.integer)):
            raise InputError(f"Ray.object_id must be an integer, got {self.object_id!r}")
        object.__setattr__(self, "object_id", int(self.object_id))
        t = self.t_s
        if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) or not math.isfinite(t):
            raise InputError(f"Ray.t_s must be a finite number of seconds, got {t!r}")
        object.__setattr__(self, "t_s", float(t))
        object.__setattr__(self, "p_cam_ned_m", _vec3(self.p_cam_ned_m, "Ray.p_cam_ned_m"))
        u = _vec3(self.los_ned, "Ray.los_ned")
        if abs(float(np.linalg.norm(u)) - 1.0) > _UNIT_TOL:
            raise InputError(f"Ray.los_ned must be a unit vector, got {u.tolist()}")
        for name in ("sigma_az_rad", "sigma_el_rad"):
            s = getattr(self, name)
            if isinstance(s, bool) or not isinstance(s, (int, float, np.floating)) or not (math.isfinite(s) and s > 0):
                raise InputError(f"Ray.{name} must be a positive finite number of radians, got {s!r}")
            object.__setattr__(self, name, float(s))
        ts = self.time_sigma_s
        if isinstance(ts, bool) or not isinstance(ts, (int, float, np.floating)) or not (math.isfinite(ts) and ts >= 0):
            raise InputError(f"Ray.time_sigma_s must be a finite number of seconds >= 0, got {ts!r}")
        object.__setattr__(self, "time_sigma_s", float(ts))
        self._own_estimate()
        n, e, d = u.tolist()
        h = math.hypot(n, e)
        if h > 1e-9:
            e_az = np.array([-e / h, n / h, 0.0])
            e_el = np.array([d * n / h, d * e / h, -h])  # du/d(el): unit, across u, towards up
        else:  # looking straight up or down: azimuth is undefined, any pair across the ray will do
            e_az = np.array([0.0, 1.0, 0.0])
            e_el = np.cross(u, e_az)
        basis = np.vstack([e_az, e_el])
        basis.setflags(write=False)
        cross = np.array([min(h * self.sigma_az_rad, math.pi), self.sigma_el_rad])
        if h <= 1e-9:
            cross[0] = self.sigma_el_rad
        cross.setflags(write=False)
        object.__setattr__(self, "basis_ned", basis)
        object.__setattr__(self, "sigma_cross_rad", cross)

    def _own_estimate(self) -> None:
        p, cov = self.own_p_ned_m, self.own_cov_ned_m2
        if p is None and cov is None:
            return
        if p is None or cov is None:
            raise InputError("Ray.own_p_ned_m and Ray.own_cov_ned_m2 go together: one was given without the other")
        object.__setattr__(self, "own_p_ned_m", _vec3(p, "Ray.own_p_ned_m"))
        try:
            c = np.array(cov, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"Ray.own_cov_ned_m2 must be a 3 x 3 matrix of numbers, got {cov!r}") from None
        if c.shape != (3, 3) or not np.all(np.isfinite(c)):
            raise InputError(f"Ray.own_cov_ned_m2 must be a finite 3 x 3 matrix, got {c.tolist()}")
        c = 0.5 * (c + c.T)
        if np.any(np.diag(c) < 0):
            raise InputError(f"Ray.own_cov_ned_m2 has a negative variance: {np.diag(c).tolist()}")
        c.setflags(write=False)
        object.__setattr__(self, "own_cov_ned_m2", c)


def modelled_cross_sigma_rad(ray: Ray, noise: NoiseModel) -> np.ndarray:
    """The angular 1-sigma across ``ray`` (2,), along ``ray.basis_ned``, that the solve models for it with its
    vehicle's ``noise``: the white part of the published sigma (:func:`white_variance_rad2`) and the configured
    attitude-bias prior ``s_b`` in quadrature.  An attitude error ``phi ~ N(0, s_b^2 I)`` turns the ray by
    ``B [u]x phi``, ``s_b`` on each axis across it.  Where the published sigma already holds ``s_b`` (the daemon's
    own prior, the fusion's default) it is the published sigma; where the fusion's prior is larger (a vehicle whose
    attitude can be off by more than it says) it is the prior's.  The gates (:func:`closest_approach`,
    :func:`ray_gate_chi2`, :func:`pair_crossing`) use it, so that a ray within its vehicle's prior pairs and joins
    the target the solve would fit it to."""
    s_b = noise.attitude_bias_sigma_rad
    return np.sqrt(white_variance_rad2(ray.sigma_cross_rad, s_b) + s_b * s_b)


@dataclass(frozen=True)
class FleetConfig:
    """The fleet fusion's settings (units in the names); the verdict's thresholds and weak priors are the
    single-vehicle estimator's (``verdict``, a :class:`MapConfig`).

    ``window_s``: rays older than this before the target's newest ray leave the solve.  ``vehicle_timeout_s``:
    a vehicle whose newest ray is this much older than the target's newest does not contribute.
    ``member_timeout_s``: an object silent this long (fleet clock) leaves its target.  ``pair_max_dt_s``: two
    rays farther apart in time do not pair.  ``max_speed_mps``: target speed allowed for in the pairing gate
    over their time difference.  ``q_m2ps3``: the constant-velocity model's white-acceleration PSD.
    ``min_range_m``: ranges are clamped to at least this in the noise model.  ``max_defer_s``: a target is
    due (:meth:`~onboard.estimation.fleet_tracker.FleetTracker.due`) once every live vehicle sent a ray newer than its last solve, or its newest
    ray is this much newer than that (fleet clock).  ``unpaired_after_s``: an object in no target this long (fleet
    clock, from its first ray in none) has each further ray counted ``ray_unpaired`` (its lines of sight are fused
    into nothing)."""

    window_s: float = 1.0
    vehicle_timeout_s: float = 0.3
    member_timeout_s: float = 2.0
    pair_max_dt_s: float = 0.1
    max_speed_mps: float = 30.0
    q_m2ps3: float = 1.0
    min_range_m: float = 10.0
    iterations: int = 20  # Gauss-Newton cap: warm-started solves take 2-3; a poorly crossing pair from a far seed ~12
    max_defer_s: float = 0.05
    # a new target pairs within a frame or two of both vehicles' first rays; a second of frames in no target is no
    # start-up but a vehicle whose rays meet no other's (its attitude off beyond its prior, or an object only it sees)
    unpaired_after_s: float = 1.0
    # the single-vehicle verdict's thresholds, priors and range floor, with a tighter range-sigma threshold:
    # triangulation's linearised covariance is consistent where rays cross well (mean NEES 3.03 over random
    # 2-4 vehicle geometries with RTK-class errors where the range sigma is below 2 % of range, 3.36 up to 5 %:
    # the range posterior grows skewed as the crossing angle closes, as a single camera's does)
    verdict: MapConfig = field(default_factory=lambda: MapConfig(observability_max_sigma_range_ratio=0.02))

    def __post_init__(self) -> None:
        require_each(
            self,
            (
                "window_s",
                "vehicle_timeout_s",
                "member_timeout_s",
                "pair_max_dt_s",
                "min_range_m",
                "max_defer_s",
                "unpaired_after_s",
            ),
            is_positive_number,
            ConfigError,
            "FleetConfig.{name}: expected a positive number of its unit, got {value!r}",
        )
        require_each(
            self,
            ("max_speed_mps", "q_m2ps3"),
            is_nonnegative_number,
            ConfigError,
            "FleetConfig.{name}: expected a number >= 0, got {value!r}",
        )
        if not is_positive_int(self.iterations):
            raise ConfigError(f"FleetConfig.iterations: expected an integer >= 1, got {self.iterations!r}")
        if not isinstance(self.verdict, MapConfig):
            raise ConfigError(f"FleetConfig.verdict: expected a MapConfig, got {type(self.verdict).__name__}")


# --------------------------------------------------------------------------- two rays


@dataclass(frozen=True)
class ClosestApproach:
    """Where two rays pass closest.  ``distance_m``: the gap along their common perpendicular; ``sigma_m``:
    its 1-sigma from both rays' noise, camera positions and the target's motion between the two times;
    ``range_a_m`` / ``range_b_m``: the distances along each ray to the closest points; ``midpoint_ned_m``:
    halfway between them; ``chi2 = (distance / sigma)^2`` (1 dof)."""

    distance_m: float
    sigma_m: float
    range_a_m: float
    range_b_m: float
    midpoint_ned_m: np.ndarray
    chi2: float


def _camera_sigma_m(noise: NoiseModel) -> float:
    return math.hypot(noise.camera_position_white_sigma_m, noise.camera_position_offset_sigma_m)


def closest_approach(
    a: Ray, b: Ray, noise_a: NoiseModel, noise_b: NoiseModel, max_speed_mps: float = 30.0
) -> ClosestApproach | None:
    """The closest approach of rays ``a`` and ``b`` (lines ``c + s u``, s > 0), or None when they are
    parallel to within their angular sigmas (no crossing to speak of) or meet behind either camera.  The angular
    sigmas are those the solve models (:func:`modelled_cross_sigma_rad`: each vehicle's configured attitude-bias
    prior in them), not only the published ones: a vehicle whose attitude is off by more than it publishes, but
    within the prior the fusion is given for it, pairs.

    Lines ``c_a + s u_a`` and ``c_b + t u_b``: with ``w = c_a - c_b``, ``k = u_a . u_b``,
    ``s = (k (u_b . w) - u_a . w) / (1 - k^2)``, ``t = ((u_b . w) - k (u_a . w)) / (1 - k^2)`` (the normal
    equations of ``min |c_a + s u_a - c_b - t u_b|^2``).  The gap is measured along ``n = u_a x u_b / |.|``;
    its variance is each ray's angular variance along ``n`` times its range squared, plus both cameras'
    position variances and ``max_speed^2 ((t_a - t_b)^2 + s_ta^2 + s_tb^2)`` (the target's motion between the
    two times and over their time sigmas)."""
    ua, ub = a.los_ned, b.los_ned
    sa, sb = modelled_cross_sigma_rad(a, noise_a), modelled_cross_sigma_rad(b, noise_b)
    n = np.cross(ua, ub)
    sin_ab = float(np.linalg.norm(n))
    min_angle = math.hypot(float(np.max(sa)), float(np.max(sb)))
    if sin_ab <= min_angle:
        return None
    n = n / sin_ab
    w = a.p_cam_ned_m - b.p_cam_ned_m
    k = float(ua @ ub)
    da, db = float(ua @ w), float(ub @ w)
    den = 1.0 - k * k
    s = (k * db - da) / den
    t = (db - k * da) / den
    if s <= 0 or t <= 0:
        return None
    pa = a.p_cam_ned_m + s * ua
    pb = b.p_cam_ned_m + t * ub
    gap = float(n @ (pa - pb))
    var = (
        s * s * float(((a.basis_ned @ n) ** 2) @ (sa**2))
        + t * t * float(((b.basis_ned @ n) ** 2) @ (sb**2))
        + _camera_sigma_m(noise_a) ** 2
        + _camera_sigma_m(noise_b) ** 2
        + max_speed_mps**2 * ((a.t_s - b.t_s) ** 2 + a.time_sigma_s**2 + b.time_sigma_s**2)
    )
    sigma = math.sqrt(var)
    return ClosestApproach(abs(gap), sigma, s, t, 0.5 * (pa + pb), gap * gap / var)


# --------------------------------------------------------------------------- many rays


@dataclass(frozen=True)
class Triangulation:
    """The MAP estimate of :func:`triangulate` at ``t_s`` (module docstring).  ``p_ned_m``, ``v_ned_mps``
    (3,); ``cov_pv`` (6, 6): the joint covariance of ``(p, v)`` (nuisances marginalised);
    ``cost``: ``J`` at the solution; ``dof``: its effective residual degrees of freedom, ``2N - 6`` plus
    the directions of ``(p, v)`` only the weak priors hold (module docstring, "Verdict"); ``iterations``; ``condition``: a lower bound of the
    column-scaled normal matrix's 2-norm condition number (the squared ratio of its Cholesky factor's extreme
    diagonal entries); ``vehicles``: those with rays in the solve."""

    t_s: float
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    cov_pv: np.ndarray
    cost: float
    dof: float
    iterations: int
    condition: float
    vehicles: tuple[str, ...]
    #: True for :func:`carried_with_bearing`'s estimate (its range carried from several vehicles' estimate)
    carried: bool = False
    #: (vehicle, attitude-bias sigma in rad) for each vehicle whose rays showed a bias beyond its configured prior
    #: (module docstring, "A bias the prior leaves out"): the solve took this sigma as its prior instead
    bias_above_prior: tuple[tuple[str, float], ...] = ()

    @property
    def cov_p_ned_m2(self) -> np.ndarray:
        return self.cov_pv[:3, :3]

    @property
    def cov_v_ned_m2ps2(self) -> np.ndarray:
        return self.cov_pv[3:, 3:]


def noise_for(noise: NoiseModel | Mapping[str, NoiseModel], vehicle: str) -> NoiseModel:
    if isinstance(noise, NoiseModel):
        return noise
    try:
        return noise[vehicle]
    except KeyError:
        raise ConfigError(f"no noise model for vehicle {vehicle!r}") from None


def _linear_start(C: np.ndarray, U: np.ndarray, dt: np.ndarray, prior_w: np.ndarray, prior_x: np.ndarray) -> np.ndarray:
    """The first linearisation point (p, v): the linear least-squares point moving at constant velocity closest
    to every ray (perpendicular distances, the weak priors as regularisation: Hartley & Zisserman, Multiple
    View Geometry, 2nd ed., sec. 12.2, with time), or the prior's centre when that point is behind a camera.
    Gauss-Newton from the prior's centre can run out of iterations where two rays nearly oppose each other
    (cameras on either side of the target: the cost is flat along the line between them); from this start
    noiseless rays are met exactly."""
    Pp = np.eye(3)[None] - U[:, :, None] * U[:, None, :]  # (N, 3, 3) projectors across each ray
    A = np.concatenate([Pp, Pp * dt[:, None, None]], axis=2)  # (N, 3, 6): p + dt v
    b = np.einsum("nij,nj->ni", Pp, C)
    H = np.einsum("nki,nkj->ij", A, A) + np.diag(prior_w)
    g = np.einsum("nki,nk->i", A, b) + prior_w * prior_x
    try:
        x = np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return prior_x
    if not np.all(np.isfinite(x)) or np.any(np.einsum("ni,ni->n", U, x[:3] + dt[:, None] * x[3:6] - C) <= 0):
        return prior_x
    return x


def triangulate(
    rays: Sequence[Ray],
    noise: NoiseModel | Mapping[str, NoiseModel],
    p_prior_ned_m,
    config: FleetConfig | None = None,
    t_s: float | None = None,
    v_prior_ned_mps=(0.0, 0.0, 0.0),
    v_prior_sigma_mps: float | None = None,
    v_time_ned_mps=None,
    *,
    check_bias: bool = True,
) -> Triangulation:
    """The MAP estimate of the target's position and velocity at ``t_s`` (default: the newest ray's time)
    from ``rays`` (module docstring: the cost, its priors, the iterations).  ``noise``: one
    :class:`NoiseModel` for every vehicle or one per vehicle name; ``p_prior_ned_m``: the centre of the weak
    position prior (and the first linearisation point); ``v_prior_ned_mps`` / ``v_prior_sigma_mps``: the
    velocity prior (default: zero, ``MapConfig.velocity_prior_sigma_mps``); ``v_time_ned_mps``: the target
    velocity that turns each ray's ``time_sigma_s`` into a miss across it (default: ``config.max_speed_mps`` in
    every direction).  ``check_bias``: test each vehicle's residual scatter for a bias beyond its prior and
    solve again with the bias it suggests (module docstring, "A bias the prior leaves out").  Raises
    :class:`InputError` without rays."""
    cfg = config or FleetConfig()
    if not rays:
        raise InputError("triangulate: no rays")
    t0 = max(r.t_s for r in rays) if t_s is None else float(t_s)
    N = len(rays)
    C = np.array([r.p_cam_ned_m for r in rays])  # (N, 3)
    U = np.array([r.los_ned for r in rays])  # (N, 3)
    Bm = np.array([r.basis_ned for r in rays])  # (N, 2, 3)
    S_total = np.array([r.sigma_cross_rad for r in rays])  # (N, 2)
    dt = np.array([r.t_s - t0 for r in rays])
    vehicles = tuple(dict.fromkeys(r.vehicle for r in rays))
    vidx = np.array([vehicles.index(r.vehicle) for r in rays])
    models = [noise_for(noise, v) for v in vehicles]
    bias_sigma = np.array([m.attitude_bias_sigma_rad for m in models])[vidx]  # (N,)
    white_var = white_variance_rad2(S_total, bias_sigma[:, None])
    cam_var = np.array([m.camera_position_white_sigma_m**2 for m in models])[vidx] + cfg.q_m2ps3 * np.abs(dt) ** 3 / 3
    # a capture time known to s_t moves the target along its velocity by v s_t: a miss across the ray (m^2, (N, 2))
    t_var = np.array([r.time_sigma_s for r in rays]) ** 2
    if v_time_ned_mps is None:
        time_var = np.outer(t_var, np.full(2, cfg.max_speed_mps**2))
    else:
        time_var = (
            np.einsum("nij,j->ni", Bm, _vec3(v_time_ned_mps, "triangulate: v_time_ned_mps")) ** 2 * t_var[:, None]
        )

    # column layout: p (3), v (3), then per vehicle beta (3) where offset sigma > 0, phi (3) where bias sigma > 0
    cols_beta: list[int | None] = []
    cols_phi: list[int | None] = []
    s_v = cfg.verdict.velocity_prior_sigma_mps if v_prior_sigma_mps is None else float(v_prior_sigma_mps)
    if not (math.isfinite(s_v) and s_v > 0):
        raise InputError(f"triangulate: v_prior_sigma_mps must be a positive number, got {v_prior_sigma_mps!r}")
    prior_diag = [1.0 / cfg.verdict.position_prior_sigma_m**2] * 3 + [1.0 / s_v**2] * 3
    n = 6
    for m in models:
        for sigma, cols in ((m.camera_position_offset_sigma_m, cols_beta), (m.attitude_bias_sigma_rad, cols_phi)):
            if sigma > 0:
                cols.append(n)
                prior_diag += [1.0 / sigma**2] * 3
                n += 3
            else:
                cols.append(None)
    P_prior = np.asarray(prior_diag)
    p_prior = _vec3(p_prior_ned_m, "triangulate: p_prior_ned_m")
    g_prior = np.zeros(n)
    g_prior[:3] = P_prior[:3] * p_prior
    g_prior[3:6] = P_prior[3:6] * _vec3(v_prior_ned_mps, "triangulate: v_prior_ned_mps")

    BU = np.cross(Bm, U[:, None, :])  # rows e_k x u: e^T [u]x phi = phi . (e x u)
    x_prior = g_prior / P_prior
    x = x_prior.copy()
    x[:6] = _linear_start(C, U, dt, P_prior[:6], x_prior[:6])
    beta_of = np.zeros((N, 3))
    iterations = 0

    def residuals(x: np.ndarray):
        """Whitened angular residuals (N, 2), the Jacobian (N, 2, n) and the along-ray distances (N,)."""
        beta_of[:] = 0.0
        phi_of = np.zeros((N, 3))
        for k in range(len(vehicles)):
            sel = vidx == k
            if (cb := cols_beta[k]) is not None:
                beta_of[sel] = x[cb : cb + 3]
            if (cp := cols_phi[k]) is not None:
                phi_of[sel] = x[cp : cp + 3]
        d = x[:3] + dt[:, None] * x[3:6] - C + beta_of
        rho = np.maximum(np.einsum("ni,ni->n", U, d), cfg.min_range_m)
        Bd = np.einsum("nij,nj->ni", Bm, d)
        res = Bd / rho[:, None] - np.einsum("nij,nj->ni", BU, phi_of)
        W = 1.0 / np.sqrt(white_var + (cam_var[:, None] + time_var) / (rho * rho)[:, None])
        Jd = (Bm - Bd[:, :, None] * U[:, None, :] / rho[:, None, None]) / rho[:, None, None]
        A = np.zeros((N, 2, n))
        A[:, :, 0:3] = Jd
        A[:, :, 3:6] = Jd * dt[:, None, None]
        for k in range(len(vehicles)):
            sel = vidx == k
            if (cb := cols_beta[k]) is not None:
                A[sel, :, cb : cb + 3] = Jd[sel]
            if (cp := cols_phi[k]) is not None:
                A[sel, :, cp : cp + 3] = -BU[sel]
        return res * W, A * W[:, :, None], rho

    def total(res: np.ndarray, x: np.ndarray) -> float:
        return float(np.sum(res * res) + ((x - x_prior) ** 2 * P_prior).sum())

    res, A, rho = residuals(x)
    while iterations < cfg.iterations:
        iterations += 1
        A2 = A.reshape(2 * N, n)
        H = A2.T @ A2 + np.diag(P_prior)
        g = A2.T @ res.reshape(2 * N) + P_prior * (x - x_prior)
        step = sla.cho_solve(sla.cho_factor(H, lower=True, check_finite=False), -g, check_finite=False)
        # backtracking: a full Gauss-Newton step overshoots where the rays cross poorly (Nocedal & Wright,
        # Numerical Optimization, 2nd ed., alg. 3.1, sufficient decrease dropped: halve while the cost grows)
        before = total(res, x)
        for _ in range(8):
            res_new, A_new, rho_new = residuals(x + step)
            if total(res_new, x + step) <= before:
                break
            step = 0.5 * step
        x = x + step
        res, A, rho = res_new, A_new, rho_new
        if float(np.max(np.abs(step[:6]))) < 1e-7 * float(np.max(rho)):  # 0.1 mm, 0.1 mm/s at 1 km
            break
    A2 = A.reshape(2 * N, n)
    H = A2.T @ A2 + np.diag(P_prior)
    cost = float(np.sum(res * res) + ((x - x_prior) ** 2 * P_prior)[6:].sum())  # the nuisances' prior rows
    scale = 1.0 / np.sqrt(np.diag(H))
    L = np.linalg.cholesky(H * scale[:, None] * scale[None, :])  # column-scaled: the condition is the geometry's
    cond = float((np.max(np.diag(L)) / np.min(np.diag(L))) ** 2)  # a cheap lower bound of cond(H_scaled)
    # the (p, v) block of H^-1: six columns of the inverse, from the factor
    E = np.zeros((n, 6))
    E[:6, :6] = np.eye(6)
    Z = sla.solve_triangular(L, E, lower=True, check_finite=False)
    cov = (Z.T @ Z) * scale[:6, None] * scale[None, :6]
    cov = 0.5 * (cov + cov.T)
    # the residual degrees of freedom: 2N rows less what the rays determine; a direction of (p, v) that only the
    # weak prior holds (the velocity of rays all taken at one time) is not fitted to them, and counts
    # P_prior_i (H^-1)_ii of its prior row back (the trace of the prior's share of the hat matrix)
    dof = 2 * N - 6 + float(np.sum(P_prior[:6] * np.diag(cov)))
    sol = Triangulation(
        t_s=t0,
        p_ned_m=x[:3].copy(),
        v_ned_mps=x[3:6].copy(),
        cov_pv=cov,
        cost=cost,
        dof=dof,
        iterations=iterations,
        condition=cond,
        vehicles=vehicles,
    )
    if not check_bias:
        return sol
    raised = _bias_beyond_prior(res, vidx, vehicles, models, S_total, white_var)
    if not raised:
        return sol
    per_vehicle = {v: m for v, m in zip(vehicles, models)}
    for v, s_b in raised:
        per_vehicle[v] = dataclasses.replace(per_vehicle[v], attitude_bias_sigma_rad=s_b)
    again = triangulate(
        rays, per_vehicle, p_prior, cfg, t0, v_prior_ned_mps, v_prior_sigma_mps, v_time_ned_mps, check_bias=False
    )
    return dataclasses.replace(again, bias_above_prior=raised)


def _bias_beyond_prior(
    res: np.ndarray,
    vidx: np.ndarray,
    vehicles: tuple[str, ...],
    models: list[NoiseModel],
    S_total: np.ndarray,
    white_var: np.ndarray,
) -> tuple[tuple[str, float], ...]:
    """(vehicle, suggested attitude-bias sigma, rad) for each vehicle whose whitened residuals ``res`` (N, 2)
    scatter about their own mean by less than :data:`BIAS_SCATTER_RATIO_MAX` of the white variance modelled for
    them (module docstring, "A bias the prior leaves out")."""
    out = []
    for k, v in enumerate(vehicles):
        sel = vidx == k
        n_k = int(np.sum(sel))
        if n_k < BIAS_SCATTER_MIN_RAYS:
            continue
        r = res[sel]
        ratio = float(np.sum((r - r.mean(axis=0)) ** 2)) / (2 * (n_k - 1))
        if not ratio < BIAS_SCATTER_RATIO_MAX:
            continue
        # what of the published variance is not seen as scatter is constant over the window: the bias's
        s_b = models[k].attitude_bias_sigma_rad
        constant = S_total[sel] ** 2 - ratio * white_var[sel]
        suggested = math.sqrt(max(float(np.median(constant)), s_b * s_b))
        if suggested > BIAS_ABOVE_PRIOR_FACTOR * s_b:
            out.append((v, suggested))
    return tuple(out)


# --------------------------------------------------------------------------- the verdict


def _ratio_along(P: np.ndarray, u: np.ndarray, range_m: float) -> float:
    """The range sigma along the unit line of sight ``u`` of covariance ``P`` over ``range_m`` (inf at range 0)."""
    sig = math.sqrt(max(float(u @ P @ u), 0.0))
    return sig / range_m if range_m > 0 else math.inf


@dataclass(frozen=True)
class Contribution:
    """One vehicle's share of a fleet estimate: its newest ray's time (s), how many rays, the range from
    its newest camera position to the estimate (m) and the range sigma over that range."""

    vehicle: str
    t_s: float
    rays: int
    range_m: float
    range_sigma_ratio: float


@dataclass(frozen=True)
class FleetEstimate(StateEstimate):
    """A fleet target's state at ``t_s`` (fleet clock, s) in the fleet's NED frame: ``p_ned_m``,
    ``v_ned_mps`` (3,), ``cov_p_ned_m2``, ``cov_v_ned_m2ps2`` (3, 3; the position's range floor applied when
    unobservable), ``observable`` (module docstring, "Verdict"), ``range_sigma_ratio`` (the worst
    contributing vehicle's, of the published covariance: after the floor when unobservable), ``adequacy_p`` (the
    residuals' chi-square p-value), ``contributions`` (one per vehicle in the solve) and the :class:`Triangulation`
    it came from."""

    target_id: int
    range_sigma_ratio: float
    adequacy_p: float
    contributions: tuple[Contribution, ...]
    solution: Triangulation

    @property
    def vehicles(self) -> tuple[str, ...]:
        return tuple(c.vehicle for c in self.contributions)

    def propagated(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, covariance) carried to ``t_s`` at constant velocity (``p + v dt``, the (p, v) joint
        covariance mapped by ``[I, dt I]``)."""
        dt = float(t_s) - self.t_s
        F = np.hstack([np.eye(3), dt * np.eye(3)])
        cov = F @ self.solution.cov_pv @ F.T
        extra = self.cov_p_ned_m2 - self.solution.cov_p_ned_m2  # the range floor, when unobservable
        return self.p_ned_m + dt * self.v_ned_mps, cov + extra


def fleet_verdict(
    sol: Triangulation,
    rays: Sequence[Ray],
    config: FleetConfig | None = None,
    target_id: int = 0,
    noise: Mapping[str, NoiseModel] | NoiseModel | None = None,
) -> FleetEstimate:
    """The fleet estimate of ``sol`` (solved from ``rays``) with its verdict and, when unobservable, its range
    floor (module docstring, "Verdict").  ``noise``: the vehicles' noise models the solve used; the floor's widening
    across each line of sight then takes the angular sigma the solve models for its ray
    (:func:`modelled_cross_sigma_rad`, the configured attitude-bias prior in it), else the published one."""
    config = config or FleetConfig()
    raised = dict(sol.bias_above_prior)

    def cross(ray: Ray) -> np.ndarray:
        if noise is None:
            return ray.sigma_cross_rad
        model = noise_for(noise, ray.vehicle)
        if ray.vehicle in raised:
            model = dataclasses.replace(model, attitude_bias_sigma_rad=raised[ray.vehicle])
        return modelled_cross_sigma_rad(ray, model)

    P = sol.cov_p_ned_m2
    p = sol.p_ned_m
    contributions = []
    newest: dict[str, Ray] = {}
    counts: dict[str, int] = {}
    for r in rays:
        counts[r.vehicle] = counts.get(r.vehicle, 0) + 1
        if r.vehicle not in newest or r.t_s > newest[r.vehicle].t_s:
            newest[r.vehicle] = r
    los_u, los_r, los_sig = [], [], []
    for v in sol.vehicles:
        # along the measured line of sight: a collapsed estimate (near the camera) has no direction of its own
        u = newest[v].los_ned
        rng = max(float(u @ (p - newest[v].p_cam_ned_m)), 0.0)
        sig_r = math.sqrt(max(float(u @ P @ u), 0.0))
        contributions.append(Contribution(v, newest[v].t_s, counts[v], rng, sig_r / rng if rng > 0 else math.inf))
        los_u.append(u)
        los_r.append(rng)
        los_sig.append(sig_r)
    worst_ratio = max(c.range_sigma_ratio for c in contributions)
    dof = sol.dof
    # chi2.sf(cost, dof) = Q(dof / 2, cost / 2), the regularised upper incomplete gamma function (scipy.stats'
    # frozen-distribution machinery cost a millisecond per call)
    # no redundancy, no test: the p-value is reported as 1 and the verdict below refuses the estimate instead
    adequacy_p = float(gammaincc(dof / 2.0, sol.cost / 2.0)) if dof > 0 else 1.0
    try:
        np.linalg.cholesky(P)
        pd = bool(np.isfinite(P).all())
    except np.linalg.LinAlgError:
        pd = False
    vc = config.verdict
    observable = bool(
        len(sol.vehicles) >= 2
        and dof >= MIN_RESIDUAL_DOF
        and worst_ratio < vc.observability_max_sigma_range_ratio
        and adequacy_p >= vc.adequacy_p_min
        and pd
    )
    cov_p = P
    if not observable:
        # the floor along every contributing line of sight: a poorly crossing pair's posterior is a banana in
        # the plane of its rays, which one line of sight's floor would not cover
        add, floor_m = range_floor(vc, np.array(los_u), np.array(los_sig), np.array(los_r))
        lone = len(sol.vehicles) < 2 and not sol.carried
        if not lone and not sol.carried:
            # cameras closer together than their bearings can tell apart at this range (two vehicles centimetres
            # apart) cross their rays no better than one vehicle: its floor, not the collapsed pair's own
            cams = np.array([newest[v].p_cam_ned_m for v in sol.vehicles])
            baseline_m = float(np.max(np.linalg.norm(cams[:, None, :] - cams[None, :, :], axis=-1)))
            sigma_rad = max(float(np.max(cross(newest[v]))) for v in sol.vehicles)
            lone = baseline_m < 3.0 * sigma_rad * max(max(los_r), vc.min_range_m)
        for i, rng in enumerate(los_r):
            # one vehicle's own rays over a short window, or an estimate collapsed onto a camera: the range is
            # the weak position prior's to say
            if lone or rng < 2.0 * vc.min_range_m:
                u = los_u[i]
                floor_m[i] = max(floor_m[i], vc.position_prior_sigma_m)
                add[i] = np.outer(u, u) * max(floor_m[i] ** 2 - los_sig[i] ** 2, 0.0)
        cov_p = P + add.sum(axis=0)
        # ... and across it, the bearing's spread at the far end of that range interval (a collapsed estimate
        # near the camera has almost no cross-range sigma of its own)
        for u, rng, f_m, ray in zip(los_u, los_r, floor_m, (newest[v] for v in sol.vehicles)):
            across = np.eye(3) - np.outer(u, u)
            cov_p = cov_p + across * (float(np.max(cross(ray))) * (rng + f_m)) ** 2
        # the ratios published beside it are the floored covariance's, as the daemon's are: a consumer that
        # thresholds on them must not read the solution's own, confident figure next to the floored covariance
        contributions = [
            dataclasses.replace(c, range_sigma_ratio=_ratio_along(cov_p, u, c.range_m))
            for c, u in zip(contributions, los_u)
        ]
        worst_ratio = max(c.range_sigma_ratio for c in contributions)
    return FleetEstimate(
        target_id=target_id,
        t_s=sol.t_s,
        p_ned_m=p,
        v_ned_mps=sol.v_ned_mps,
        cov_p_ned_m2=cov_p,
        cov_v_ned_m2ps2=sol.cov_v_ned_m2ps2,
        observable=observable,
        range_sigma_ratio=float(worst_ratio),
        adequacy_p=adequacy_p,
        contributions=tuple(contributions),
        solution=sol,
    )


def ray_gate_chi2(ray: Ray, p_ned_m: np.ndarray, cov_p_ned_m2: np.ndarray, noise: NoiseModel, v_ned_mps=None) -> float:
    """The squared Mahalanobis distance (2 dof) of the target at ``p_ned_m`` (covariance ``cov_p_ned_m2``)
    from ``ray``: ``z = B (p - c)``, ``S = B P B^T + r^2 diag(s_cross^2) + s_cam^2 I + diag((B v)^2) s_t^2``
    (the last with the target's velocity ``v_ned_mps``, when given, and the ray's time sigma); inf behind the
    camera.  ``s_cross``: the angular sigmas the solve models for the ray with its vehicle's ``noise``
    (:func:`modelled_cross_sigma_rad`: its attitude-bias prior in them)."""
    d = p_ned_m - ray.p_cam_ned_m
    r = float(ray.los_ned @ d)
    if r <= 0:
        return math.inf
    z = ray.basis_ned @ d
    S = ray.basis_ned @ cov_p_ned_m2 @ ray.basis_ned.T + np.diag((r * modelled_cross_sigma_rad(ray, noise)) ** 2)
    S += np.eye(2) * _camera_sigma_m(noise) ** 2
    if v_ned_mps is not None and ray.time_sigma_s > 0:
        S += np.diag((ray.basis_ned @ np.asarray(v_ned_mps, dtype=float)) ** 2) * ray.time_sigma_s**2
    try:
        return float(z @ np.linalg.solve(S, z))
    except np.linalg.LinAlgError:
        return math.inf


def own_estimate_chi2(ray: Ray, p_ned_m: np.ndarray, cov_p_ned_m2: np.ndarray, v_ned_mps=None) -> float | None:
    """The squared Mahalanobis distance (3 dof) between ``ray``'s own estimate of its object and a fleet position
    ``p_ned_m`` (covariance ``cov_p_ned_m2``) at the ray's time; None when the ray carries no own estimate.

    ``S = P_own + P`` (plus the target's motion over the ray's time sigma, with ``v_ned_mps`` when given).  The
    two share this vehicle's bearings, so their difference varies less than ``S`` says: the test errs towards
    keeping an object.  What it sees that the ray gate cannot: two vehicles on two objects whose rays cross, or a
    vehicle whose tracker moved to another object near the same line of sight, are told apart by the range a
    manoeuvring vehicle has measured itself."""
    if ray.own_p_ned_m is None or ray.own_cov_ned_m2 is None:
        return None
    d = ray.own_p_ned_m - np.asarray(p_ned_m, dtype=float)
    S = ray.own_cov_ned_m2 + np.asarray(cov_p_ned_m2, dtype=float)
    if v_ned_mps is not None and ray.time_sigma_s > 0:
        v = np.asarray(v_ned_mps, dtype=float)
        S = S + np.outer(v, v) * ray.time_sigma_s**2
    try:
        return float(d @ np.linalg.solve(S, d))
    except np.linalg.LinAlgError:
        return None  # no spread at all on either side: nothing to test against


def pair_crossing(
    a: Ray, b: Ray, ca: ClosestApproach, noise_a: NoiseModel, noise_b: NoiseModel
) -> tuple[np.ndarray, np.ndarray]:
    """Where rays ``a`` and ``b`` cross, weighted, and its covariance (3,), (3, 3): each ray's information across
    itself at its range (``A = B^T diag(1 / ((r s_cross)^2 + s_cam^2)) B``, ``s_cross`` as the solve models it:
    :func:`modelled_cross_sigma_rad`), the point that minimises both rays'
    weighted cross-range offsets (``(A_a + A_b) x = A_a c_a + A_b c_b``) and the inverse of the summed information.
    Not ``ca.midpoint_ned_m``: halfway between the closest points carries half the far ray's cross-range error, which
    this covariance does not hold when the ranges differ.  Along a direction neither ray measures (near-parallel
    rays) the point is the midpoint's and the variance is left huge, so a test against it passes."""
    info = np.zeros((3, 3))
    rhs = np.zeros(3)
    for ray, r, noise in ((a, ca.range_a_m, noise_a), (b, ca.range_b_m, noise_b)):
        w = 1.0 / ((r * modelled_cross_sigma_rad(ray, noise)) ** 2 + _camera_sigma_m(noise) ** 2)
        A = ray.basis_ned.T @ (w[:, None] * ray.basis_ned)
        info += A
        rhs += A @ ray.p_cam_ned_m
    vals, vecs = np.linalg.eigh(info)
    ok = vals > float(vals[-1]) * 1e-12
    inv = np.where(ok, 1.0 / np.maximum(vals, 1e-300), 0.0)
    x = (vecs * inv) @ vecs.T @ rhs + (vecs * ~ok) @ vecs.T @ ca.midpoint_ned_m
    return x, (vecs * np.where(ok, inv, 1e12)) @ vecs.T


def carried_with_bearing(last: FleetEstimate, ray: Ray, noise: NoiseModel, config: FleetConfig) -> Triangulation:
    """``last`` carried to ``ray.t_s`` at constant velocity and corrected across ``ray`` only: what one vehicle
    left alone can still say.

    Prediction: ``p = p_0 + v dt``, ``P = [I dt I] Cov(p, v) [I dt I]^T + q |dt|^3 / 3 I``, ``V = Cov(v) +
    q |dt| I`` (white acceleration, the constant-velocity model's).  Update: the Kalman update with the
    linear measurement "the target is on the ray": ``z = B (p - c) = 0`` with ``R = diag((r s_cross)^2) +
    s_cam^2 I`` (as :meth:`onboard.estimation.sliding.TrackEstimate.with_bearing`), Joseph form, ``s_cross`` the
    angular sigmas the solve models for the ray (:func:`modelled_cross_sigma_rad`: its vehicle's attitude-bias prior
    in them; with the published sigmas alone a lone vehicle off by its larger prior pulled the estimate onto its
    ray, confidently).  The range
    stays the prediction's and its uncertainty grows; the verdict (one vehicle) calls it unobservable."""
    dt = ray.t_s - last.t_s
    F = np.hstack([np.eye(3), dt * np.eye(3)])
    q = config.q_m2ps3
    p = last.p_ned_m + dt * last.v_ned_mps
    P = F @ last.solution.cov_pv @ F.T + np.eye(3) * q * abs(dt) ** 3 / 3.0
    V = last.cov_v_ned_m2ps2 + np.eye(3) * q * abs(dt)
    d = p - ray.p_cam_ned_m
    r = max(float(ray.los_ned @ d), config.min_range_m)
    B = ray.basis_ned
    R = np.diag((r * modelled_cross_sigma_rad(ray, noise)) ** 2 + (B @ last.v_ned_mps) ** 2 * ray.time_sigma_s**2)
    R += np.eye(2) * _camera_sigma_m(noise) ** 2
    S = B @ P @ B.T + R
    K = np.linalg.solve(S, B @ P).T  # P B^T S^-1
    p = p - K @ (B @ d)
    IKB = np.eye(3) - K @ B
    P = IKB @ P @ IKB.T + K @ R @ K.T
    cov = np.zeros((6, 6))
    cov[:3, :3] = 0.5 * (P + P.T)
    cov[3:, 3:] = V
    return Triangulation(ray.t_s, p, last.v_ned_mps.copy(), cov, 0.0, 0.0, 0, math.nan, (ray.vehicle,), carried=True)
