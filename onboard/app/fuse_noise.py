"""The noise models of ``python -m onboard.fuse`` (its module docstring, "Noise"): from its options
(``--attitude-bias-deg``, ``--camera-white-m``, ``--camera-offset-m``, ``--vehicle-noise``), and each vehicle's
attitude-bias prior as its rays come: the operator's ``--vehicle-noise NAME:attitude_bias_deg=..``, else what the
vehicle's tracks state (``los_sigma_bias_deg``: its daemon's ``estimator.attitude_bias_sigma_deg``), else
``--attitude-bias-deg`` (a daemon before the key), set on the fleet tracker and said in the fusion's status."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
from collections.abc import Collection, Iterable, Mapping

from onboard.app.cli_args import number_in
from onboard.core.errors import IrtrackError
from onboard.estimation.fleet import VehicleNoise, noise_for
from onboard.estimation.fleet_tracker import FleetTracker
from onboard.estimation.map_estimator import NoiseModel
from onboard.io.fleet_wire import FLEET_NAME
from onboard.io.zenoh_session import check_vehicle_name

__all__ = [
    "BIAS_APART_FACTOR",
    "BiasPrior",
    "BiasPriors",
    "attitude_bias_deg_arg",
    "bias_named",
    "camera_offset_m_arg",
    "camera_white_m_arg",
    "noise_models",
    "vehicle_arg",
    "vehicle_noise_arg",
]

log = logging.getLogger(__name__)


def vehicle_arg(text: str) -> str:
    """A vehicle's name as an option gives it (zenoh's key rules; not the fusion's own key)."""
    try:
        name = check_vehicle_name(text)
    except IrtrackError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if name == FLEET_NAME:
        raise argparse.ArgumentTypeError(f"{FLEET_NAME!r} is the fusion's own key, not a vehicle")
    return name


# the noise a vehicle can have (degrees, metres): zero allowed for the nuisances a zero switches off, not for the
# white noise; beyond the upper bounds no camera is placed at all, and the solve would overflow
attitude_bias_deg_arg = number_in(0.0, 90.0)
camera_white_m_arg = number_in(0.0, 1000.0, lo_open=True)
camera_offset_m_arg = number_in(0.0, 1000.0)

#: --vehicle-noise's keys (the global options' names and units) and the parser each value takes
_NOISE_KEYS = {
    "attitude_bias_deg": attitude_bias_deg_arg,
    "camera_white_m": camera_white_m_arg,
    "camera_offset_m": camera_offset_m_arg,
}


def vehicle_noise_arg(text: str) -> tuple[str, dict[str, float]]:
    """``NAME:key=value,...`` with keys of ``_NOISE_KEYS`` (degrees, metres: the global options' units)."""
    name, sep, rest = text.partition(":")
    usage = f"expected NAME:KEY=VALUE[,KEY=VALUE...] with KEY one of {', '.join(_NOISE_KEYS)}, got {text!r}"
    try:
        name = vehicle_arg(name)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(usage) from None
    values: dict[str, float] = {}
    for item in rest.split(",") if sep else []:
        k, eq, v = item.strip().partition("=")
        if k not in _NOISE_KEYS or not eq or k in values:
            raise argparse.ArgumentTypeError(usage)
        try:
            values[k] = _NOISE_KEYS[k](v)
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"{name}: {k}: {exc}") from None
    if not values:
        raise argparse.ArgumentTypeError(usage)
    return name, values


def noise_models(args: argparse.Namespace) -> VehicleNoise:
    """The global noise model with each ``--vehicle-noise`` vehicle's own (unnamed keys: the global values)."""
    default = {
        "attitude_bias_deg": args.attitude_bias_deg,
        "camera_white_m": args.camera_white_m,
        "camera_offset_m": args.camera_offset_m,
    }

    def model(v: Mapping[str, float]) -> NoiseModel:
        return NoiseModel(
            attitude_bias_sigma_rad=math.radians(v["attitude_bias_deg"]),
            camera_position_white_sigma_m=v["camera_white_m"],
            camera_position_offset_sigma_m=v["camera_offset_m"],
        )

    per: dict[str, dict[str, float]] = {}
    for name, values in args.vehicle_noise:
        per.setdefault(name, dict(default)).update(values)
    return VehicleNoise(model(default), {name: model(v) for name, v in per.items()})


#: a vehicle's tracks stating an attitude bias more than this factor from its --vehicle-noise attitude_bias_deg are
#: warned of (once): one of the two is not its attitude (the scatter test's factor, BIAS_ABOVE_PRIOR_FACTOR)
BIAS_APART_FACTOR = 1.5


@dataclasses.dataclass(frozen=True)
class BiasPrior:
    """A vehicle's attitude-bias prior in use: ``deg`` (1 sigma per axis), ``source`` (``vehicle_noise``: the
    operator's --vehicle-noise; ``track``: its tracks' ``los_sigma_bias_deg``; ``attitude_bias_deg``: the global
    option, its tracks stating none) and ``stated_deg``, what its newest track stated (None: nothing)."""

    deg: float
    source: str
    stated_deg: float | None


_BIAS_SOURCE_TEXT = {
    "vehicle_noise": "from --vehicle-noise",
    "track": "stated by its tracks (los_sigma_bias_deg)",
    "attitude_bias_deg": "from --attitude-bias-deg (its tracks state none: a daemon before los_sigma_bias_deg)",
}


def bias_named(vehicle_noise: Iterable[tuple[str, dict[str, float]]]) -> list[str]:
    """The vehicles whose attitude-bias prior the operator gave (``--vehicle-noise NAME:attitude_bias_deg=..``, as
    the option parses): their tracks' own does not replace it."""
    return [name for name, values in vehicle_noise if "attitude_bias_deg" in values]


class BiasPriors:
    """The attitude-bias prior of each vehicle heard (:meth:`take`), set on ``tracker`` as its own noise model where
    its tracks give it; ``named``: :func:`bias_named`'s vehicles."""

    def __init__(self, tracker: FleetTracker, named: Collection[str] = ()) -> None:
        self.tracker = tracker
        self.named = frozenset(named)
        self._priors: dict[str, BiasPrior] = {}
        self._apart_warned: set[str] = set()

    def take(self, vehicle: str, stated_deg: float | None) -> None:
        """Set ``vehicle``'s attitude-bias prior from its newest ray's track (module docstring, "Noise"): the
        operator's ``--vehicle-noise NAME:attitude_bias_deg=..`` where given (WARNING once when the track states one
        more than :data:`BIAS_APART_FACTOR` apart), else what the track states, else ``--attitude-bias-deg``.  Said at
        INFO for each vehicle when first set and whenever it changes (a daemon restarted with another setting)."""
        configured = noise_for(self.tracker.configured_noise, vehicle)
        option_deg = math.degrees(configured.attitude_bias_sigma_rad)
        if vehicle in self.named:
            prior = BiasPrior(option_deg, "vehicle_noise", stated_deg)
            if stated_deg is not None and vehicle not in self._apart_warned:
                low, high = sorted((stated_deg, option_deg))
                if high > BIAS_APART_FACTOR * low:
                    self._apart_warned.add(vehicle)
                    log.warning(
                        "%s: its tracks state an attitude-bias sigma of %.3g deg (its daemon's "
                        "estimator.attitude_bias_sigma_deg), --vehicle-noise %s:attitude_bias_deg=%g says %g deg: the "
                        "option's is used; one of them is not this vehicle's attitude (correct the daemon's setting, "
                        "or drop the option to take the track's)",
                        vehicle,
                        stated_deg,
                        vehicle,
                        option_deg,
                        option_deg,
                    )
        elif stated_deg is not None:
            prior = BiasPrior(stated_deg, "track", stated_deg)
        else:
            prior = BiasPrior(option_deg, "attitude_bias_deg", None)
        last = self._priors.get(vehicle)
        self._priors[vehicle] = prior
        if last is not None and (last.deg, last.source) == (prior.deg, prior.source):
            return
        if prior.source == "track":
            own = dataclasses.replace(configured, attitude_bias_sigma_rad=math.radians(prior.deg))
            self.tracker.set_vehicle_noise(vehicle, own)
        else:
            self.tracker.set_vehicle_noise(vehicle, None)
        log.info("%s: attitude-bias prior %.3g deg, %s", vehicle, prior.deg, _BIAS_SOURCE_TEXT[prior.source])

    def forget(self, vehicle: str) -> None:
        """``vehicle`` is forgotten by the fusion: its prior, its warning and its own noise model with it."""
        self._priors.pop(vehicle, None)
        self._apart_warned.discard(vehicle)
        self.tracker.set_vehicle_noise(vehicle, None)

    def status(self) -> dict[str, dict]:
        """The status's ``attitude_bias_prior``: each vehicle's ``{deg, source, stated_deg}``."""
        return {
            v: {"deg": round(p.deg, 4), "source": p.source, "stated_deg": p.stated_deg}
            for v, p in sorted(self._priors.items())
        }
