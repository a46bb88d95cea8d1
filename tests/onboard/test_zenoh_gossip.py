"""The daemon's zenoh session dials only the endpoints it was given: with ``gossip_autoconnect`` off (its
default) a peer that another peer names is not dialed; with it on (zenoh's peer default, what the commands on the
ground keep) it is.  Three sessions in this process on 127.0.0.1: D (the daemon's settings, listening), Y (a peer
listening elsewhere that dials nobody itself, so that a link between D and Y is D's doing), X (connects to both, so
that its gossip tells D about Y)."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from groundsim.io.ports import free_tcp_port
from onboard.io.zenoh_session import CONNECT_RETRY, ZenohConfig, build_config, config_from_options

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

DIAL_WAIT_S = 15.0  # what zenoh takes to act on gossip here is ~1-3 s; the dialing case bounds the silent one


def _peer(listen: list[str], connect: list[str], zid: str, dials_gossip: bool = True):
    c = zenoh.Config()
    if not dials_gossip:
        c.insert_json5("scouting/gossip/autoconnect", "[]")
    c.insert_json5("mode", '"peer"')
    c.insert_json5("id", json.dumps(zid))
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def _d_dials_y_within(gossip_autoconnect: bool | None, wait_s: float) -> float | None:
    """Seconds until D has Y as a peer (None: not within ``wait_s``)."""
    d_port, y_port = free_tcp_port(), free_tcp_port()
    settings = ZenohConfig(listen=(f"tcp/127.0.0.1:{d_port}",), gossip_autoconnect=gossip_autoconnect)
    cfg = build_config(settings)
    cfg.insert_json5("id", json.dumps("ffffffffffffffffffffffffffffff0d"))
    d = zenoh.open(cfg)
    y = _peer([f"tcp/127.0.0.1:{y_port}"], [], "1", dials_gossip=False)
    x = _peer([], [f"tcp/127.0.0.1:{d_port}", f"tcp/127.0.0.1:{y_port}"], "2")
    try:
        y_zid = str(y.info.zid())
        t0 = time.monotonic()
        while time.monotonic() - t0 < wait_s:
            if y_zid in {str(z) for z in d.info.peers_zid()}:
                return time.monotonic() - t0
            time.sleep(0.05)
        return None
    finally:
        for s in (x, y, d):
            s.close()


def test_the_daemon_dials_no_peer_that_gossip_names_and_a_command_does():
    dialed_after_s = _d_dials_y_within(None, DIAL_WAIT_S)
    assert dialed_after_s is not None, "zenoh's default no longer dials gossiped peers: this test proves nothing"
    assert _d_dials_y_within(True, DIAL_WAIT_S) is not None
    assert _d_dials_y_within(False, max(10.0 * dialed_after_s, 1.0)) is None


def test_the_defaults_daemon_off_commands_as_zenoh():
    assert ZenohConfig().gossip_autoconnect is False
    assert config_from_options(connect=("tcp/127.0.0.1:7447",)).gossip_autoconnect is None


def test_shared_memory_is_off_unless_a_config_file_says(tmp_path):
    """zenoh keeps a departed peer's shared-memory segments mapped: off in every session built from settings alone;
    a zenoh config file keeps the say."""
    cfg = build_config(ZenohConfig(listen=("tcp/127.0.0.1:0",)))
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    f = tmp_path / "z.json5"
    f.write_text("{ transport: { shared_memory: { enabled: true } } }")
    assert json.loads(build_config(ZenohConfig(config_file=str(f))).get_json("transport/shared_memory/enabled")) is True


def test_a_connect_endpoint_is_dialed_again_within_a_second_unless_a_config_file_says(tmp_path):
    """zenoh's own backoff grows to 4 s between dials, so a peer that came up late was joined up to 4 s after it
    listened; sessions dial again at most a second apart, unless their config file sets its own retry."""
    cfg = build_config(ZenohConfig(connect=("tcp/127.0.0.1:7447",)))
    retry = json.loads(cfg.get_json("connect/retry"))
    assert retry["period_max_ms"] <= 1000 and retry["period_init_ms"] <= retry["period_max_ms"]
    f = tmp_path / "z.json5"
    f.write_text("{ connect: { retry: { period_init_ms: 3000, period_max_ms: 9000, period_increase_factor: 2 } } }")
    assert json.loads(build_config(ZenohConfig(config_file=str(f))).get_json("connect/retry"))["period_max_ms"] == 9000
    quiet = tmp_path / "quiet.json5"  # a file that says nothing of it (the fleet's router file, say)
    quiet.write_text("{ mode: 'peer' }")
    assert json.loads(build_config(ZenohConfig(config_file=str(quiet))).get_json("connect/retry")) == CONNECT_RETRY
