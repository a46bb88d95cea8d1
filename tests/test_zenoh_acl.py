"""The zenoh access-control sample we ship in deploy/ works as written: on loopback, with generated certificates.

``deploy/zenoh-acl-certs.sh`` makes a CA and certificates for camera, daemon, ground and an
"intruder" (same CA, a name no ACL subject lists); the router runs ``deploy/zenoh-acl-router.json5``
and every node ``deploy/zenoh-acl-client.json5``, only paths and ports replaced, all in this process
on 127.0.0.1.  Shown: the camera's frames reach the daemon and the daemon's tracks and status reach
the ground; frames from the intruder, the ground or the daemon, and tracks from the intruder or the
camera, are refused; the intruder cannot read tracks; a node without a certificate cannot connect.
Control: the same router with ``access_control.enabled: false`` delivers the intruder's frames,
so the refusals above are the ACL's.

Waits are bounded: a delivery is awaited up to ``DELIVERY_TIMEOUT_S`` (re-putting until the routes
exist); a refusal is "nothing arrived while the allowed publisher's later messages did", plus
``SETTLE_S`` after them.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from groundsim.io.ports import free_tcp_port

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
ROUTER_FILE = DEPLOY / "zenoh-acl-router.json5"
CLIENT_FILE = DEPLOY / "zenoh-acl-client.json5"
CERT_SCRIPT = DEPLOY / "zenoh-acl-certs.sh"
DELIVERY_TIMEOUT_S = 10.0
SETTLE_S = 0.5
CERT_TIMEOUT_S = 60.0
VEHICLE = "uav1"
FRAME_KEY = f"irtrack/{VEHICLE}/ir/frame"
TRACK_KEY = f"irtrack/{VEHICLE}/track"
STATUS_KEY = f"irtrack/{VEHICLE}/status"
GUIDANCE_KEY = f"irtrack/{VEHICLE}/guidance"
OBJECTS_KEY = f"irtrack/{VEHICLE}/objects"

pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(120),
    pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command"),
]


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("acl") / "tls"
    env = {**os.environ, "VEHICLE_DNS": "localhost", "VEHICLE_IP": "127.0.0.1"}
    done = subprocess.run(
        ["bash", str(CERT_SCRIPT), str(out), "irtrack-intruder"],
        env=env,
        capture_output=True,
        text=True,
        timeout=CERT_TIMEOUT_S,
    )
    assert done.returncode == 0, done.stderr
    assert {p.name for p in out.iterdir()} >= {
        f"{n}.{e}" for n in ("ca", "router", "camera", "daemon", "ground", "intruder") for e in ("pem", "key")
    }
    return out


def _router_config(tls: Path, port: int, acl: bool = True):
    import zenoh

    text = (
        ROUTER_FILE.read_text(encoding="utf-8")
        .replace("/zenoh/tls/", f"{tls}/")
        .replace("tls/0.0.0.0:7448", f"tls/127.0.0.1:{port}")
    )
    cfg = zenoh.Config.from_json5(text)
    if not acl:
        cfg.insert_json5("access_control/enabled", "false")
    return cfg


def _client_config(tls: Path, port: int, node: str | None):
    """The sample client file as ``node``; ``node=None``: no client certificate at all."""
    import zenoh

    text = (
        CLIENT_FILE.read_text(encoding="utf-8")
        .replace("/config/tls/daemon.", f"/config/tls/{node or 'daemon'}.")
        .replace("/config/tls/", f"{tls}/")
        .replace("tls/uav1.irtrack.lan:7448", f"tls/localhost:{port}")
    )
    cfg = zenoh.Config.from_json5(text)
    if node is None:
        cfg.insert_json5("transport/link/tls/connect_certificate", "null")
        cfg.insert_json5("transport/link/tls/connect_private_key", "null")
    return cfg


class Inbox:
    """A subscriber that records payloads."""

    def __init__(self, session, key: str) -> None:
        self.got: list[bytes] = []
        self._cond = threading.Condition()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        with self._cond:
            self.got.append(bytes(sample.payload.to_bytes()))
            self._cond.notify_all()

    def wait_for(self, payload: bytes, republish, timeout_s: float = DELIVERY_TIMEOUT_S) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while payload not in self.got:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                republish()  # until the routes exist (subscriber declarations travel too)
                self._cond.wait(min(left, 0.1))
        return True


class Stack:
    def __init__(self, tls: Path, acl: bool = True) -> None:
        import zenoh

        self.port = free_tcp_port()
        self.sessions = []
        self.sessions.append(zenoh.open(_router_config(tls, self.port, acl)))
        # node -> its certificate; "daemon_rx" is a second session with the daemon's certificate, the
        # receiver when the daemon itself publishes (a session's own put reaches its own subscriber
        # locally, never through the router)
        certs = {
            "camera": "camera",
            "daemon": "daemon",
            "daemon_rx": "daemon",
            "ground": "ground",
            "intruder": "intruder",
        }
        self.nodes = {n: self._open(_client_config(tls, self.port, c)) for n, c in certs.items()}

    def _open(self, cfg):
        import zenoh

        s = zenoh.open(cfg)
        self.sessions.append(s)
        return s

    def close(self) -> None:
        for s in reversed(self.sessions):
            s.close()


def _refused(inbox: Inbox, allowed_pub, key: str, forbidden: dict[str, object]) -> list[bytes]:
    """Each forbidden session puts its name on ``key`` (several times, interleaved with the allowed
    publisher); returns what of theirs arrived once the allowed publisher's later message did."""
    for round_ in range(3):
        for name, session in forbidden.items():
            session.put(key, f"forbidden {name} {round_}".encode())
        marker = f"allowed {round_}".encode()
        assert inbox.wait_for(marker, lambda m=marker: allowed_pub.put(key, m)), (
            f"the allowed publisher's {marker!r} never arrived"
        )
    time.sleep(SETTLE_S)  # bounded: anything in flight from the forbidden ones has had its chance
    return [p for p in inbox.got if p.startswith(b"forbidden")]


def test_the_acl_sample_loads_and_is_what_the_readme_says():
    import zenoh

    router = zenoh.Config.from_file(str(ROUTER_FILE))
    acl = json.loads(router.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert json.loads(router.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(router.get_json("scouting/gossip/enabled")) is False  # no peer-to-peer links past the ACL
    client = zenoh.Config.from_file(str(CLIENT_FILE))
    assert json.loads(client.get_json("mode")) == "client"
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects == {"camera": ["irtrack-camera"], "daemon": ["irtrack-daemon"], "ground": ["irtrack-ground"]}
    rules = {r["id"]: r for r in acl["rules"]}
    puts = {
        p["id"]: [rules[r] for r in p["rules"] if "put" in rules[r]["messages"] and rules[r]["flows"] == ["ingress"]]
        for p in acl["policies"]
    }
    who_puts = {tuple(p["subjects"]): sorted(k for r in puts[p["id"]] for k in r["key_exprs"]) for p in acl["policies"]}
    assert who_puts == {
        ("camera",): ["irtrack/*/ir/frame"],
        ("daemon",): ["irtrack/*/guidance", "irtrack/*/objects", "irtrack/*/status", "irtrack/*/track"],
        ("ground",): [],
    }


def test_only_the_camera_publishes_frames_and_only_the_daemon_tracks(tls_dir):
    stack = Stack(tls_dir)
    try:
        n = stack.nodes
        frames = Inbox(n["daemon_rx"], FRAME_KEY)
        leaked = _refused(frames, n["camera"], FRAME_KEY, {k: n[k] for k in ("intruder", "ground", "daemon")})
        assert leaked == [], f"frames from unauthorised nodes reached the daemon: {leaked}"

        for key in (TRACK_KEY, STATUS_KEY, GUIDANCE_KEY, OBJECTS_KEY):
            tracks = Inbox(n["ground"], key)
            spy = Inbox(n["intruder"], key)  # an authenticated node no subject names reads nothing
            leaked = _refused(tracks, n["daemon"], key, {k: n[k] for k in ("intruder", "camera")})
            assert leaked == [], f"{key} from unauthorised nodes reached the ground: {leaked}"
            read = [p for p in spy.got if not p.startswith(b"forbidden intruder")]  # its own puts reach it locally
            assert read == [], f"the intruder read {key}: {read[:3]}"
        # a daemon hears another daemon's status (two daemons under one vehicle name warn name_clash), and no track
        heard = Inbox(n["daemon_rx"], STATUS_KEY)
        assert heard.wait_for(
            b"status of another daemon", lambda: n["daemon"].put(STATUS_KEY, b"status of another daemon")
        )
        tracks_heard = Inbox(n["daemon_rx"], TRACK_KEY)
        n["daemon"].put(TRACK_KEY, b"a track")
        time.sleep(SETTLE_S)
        assert tracks_heard.got == []
    finally:
        stack.close()


def test_without_the_acl_the_intruders_frames_arrive(tls_dir):
    """Control: the same stack with access_control disabled delivers the intruder's frames."""
    stack = Stack(tls_dir, acl=False)
    try:
        n = stack.nodes
        frames = Inbox(n["daemon"], FRAME_KEY)
        assert frames.wait_for(b"intruder frame", lambda: n["intruder"].put(FRAME_KEY, b"intruder frame"))
    finally:
        stack.close()


def test_a_node_without_a_certificate_cannot_connect(tls_dir):
    import zenoh

    port = free_tcp_port()
    router = zenoh.open(_router_config(tls_dir, port))
    try:
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            zenoh.open(_client_config(tls_dir, port, None)).close()
    finally:
        router.close()


def test_the_daemon_opens_its_session_from_the_sample_client_file(tls_dir, tmp_path):
    """``zenoh.config_file`` = the client sample (connect/listen left empty): the daemon's own session
    builder keeps the file's mode and TLS, adds only its receive limit, and reaches the router."""
    from onboard.io.zenoh_session import ZenohConfig, build_config

    port = free_tcp_port()
    client_file = tmp_path / "daemon.json5"
    client_file.write_text(
        CLIENT_FILE.read_text(encoding="utf-8")
        .replace("/config/tls/", f"{tls_dir}/")
        .replace("tls/uav1.irtrack.lan:7448", f"tls/localhost:{port}"),
        encoding="utf-8",
    )
    cfg = build_config(ZenohConfig(config_file=str(client_file)), max_payload_bytes=1 << 20)
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == [f"tls/localhost:{port}"]
    import zenoh

    router = zenoh.open(_router_config(tls_dir, port))
    sessions = [router]
    try:
        sessions.append(daemon := zenoh.open(cfg))
        sessions.append(ground := zenoh.open(_client_config(tls_dir, port, "ground")))
        inbox = Inbox(ground, STATUS_KEY)
        assert inbox.wait_for(b'{"acl": true}', lambda: daemon.put(STATUS_KEY, b'{"acl": true}'))
    finally:
        for s in reversed(sessions):
            s.close()
