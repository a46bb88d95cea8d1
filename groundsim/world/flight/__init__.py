"""JSBSim flight of observer and target: a multirotor model, guidance and control, truth states.

``vehicle`` is the JSBSim adapter (:class:`FlownVehicle`, :func:`fly`); ``guidance`` is the pure
control law it runs.  Importing this package does not import or start JSBSim.
"""

from groundsim.world.flight.guidance import GuidanceGains, TrackingStats
from groundsim.world.flight.vehicle import FlightError, FlownState, FlownTrajectory, FlownVehicle, fly, fly_pair

__all__ = [
    "FlightError",
    "FlownState",
    "FlownTrajectory",
    "FlownVehicle",
    "GuidanceGains",
    "TrackingStats",
    "fly",
    "fly_pair",
]
