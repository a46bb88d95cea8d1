"""deploy/compose.fleet.yaml and config/fleet/*.yaml, checked without a container engine, as
tests/test_deploy_files.py checks compose.yaml: loaded with the libraries that consume them (yaml,
onboard.app.config, zenoh, groundsim's scenario loader) and the commands parsed by the real argparsers,
then checked for agreement: one daemon per observer of the flown scenario, its MAVLink port the one the
simulator sends that vehicle's telemetry to, every zenoh peer connecting to the router's endpoint and
listening on loopback, the fusion node fusing exactly the daemons' vehicles, each daemon's camera the
scenario's."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.test_deploy_files import (
    DAEMON_MIN_MEMORY_BYTES,
    assert_service_hardened,
    expand,
    load_compose,
    memory_bytes,
)

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
FLEET_COMPOSE = DEPLOY / "compose.fleet.yaml"
COMPOSE = DEPLOY / "compose.yaml"
ROUTER_JSON5 = DEPLOY / "zenoh-router.json5"
DAEMONS = ("uav1", "uav2")
INTRINSICS_ATOL_PX = 1e-9  # the fleet files copy the scenario's numbers
MOUNT_ATOL = 1e-12


@pytest.fixture(scope="module")
def fleet() -> dict:
    return load_compose(FLEET_COMPOSE)


@pytest.fixture(scope="module")
def daemon_configs(fleet) -> dict:
    """Each daemon service's mounted configuration file, loaded as the daemon loads it (compose's environment)."""
    from onboard.app.config import load_config

    out = {}
    for name in DAEMONS:
        svc = fleet["services"][name]
        mounts = [v.split(":") for v in svc["volumes"]]
        [(src, dst, mode)] = [m for m in mounts if m[1].startswith("/config")]
        assert dst == "/config/onboard.yaml" and mode == "ro", "the image's CMD reads /config/onboard.yaml"
        path = (DEPLOY / src).resolve()
        assert path == REPO / "config" / "fleet" / f"{name}.yaml"
        env = {k: expand(str(v)) for k, v in svc.get("environment", {}).items()}
        out[name] = load_config(path, environ=env)
    return out


@pytest.fixture(scope="module")
def sim_args(fleet):
    from groundsim.app.cli import build_parser

    svc = fleet["services"]["groundsim"]
    assert svc["entrypoint"] == ["python", "-m", "groundsim"]
    return build_parser().parse_args(svc["command"])


@pytest.fixture(scope="module")
def fuse_args(fleet):
    from onboard.app.fuse import build_parser

    svc = fleet["services"]["fuse"]
    assert svc["entrypoint"] == ["python", "-m", "onboard.fuse"]
    return build_parser().parse_args(svc["command"])


def _router_listen() -> tuple[str, ...]:
    import zenoh

    return tuple(json.loads(zenoh.Config.from_file(str(ROUTER_JSON5)).get_json("listen/endpoints")))


def test_services_host_network_hardening_and_limits(fleet):
    services = fleet["services"]
    assert set(services) == {"zenoh", *DAEMONS, "fuse", "groundsim"}
    for name, svc in services.items():
        assert_service_hardened(name, svc)
    for name in DAEMONS:  # as the single-vehicle stack's daemon
        assert memory_bytes(services[name]["deploy"]["resources"]["limits"]["memory"]) >= DAEMON_MIN_MEMORY_BYTES


def test_images_and_router_are_the_single_vehicle_stacks(fleet):
    single = load_compose(COMPOSE)["services"]
    services = fleet["services"]
    assert services["zenoh"]["image"] == single["zenoh"]["image"]
    assert services["zenoh"]["volumes"] == single["zenoh"]["volumes"]
    for name in (*DAEMONS, "fuse"):
        assert services[name]["image"] == single["onboard"]["image"], name
    assert services["groundsim"]["image"] == single["groundsim"]["image"]
    assert services["groundsim"]["build"]["args"] == single["groundsim"]["build"]["args"]
    assert services["fuse"]["healthcheck"] == services["groundsim"]["healthcheck"] == {"disable": True}


def test_daemon_configs_name_their_service_and_probe_the_image_health_file(daemon_configs):
    from onboard.app.health import DEFAULT_HEALTH_FILE

    for name, cfg in daemon_configs.items():
        assert cfg.vehicle == name
        assert cfg.output.health_file == DEFAULT_HEALTH_FILE, "the image's HEALTHCHECK probes this file"
        assert cfg.output.unobservable_positions is True
        assert cfg.zenoh.multicast_scouting is False


def test_simulator_flies_one_observer_per_daemon_to_its_mavlink_port(sim_args, daemon_configs):
    from groundsim.app.run import RateSpec, mavlink_endpoints
    from groundsim.world.scenario import load_scenario
    from onboard.io.mavlink_link import parse_connection

    scenario = load_scenario(REPO / sim_args.scenario)
    assert [o.name for o in scenario.observers] == list(DAEMONS)
    assert RateSpec.parse(sim_args.rate) == RateSpec.parse("realtime")
    assert sim_args.start_time_utc == "now", "the fusion's staleness check compares the simulated UTC with its clock"
    endpoints = dict(mavlink_endpoints(scenario, sim_args.mavlink, "uav1"))
    assert set(endpoints) == set(DAEMONS)
    for name, cfg in daemon_configs.items():
        out, into = parse_connection(endpoints[name]), parse_connection(cfg.mavlink.connection)
        assert (out.kind, into.kind) == ("udpout", "udpin")
        assert out.device.split(":")[1:] == into.device.split(":")[1:], name
        assert into.device.split(":")[1] == "127.0.0.1"
    ports = [parse_connection(endpoints[n]).device for n in DAEMONS]
    assert len(set(ports)) == len(ports), "one port per vehicle"


def test_every_zenoh_peer_meets_at_the_router(sim_args, fuse_args, daemon_configs):
    router = _router_listen()
    peers = {"groundsim": (tuple(sim_args.zenoh_connect), tuple(sim_args.zenoh_listen))}
    peers["fuse"] = (tuple(fuse_args.zenoh_connect), tuple(fuse_args.zenoh_listen))
    peers.update({n: (c.zenoh.connect, c.zenoh.listen) for n, c in daemon_configs.items()})
    for name, (connect, listen) in peers.items():
        assert connect == router, name
        # a zenoh 1.10 router does not relay between peers: each listens so that gossip can introduce them
        assert listen == ("tcp/127.0.0.1:0",), name


def test_fusion_fuses_exactly_the_daemons(fuse_args, daemon_configs):
    assert fuse_args.vehicles == [c.vehicle for c in daemon_configs.values()]


def test_daemon_cameras_match_the_scenario(sim_args, daemon_configs):
    from groundsim.world.scenario import load_scenario

    scenario = load_scenario(REPO / sim_args.scenario)
    for obs in scenario.observers:
        cfg = daemon_configs[obs.name]
        want_k, got_k = obs.camera.intrinsics, cfg.camera.pinhole()
        for name in ("fx_px", "fy_px", "cx_px", "cy_px"):
            assert getattr(got_k, name) == pytest.approx(getattr(want_k, name), abs=INTRINSICS_ATOL_PX), name
        assert (got_k.width_px, got_k.height_px) == (want_k.width_px, want_k.height_px)
        want_m, got_m = obs.camera.mount, cfg.camera.camera_mount()
        assert got_m.lever_arm_frd_m == pytest.approx(want_m.lever_arm_frd_m, abs=MOUNT_ATOL)
        assert got_m.q_body_from_mount == pytest.approx(want_m.q_body_from_mount, abs=MOUNT_ATOL)
        assert got_m.gimballed == want_m.gimballed == (obs.camera.gimbal is not None)
