"""The daemon's observer guidance (``guidance`` section): an output tap (:class:`~onboard.app.observers.FrameObserver`)
that runs :class:`~onboard.estimation.guidance.GuidanceAdvisor` on the newest track and pose in a thread of its own,
and publishes each advised manoeuvre on ``irtrack/<vehicle>/guidance`` (JSON ``irtrack.guidance/1``).

The pipeline thread only replaces a one-slot mailbox (``on_frame``); planning (about 15 ms of CPU per update, at
most once per ``guidance.update_interval_s`` of capture time) happens in the tap's thread, so the frames never
wait for it.  Nothing is published while the target is observable with margin, nor when no manoeuvre helps: a
consumer stops following an advice at its ``valid_until_boot_us``.
"""

from __future__ import annotations

import json
import logging
import threading
from typing import Any

from onboard.app.config import OnboardConfig
from onboard.core.irframe import IrFrame
from onboard.estimation.guidance import Advice, GuidanceAdvisor, GuidancePlanner, advice_to_json

__all__ = ["GuidanceTap", "make_guidance_tap"]

log = logging.getLogger(__name__)


class GuidanceTap:
    """Advice from the newest (track, pose), published through ``publish(bytes)`` once :meth:`attach` gave it."""

    name = "guidance"

    def __init__(self, config: OnboardConfig, advisor: GuidanceAdvisor) -> None:
        self.vehicle = config.vehicle
        self.in_loop = config.guidance.enabled
        self.advisor = advisor
        self._publish: Any = None
        self._slot: tuple[Any, Any] | None = None  # (track, pose), replaced whole by the pipeline thread
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
        self._thread = threading.Thread(target=self._loop, name="irtrack-guidance", daemon=True)
        self._thread.start()

    def on_received(self, frame: IrFrame, received_ns: int) -> None:
        pass

    def on_frame(self, frame: IrFrame, result: Any) -> None:  # an observers.FrameResult
        track, pose = result.track, result.pose
        if track is None or pose is None or not track.has_position:
            return
        if not self.advisor.due(track.time_boot_us):
            return
        self._slot = (track, pose)
        self._wake.set()

    def on_status(self, data: bytes) -> None:
        pass

    def step(self, track: Any, pose: Any) -> bytes | None:
        """One update from a track and its frame's pose; the payload published (None: nothing advised)."""
        advice = self.advisor.update(track, pose.p_cam_ned_m, pose.body.v_ned_mps)
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
        if not advice.recommended:
            return None
        payload = json.dumps(advice_to_json(advice, self.vehicle, track.time_boot_us, self.in_loop)).encode()
        if self._publish is not None:
            try:
                self._publish(payload)
                self.published += 1
            except Exception as exc:  # noqa: BLE001 - a failed put is counted, the tap carries on
                self.publish_errors += 1
                if "publish" not in self._logged:
                    self._logged.add("publish")
                    log.warning("guidance: publish failed: %s: %s", type(exc).__name__, exc)
        return payload

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            slot, self._slot = self._slot, None
            if slot is None:
                continue
            try:
                self.step(*slot)
            except Exception as exc:  # noqa: BLE001 - guidance must never stop the daemon
                self.advisor.skipped["error"] = self.advisor.skipped.get("error", 0) + 1
                if "error" not in self._logged:
                    self._logged.add("error")
                    log.warning("guidance: update failed: %s: %s", type(exc).__name__, exc)

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
        }

    def close(self, timeout_s: float) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)


def make_guidance_tap(config: OnboardConfig) -> GuidanceTap | None:
    """The tap ``config.guidance`` asks for (None when ``advise`` is off), planning with the estimator's noise
    model and spline and the camera's focal lengths."""
    g = config.guidance
    if not g.advise:
        return None
    k = config.camera.intrinsics
    knot_s = float(config.estimator.sliding.get("knot_spacing_s", 1.0))  # the online spline's (SlidingConfig)
    planner = GuidancePlanner.for_noise(g, config.estimator.noise_model(), (k.fx_px, k.fy_px), knot_s)
    return GuidanceTap(config, GuidanceAdvisor(planner))
