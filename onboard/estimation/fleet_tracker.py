r"""The fleet's tracker: rays of several vehicles associated with targets, each target estimated from all its
rays together (:mod:`onboard.estimation.fleet`: the rays, the triangulation and its verdict).

Pure core, as :mod:`onboard.estimation.fleet` is.

Association
-----------
A ray carries its vehicle's own object id (the daemon's ``track_id``).  An object already in a target stays
there while its rays pass the target's gate: the Mahalanobis distance of the ray's cross-range offset from
the target's estimate, chi-square 2 dof at 1e-4 (``BEARING_GATE_CHI2``).  An unassigned object joins the
target it gates best with (never a target that has a live object of the same vehicle), else it pairs with
another vehicle's unassigned object whose rays' closest approach (:func:`closest_approach`) is within the
chi-square 1 dof gate at 1e-4 of its sigma, the one with the smallest normalised distance.  A ray that carries
its vehicle's own observable estimate of the object (:attr:`Ray.own_p_ned_m`) must also agree with the position
it joins, pairs at or stays in (chi-square 3 dof at 1e-4, :func:`own_estimate_chi2`): the ray gate alone is as
wide as a one-vehicle target's range and cannot tell two objects on one line of sight apart, nor two vehicles on
two objects whose rays cross; a vehicle that has ranged its object itself can (counted ``own_estimate_disagrees``
where it kept a ray out of a join or a pair; an object in a target leaves it, ``object_left``).  A vehicle whose
newest ray is ``vehicle_timeout_s`` older than the target's newest leaves the solution (and comes back
with its next ray that gates); objects silent for ``member_timeout_s`` leave the target; a target with no
object left is dropped.

The gates take each ray's angular sigmas as the solve models them
(:func:`~onboard.estimation.fleet.modelled_cross_sigma_rad`: the vehicle's configured attitude-bias prior in them),
so a vehicle whose attitude is off by more than it publishes, but within the prior the fusion is given for it, pairs
and stays.  An object whose rays meet no other vehicle's and no target's gate for ``unpaired_after_s`` (its attitude
off beyond its prior, its clock off, or an object only it sees) is fused into nothing: each further ray is counted
``ray_unpaired``, the WARNING naming the vehicle, how long and the nearest miss (the closest other vehicle's ray and
target, in their gates' chi-square).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError
from onboard.estimation.fleet import (
    CLOSEST_APPROACH_GATE_CHI2,
    OWN_ESTIMATE_GATE_CHI2,
    FleetConfig,
    FleetEstimate,
    Ray,
    carried_with_bearing,
    closest_approach,
    fleet_verdict,
    noise_for,
    own_estimate_chi2,
    pair_crossing,
    ray_gate_chi2,
    triangulate,
)
from onboard.estimation.map_estimator import NoiseModel
from onboard.estimation.sliding import BEARING_GATE_CHI2

__all__ = ["FleetTracker"]


class _NoiseOver(Mapping[str, NoiseModel]):
    """The configured noise (one model or one per vehicle) with some vehicles' own models over it (a mapping, as
    :func:`~onboard.estimation.fleet.triangulate` and the gates take it)."""

    def __init__(self, configured: NoiseModel | Mapping[str, NoiseModel], own: dict[str, NoiseModel]) -> None:
        self._configured, self._own = configured, own

    def __getitem__(self, vehicle: str) -> NoiseModel:
        own = self._own.get(vehicle)
        return own if own is not None else noise_for(self._configured, vehicle)

    def __contains__(self, vehicle: object) -> bool:
        return vehicle in self._own or isinstance(self._configured, NoiseModel) or vehicle in self._configured

    def __iter__(self):
        return iter(self._own)

    def __len__(self) -> int:
        return len(self._own)


@dataclass
class _Target:
    """A fleet target's mutable state: its objects (vehicle, object id), the centre of its weak position
    prior and its last estimate."""

    target_id: int
    members: set[tuple[str, int]]
    p_seed_ned_m: np.ndarray
    t_seed_s: float
    last: FleetEstimate | None = None
    last_multi: FleetEstimate | None = None  # the last estimate several vehicles made


class FleetTracker:
    """Associates rays from several vehicles with targets and estimates them (module docstring).

    Step methods: :meth:`add` takes one ray and returns the id of the target it went to (None: kept
    unassigned, or refused and counted); :meth:`solve` estimates one target from its rays now.  Refused
    rays are counted in ``counter`` by reason: ``ray_stale`` (older than the fleet's clock ``now_s`` by more
    than the window), ``ray_out_of_order`` (not newer than the same object's last ray); kept but in no target for
    ``unpaired_after_s``: ``ray_unpaired`` (module docstring).  ``attitude_bias_above_prior``: a solve whose rays
    showed a vehicle's attitude bias beyond its configured prior and took the bias they suggest instead
    (:func:`~onboard.estimation.fleet.triangulate`), counted per solve, a WARNING the first time for each vehicle
    naming the ``--vehicle-noise`` setting that fits.  Events counted
    at DEBUG level: ``target_created``, ``target_dropped``, ``object_left`` (failed its target's gate, went
    silent or its vehicle was withdrawn, :meth:`withdraw`).

    The fleet's clock ``now_s`` (staleness, silence) is the lower median of the vehicles' newest ray times,
    over the vehicles whose newest ray is within ``member_timeout_s`` of the newest of all: one vehicle whose
    clock runs ahead cannot make the others' rays stale (with two vehicles it is the older one's time, so a
    vehicle is stale only against its own stream; with three or more the outlier is the one refused).  A vehicle
    further ahead than ``member_timeout_s`` would leave the others out of the median: the fusion refuses such
    rays first (``--max-age-s``, the clock check)."""

    def __init__(
        self,
        config: FleetConfig | None = None,
        noise: NoiseModel | Mapping[str, NoiseModel] | None = None,
        counter: RejectCounter | None = None,
    ) -> None:
        self.config = config or FleetConfig()
        #: the noise models the tracker was given (the fusion's options); ``noise``: those in use, with each
        #: vehicle's own set by :meth:`set_vehicle_noise` over them
        self.configured_noise: NoiseModel | Mapping[str, NoiseModel] = noise if noise is not None else NoiseModel()
        self.noise: NoiseModel | Mapping[str, NoiseModel] = self.configured_noise
        self._vehicle_noise: dict[str, NoiseModel] = {}
        self.counter = counter or RejectCounter()
        self._rays: dict[tuple[str, int], deque[Ray]] = {}
        self._owner: dict[tuple[str, int], int] = {}
        self._targets: dict[int, _Target] = {}
        self._next_id = 1
        self._vehicle_newest_s: dict[str, float] = {}
        # each object in no target: the time of its first ray in none (fleet clock)
        self._unpaired_since: dict[tuple[str, int], float] = {}
        # the nearest miss of the last association that found nothing: (chi2, what) for a target and for a pairing
        self._miss: tuple[tuple[float, str], tuple[float, str]] = ((math.inf, ""), (math.inf, ""))
        # each vehicle warned of as attitude_bias_above_prior (once: the count goes on per solve) and the bias its
        # rays suggested last, rad
        self._bias_named: dict[str, float] = {}
        self.now_s = -math.inf

    def _fleet_now(self) -> float:
        times = sorted(self._vehicle_newest_s.values())
        live = [t for t in times if t >= times[-1] - self.config.member_timeout_s]
        return live[(len(live) - 1) // 2]

    @property
    def targets(self) -> tuple[int, ...]:
        return tuple(self._targets)

    @property
    def vehicles(self) -> tuple[str, ...]:
        """The vehicles whose rays the tracker holds, sorted."""
        return tuple(sorted({v for v, _ in self._rays}))

    def members(self, target_id: int) -> frozenset[tuple[str, int]]:
        return frozenset(self._targets[target_id].members)

    @property
    def biases_above_prior_rad(self) -> dict[str, float]:
        """Each vehicle whose rays have shown an attitude bias beyond its configured prior (counted
        ``attitude_bias_above_prior``) and the bias they suggested last, rad."""
        return dict(self._bias_named)

    def last_estimate(self, target_id: int) -> FleetEstimate | None:
        return self._targets[target_id].last

    def _noise(self, vehicle: str) -> NoiseModel:
        return noise_for(self.noise, vehicle)

    def set_vehicle_noise(self, vehicle: str, model: NoiseModel | None) -> None:
        """``vehicle``'s noise model from its next ray and solve on (its gates, its solve's priors, the scatter test
        of a bias beyond its prior), the other vehicles' unchanged; None: the configured one again.  The fusion sets
        the attitude-bias prior a vehicle's tracks state (``los_sigma_bias_deg``) this way."""
        if model is None:
            self._vehicle_noise.pop(vehicle, None)
        elif not isinstance(model, NoiseModel):
            raise ConfigError(f"set_vehicle_noise({vehicle!r}): expected a NoiseModel, got {type(model).__name__}")
        else:
            self._vehicle_noise[vehicle] = model
        self.noise = (
            _NoiseOver(self.configured_noise, dict(self._vehicle_noise))
            if self._vehicle_noise
            else self.configured_noise
        )

    def add(self, ray: Ray) -> int | None:
        """Take ``ray``; the target it belongs to (None: unassigned or refused)."""
        cfg = self.config
        key = (ray.vehicle, ray.object_id)
        self._vehicle_newest_s[ray.vehicle] = max(self._vehicle_newest_s.get(ray.vehicle, -math.inf), ray.t_s)
        self.now_s = self._fleet_now()
        if ray.t_s < self.now_s - cfg.window_s:
            self.counter.count("ray_stale", f"{ray.vehicle} object {ray.object_id} at {ray.t_s:.3f} s")
            return None
        buf = self._rays.get(key)
        if buf and ray.t_s <= buf[-1].t_s:
            self.counter.count("ray_out_of_order", f"{ray.vehicle} object {ray.object_id} at {ray.t_s:.3f} s")
            return None
        if buf is None:
            buf = self._rays[key] = deque()
        buf.append(ray)
        while buf and buf[0].t_s < ray.t_s - cfg.window_s:
            buf.popleft()
        self._expire()
        owner = self._owner.get(key)
        if owner is not None:
            target = self._targets[owner]
            last = target.last
            if last is None:
                return owner
            p, P = last.propagated(ray.t_s)
            if ray_gate_chi2(ray, p, P, self._noise(ray.vehicle), last.v_ned_mps) > BEARING_GATE_CHI2:
                why = "failed its target's gate"
            elif self._own_disagrees(ray, p, P, last.v_ned_mps):
                why = "its vehicle's own estimate disagrees with its target's"
            else:
                return owner
            self._leave(key, why)
            buf.clear()
            buf.append(ray)
        tid = self._associate(key, ray)
        if tid is None:
            self._note_unpaired(key, ray)
        return tid

    def _note_unpaired(self, key: tuple[str, int], ray: Ray) -> None:
        """Count ``ray`` ``ray_unpaired`` once its object has been in no target for ``unpaired_after_s``: nothing
        else would say that a vehicle's lines of sight are taken and fused into nothing."""
        since = self._unpaired_since.setdefault(key, ray.t_s)
        alone_s = ray.t_s - since
        if alone_s < self.config.unpaired_after_s:
            return
        (t_chi2, t_what), (p_chi2, p_what) = self._miss
        nearest = []
        if t_what:
            nearest.append(f"{t_what} at chi2 {t_chi2:.3g} (gate {BEARING_GATE_CHI2:g})")
        if p_what:
            at = f" at chi2 {p_chi2:.3g} (gate {CLOSEST_APPROACH_GATE_CHI2:g})" if math.isfinite(p_chi2) else ""
            nearest.append(p_what + at)
        elif not nearest:
            nearest.append(f"no other vehicle's ray in no target within {self.config.pair_max_dt_s:g} s, and no target")
        self.counter.count(
            "ray_unpaired",
            f"{key[0]} object {key[1]}: in no fleet target for {alone_s:.1f} s, its lines of sight fused into "
            f"nothing; nearest: {'; '.join(nearest)}; its attitude may be off by more than its prior "
            "(--vehicle-noise NAME:attitude_bias_deg=...), its clock off, or no other vehicle sees its object",
        )

    def _note_bias(self, vehicle: str, bias_rad: float) -> None:
        configured_deg = math.degrees(self._noise(vehicle).attitude_bias_sigma_rad)
        first = vehicle not in self._bias_named
        self._bias_named[vehicle] = bias_rad
        self.counter.count(
            "attitude_bias_above_prior",
            f"{vehicle}: its lines of sight are off by a constant beyond its attitude-bias prior "
            f"({configured_deg:.2g} deg): their scatter is well below the white noise their published sigma leaves "
            f"after the prior; fused with the bias they suggest, {math.degrees(bias_rad):.2g} deg; configure it: "
            f"--vehicle-noise {vehicle}:attitude_bias_deg={math.degrees(bias_rad):.2g}",
            level=logging.WARNING if first else logging.DEBUG,
            subject=vehicle,
        )

    def withdraw(self, vehicle: str, why: str) -> None:
        """Take every object of ``vehicle`` out of its target and forget its rays (a name shared by two
        vehicles: none of its rays can be trusted to be the vehicle's own)."""
        for _, object_id in [k for k in self._rays if k[0] == vehicle]:
            self.retire(vehicle, object_id, why)
        self._vehicle_newest_s.pop(vehicle, None)

    def retire(self, vehicle: str, object_id: int, why: str) -> None:
        """Take one object of ``vehicle`` out of its target and forget its rays: it went silent, its vehicle was
        withdrawn, or its vehicle said it is done with it (a daemon's track moved to another object id, so its target
        need not wait for its silence before the vehicle's next object may join)."""
        key = (vehicle, object_id)
        self._unpaired_since.pop(key, None)
        if key in self._rays:
            self._leave(key, why)
            del self._rays[key]

    def _leave(self, key: tuple[str, int], why: str) -> None:
        tid = self._owner.pop(key, None)
        if tid is None:
            return
        target = self._targets[tid]
        target.members.discard(key)
        self.counter.count("object_left", f"{key[0]} object {key[1]} left target {tid}: {why}", level=10)
        if not target.members:
            del self._targets[tid]
            self.counter.count("target_dropped", f"target {tid}", level=10)

    def _expire(self) -> None:
        cutoff = self.now_s - self.config.member_timeout_s
        for vehicle, object_id in [k for k, buf in self._rays.items() if not buf or buf[-1].t_s < cutoff]:
            self.retire(vehicle, object_id, "silent")

    @staticmethod
    def _own_disagrees(ray: Ray, p: np.ndarray, P: np.ndarray, v=None) -> bool:
        c2 = own_estimate_chi2(ray, p, P, v)
        return c2 is not None and c2 > OWN_ESTIMATE_GATE_CHI2

    def _live_vehicles(self, target: _Target, t_s: float) -> set[str]:
        return {
            v
            for v, k in target.members
            if (buf := self._rays.get((v, k))) and buf[-1].t_s >= t_s - self.config.vehicle_timeout_s
        }

    def _associate(self, key: tuple[str, int], ray: Ray) -> int | None:
        cfg = self.config
        noise = self._noise(ray.vehicle)
        best, best_chi2 = None, BEARING_GATE_CHI2
        near_target: tuple[float, str] = (math.inf, "")
        near_pair: tuple[float, str] = (math.inf, "")
        for target in list(self._targets.values()):
            if ray.vehicle in self._live_vehicles(target, ray.t_s):
                continue
            if target.last is None:  # created since the last solve (several rays arrived at once): solve it now
                self.solve(target.target_id)
            if target.last is None:
                continue
            p, P = target.last.propagated(ray.t_s)
            c2 = ray_gate_chi2(ray, p, P, noise, target.last.v_ned_mps)
            if c2 < near_target[0]:
                near_target = (c2, f"target {target.target_id}")
            if c2 > best_chi2:
                continue
            if self._own_disagrees(ray, p, P, target.last.v_ned_mps):
                self.counter.count(
                    "own_estimate_disagrees",
                    f"{key[0]} object {key[1]} kept out of target {target.target_id}",
                    level=10,
                )
                continue
            best, best_chi2 = target, c2
        if best is not None:
            best.members.add(key)
            self._owner[key] = best.target_id
            self._unpaired_since.pop(key, None)
            return best.target_id
        partner, pair, pair_chi2 = None, None, CLOSEST_APPROACH_GATE_CHI2
        for other, buf in self._rays.items():
            if other[0] == ray.vehicle or other in self._owner or not buf:
                continue
            cand = buf[-1]
            if abs(cand.t_s - ray.t_s) > cfg.pair_max_dt_s:
                continue
            ca = closest_approach(ray, cand, noise, self._noise(other[0]), cfg.max_speed_mps)
            if ca is None:
                if not near_pair[1]:
                    near_pair = (math.inf, f"{other[0]} object {other[1]}'s ray, parallel or crossing behind a camera")
                continue
            if ca.chi2 < near_pair[0]:
                near_pair = (ca.chi2, f"{other[0]} object {other[1]}'s ray")
            if ca.chi2 > pair_chi2:
                continue
            if ray.own_p_ned_m is not None or cand.own_p_ned_m is not None:
                x, P = pair_crossing(ray, cand, ca, noise, self._noise(other[0]))
                # the target's motion between the two rays and over their time sigmas, as closest_approach allows
                dt2 = (ray.t_s - cand.t_s) ** 2 + ray.time_sigma_s**2 + cand.time_sigma_s**2
                P += np.eye(3) * cfg.max_speed_mps**2 * dt2
                if self._own_disagrees(ray, x, P) or self._own_disagrees(cand, x, P):
                    self.counter.count(
                        "own_estimate_disagrees", f"{key[0]} object {key[1]} not paired with {other}", level=10
                    )
                    continue
            partner, pair, pair_chi2 = other, ca, ca.chi2
        if partner is None or pair is None:
            self._miss = (near_target, near_pair)
            return None
        tid = self._next_id
        self._next_id += 1
        self._targets[tid] = _Target(tid, {key, partner}, pair.midpoint_ned_m, ray.t_s)
        self._owner[key] = self._owner[partner] = tid
        self._unpaired_since.pop(key, None)
        self._unpaired_since.pop(partner, None)
        self.counter.count("target_created", f"target {tid} from {key} and {partner}", level=10)
        return tid

    def rays(self, target_id: int) -> list[Ray]:
        """The rays of ``target_id`` that the next :meth:`solve` uses: its live vehicles' rays in the window."""
        target = self._targets[target_id]
        bufs = [self._rays[k] for k in target.members if self._rays.get(k)]
        if not bufs:
            return []
        newest = max(b[-1].t_s for b in bufs)
        live = self._live_vehicles(target, newest)
        return [r for b in bufs if b[-1].vehicle in live for r in b if r.t_s >= newest - self.config.window_s]

    def due(self, target_id: int) -> bool:
        """Whether ``target_id`` has news worth a solve: no estimate yet; every live vehicle has a ray newer than
        the last estimate (the frames of one camera period are in); every live vehicle caught up with the newest
        ray and one of them was not in the last estimate (a late frame after a deferred solve); or its newest ray
        is ``max_defer_s`` past the last estimate (a vehicle is late).  On the fleet clock: no timer involved."""
        target = self._targets.get(target_id)
        if target is None:
            return False
        if target.last is None:
            return True
        newest: dict[str, float] = {}
        for v, k in target.members:
            buf = self._rays.get((v, k))
            if buf:
                newest[v] = max(newest.get(v, -math.inf), buf[-1].t_s)
        if not newest:
            return False
        t_new = max(newest.values())
        t_last = target.last.t_s
        if t_new - t_last >= self.config.max_defer_s:
            return True
        live = {v: t for v, t in newest.items() if t >= t_new - self.config.vehicle_timeout_s}
        used = {c.vehicle: c.t_s for c in target.last.contributions}
        oldest = min(live.values())
        if oldest > t_last:  # every live vehicle has a frame past the last estimate: a new camera period is in
            return True
        # a late vehicle's frame of the period the last (deferred) estimate already reached
        return oldest >= t_new and any(t > used.get(v, -math.inf) for v, t in live.items())

    def solve(self, target_id: int) -> FleetEstimate | None:
        """Estimate ``target_id`` from its rays now (None: no rays in the window)."""
        target = self._targets.get(target_id)
        if target is None:
            return None
        rays = self.rays(target_id)
        if not rays:
            return None
        t0 = max(r.t_s for r in rays)
        if target.last is not None:
            seed = target.last.p_ned_m + (t0 - target.last.t_s) * target.last.v_ned_mps
        else:
            seed = target.p_seed_ned_m
        if target.last_multi is not None and len({r.vehicle for r in rays}) < 2:
            newest = max(rays, key=lambda r: r.t_s)
            sol = carried_with_bearing(target.last_multi, newest, self._noise(newest.vehicle), self.config)
            est = fleet_verdict(sol, [newest], self.config, target_id, self.noise)
        else:
            v_time = None if target.last is None else target.last.v_ned_mps
            sol = triangulate(rays, self.noise, seed, self.config, v_time_ned_mps=v_time)
            est = fleet_verdict(sol, rays, self.config, target_id, self.noise)
            for vehicle, bias_rad in sol.bias_above_prior:
                self._note_bias(vehicle, bias_rad)
        target.last = est
        if len(est.contributions) >= 2:
            target.last_multi = est
        return est
