"""The scripted autopilot's paced flight (``ScriptedAutopilot.fly_paced``), as the benchmarks fly it."""

from __future__ import annotations

import inspect
import socket
import time

from bench.onboard import SyntheticScene
from groundsim.io.scripted_autopilot import ScriptedAutopilot
from onboard.io.mavlink_wire import parse_datagram

FLIGHT_S = 0.15  # a few 50 Hz periods: the counts below hold for any number of them


def _fly(answer: bool, attitude_rate_hz: float = 50.0) -> list[str]:
    """The message types a receiver on 127.0.0.1 gets from ``fly_paced`` over ``FLIGHT_S``, in order."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.bind(("127.0.0.1", 0))
        ap = ScriptedAutopilot(rx.getsockname()[1], scene=SyntheticScene())
        try:
            ap.fly_paced(time.monotonic() + FLIGHT_S, answer=answer, attitude_rate_hz=attitude_rate_hz)
        finally:
            ap.close()
        rx.setblocking(False)
        types = []
        while True:
            try:
                data = rx.recv(65536)
            except BlockingIOError:
                return types
            types += [msg.get_type() for msg in parse_datagram(data)]
    finally:
        rx.close()


def test_fly_paced_sends_a_position_every_second_attitude():
    types = _fly(answer=False)
    n_att = types.count("ATTITUDE_QUATERNION")
    assert n_att >= 2
    assert types.count("GLOBAL_POSITION_INT") == (n_att + 1) // 2  # on the 1st, 3rd, 5th ... attitude
    assert types[:2] == ["ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT"]
    assert set(types) == {"ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT"}  # telemetry only: no heartbeat


def test_fly_paced_answering_starts_with_a_heartbeat():
    types = _fly(answer=True)
    assert types[0] == "HEARTBEAT"
    assert types.count("HEARTBEAT") == 1  # one a second (50 periods), and the flight is shorter
    assert types.count("GLOBAL_POSITION_INT") == (types.count("ATTITUDE_QUATERNION") + 1) // 2


def test_fly_paced_sends_the_attitude_at_the_rate_the_daemon_asks_for_by_default():
    """Hard-wired to 50 Hz, the benchmarks' paced telemetry was half what the daemon asks an autopilot for."""
    from onboard.app.config import OnboardConfig

    default = inspect.signature(ScriptedAutopilot.fly_paced).parameters["attitude_rate_hz"].default
    assert default == OnboardConfig().mavlink.attitude_rate_hz == 100.0
    types = _fly(answer=False, attitude_rate_hz=default)
    n_att = types.count("ATTITUDE_QUATERNION")
    assert n_att >= 10  # 0.15 s at 100 Hz: 15, less a late wake-up or two
    assert types.count("GLOBAL_POSITION_INT") == (n_att + 3) // 4  # 25 Hz: on every 4th attitude
