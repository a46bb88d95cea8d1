"""zenoh's own message-size limit and endpoint checks (a peer may send anything).  Loopback sessions only."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from groundsim.io.ports import free_tcp_port
from onboard.app.config import build_config
from onboard.core.errors import ConfigError
from onboard.io.zenoh_session import ZenohConfig, open_session

# the loopback sessions are ``integration``; the ``--check`` runs are short-lived children with no socket
# (``subprocess``), the configuration checks in-process
pytestmark = pytest.mark.timeout(60)

LIMIT_BYTES = 1 << 20  # 1 MiB payloads allowed at the receiver
WAIT_S = 5.0
# the 8 MiB of fragments pass the loopback before the small message: ~1.5 s on an idle 2-core machine, 3-4 s with
# three busy loops beside it, and over 5 s once in a full `make test` beside two benchmarks
DELIVERY_WAIT_S = 30.0


@pytest.mark.integration
def test_the_transport_drops_a_message_over_the_receivers_limit():
    port = free_tcp_port()
    rx = open_session(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",)), max_payload_bytes=LIMIT_BYTES)
    tx = open_session(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",), connect_timeout_s=WAIT_S))
    got: list[int] = []
    small = threading.Event()

    def on_sample(sample) -> None:
        n = len(sample.payload.to_bytes())
        got.append(n)
        if n < 100:
            small.set()

    try:
        sub = rx.declare_subscriber("irtrack/test/ir/frame", on_sample)
        warm = threading.Event()
        probe = rx.declare_subscriber("irtrack/test/probe", lambda s: warm.set())
        for _ in range(50):  # wait until the route exists
            tx.put("irtrack/test/probe", b"x")
            if warm.wait(0.1):
                break
        assert warm.is_set()
        tx.put("irtrack/test/ir/frame", bytes(8 * LIMIT_BYTES))  # 8 MiB: fragmented, over the limit
        tx.put("irtrack/test/ir/frame", bytes(LIMIT_BYTES // 2))  # within it
        tx.put("irtrack/test/ir/frame", b"small")
        assert small.wait(DELIVERY_WAIT_S)
        assert LIMIT_BYTES // 2 in got and 8 * LIMIT_BYTES not in got
        sub.undeclare()
        probe.undeclare()
    finally:
        tx.close()
        rx.close()


def test_config_passes_max_frame_bytes_to_zenoh():
    cfg = build_config({"input": {"max_frame_bytes": 2_000_000}})
    from onboard.io.zenoh_session import build_config as zenoh_config

    zc = zenoh_config(cfg.zenoh, max_payload_bytes=cfg.input.max_frame_bytes)
    assert zc.get_json("transport/link/rx/max_message_size") == str(2_000_000 + 4096)


@pytest.mark.parametrize(
    "section, value, field",
    [
        ("zenoh", {"listen": ["tcp/127.0.0.1:99999"]}, "zenoh.listen[0]"),
        ("zenoh", {"connect": ["tcp/127.0.0.1:7447", "tls/host"]}, "zenoh.connect[1]"),
        ("mavlink", {"connection": "udpin:127.0.0.1:99999"}, "mavlink.connection"),
        ("video", {"destination": "127.0.0.1:99999"}, "video.destination"),
        ("video", {"destination": "127.0.0.1:0"}, "video.destination"),
    ],
)
def test_bad_ports_fail_naming_the_field(section, value, field):
    with pytest.raises(ConfigError, match=field.replace("[", r"\[").replace("]", r"\]")):
        build_config({section: value})


@pytest.mark.parametrize("endpoint", ["tcpp/127.0.0.1:7447", "serial/dev/ttyUSB0", "unixpipe/tmp/p"])
def test_a_protocol_zenoh_does_not_link_is_refused_naming_the_option(endpoint, capsys):
    """`--check` said ok and the start exited 2 ('Unicast not supported for tcpp protocol')."""
    from onboard.app.main import main

    assert main(["--check", "--zenoh-connect", endpoint]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("--zenoh-connect: zenoh.connect[0]: expected a zenoh endpoint whose protocol is one "), err
    assert err.endswith(f"got {endpoint!r}") and "unixsock-stream" in err, err
    with pytest.raises(ConfigError, match=r": listen\[0\]: expected a zenoh endpoint whose protocol"):
        ZenohConfig(listen=(endpoint,))


@pytest.mark.integration
def test_every_accepted_protocol_is_one_the_installed_zenoh_links(tmp_path):
    """The list follows the wheel's build: a protocol it lacks fails at open with 'Unicast not supported'."""
    import json

    import zenoh

    from onboard.io.zenoh_session import LINK_PROTOCOLS

    address = {"unixsock-stream": str(tmp_path / "s")}

    def refusal(protocol: str) -> str:
        conf = zenoh.Config()
        conf.insert_json5("listen/endpoints", json.dumps([f"{protocol}/{address.get(protocol, '127.0.0.1:0')}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        try:
            zenoh.open(conf).close()
        except Exception as exc:  # tls and quic: no certificate here, a refusal other than the protocol's
            return str(exc)
        return ""

    for protocol in LINK_PROTOCOLS:
        assert "not supported for" not in refusal(protocol), protocol
    assert "Unicast not supported for tcpp protocol" in refusal("tcpp")  # the control: the message looked for


@pytest.mark.subprocess
def test_check_exits_2_naming_the_port_field(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("zenoh:\n  listen: [tcp/127.0.0.1:99999]\n")
    r = subprocess.run(
        [sys.executable, "-m", "onboard", "--config", str(cfg), "--check"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 2
    assert "zenoh.listen[0]" in r.stderr and "99999" in r.stderr


@pytest.mark.subprocess
@pytest.mark.parametrize("content", [None, "{ not json5"])
def test_check_reads_the_zenoh_config_file_naming_its_field(tmp_path, content):
    zc = tmp_path / "zenoh.json5"
    if content is not None:
        zc.write_text(content)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"zenoh:\n  config_file: {zc}\n")
    r = subprocess.run(
        [sys.executable, "-m", "onboard", "--config", str(cfg), "--check"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.startswith(f"{cfg}: zenoh.config_file {zc}: "), r.stderr
    assert ("no such file" in r.stderr) == (content is None)
    zc.write_text("{}")
    ok = subprocess.run(
        [sys.executable, "-m", "onboard", "--config", str(cfg), "--check"], capture_output=True, text=True, timeout=60
    )
    assert ok.returncode == 0 and ok.stdout.startswith(f"{cfg}: ok (every field, zenoh config"), ok.stdout + ok.stderr


def test_a_zenoh_config_file_that_is_a_folder_is_called_one():
    from onboard.io.zenoh_session import ZenohConfig, ZenohConfigError, build_config

    with pytest.raises(ZenohConfigError, match=r"/tmp: a folder, not a file$"):
        build_config(ZenohConfig(config_file="/tmp"))


@pytest.mark.integration
def test_a_session_that_cannot_open_names_its_endpoints():
    from onboard.io.zenoh_session import ZenohSessionError

    with pytest.raises(ZenohSessionError, match=r"^zenoh: cannot open session \(listen tcp/999\.1\.1\.1:7447\): "):
        open_session(ZenohConfig(listen=("tcp/999.1.1.1:7447",)))
