"""Observer guidance in the lockstep evaluation (``groundsim eval --guidance``): the daemon's own guidance tap and
setpoint gate (:class:`onboard.app.guidance_tap.GuidanceTap`, :class:`onboard.estimation.guidance.SetpointGate`),
driven frame by frame on the scenario's clock, with the simulated vehicle behind a stand-in for the autopilot link.

Each frame the pipeline took goes to the tap as the daemon's pipeline hands it over; a frame due an update is planned
at once (the daemon plans in a thread of its own, ~15 ms later); then the tap's setpoint step, which the daemon's main
loop runs, sends what the gate allows at ``guidance.setpoint_rate_hz``.  So the advice ends as in the daemon: a newer
answer without a manoeuvre, the target lost or another one selected end it at once, and every stream ends in zero
velocity.  Each setpoint reaches the simulated vehicle's GUIDED-like mode (:mod:`groundsim.world.guided`) as the
real-time simulator's MAVLink vehicle passes one on: held for :data:`~groundsim.world.guided.GUIDED_SETPOINT_TIMEOUT_S`
unless a newer one comes.  The stand-in autopilot is always heard, reports another mode at the first step and the
accepting one from then on (the pilot's hand-over, as the real-time simulator's vehicle makes it once it has heard the
companion), and its home is the scenario's origin.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from groundsim.world.guided import GUIDED_SETPOINT_TIMEOUT_S

__all__ = ["LockstepGuidance"]

#: MAV_MODE_FLAG_SAFETY_ARMED | MAV_MODE_FLAG_CUSTOM_MODE_ENABLED (common.xml): an armed autopilot in a custom mode
_ARMED_CUSTOM = 128 | 1


class _SimulatedAutopilot:
    """The part of :class:`onboard.io.mavlink_link.MavlinkLink` the guidance tap uses, over the simulated flight."""

    state = "connected"

    def __init__(self, flight: Any, home_alt_amsl_m: float, mode: tuple[int, int, int]) -> None:
        self._flight = flight
        self.home_alt_amsl_m = home_alt_amsl_m
        self.autopilot_mode = mode
        self.t_s = -math.inf  # the scenario time of the step under way

    def heartbeat_age_s(self) -> float:
        return 0.0

    def send_setpoint(self, v_ned_mps) -> bool:
        self._flight.command_observer(self.t_s, v_ned_mps, self.t_s + GUIDED_SETPOINT_TIMEOUT_S)
        return True


class LockstepGuidance:
    """Guidance in the loop for one lockstep run: :meth:`frame` once per frame, in order; ``advices`` the
    (scenario t_s, manoeuvre) of each advice planned (a manoeuvre recommended)."""

    def __init__(self, cfg: Any, flight: Any, home_alt_amsl_m: float) -> None:
        from onboard.app.guidance_tap import make_guidance_tap

        cfg = dataclasses.replace(cfg, guidance=dataclasses.replace(cfg.guidance, enabled=True))
        self._now = -math.inf
        # each frame is handed over as it arrives (no queue, no pipeline delay): received_ns 0 on a clock_ns at 0
        tap = make_guidance_tap(cfg, clock=lambda: self._now, clock_ns=lambda: 0)
        assert tap is not None  # guidance.enabled needs guidance.advise (GuidanceConfig)
        self.tap = tap
        g = cfg.guidance
        self._accepting = (g.accept_autopilot, _ARMED_CUSTOM, g.accept_custom_mode)
        other = (g.accept_autopilot, _ARMED_CUSTOM, 0 if g.accept_custom_mode else 1)
        self.link = _SimulatedAutopilot(flight, home_alt_amsl_m, other)
        self.advices: list[tuple[float, str]] = []

    def frame(self, t_s: float, took_frame: bool, pose: Any = None, track: Any = None) -> None:
        """One frame's turn at scenario time ``t_s``: the frame (when the pipeline took it: its pose and track, either
        None) to the tap, its planning, then the setpoint step."""
        from onboard.app.observers import FrameResult

        self._now = self.link.t_s = float(t_s)
        if self.link.autopilot_mode != self._accepting:  # heard in the pilot's mode first, then handed over
            self.tap.setpoint_step(self._now, self.link)
            self.link.autopilot_mode = self._accepting
        if took_frame:
            self.tap.on_frame(None, FrameResult(0, True, pose, track, None))
        if self.tap.plan_pending() is not None and self.tap.last_advice is not None:
            self.advices.append((self._now, str(self.tap.last_advice.manoeuvre)))
        self.tap.setpoint_step(self._now, self.link)

    def summary(self, t0_s: float | None) -> dict:
        """``RunResult.guidance``: advices, the first one's time from ``t0_s`` (the first frame's), manoeuvres, the
        planner's updates and skips, setpoints sent and the gate's stops by reason."""
        a = self.tap.advisor
        return {
            "advices": len(self.advices),
            "first_advice_s": self.advices[0][0] - t0_s if self.advices and t0_s is not None else None,
            "manoeuvres": [m for _, m in self.advices],
            "updates": a.updates,
            "skipped": dict(a.skipped),
            "setpoints": self.tap.setpoints_sent,
            "stops": dict(self.tap.gate.stops),
        }
