"""Zenoh plumbing on 127.0.0.1: frames arrive byte-exact; options and errors are typed."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from groundsim.io.ports import free_tcp_port
from groundsim.io.zenoh_video import FramePublisher
from onboard.core.errors import ConfigError, IrtrackError
from onboard.core.irframe import IrFrame, decode_irframe, encode_irframe
from onboard.core.schema import SchemaError
from onboard.io.zenoh_session import (
    ZenohConfig,
    ZenohConfigError,
    ZenohSessionError,
    build_config,
    check_vehicle_name,
    config_from_options,
    frame_key,
    open_session,
    status_key,
    track_key,
)

pytestmark = pytest.mark.timeout(30)

DELIVERY_TIMEOUT_S = 10.0  # a frame must cross the loopback within this


def _frame(seq: int, h=512, w=640) -> IrFrame:
    rng = np.random.default_rng(seq)
    return IrFrame(
        seq=seq, time_boot_us=1_000_000 + 40_000 * seq, pixels=rng.integers(0, 2**16, (h, w), dtype=np.uint16)
    )


@pytest.fixture
def peers():
    """A listening peer on a free loopback port and a peer that connects to it."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    listener = open_session(ZenohConfig(listen=(ep,)))
    connector = open_session(ZenohConfig(connect=(ep,)))
    try:
        yield listener, connector
    finally:
        connector.close()
        listener.close()


def _receive(session, key, n, send):
    got: list[bytes] = []
    done = threading.Event()

    def on_sample(sample):
        got.append(sample.payload.to_bytes())
        if len(got) >= n:
            done.set()

    sub = session.declare_subscriber(key, on_sample)
    try:
        deadline = time.monotonic() + DELIVERY_TIMEOUT_S
        while not done.is_set() and time.monotonic() < deadline:
            send()
            done.wait(0.05)
    finally:
        sub.undeclare()
    return got


def test_keys():
    assert frame_key() == "irtrack/uav1/ir/frame"
    assert frame_key("uav7") == "irtrack/uav7/ir/frame"
    assert track_key("a-b_c.1") == "irtrack/a-b_c.1/track"
    assert status_key() == "irtrack/uav1/status"
    for bad in ("", "a/b", "uav*", "$x", "a b", None):
        with pytest.raises(ZenohConfigError) as e:
            check_vehicle_name(bad)
        assert str(e.value) == (
            f"vehicle name must be non-empty letters, digits, '_', '.', '-' (one zenoh key chunk), got {bad!r}"
        )


@pytest.mark.integration
def test_frame_crosses_loopback_byte_exact(peers):
    listener, connector = peers
    pub = FramePublisher(listener, "uav1")
    frames = iter(_frame(i) for i in range(10_000))
    sent: dict[int, bytes] = {}

    def send():
        f = next(frames)
        sent[f.seq] = encode_irframe(f)
        assert pub.publish(f) == 32 + 640 * 512 * 2

    got = _receive(connector, frame_key("uav1"), 3, send)
    pub.close()
    assert len(got) >= 3, "no frames delivered within the timeout"
    for payload in got:
        f = decode_irframe(payload)
        assert payload == sent[f.seq]
        np.testing.assert_array_equal(f.pixels, _frame(f.seq).pixels)
    seqs = [decode_irframe(p).seq for p in got]
    assert seqs == sorted(seqs)
    assert pub.frames_published == len(sent)


@pytest.mark.integration
def test_other_vehicle_key_does_not_receive(peers):
    listener, connector = peers
    pub = FramePublisher(listener, "uav2")
    probe = listener.declare_publisher(frame_key("uav1"))
    got2 = []
    sub2 = connector.declare_subscriber(frame_key("uav2"), lambda s: got2.append(1))
    # uav1 traffic reaches a uav1 subscriber, while the uav2 subscriber hears only uav2
    got1 = _receive(connector, frame_key("uav1"), 1, lambda: probe.put(b"x"))
    assert got1 and set(got1) == {b"x"}
    assert got2 == []
    pub.publish(_frame(1, 4, 4))
    deadline = time.monotonic() + DELIVERY_TIMEOUT_S
    while not got2 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert len(got2) == 1
    sub2.undeclare()
    probe.undeclare()
    pub.close()


@pytest.mark.integration
def test_listen_port_in_use_is_a_typed_one_line_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        with pytest.raises(ZenohSessionError) as e:
            open_session(ZenohConfig(listen=(ep,)))
    msg = str(e.value)
    assert isinstance(e.value, IrtrackError)
    assert "\n" not in msg and ep in msg and "in use" in msg and ".rs" not in msg


@pytest.mark.integration
def test_unreachable_peer_does_not_fail_open_and_joins_later():
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    late = open_session(ZenohConfig(connect=(ep,)))  # nobody listening yet
    try:
        assert not late.is_closed()
        listener = open_session(ZenohConfig(listen=(ep,)))
        try:
            probe = listener.declare_publisher("irtrack/test/late")
            got = _receive(late, "irtrack/test/late", 1, lambda: probe.put(b"hello"))
            assert got and got[0] == b"hello"
        finally:
            listener.close()
    finally:
        late.close()


@pytest.mark.integration
def test_connect_timeout_makes_an_unreachable_peer_a_typed_error():
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    t0 = time.monotonic()
    with pytest.raises(ZenohSessionError) as e:
        open_session(ZenohConfig(connect=(ep,), connect_timeout_s=0.5))
    assert time.monotonic() - t0 < 10.0
    assert ep in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("field", ["connect", "listen"])
@pytest.mark.parametrize("ep", ["bogus", "tcp/", 7447])
def test_malformed_endpoint_is_a_config_error_naming_it(field, ep):
    with pytest.raises(SchemaError) as e:
        config_from_options(**{field: (ep,)})
    assert isinstance(e.value, ConfigError)
    assert str(e.value).startswith(f"--zenoh-{field}: {field}") and repr(ep) in str(e.value)


@pytest.mark.parametrize(
    "fields, option",
    [
        (dict(config_file=""), "--zenoh-config"),
        (dict(multicast_scouting="yes"), "--zenoh-multicast-scouting"),
        (dict(connect_timeout_s=-1.0), "--zenoh-connect-timeout"),
    ],
)
def test_an_invalid_option_is_named(fields, option):
    with pytest.raises(SchemaError) as e:
        config_from_options(**fields)
    assert str(e.value).startswith(f"{option}: {next(iter(fields))}: expected ")


def test_endpoint_zenoh_itself_refuses_is_a_config_error():
    with pytest.raises(ZenohConfigError) as e:
        build_config(ZenohConfig(connect=("tcp/127.0.0.1:7447#iface=eth0#x=y?",)))
    assert "--zenoh-connect" in str(e.value)


def test_options_map_onto_the_config(tmp_path):
    cfg = build_config(ZenohConfig(connect=("tcp/127.0.0.1:7001",), listen=("tcp/127.0.0.1:7002",)))
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7001"]
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7002"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    # only connecting: listens nowhere (no port opened on every interface)
    cfg = build_config(ZenohConfig(connect=("tcp/127.0.0.1:7001",)))
    assert json.loads(cfg.get_json("listen/endpoints")) == []
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(build_config(ZenohConfig(multicast_scouting=True)).get_json("scouting/multicast/enabled"))


def test_config_file_is_merged_under_the_options(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text(
        "{ // JSON5: comments and unquoted keys\n"
        '  connect: { endpoints: ["tcp/127.0.0.1:7100"] },\n'
        '  listen: { endpoints: ["tcp/127.0.0.1:7101"] },\n'
        "  scouting: { multicast: { enabled: true } } }\n"
    )
    cfg = build_config(ZenohConfig(config_file=str(f), connect=("tcp/127.0.0.1:7200",), multicast_scouting=None))
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7100", "tcp/127.0.0.1:7200"]
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7101"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is True  # the file asked for it
    cfg = build_config(ZenohConfig(config_file=str(f), multicast_scouting=False))
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False  # the option wins


@pytest.mark.parametrize(
    "name, text",
    [
        ("bad.json5", "{ mode: 'peer', scouting: { multicast: { enabled: tru"),
        ("unknown.json5", "{ modez: 1 }"),
        ("conf.txt", "{ mode: 'peer' }"),
    ],
)
def test_bad_config_file_is_a_config_error_naming_the_file(tmp_path, name, text):
    f = tmp_path / name
    f.write_text(text)
    with pytest.raises(ZenohConfigError) as e:
        build_config(ZenohConfig(config_file=str(f)))
    assert str(f) in str(e.value) and "\n" not in str(e.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(ZenohConfigError) as e:
        build_config(ZenohConfig(config_file=str(tmp_path / "nope.json5")))
    assert "no such file" in str(e.value)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (
            dict(connect=("bogus",)),
            "connect[0]: expected a zenoh endpoint <protocol>/<address>, e.g. tcp/127.0.0.1:7447, got 'bogus'",
        ),
        (
            dict(listen=("tcp/127.0.0.1:99999",)),
            "listen[0]: expected a tcp endpoint tcp/HOST:PORT with PORT in 0..65535, got 'tcp/127.0.0.1:99999'",
        ),
        (dict(connect_timeout_s=0), "connect_timeout_s: expected a number in (0, 3600] or null, got 0"),
        (dict(connect_timeout_s=float("nan")), "connect_timeout_s: expected a number in (0, 3600] or null, got nan"),
        (dict(multicast_scouting="yes"), "multicast_scouting: expected true or false or null, got 'yes'"),
    ],
)
def test_settings_validation(kwargs, message):
    with pytest.raises(SchemaError) as e:
        ZenohConfig(**kwargs)
    assert str(e.value) == f"<ZenohConfig>: {message}"


@pytest.mark.integration
def test_publish_after_close_raises(peers):
    listener, _ = peers
    pub = FramePublisher(listener)
    pub.close()
    pub.close()  # idempotent
    with pytest.raises(RuntimeError):
        pub.publish(_frame(0, 2, 2))
