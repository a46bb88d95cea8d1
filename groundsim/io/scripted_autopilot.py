"""A scripted PX4-like autopilot over UDP MAVLink 2, for the tests and the latency benchmark
(``bench.onboard``): it sends what it is told, or flies a scene's observer, and answers
SET_MESSAGE_INTERVAL and TIMESYNC.  Every message goes through :mod:`onboard.io.mavlink_wire`.

Not the simulated vehicle (:mod:`groundsim.io.mavlink_vehicle`, which flies JSBSim and speaks to ground
stations): this one is driven call by call, so a test or a benchmark controls every message and its time."""

from __future__ import annotations

__all__ = ["ScriptedAutopilot"]


class ScriptedAutopilot:
    """The one scripted PX4-like autopilot of the tests and the latency benchmark: MAVLink 2 over UDP to
    ``udpout:HOST:PORT``, every message encoded by :mod:`onboard.io.mavlink_wire`.

    Sends what it is told: :meth:`heartbeat`, :meth:`attitude` (#31), :meth:`position` (#33), any typed
    wire value or pymavlink message (:meth:`send`; hostile values that the typed encoders refuse -- a NaN
    quaternion, INT32_MAX dropout sentinels -- go as raw pymavlink messages), raw bytes (:meth:`raw`,
    :meth:`junk`).  Its boot clock reads ``boot_us`` at construction.  With a ``scene`` (an object with
    ``boot_us0``, ``body(t_s) -> (p_ned_m, v_ned_mps, q_ned_from_body)``, ``body_rates_frd(t_s)`` and
    ``geodetic(p_ned_m)``, e.g. ``bench.onboard.SyntheticScene``) it flies that scene's observer:
    :meth:`attitude` / :meth:`position` without values take the scene's at ``t_us``.

    :meth:`pump` reads what arrived (kept in ``received``): SET_MESSAGE_INTERVAL is recorded in
    ``commands`` as (message id, interval us, confirmation) and answered with the next of
    ``results[message id]`` (ACCEPTED when none is scripted; None = stay silent); a TIMESYNC request is
    answered with the boot clock in ns.
    """

    def __init__(
        self,
        port: int,
        sysid: int = 1,
        compid: int = 1,
        host: str = "127.0.0.1",
        scene=None,
        boot_us: int | None = None,
        mav_type: int | None = None,
    ) -> None:
        import time

        from onboard.io.mavlink_endpoint import parse_endpoint
        from onboard.io.mavlink_wire import connect, mavlink2

        self.mav = mavlink2
        self.conn = connect(parse_endpoint(f"udpout:{host}:{port}"), sysid, compid)
        self.scene = scene
        if boot_us is None:
            boot_us = scene.boot_us0 if scene is not None else 5_000_000  # "booted" 5 s ago
        self.boot_ns = time.monotonic_ns() - int(boot_us) * 1000
        self.mav_type = mavlink2.MAV_TYPE_QUADROTOR if mav_type is None else mav_type
        self.commands: list[tuple[int, int, int]] = []
        self.results: dict[int, list[int | None]] = {}
        self.received: list = []

    # -- clock

    def boot_ns_now(self) -> int:
        import time

        return time.monotonic_ns() - self.boot_ns

    def boot_us(self) -> int:
        return self.boot_ns_now() // 1000

    # -- sending

    def as_component(self, sysid: int, compid: int) -> None:
        self.conn.mav.srcSystem, self.conn.mav.srcComponent = sysid, compid

    def send(self, value) -> None:
        """A typed value of :mod:`onboard.io.mavlink_wire` (``to_message()``) or a pymavlink message."""
        self.conn.mav.send(value.to_message() if hasattr(value, "to_message") else value)

    def heartbeat(self, mav_type: int | None = None, autopilot: int | None = None) -> None:
        from onboard.io.mavlink_wire import Heartbeat

        self.send(
            Heartbeat(
                self.mav_type if mav_type is None else mav_type,
                self.mav.MAV_AUTOPILOT_PX4 if autopilot is None else autopilot,
            )
        )

    def attitude(self, t_us: int, q=None, omega_frd_rps=None) -> None:
        """#31 at ``t_us``: ``q`` (w, x, y, z) with ``omega_frd_rps`` (default zeros), or the scene's (turned into
        the local level where the observer is, as an autopilot reports it: :mod:`onboard.core.frames`)."""
        from onboard.core.frames import quat_multiply, quat_normalize
        from onboard.io.mavlink_wire import AttitudeQuaternion

        if q is None:
            t_s = (t_us - self.scene.boot_us0) / 1e6
            p, _, q_nb = self.scene.body(t_s)
            lat_deg, lon_deg, _ = self.scene.geodetic(p)
            q = quat_normalize(quat_multiply(self._q_level_from_ned(lat_deg, lon_deg), q_nb))
            omega_frd_rps = self.scene.body_rates_frd(t_s)
        w = (0.0, 0.0, 0.0) if omega_frd_rps is None else omega_frd_rps
        self.send(AttitudeQuaternion(int(t_us), tuple(float(c) for c in q), tuple(float(c) for c in w)))

    def position(
        self, t_us: int, lat_deg=None, lon_deg=None, alt_m=None, v_ned_mps=(0.0, 0.0, 0.0), alt_rel_m: float = 0.0
    ) -> None:
        """#33 at ``t_us``: the given WGS84 position, or the scene's (its altitude above the origin as ``alt_rel_m``)."""
        from onboard.core.frames import quat_rotate
        from onboard.io.mavlink_wire import GlobalPositionInt

        if lat_deg is None:
            p, v_ned_mps, _ = self.scene.body((t_us - self.scene.boot_us0) / 1e6)
            lat_deg, lon_deg, alt_m = self.scene.geodetic(p)
            alt_rel_m = -float(p[2])
            v_ned_mps = quat_rotate(self._q_level_from_ned(lat_deg, lon_deg), v_ned_mps)
        self.send(
            GlobalPositionInt(int(t_us), lat_deg, lon_deg, alt_m, alt_rel_m, tuple(float(c) for c in v_ned_mps), 0.0)
        )

    def _q_level_from_ned(self, lat_deg: float, lon_deg: float):
        """The turn from the scene's NED into the local level at (lat, lon), where an autopilot reports."""
        from onboard.core.frames import q_ned_from_level, quat_conjugate

        return quat_conjugate(q_ned_from_level(lat_deg, lon_deg, self.scene.origin))

    def fly_paced(self, until_s: float, answer: bool = False, attitude_rate_hz: float = 100.0) -> None:
        """The scene's observer in real time until ``until_s`` (``time.monotonic``): ATTITUDE_QUATERNION at
        ``attitude_rate_hz`` (the daemon's default request, ``mavlink.attitude_rate_hz``, which a test holds this
        default to) and GLOBAL_POSITION_INT at 25 Hz (at most the attitude's rate).  With ``answer`` it also reads what came back (:meth:`pump`: the daemon's
        interval requests are answered) and sends a HEARTBEAT a second, as an autopilot does; without, it only
        sends telemetry (a receiver that parses nothing)."""
        import time

        period_s = 1.0 / attitude_rate_hz
        pos_every = max(round(attitude_rate_hz / 25.0), 1)
        heartbeat_every = max(round(attitude_rate_hz), 1)
        n, t0 = 0, time.monotonic()
        while time.monotonic() < until_s:
            if answer:
                self.pump()
                if n % heartbeat_every == 0:
                    self.heartbeat()
            t_us = self.boot_us()
            self.attitude(t_us)
            if n % pos_every == 0:
                self.position(t_us)
            n += 1
            # paced against the start, not the last wake-up, so that late wake-ups do not slow the rate
            time.sleep(max(t0 + n * period_s - time.monotonic(), 0.0))

    def raw(self, data: bytes) -> None:
        self.conn.write(data)

    def junk(self) -> None:
        """300 random bytes, then a HEARTBEAT with a broken CRC."""
        import numpy as np

        from onboard.io.mavlink_wire import Heartbeat, pack

        self.raw(np.random.default_rng(3).integers(0, 256, 300, dtype=np.uint8).tobytes())
        buf = bytearray(pack(Heartbeat(self.mav_type, self.mav.MAV_AUTOPILOT_PX4).to_message(), codec=self.conn.mav))
        buf[-1] ^= 0xFF
        self.raw(bytes(buf))

    # -- receiving

    def pump(self) -> None:
        from onboard.io.mavlink_wire import Timesync, command_ack_message

        m = self.mav
        while True:
            msg = self.conn.recv_match(blocking=False)
            if msg is None:
                return
            self.received.append(msg)
            if len(self.received) > 10_000:
                del self.received[:5_000]
            t = msg.get_type()
            if t == "COMMAND_LONG" and msg.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
                mid = int(msg.param1)
                self.commands.append((mid, int(msg.param2), msg.confirmation))
                queue = self.results.get(mid, [])
                result = queue.pop(0) if queue else m.MAV_RESULT_ACCEPTED
                if result is not None:
                    self.send(command_ack_message(msg.command, result, msg.get_srcSystem(), msg.get_srcComponent()))
            elif t == "TIMESYNC" and msg.tc1 == 0:
                self.send(Timesync(self.boot_ns_now(), msg.ts1))

    def got(self, mtype: str) -> list:
        return [msg for msg in self.received if msg.get_type() == mtype]

    def close(self) -> None:
        self.conn.close()
