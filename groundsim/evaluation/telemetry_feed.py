"""The lockstep loop's telemetry: a simulated observer's state offered to the daemon's pose buffer as MAVLink
carries it (:class:`TelemetryFeed`; :func:`groundsim.evaluation.eval.run_lockstep` drives it frame by frame)."""

from __future__ import annotations

__all__ = ["ATT_RATE_HZ", "POS_RATE_HZ", "GIMBAL_RATE_HZ", "FEED_LEAD_MAX_US", "TelemetryFeed"]

ATT_RATE_HZ, POS_RATE_HZ, GIMBAL_RATE_HZ = 50.0, 25.0, 10.0  # MavlinkVehicle's default streams
#: how far past a frame the lockstep feed goes for the telemetry that brackets it (the widest bracket a lookup
#: accepts, ``pose.position_max_gap_ms``)
FEED_LEAD_MAX_US = 300_000
US_PER_S = 1_000_000


class TelemetryFeed:
    """Offers a :class:`~groundsim.world.sim.SimCore`'s observer state to a pose buffer, tick by tick, on
    MavlinkVehicle's stream schedule and with the wire's quantisation (:mod:`groundsim.evaluation.eval`'s docstring,
    "Telemetry").

    The state is what the simulated vehicle reports: the truth with the core's navigation error of
    that tick (``core.nav_error(i)``, when the core has one) applied by the same function the MAVLink
    vehicle uses, :func:`groundsim.world.nav_errors.reported_state`.  ``rates_hz``: ``(attitude, position,
    gimbal)`` -- the rates the daemon requests (``mavlink.*_rate_hz`` of its configuration), which the
    simulated vehicle honours; default MavlinkVehicle's own defaults.
    """

    def __init__(
        self,
        core,
        pose_buffer,
        gimballed: bool,
        rates_hz: tuple[float, float, float] = (ATT_RATE_HZ, POS_RATE_HZ, GIMBAL_RATE_HZ),
        gnss_outage_us: tuple[int, int] | None = None,
        body_rates: bool = False,
        gimbal_frame: str = "earth",
    ) -> None:
        self.core = core
        #: #285's frame, encoded as MavlinkVehicle encodes it (groundsim.io.vehicle_messages.gimbal_device_attitude_status)
        self.gimbal_frame = gimbal_frame
        #: feed the attitude's body rates, as the daemon's link gets them, so that a pose past the newest sample is
        #: extrapolated as in the daemon (:meth:`feed_for_rotation`); off, a lookup waits for its bracket
        self.body_rates = bool(body_rates)
        self.gnss_outage_us = gnss_outage_us
        self.pose = pose_buffer
        self.gimballed = gimballed
        self.next_tick = 0
        att_hz, pos_hz, gim_hz = (float(x) for x in rates_hz)
        self._interval_us = {"att": round(US_PER_S / att_hz), "pos": round(US_PER_S / pos_hz)}
        if gimballed:
            self._interval_us["gim"] = round(US_PER_S / gim_hz)
        self._due_us = {k: 0 for k in self._interval_us}

    @property
    def exhausted(self) -> bool:
        return self.next_tick >= self.core.tick_count

    def feed_next(self) -> None:
        """Offer the next tick's state (streams due at that tick only), encoded and decoded by
        :mod:`onboard.io.mavlink_wire` as the MAVLink vehicle and the daemon's link do (packed and parsed:
        the wire's quantisation).  The body rates are fed only with ``body_rates`` (the gimbal's are NaN on the
        simulated vehicle's wire anyway): the lockstep loop waits for the bracketing sample instead of
        extrapolating (the benchmark's accuracy tables are defined so)."""
        from groundsim.io.vehicle_messages import gimbal_device_attitude_status
        from groundsim.world.nav_errors import reported_state
        from onboard.io.mavlink_wire import (
            AttitudeQuaternion,
            GimbalDeviceAttitudeStatus,
            GlobalPositionInt,
            wire_roundtrip,
        )

        i = self.next_tick
        self.next_tick += 1
        nav_error = getattr(self.core, "nav_error", None)
        st = reported_state(self.core.vehicle_state(i), None if nav_error is None else nav_error(i))
        now = int(st["time_boot_us"])
        for name, interval in self._interval_us.items():
            if now < self._due_us[name]:
                continue
            if name == "att":
                att = AttitudeQuaternion.from_message(
                    wire_roundtrip(
                        AttitudeQuaternion(
                            now, tuple(st["q_ned_from_body"]), tuple(st["body_rates_radps"])
                        ).to_message()
                    )
                )
                if self.body_rates:
                    self.pose.add_attitude(att.time_boot_us, att.q_ned_from_body, att.omega_frd_rps)
                else:
                    self.pose.add_attitude(att.time_boot_us, att.q_ned_from_body)
            elif name == "pos":
                w = self.gnss_outage_us
                if w is not None and w[0] <= now < w[1]:  # withheld, as MavlinkVehicle does in a GNSS dropout
                    self._due_us[name] = now + interval
                    continue
                pos = GlobalPositionInt.from_message(
                    wire_roundtrip(
                        GlobalPositionInt(
                            now,
                            st["lat_deg"],
                            st["lon_deg"],
                            st["alt_amsl_m"],
                            st["alt_rel_m"],
                            tuple(st["v_ned_mps"]),
                            st["heading_rad"],
                        ).to_message()
                    )
                )
                self.pose.add_position(pos.time_boot_us, pos.lat_deg, pos.lon_deg, pos.alt_amsl_m, pos.v_ned_mps)
            elif st["q_gimbal"] is not None:
                gim = GimbalDeviceAttitudeStatus.from_message(
                    wire_roundtrip(
                        gimbal_device_attitude_status(
                            now, now, st["q_gimbal"], st["q_ned_from_body"], self.gimbal_frame
                        ).to_message()
                    )
                )
                self.pose.add_gimbal_status(gim.time_boot_us, gim.q_ref_from_gimbal, gim.reference)
            nxt = self._due_us[name] + interval
            self._due_us[name] = nxt if nxt > now else now + interval

    def feed_for(self, frame_tick: int, time_boot_us: int) -> None:
        """Feed through ``frame_tick``, then on until the pose at ``time_boot_us`` is known or will not be, at
        most ``FEED_LEAD_MAX_US`` past it (a stream that stopped, as in a GNSS dropout: the pose is
        extrapolated then, as in the daemon)."""

        def decided() -> bool:
            res = self.pose.lookup(time_boot_us)
            return res.pose is not None or not res.retry

        self._feed_until(frame_tick, time_boot_us + FEED_LEAD_MAX_US, decided)

    def feed_for_rotation(self, frame_tick: int, time_boot_us: int, wait_us: int) -> None:
        """Feed through ``frame_tick`` (a frame sent at its capture: the telemetry up to it), then the samples
        within ``wait_us`` after ``time_boot_us`` until the rotation's streams bracket it (the daemon's chain
        waiting for them, ``imaging.pose_wait_ms``)."""

        def bracketed() -> bool:
            newest = self.pose.newest_rotation_time_boot_us()
            return newest is not None and newest >= time_boot_us

        self._feed_until(frame_tick, time_boot_us + wait_us, bracketed)

    def _feed_until(self, frame_tick: int, last_us: int, done) -> None:
        """Feed through ``frame_tick``, then the ticks up to ``last_us`` until ``done()``."""
        while self.next_tick <= frame_tick and not self.exhausted:
            self.feed_next()
        while not self.exhausted and self.core.time_boot_us(self.next_tick) <= last_us:
            if done():
                return
            self.feed_next()
