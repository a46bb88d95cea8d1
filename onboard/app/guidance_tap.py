"""The daemon's observer guidance (``guidance`` section): an output tap (:class:`~onboard.app.observers.FrameObserver`)
that runs :class:`~onboard.estimation.guidance.GuidanceAdvisor` on the newest track and pose in a thread of its own,
and publishes each advised manoeuvre on ``irtrack/<vehicle>/guidance`` (JSON ``irtrack.guidance/1``).

The pipeline thread only replaces a one-slot mailbox (``on_frame``); planning (about 15 ms of CPU per update, at
most once per ``guidance.update_interval_s`` of capture time) happens in the tap's thread, so the frames never
wait for it.  Nothing is published while the target is observable with margin, nor when no manoeuvre helps: a
consumer stops following an advice at its ``valid_until_boot_us``.

In the loop (``guidance.enabled``): the service's main thread calls :meth:`GuidanceTap.setpoint_step` with the
autopilot link; :class:`~onboard.estimation.guidance.SetpointGate` decides, and the advice in force goes to the
autopilot as SET_POSITION_TARGET_LOCAL_NED at ``guidance.setpoint_rate_hz`` while the gate allows; the status
JSON's ``guidance.setpoints`` says what it does and why not.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from typing import Any

from onboard.app.config import OnboardConfig
from onboard.core.irframe import IrFrame
from onboard.estimation.guidance import Advice, GuidanceAdvisor, GuidancePlanner, SetpointGate, advice_to_json

#: what ends a stop of the setpoints (the gate latches it), in the log line and the status
RESUMES_AFTER_STOP = "until the autopilot leaves the accepting mode and re-enters it (the pilot's hand-over)"

__all__ = ["GuidanceTap", "fixed_pod_heading_warning", "make_guidance_tap", "moving_geofence_warning"]

log = logging.getLogger(__name__)

_LOST = object()  # the newest frame's track has no position: the target is lost
_UNSEEN = object()  # no frame yet


def _origin_alt_m(pose: Any) -> float:
    """The altitude (m AMSL) of the local NED origin a pose is in (0 when it carries none)."""
    origin = getattr(pose, "origin", None)
    return float(origin.alt_m) if origin is not None else 0.0


def _target_of(track: Any) -> Any:
    """What an advice is planned for: the track's target and the estimate it has of it, (track_id,
    estimate_epoch); :data:`_LOST` without a position."""
    return (track.track_id, int(getattr(track, "estimate_epoch", 0))) if track.has_position else _LOST


def reference_alt_m(pose: Any, altitude_reference: str, home_alt_amsl_m: float | None) -> float | None:
    """The height of a pose's NED origin above the guidance band's reference (``guidance.altitude_reference``):
    above home (the origin's AMSL altitude minus home's; None while the autopilot has not said where home is),
    or AMSL."""
    if altitude_reference == "amsl":
        return _origin_alt_m(pose)
    if home_alt_amsl_m is None or not math.isfinite(home_alt_amsl_m):
        return None
    return _origin_alt_m(pose) - float(home_alt_amsl_m)


def fixed_pod_heading_warning(config: OnboardConfig) -> str | None:
    """What to warn of when guidance is in the loop (``guidance.enabled``) with a fixed pod and no bound on the
    target's bearing off the commanded velocity's heading that keeps it in the camera's horizontal field of view
    (``guidance.max_los_off_heading_deg`` above half of it); None otherwise.

    The setpoints command no yaw, and an autopilot may turn the nose along the velocity (ArduCopter:
    WP_YAW_BEHAVIOR), so a manoeuvre across the line of sight can point a fixed pod away from its target.  A
    warning, not a refusal: whether the nose follows the velocity is the autopilot's setting, which the daemon
    cannot see, and the bound rules out the crossing manoeuvres that range best."""
    g, cam = config.guidance, config.camera
    if not g.enabled or cam.mount.gimballed:
        return None
    k = cam.pinhole()
    half_fov_deg = math.degrees(math.atan(min(k.cx_px, k.width_px - k.cx_px) / k.fx_px))
    if g.max_los_off_heading_deg <= half_fov_deg:
        return None
    return (
        f"guidance in the loop (guidance.enabled) with a fixed pod (camera.mount.gimballed false) and "
        f"guidance.max_los_off_heading_deg {g.max_los_off_heading_deg:g} over the camera's half horizontal field of "
        f"view ({half_fov_deg:.1f} deg): an autopilot that turns its nose along the commanded velocity "
        f"(ArduCopter: WP_YAW_BEHAVIOR) can point the pod away from the target; set "
        f"guidance.max_los_off_heading_deg <= {half_fov_deg:.1f}, or have the autopilot hold its heading"
    )


def moving_geofence_warning(config: OnboardConfig) -> str | None:
    """What to warn of when guidance is in the loop with no fixed NED origin (``pose.origin`` null): the geofence
    box (``guidance.geofence_north_m`` / ``_east_m``) is then centred on each run's first position fix, so it moves
    with wherever the daemon starts; None otherwise.  A warning, not a refusal: a box about the take-off point is
    what a field test often wants."""
    if not config.guidance.enabled or config.pose.origin is not None:
        return None
    return (
        "guidance in the loop (guidance.enabled) with no pose.origin: the geofence (guidance.geofence_north_m, "
        "geofence_east_m) is centred on this run's first position fix and moves with it from run to run; set "
        "pose.origin to fix it on the ground"
    )


class GuidanceTap:
    """Advice from the newest (track, pose), published through ``publish(bytes)`` once :meth:`attach` gave it."""

    name = "guidance"

    def __init__(
        self,
        config: OnboardConfig,
        advisor: GuidanceAdvisor,
        clock: Any = time.monotonic,
        clock_ns: Any = time.monotonic_ns,
    ) -> None:
        self.vehicle = config.vehicle
        self.in_loop = config.guidance.enabled
        # logged once each, at start
        self._warnings = [w for w in (fixed_pod_heading_warning(config), moving_geofence_warning(config)) if w]
        self.altitude_reference = config.guidance.altitude_reference
        self.home_alt_amsl_m: float | None = None  # from the autopilot link (setpoint_step), for a band above home
        self.advisor = advisor
        self._clock = clock
        self._clock_ns = clock_ns  # the clock FrameResult.received_ns is on (the daemon's frame receipt)
        self.gate = SetpointGate(config.guidance)
        self._pose: tuple[float, Any, Any] | None = None  # (clock when it came, vehicle p NED, v NED)
        # (clock until which it holds, v NED, the target it was planned for) of the advice in force
        self._advice: tuple[float, Any, Any] | None = None
        # the newest frame's target: (track_id, estimate_epoch) while it has a position, _LOST without (_UNSEEN before
        # any frame); an advice holds only for the estimate it was planned on
        self._target: Any = _UNSEEN
        self.advice_ends: dict[str, int] = {}  # advices in force ended early, by reason (status setpoints.advice_ends)
        self._ended = ""  # why the last advice in force ended early (the gate's why says it while none is in force)
        self._next_setpoint_s = -math.inf
        self.setpoints_sent = 0
        self.setpoint_errors = 0
        self._last_state = self.gate.state
        self._publish: Any = None
        # (track, pose, the tap's clock when the frame arrived), replaced whole by the pipeline thread
        self._slot: tuple[Any, Any, float] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.published = 0
        self.publish_errors = 0
        self.last_advice: Advice | None = None
        self._logged: set[str] = set()

    def attach(self, publish: Any) -> None:
        """Where the payloads go (the zenoh publisher's ``put``), once the session is open."""
        self._publish = publish

    def start(self) -> None:
        for warning in self._warnings:
            log.warning("%s", warning)
        self._thread = threading.Thread(target=self._loop, name="irtrack-guidance", daemon=True)
        self._thread.start()

    def on_received(self, frame: IrFrame, received_ns: int) -> None:
        pass

    def on_frame(self, frame: IrFrame, result: Any) -> None:  # an observers.FrameResult
        track, pose = result.track, result.pose
        # the frame's age counts from its arrival at the daemon, not from now: a frame that waited in the queue, for
        # telemetry or behind a slow pipeline carries a pose (and a target) that old, and the gate's other ages (the
        # heartbeat's, the setpoint schedule) are on this local clock too.  Its capture time is on the autopilot's
        # boot clock, which only TIMESYNC maps here; the camera-to-daemon leg before arrival is not counted (status
        # capture_to_track_ms shows it, as the heartbeat's own transport is not counted either)
        arrived = self._clock() - max(self._clock_ns() - int(result.received_ns), 0) * 1e-9
        if pose is not None and self.in_loop:  # the gate's altitude band has the planner's reference
            ref_m = reference_alt_m(pose, self.altitude_reference, self.home_alt_amsl_m)
            if ref_m is not None:
                # stamped when its newest measured position was: a pose dead-reckoned through a GNSS outage is not a
                # fresh one, and guidance.pose_timeout_s must see the outage
                measured = arrived - max(int(pose.pos_extrapolated_us), 0) * 1e-6
                self._pose = (measured, pose.body.p_ned_m - [0.0, 0.0, ref_m], pose.body.v_ned_mps)
        if track is not None:  # (a frame without a track, one refused, says nothing of the target)
            with self._lock:
                self._target = _target_of(track)
                advice = self._advice
                if advice is not None and advice[2] != self._target:
                    # the target it was planned for is lost, another one, or its estimate started again (a new
                    # estimate_epoch: a reset holds nothing from before): no manoeuvre for it
                    if self._target is _LOST:
                        # a target still measured, with a pose, whose line of sight the daemon withholds (a zoom, a
                        # camera or gimbal mismatch: the status's geometry) is not lost, nor one measured in a frame
                        # that got no pose (the telemetry stopped: a MAVLink link cut): say which
                        if track.geometry_withheld:
                            self._end_advice("geometry_withheld")
                        elif track.measurement_valid and not track.pose_valid:
                            self._end_advice("no_pose")
                        else:
                            self._end_advice("target_lost")
                    elif isinstance(advice[2], tuple) and advice[2][0] == self._target[0]:
                        self._end_advice("estimate_reset")
                    else:
                        self._end_advice("target_changed")
        if track is None or pose is None or not track.has_position:
            return
        if track.state == "coasting":
            # the target not seen in this frame, its position the estimate carried on: the advice in force runs out
            # (valid_for_s from the last frame that saw it) instead of being renewed for a target nobody sees
            return
        if not self.advisor.due(track.time_boot_us):
            return
        self._slot = (track, pose, arrived)
        self._wake.set()

    def on_status(self, data: bytes) -> None:
        pass

    def step(self, track: Any, pose: Any, frame_clock: float | None = None) -> bytes | None:
        """One update from a track and its frame's pose (``frame_clock``: the tap's clock when the frame arrived at
        the daemon, from which the advice's validity counts; None: now); the payload published (None: nothing
        advised)."""
        ref_m = reference_alt_m(pose, self.altitude_reference, self.home_alt_amsl_m)
        if ref_m is None:  # a band above home, and the autopilot has not said where home is yet
            self.advisor.skipped["no_home"] = self.advisor.skipped.get("no_home", 0) + 1
            if "no_home" not in self._logged:
                self._logged.add("no_home")
                log.info("guidance: waiting for the autopilot's home altitude (the band is above home)")
            return None
        advice = self.advisor.update(track, pose.p_cam_ned_m, pose.body.v_ned_mps, ref_m)
        for reason, n in self.advisor.skipped.items():
            if n and reason not in self._logged:  # each reason logged once; the status counts them all
                self._logged.add(reason)
                log.warning(
                    "guidance: update skipped (%s)%s",
                    reason,
                    f": {self.advisor.last_error}" if reason == "bad_input" else "",
                )
        if advice is None:
            return None
        with self._lock:
            self.last_advice = advice
        if not advice.recommended:  # a newer answer (observable, no manoeuvre helps): the one in force ends
            with self._lock:
                if self._advice is not None:
                    self._end_advice(f"answer_{advice.status}")
            return None
        start = self._clock() if frame_clock is None else frame_clock
        with self._lock:  # planned on an older frame: not if the target was lost or changed since
            target = _target_of(track)
            if self._target is _UNSEEN or target == self._target:
                self._advice = (start + advice.valid_until_s - advice.t_s, advice.v_ned_mps, target)
                self._ended = ""
        payload = json.dumps(advice_to_json(advice, self.vehicle, track.time_boot_us, self.in_loop)).encode()
        if self._publish is not None:
            try:
                self._publish(payload)
                self.published += 1
            except Exception as exc:  # noqa: BLE001 - a failed put is counted, the tap carries on
                self.publish_errors += 1
                self._log_failure_once("publish", "publish", exc)
        return payload

    def setpoint_step(self, now: float, link: Any) -> bool:
        """In the loop (``guidance.enabled``), on the main thread with the autopilot link: at most
        ``setpoint_rate_hz``, ask the gate and send the advice in force as SET_POSITION_TARGET_LOCAL_NED when it
        allows; a change of the gate's state is logged once.  True when a setpoint was written.  It also takes
        the autopilot's home altitude from the link, for a band above home (advisory too)."""
        home = None if link is None else getattr(link, "home_alt_amsl_m", None)
        if home is not None:
            self.home_alt_amsl_m = home
        if not self.in_loop or now < self._next_setpoint_s:
            return False
        # on a schedule, not a period from whenever the loop came round: each setpoint's lateness would add to the gap
        # (PX4's OFFBOARD counts a slow stream as lost); after a stall it starts again from now, without a burst
        period_s = 1.0 / self.gate.config.setpoint_rate_hz
        scheduled_s = self._next_setpoint_s + period_s
        self._next_setpoint_s = scheduled_s if scheduled_s > now else now + period_s
        try:
            return self._setpoint_step(now, link)
        except Exception as exc:  # noqa: BLE001 - the main loop must go on; counted in the status, logged once
            self.setpoint_errors += 1
            self._log_failure_once("setpoint", "setpoint step", exc)
            return False

    @property
    def next_setpoint_s(self) -> float:
        """When :meth:`setpoint_step` next has a setpoint to decide (the clock's s; inf when not in the loop): the
        main loop wakes for it."""
        return self._next_setpoint_s if self.in_loop else math.inf

    def _setpoint_step(self, now: float, link: Any) -> bool:
        connected = link is not None and getattr(link, "state", None) == "connected"
        advice = self._advice
        decision = self.gate.step(
            now,
            link_connected=connected,
            mode=None if link is None else link.autopilot_mode,
            pose=self._pose,
            advice=None if advice is None else (advice[0], advice[1]),
            ended=self._ended,
            heartbeat_age_s=math.inf if link is None else link.heartbeat_age_s(),
            gnss=None if link is None else getattr(link, "gnss", None),  # (the lockstep's stand-in has none)
        )
        if decision.state != self._last_state:
            level = logging.WARNING if decision.state == "stopped" else logging.INFO
            # a stop is latched: the operator reading it must learn what ends it, not only why it came
            latched = f"; no setpoints {RESUMES_AFTER_STOP}" if decision.state == "stopped" else ""
            log.log(
                level,
                "guidance in the loop: %s%s%s",
                decision.state,
                f" ({decision.why})" if decision.why else "",
                latched,
            )
            self._last_state = decision.state
        return self._send(decision, link)

    def _send(self, decision, link: Any) -> bool:
        """Write ``decision``'s setpoint when the gate said to send one; True when written."""
        if decision.send and decision.v_ned_mps is not None and link.send_setpoint(decision.v_ned_mps):
            self.setpoints_sent += 1
            return True
        return False

    def halt(self, link: Any) -> bool:
        """The daemon is stopping, its autopilot link still open: a zero-velocity setpoint when guidance was
        commanding the vehicle (:meth:`SetpointGate.halt`), so that it does not fly the last one on until the
        autopilot's timeout.  True when one was written; never raises."""
        if not self.in_loop or link is None:
            return False
        try:
            if self._send(self.gate.halt(self._clock()), link):
                log.info("guidance in the loop: stopped (shutdown: a zero-velocity setpoint sent)")
                return True
        except Exception as exc:  # noqa: BLE001 - the shutdown must go on
            self.setpoint_errors += 1
            self._log_failure_once("setpoint", "setpoint at shutdown", exc)
        return False

    def plan_pending(self) -> bytes | None:
        """Plan from the newest frame :meth:`on_frame` handed over, if one is waiting (the tap's thread's turn; the
        lockstep evaluation calls it in line); the payload published, as :meth:`step`."""
        slot, self._slot = self._slot, None
        return None if slot is None else self.step(*slot)

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            try:
                self.plan_pending()
            except Exception as exc:  # noqa: BLE001 - guidance must never stop the daemon
                self.advisor.skipped["error"] = self.advisor.skipped.get("error", 0) + 1
                self._log_failure_once("error", "update", exc)

    def _end_advice(self, reason: str) -> None:
        """End the advice in force early (the caller holds the lock): counted by ``reason``, the first of each
        logged, and said by the gate's why until the next advice."""
        self._advice = None
        self._ended = reason
        self.advice_ends[reason] = self.advice_ends.get(reason, 0) + 1
        if f"ended:{reason}" not in self._logged:
            self._logged.add(f"ended:{reason}")
            log.info("guidance: the advice in force ended (%s)", reason)

    def _log_failure_once(self, key: str, what: str, exc: Exception) -> None:
        """Log the first failure of ``key`` ("guidance: <what> failed: ..."); the status counts every one, and
        a failure that repeats each frame would flood the log."""
        if key not in self._logged:
            self._logged.add(key)
            log.warning("guidance: %s failed: %s: %s", what, type(exc).__name__, exc)

    def status(self) -> dict[str, Any]:
        a = self.advisor
        with self._lock:
            last = self.last_advice
        return {
            "in_loop": self.in_loop,
            "updates": a.updates,
            "advised": a.advised,
            "published": self.published,
            "publish_errors": self.publish_errors,
            "skipped": dict(a.skipped),
            "last_status": None if last is None else last.status,
            "last_manoeuvre": None if last is None else last.manoeuvre,
            "setpoints": {
                "state": self.gate.state,
                "why": self.gate.why,
                # a stop is latched: what ends it, for an operator reading the status rather than the log
                "resumes": RESUMES_AFTER_STOP if self.gate.state == "stopped" else None,
                "sent": self.setpoints_sent,
                "errors": self.setpoint_errors,
                "stops": dict(self.gate.stops),
                "advice_ends": dict(self.advice_ends),
            },
        }

    def close(self, timeout_s: float) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)


def make_guidance_tap(
    config: OnboardConfig, clock: Any = time.monotonic, clock_ns: Any = time.monotonic_ns
) -> GuidanceTap | None:
    """The tap ``config.guidance`` asks for (None when ``advise`` is off), planning with the estimator's noise
    model and spline and the camera's focal lengths; ``clock_ns``: the one frames' ``received_ns`` are on."""
    g = config.guidance
    if not g.advise:
        return None
    k = config.camera.intrinsics
    knot_s = config.estimator.sliding_config().knot_spacing_s  # the online spline's
    planner = GuidancePlanner.for_noise(g, config.estimator.noise_model(), (k.fx_px, k.fy_px), knot_s)
    return GuidanceTap(config, GuidanceAdvisor(planner), clock, clock_ns)
