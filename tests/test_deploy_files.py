"""Deployment files, checked without a container engine (none runs on our machines).

Dockerfile: parsed into instructions (continuations, flags, exec/JSON forms) and checked against
what the issue asks.  .dockerignore: Docker's matching rules (last matching pattern wins, a
pattern matching a parent directory matches its contents, ``**``) re-implemented for the patterns
we use, so every COPY source is known to reach the build context.  compose.yaml,
onboard.container.yaml, zenoh-router.json5 and deploy/README.md: loaded with the same libraries
that consume them (yaml, onboard.app.config, zenoh, configparser) and checked for agreement with each
other.  Two loopback tests run real zenoh sessions: the router file relaying between sessions set
up as the daemon and the simulator are, and the README's TLS example (certificates from the
README's own script).
"""

from __future__ import annotations

import configparser
import dataclasses
import importlib.metadata
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from groundsim.io.ports import free_tcp_port

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
DOCKERFILE = REPO / "Dockerfile"
DOCKERIGNORE = REPO / ".dockerignore"
COMPOSE = DEPLOY / "compose.yaml"
CONTAINER_CONFIG = DEPLOY / "onboard.container.yaml"
ROUTER_JSON5 = DEPLOY / "zenoh-router.json5"
DEPLOY_README = DEPLOY / "README.md"

IMAGE_WORKDIR = "/opt/irtrack"
DELIVERY_TIMEOUT_S = 8.0  # zenoh peers meet through gossip in ~0.1-1.5 s on loopback
SUBPROCESS_TIMEOUT_S = 60.0
INTRINSICS_ATOL_PX = 1e-9  # the container file copies the scenario's numbers
MOUNT_ATOL = 1e-12  # quaternion components / metres, same numbers through the same function


# ============================================================================ Dockerfile parsing


@dataclass(frozen=True)
class Instruction:
    keyword: str  # upper case
    flags: tuple[str, ...]  # leading --name=value options
    args: str  # the rest, continuation lines joined
    line: int  # 1-based line of the keyword


def parse_dockerfile(text: str) -> list[Instruction]:
    """Instructions of a Dockerfile: comments and parser directives dropped, ``\\`` continuations
    joined (comment lines inside a continuation are skipped, as BuildKit does)."""
    out: list[Instruction] = []
    buf: list[str] = []
    start = 0
    for n, raw in enumerate(text.splitlines(), 1):
        stripped = raw.strip()
        if stripped.startswith("#") or (not stripped and not buf):
            continue
        if not buf:
            start = n
        if stripped.endswith("\\"):
            buf.append(stripped[:-1].strip())
            continue
        buf.append(stripped)
        joined = " ".join(p for p in buf if p)
        buf = []
        keyword, _, rest = joined.partition(" ")
        flags = []
        rest = rest.strip()
        while rest.startswith("--"):
            flag, _, rest = rest.partition(" ")
            flags.append(flag)
            rest = rest.strip()
        out.append(Instruction(keyword.upper(), tuple(flags), rest, start))
    assert not buf, "Dockerfile ends inside a line continuation"
    return out


def exec_form(args: str) -> list[str]:
    """The JSON array of an exec-form instruction (fails the test when it is shell form)."""
    value = json.loads(args)
    assert isinstance(value, list) and all(isinstance(x, str) for x in value), args
    return value


def env_of(instrs: list[Instruction]) -> dict[str, str]:
    env: dict[str, str] = {}
    for ins in instrs:
        if ins.keyword == "ENV":
            for token in shlex.split(ins.args):
                key, sep, value = token.partition("=")
                assert sep, f"ENV line {ins.line}: use KEY=VALUE, got {token!r}"
                env[key] = value
    return env


@pytest.fixture(scope="module")
def instructions() -> list[Instruction]:
    return parse_dockerfile(DOCKERFILE.read_text(encoding="utf-8"))


def _one(instrs: list[Instruction], keyword: str) -> Instruction:
    found = [i for i in instrs if i.keyword == keyword]
    assert len(found) == 1, f"expected exactly one {keyword}, found {len(found)}"
    return found[0]


def test_parser_on_a_tricky_sample():
    sample = (
        "# syntax=docker/dockerfile:1\n"
        "FROM python:3.11-slim AS base\n"
        "RUN --mount=type=cache,target=/x \\\n"
        "    echo a \\\n"
        "# a comment inside the continuation\n"
        " && echo b\n"
        "\n"
        'HEALTHCHECK --interval=5s CMD ["true"]\n'
    )
    got = parse_dockerfile(sample)
    assert [i.keyword for i in got] == ["FROM", "RUN", "HEALTHCHECK"]
    assert got[1].flags == ("--mount=type=cache,target=/x",)
    assert got[1].args == "echo a && echo b"
    assert got[1].line == 3
    assert got[2].flags == ("--interval=5s",) and got[2].args == 'CMD ["true"]'


def test_base_is_python_311_slim(instructions):
    froms = [i for i in instructions if i.keyword == "FROM"]
    assert froms, "no FROM"
    assert instructions[0].keyword == "FROM"
    image = froms[-1].args.split()[0]
    assert re.fullmatch(r"python:3\.11-slim(-bookworm)?", image), image


def test_user_created_with_fixed_uid_and_used(instructions):
    commands = [c.strip() for i in instructions if i.keyword == "RUN" for c in i.args.split("&&")]
    useradd = [shlex.split(c) for c in commands if c.startswith("useradd ")]
    groupadd = [shlex.split(c) for c in commands if c.startswith("groupadd ")]
    assert len(useradd) == 1 and len(groupadd) == 1, "one useradd and one groupadd"
    user_cmd, group_cmd = useradd[0], groupadd[0]
    uid = user_cmd[user_cmd.index("--uid") + 1]
    gid = group_cmd[group_cmd.index("--gid") + 1]
    assert uid.isdigit() and gid.isdigit(), "literal (fixed) ids"
    assert int(uid) >= 1000 and int(gid) >= 1000, "outside the system range"
    user_name, group_name = user_cmd[-1], group_cmd[-1]
    assert user_cmd[user_cmd.index("--gid") + 1] in (gid, group_name)
    users = [i for i in instructions if i.keyword == "USER"]
    assert users, "no USER instruction: the image would run as root"
    last = users[-1].args.strip()
    user, _, group = last.partition(":")
    assert user not in ("root", "0"), last
    assert user in (uid, user_name), f"USER {last} is not the created user ({user_name}, uid {uid})"
    assert group in ("", gid, group_name), last
    # the last USER precedes the entry point and follows every RUN (installs run as root)
    idx = instructions.index(users[-1])
    assert all(instructions.index(i) < idx for i in instructions if i.keyword == "RUN")
    assert idx < instructions.index(_one(instructions, "ENTRYPOINT"))


def test_user_can_open_serial_ports(instructions):
    runs = " ".join(i.args for i in instructions if i.keyword == "RUN")
    assert re.search(r"useradd\b[^&;]*--groups\s+dialout", runs), "the user belongs to dialout (serial autopilots)"
    # `USER uid:gid` gives the process only that group (Docker's USER reference; runc's GetExecUser fills the
    # supplementary groups from /etc/group only when no group is named): the membership above would be lost.
    last = [i for i in instructions if i.keyword == "USER"][-1].args.strip()
    assert ":" not in last, f"USER {last} names a group, which drops the user's supplementary groups (dialout)"


def test_entrypoint_and_cmd_are_exec_form(instructions):
    entry = exec_form(_one(instructions, "ENTRYPOINT").args)
    assert entry[:3] == ["python", "-m", "onboard"]
    cmd = exec_form(_one(instructions, "CMD").args)
    assert cmd == ["--config", "/config/onboard.yaml"]


def test_healthcheck_runs_the_probe(instructions):
    hc = _one(instructions, "HEALTHCHECK")
    kind, _, rest = hc.args.partition(" ")
    assert kind == "CMD"
    assert exec_form(rest) == ["python", "-m", "onboard.health"]
    opts = dict(f[2:].split("=", 1) for f in hc.flags)

    def seconds(text: str) -> float:
        m = re.fullmatch(r"(\d+(?:\.\d+)?)(ms|s|m)", text)
        assert m, text
        return float(m.group(1)) * {"ms": 1e-3, "s": 1.0, "m": 60.0}[m.group(2)]

    interval_s, timeout_s = seconds(opts["interval"]), seconds(opts["timeout"])
    assert timeout_s < interval_s
    assert seconds(opts["start-period"]) >= 10.0  # imports take seconds on a small ARM board
    assert int(opts["retries"]) >= 2  # one failure from a wall-clock step must not flip the state
    from onboard.app import health

    # the probe's freshness limit must exceed the interval of the daemon's touches, which is 1 s
    assert health.DEFAULT_MAX_AGE_S > 1.0


def test_env_single_threaded_and_venv_on_path(instructions):
    env = env_of(instructions)
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "OPENCV_FOR_THREADS_NUM"):
        assert env.get(name) == "1", name
    assert env["PATH"].split(":")[0] == "/opt/venv/bin"


def test_env_is_accepted_by_the_daemon_config(instructions):
    """Every IRTRACK_* variable the image sets is a known override (a typo would stop the daemon)."""
    from onboard.app.config import env_overrides
    from onboard.app.health import DEFAULT_HEALTH_FILE, HEALTH_FILE_ENV

    env = env_of(instructions)
    ours = {k: v for k, v in env.items() if k.startswith("IRTRACK_")}
    assert ours.get(HEALTH_FILE_ENV) == DEFAULT_HEALTH_FILE
    overrides = env_overrides(ours)
    assert overrides["output.health_file"][0] == DEFAULT_HEALTH_FILE


def _build_args(instrs: list[Instruction]) -> dict[str, str]:
    """``ARG NAME=default`` declarations (a default in quotes unquoted; no default -> "")."""
    out: dict[str, str] = {}
    for ins in instrs:
        if ins.keyword == "ARG":
            name, _, default = ins.args.partition("=")
            out[name.strip()] = shlex.split(default)[0] if default.strip() else ""
    return out


def _install_extras(instrs: list[Instruction], build_args: dict[str, str]) -> str:
    """The extras the image's install RUN passes to install.sh, with the build args substituted."""
    runs = [i for i in instrs if i.keyword == "RUN"]
    calls = [i for i in runs if "scripts/install.sh" in i.args]
    assert len(calls) == 1, "exactly one RUN calls scripts/install.sh"
    m = re.search(r"bash scripts/install\.sh\s+(\S+)(?:\s+(\S+))?", calls[0].args)
    assert m and m.group(1) == "/opt/venv"
    extras = m.group(2)
    if extras in (None, "&&"):
        return ""
    args = {**_build_args(instrs), **build_args}
    words = shlex.split(re.sub(r"\$\{?(\w+)\}?", lambda v: args.get(v.group(1), ""), extras))
    return words[0] if words else ""


def test_run_installs_the_onboard_runtime_only(instructions):
    """The default build installs ``pip install .`` (no extras: not sim, not dev); the one build arg
    the RUN reads selects extras for the simulator's image, and only ``sim``."""
    assert _install_extras(instructions, {}) == "", "no extras in the default (onboard) image"
    assert _install_extras(instructions, {"IRTRACK_EXTRAS": "sim"}) == "sim"
    assert set(_build_args(instructions)) <= {"IRTRACK_EXTRAS"}
    runs = [i for i in instructions if i.keyword == "RUN"]
    assert not any(re.search(r"\bpip3? install\b", i.args) for i in runs), "installs go through install.sh only"
    script = (REPO / "scripts" / "install.sh").read_text(encoding="utf-8")
    assert 'venv="${1:-.venv}"' in script and 'extras="${2:-}"' in script  # the interface relied on
    makefile = (REPO / "Makefile").read_text(encoding="utf-8")
    assert "bash scripts/install.sh $(VENV) sim,dev" in makefile, (
        "CI (make test) runs the same script, with sim and dev"
    )


def test_copy_sources_exist_and_are_only_what_install_needs(instructions):
    copies = [i for i in instructions if i.keyword in ("COPY", "ADD")]
    assert copies and all(i.keyword == "COPY" for i in copies), "COPY only (no ADD)"
    sources: list[str] = []
    for ins in copies:
        assert not any(f.startswith("--from") for f in ins.flags)
        parts = ins.args.split()
        assert len(parts) >= 2
        for src in parts[:-1]:
            assert src not in (".", "./", "*"), "never COPY the whole context"
            assert (REPO / src).exists(), f"COPY source {src} (line {ins.line}) is not in the repository"
            sources.append(src.rstrip("/"))
    assert set(sources) == {
        "pyproject.toml",
        "README.md",
        "scripts",
        "onboard",
        "groundsim",
        "bench",
        "config",
        "deploy/onboard.container.yaml",
    }
    workdir = _one(instructions, "WORKDIR").args
    assert workdir == IMAGE_WORKDIR


def test_default_config_copied_into_the_image_exists(instructions):
    """The RUN copies the stack's configuration to /config (the fallback when nothing is mounted): the image alone
    joins the router and the MAVLink endpoint on the host, which config/onboard.yaml (no zenoh peers) would not."""
    run = next(i for i in instructions if "scripts/install.sh" in i.args)
    assert "cp deploy/onboard.container.yaml /config/onboard.yaml" in run.args
    assert (REPO / "deploy" / "onboard.container.yaml").is_file(), "the image build would fail"
    assert "install -d -m 0755 -o 10001 -g 10001 /recordings" in run.args  # a volume there is the daemon's to write


# ============================================================================ .dockerignore


def _pattern_regex(pattern: str) -> re.Pattern:
    out = ""
    i = 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out += "(?:.*/)?"
            i += 3
        elif pattern.startswith("**", i):
            out += ".*"
            i += 2
        elif pattern[i] == "*":
            out += "[^/]*"
            i += 1
        elif pattern[i] == "?":
            out += "[^/]"
            i += 1
        else:
            out += re.escape(pattern[i])
            i += 1
    return re.compile(out + r"\Z")


def load_dockerignore(path: Path = DOCKERIGNORE) -> list[tuple[bool, re.Pattern]]:
    rules = []
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pat = line[1:].strip() if negate else line
        pat = os.path.normpath(pat).lstrip("/")
        rules.append((negate, _pattern_regex(pat)))
    return rules


def is_excluded(rel_path: str, rules) -> bool:
    """Docker's rule: the last pattern matching the path or one of its parent directories wins."""
    parts = rel_path.split("/")
    candidates = ["/".join(parts[: k + 1]) for k in range(len(parts))]
    excluded = False
    for negate, rx in rules:
        if any(rx.match(c) for c in candidates):
            excluded = not negate
    return excluded


def test_dockerignore_matcher_semantics():
    rules = [(False, _pattern_regex("*")), (True, _pattern_regex("src")), (False, _pattern_regex("**/__pycache__"))]
    assert is_excluded("README.md", rules)
    assert not is_excluded("src/a/b.py", rules)
    assert is_excluded("src/a/__pycache__/b.pyc", rules)
    assert is_excluded("other/src/x", rules)  # '*' matched 'other' first; 'src' is anchored


def test_dockerignore_lets_every_copied_file_in(instructions):
    rules = load_dockerignore()
    debris = re.compile(r"(^|/)(__pycache__|\.pytest_cache|\.hypothesis|[^/]*\.egg-info)(/|$)|\.pyc$")
    checked = 0
    for ins in (i for i in instructions if i.keyword == "COPY"):
        for src in ins.args.split()[:-1]:
            root = REPO / src
            files = [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file()]
            for f in files:
                rel = f.relative_to(REPO).as_posix()
                if debris.search(rel):
                    assert is_excluded(rel, rules), f"{rel} is build debris and should stay out"
                    continue
                assert not is_excluded(rel, rules), f"{rel} is COPYed but .dockerignore excludes it"
                checked += 1
    assert checked > 20
    assert any(p.suffix == ".xml" for p in (REPO / "groundsim").rglob("*.xml")), "JSBSim models expected"


@pytest.mark.parametrize(
    "rel",
    [
        ".venv/bin/python",
        ".git/HEAD",
        "tests/onboard/test_health.py",
        "deploy/tls/router.key",
        "out/truth.csv",
        "Makefile",
        "docs/scenarios.md",
        "onboard/__pycache__/health.cpython-311.pyc",
    ],
)
def test_dockerignore_keeps_the_rest_out(rel):
    assert is_excluded(rel, load_dockerignore())


# ============================================================================ compose.yaml


# load_compose, memory_bytes, expand and assert_service_hardened serve tests/test_deploy_fleet.py too: both compose files are read alike


def load_compose(path: Path) -> dict:
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    assert isinstance(data, dict) and isinstance(data.get("services"), dict)
    return data


@pytest.fixture(scope="module")
def compose() -> dict:
    return load_compose(COMPOSE)


def memory_bytes(text: str) -> int:
    m = re.fullmatch(r"(\d+)([kKmMgG])?[bB]?", str(text))
    assert m, f"memory limit {text!r}"
    return int(m.group(1)) * {None: 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30}[(m.group(2) or "").lower() or None]


def expand(value: str) -> str:
    """Compose's ${VAR:-default} with nothing set."""
    return re.sub(r"\$\{[A-Za-z_][A-Za-z0-9_]*:?-([^}]*)\}", r"\1", value)


# a daemon's memory limit leaves headroom over its measured footprint (daemon + estimator worker + fork server:
# ~400 MB PSS, deploy/README.md) and the /tmp tmpfs charged to it
DAEMON_MIN_MEMORY_BYTES = 640 << 20


def assert_service_hardened(name: str, svc: dict) -> None:
    """What every service of both stacks must have: host networking, CPU and memory limits, a read-only root with a
    /tmp tmpfs, no capabilities."""
    assert svc.get("network_mode") == "host", f"{name}: host networking (UDP MAVLink, loopback zenoh)"
    limits = svc["deploy"]["resources"]["limits"]
    assert 0.0 < float(limits["cpus"]) <= 4.0, name
    assert 32 << 20 <= memory_bytes(limits["memory"]) <= 4 << 30, name
    assert svc.get("read_only") is True and svc.get("cap_drop") == ["ALL"], name
    assert any(str(t).startswith("/tmp") for t in svc.get("tmpfs", [])), f"{name}: /tmp tmpfs on a read-only root"


def _opt(command: list[str], name: str) -> list[str]:
    return [command[k + 1] for k, a in enumerate(command[:-1]) if a == name]


def test_compose_services_host_network_and_limits(compose):
    services = compose["services"]
    assert {"onboard", "groundsim", "zenoh"} <= set(services)
    for name, svc in services.items():
        assert_service_hardened(name, svc)
    assert memory_bytes(services["onboard"]["deploy"]["resources"]["limits"]["memory"]) >= DAEMON_MIN_MEMORY_BYTES


def test_compose_builds_the_repository_dockerfile(compose, instructions):
    """The daemon's image is the onboard runtime (no extras); the simulator's is another image from
    the same Dockerfile with the ``sim`` extras (jsbsim and the plots are never in the daemon's)."""
    for name in ("onboard", "groundsim"):
        build = compose["services"][name]["build"]
        assert (DEPLOY / build["context"]).resolve() == REPO
        assert (DEPLOY / build["context"] / build["dockerfile"]).resolve() == DOCKERFILE
    onboard_args = compose["services"]["onboard"]["build"].get("args", {})
    sim_args = compose["services"]["groundsim"]["build"].get("args", {})
    assert _install_extras(instructions, onboard_args) == ""
    assert _install_extras(instructions, sim_args) == "sim"
    assert compose["services"]["onboard"]["image"] != compose["services"]["groundsim"]["image"]


def test_compose_mounts_config_read_only(compose):
    vols = compose["services"]["onboard"]["volumes"]
    config_mounts = [v for v in vols if v.split(":")[1].startswith("/config")]
    assert config_mounts, "a /config volume"
    src, dst, mode = config_mounts[0].split(":")
    assert dst == "/config/onboard.yaml" and mode == "ro"
    assert (DEPLOY / src).resolve() == CONTAINER_CONFIG
    zsrc, zdst, zmode = compose["services"]["zenoh"]["volumes"][0].split(":")
    assert (DEPLOY / zsrc).resolve() == ROUTER_JSON5 and zmode == "ro"
    assert compose["services"]["zenoh"]["command"] == ["-c", zdst]


def test_compose_groundsim_command(compose):
    sim = compose["services"]["groundsim"]
    assert sim["entrypoint"] == ["python", "-m", "groundsim"]
    cmd = sim["command"]
    assert cmd[0] == "run"
    assert _opt(cmd, "--rate") == ["realtime"]
    assert _opt(cmd, "--duration") == ["30"], "long enough for an observable 3-D track (README, Use it)"
    assert _opt(cmd, "--mavlink") == ["udpout:127.0.0.1:14540"]
    assert _opt(cmd, "--zenoh-connect") == ["tcp/127.0.0.1:7447"]
    from groundsim.world.nav_errors import resolve_nav_noise

    assert _opt(cmd, "--nav-noise") == ["RTK"] and resolve_nav_noise("RTK")  # realistic telemetry, a shipped case
    scenario = _opt(cmd, "--scenario")
    assert len(scenario) == 1 and (REPO / scenario[0]).is_file(), "scenario path relative to the image WORKDIR"
    assert sim["healthcheck"] == {"disable": True}, "the image's HEALTHCHECK is the daemon's"
    assert sim.get("profiles") == ["sim"], "never started on a vehicle by a plain `docker compose up`"
    assert "profiles" not in compose["services"]["onboard"]


def test_compose_zenoh_image_matches_the_python_binding(compose):
    tag = compose["services"]["zenoh"]["image"].rsplit(":", 1)[1]
    binding = importlib.metadata.version("eclipse-zenoh")
    assert tag.split(".")[:2] == binding.split(".")[:2], f"router {tag} vs eclipse-zenoh {binding}"


# ============================================================================ container config, cross-checks


@pytest.fixture(scope="module")
def compose_env(compose) -> dict[str, str]:
    return {k: expand(str(v)) for k, v in compose["services"]["onboard"].get("environment", {}).items()}


@pytest.fixture(scope="module")
def container_config(compose_env):
    from onboard.app.config import load_config

    return load_config(CONTAINER_CONFIG, environ=compose_env)


def test_container_config_loads_with_compose_env(container_config, instructions):
    from onboard.app.health import DEFAULT_HEALTH_FILE

    assert container_config.output.health_file == env_of(instructions)["IRTRACK_HEALTH_FILE"] == DEFAULT_HEALTH_FILE
    assert container_config.zenoh.multicast_scouting is False


@pytest.mark.subprocess
def test_daemon_accepts_the_container_config_as_the_image_runs_it(compose_env, instructions):
    """ENTRYPOINT + CMD with the mounted file's path swapped for the repository copy, compose's
    environment on top of the image's: ``--check`` validates and exits 0 without opening links."""
    entry = exec_form(_one(instructions, "ENTRYPOINT").args)
    cmd = exec_form(_one(instructions, "CMD").args)
    args = [str(CONTAINER_CONFIG) if a == "/config/onboard.yaml" else a for a in cmd]
    env = {k: v for k, v in os.environ.items() if not k.startswith("IRTRACK_")}
    env.update({k: v for k, v in env_of(instructions).items() if k.startswith("IRTRACK_")})
    env.update(compose_env)
    done = subprocess.run(
        [sys.executable, *entry[1:], *args, "--check"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=SUBPROCESS_TIMEOUT_S,
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_mavlink_ports_agree(compose, container_config):
    from onboard.io.mavlink_link import parse_connection

    sim_out = parse_connection(_opt(compose["services"]["groundsim"]["command"], "--mavlink")[0])
    daemon_in = parse_connection(container_config.mavlink.connection)
    assert (sim_out.kind, daemon_in.kind) == ("udpout", "udpin")
    assert sim_out.device.split(":")[1:] == daemon_in.device.split(":")[1:] == ["127.0.0.1", "14540"]


def test_zenoh_endpoints_agree(compose, container_config):
    import zenoh

    router = zenoh.Config.from_file(str(ROUTER_JSON5))
    router_listen = json.loads(router.get_json("listen/endpoints"))
    sim_cmd = compose["services"]["groundsim"]["command"]
    assert container_config.zenoh.connect == tuple(_opt(sim_cmd, "--zenoh-connect")) == tuple(router_listen)
    # peers must listen (on loopback) to meet: the router does not relay between peers
    assert container_config.zenoh.listen == tuple(_opt(sim_cmd, "--zenoh-listen")) == ("tcp/127.0.0.1:0",)


def test_container_camera_matches_the_sim_scenario(compose, container_config):
    """`--profile sim` flies scenario P1; the daemon must assume the same camera and mount."""
    from groundsim.world.scenario import load_scenario

    scenario = load_scenario(REPO / _opt(compose["services"]["groundsim"]["command"], "--scenario")[0])
    want_k, got_k = scenario.camera.intrinsics, container_config.camera.pinhole()
    for name in ("fx_px", "fy_px", "cx_px", "cy_px"):
        assert getattr(got_k, name) == pytest.approx(getattr(want_k, name), abs=INTRINSICS_ATOL_PX), name
    assert (got_k.width_px, got_k.height_px) == (want_k.width_px, want_k.height_px)
    assert got_k.distortion == pytest.approx(want_k.distortion, abs=INTRINSICS_ATOL_PX)
    want_m, got_m = scenario.camera.mount, container_config.camera.camera_mount()
    assert got_m.lever_arm_frd_m == pytest.approx(want_m.lever_arm_frd_m, abs=MOUNT_ATOL)
    assert got_m.q_body_from_mount == pytest.approx(want_m.q_body_from_mount, abs=MOUNT_ATOL)
    assert got_m.gimballed == want_m.gimballed == (scenario.camera.gimbal is not None)


def test_vehicle_names_agree(compose, container_config):
    sim_vehicle = _opt(compose["services"]["groundsim"]["command"], "--vehicle") or ["uav1"]  # groundsim default
    assert container_config.vehicle == sim_vehicle[0]


# ============================================================================ zenoh router file


def test_router_file_keys():
    import zenoh

    cfg = zenoh.Config.from_file(str(ROUTER_JSON5))  # zenoh's own parser and schema
    get = lambda key: json.loads(cfg.get_json(key))  # noqa: E731
    assert get("mode") == "router"
    endpoints = get("listen/endpoints")
    assert endpoints and all(ep.startswith(("tcp/127.0.0.1:", "tls/")) for ep in endpoints), endpoints
    assert get("scouting/multicast/enabled") is False
    assert get("scouting/gossip/enabled") is True
    assert get("adminspace/enabled") is False
    # zenohd enables the admin space whatever the file says: these permissions are what keeps remote sessions out
    assert get("adminspace/permissions") == {"read": False, "write": False}


def _await_delivery(pub_session, key: str, sub_session, payload: bytes) -> bool:
    got = threading.Event()
    seen: list[bytes] = []

    def on_sample(sample) -> None:
        seen.append(bytes(sample.payload.to_bytes()))
        got.set()

    sub = sub_session.declare_subscriber(key, on_sample)
    try:
        deadline = time.monotonic() + DELIVERY_TIMEOUT_S
        while not got.is_set() and time.monotonic() < deadline:  # re-put until the routes exist
            pub_session.put(key, payload)
            got.wait(0.1)
        return got.is_set() and seen[0] == payload
    finally:
        sub.undeclare()


@pytest.mark.integration
def test_router_relays_daemon_simulator_and_ground(compose, container_config):
    """The stack on loopback: router from the shipped file, the daemon's and the simulator's
    sessions built from their shipped settings, a ground client; only ports are changed."""
    import zenoh

    from onboard.io.zenoh_session import build_config, config_from_options, frame_key, status_key

    port = free_tcp_port()
    local = f"tcp/127.0.0.1:{port}"
    router_cfg = zenoh.Config.from_file(str(ROUTER_JSON5))
    router_cfg.insert_json5("listen/endpoints", json.dumps([local]))
    daemon_settings = dataclasses.replace(
        container_config.zenoh,
        connect=tuple(local if ep == "tcp/127.0.0.1:7447" else ep for ep in container_config.zenoh.connect),
    )
    sim_cmd = compose["services"]["groundsim"]["command"]
    sim_settings = config_from_options(  # as groundsim run builds it from its options (gossip as zenoh's)
        connect=tuple(local if ep == "tcp/127.0.0.1:7447" else ep for ep in _opt(sim_cmd, "--zenoh-connect")),
        listen=tuple(_opt(sim_cmd, "--zenoh-listen")),
    )
    ground_cfg = zenoh.Config()
    ground_cfg.insert_json5("mode", '"client"')
    ground_cfg.insert_json5("connect/endpoints", json.dumps([local]))
    ground_cfg.insert_json5("scouting/multicast/enabled", "false")

    sessions = []
    try:
        sessions.append(router := zenoh.open(router_cfg))
        sessions.append(daemon := zenoh.open(build_config(daemon_settings)))
        sessions.append(sim := zenoh.open(build_config(sim_settings)))
        sessions.append(ground := zenoh.open(ground_cfg))
        assert router is not None
        vehicle = container_config.vehicle
        assert _await_delivery(sim, frame_key(vehicle), daemon, b"IRF1-frame"), "simulator -> daemon frames"
        assert _await_delivery(daemon, status_key(vehicle), ground, b'{"status": 1}'), "daemon -> ground status"
    finally:
        for s in reversed(sessions):
            s.close()


# ============================================================================ README


def _fenced_blocks(lang: str) -> list[str]:
    text = DEPLOY_README.read_text(encoding="utf-8")
    return re.findall(rf"^```{re.escape(lang)}\n(.*?)^```", text, flags=re.S | re.M)


def test_readme_says_ci_runs_the_install_script():
    text = " ".join(DEPLOY_README.read_text(encoding="utf-8").split())
    assert "No container engine" in text
    assert "bash scripts/install.sh /opt/venv" in text and "CI" in text


def test_readme_json5_blocks_load_with_zenoh():
    import zenoh

    blocks = _fenced_blocks("json5")
    assert len(blocks) >= 2
    for block in blocks:
        cfg = zenoh.Config.from_json5(block)  # unknown keys / bad values raise here
        tls = json.loads(cfg.get_json("transport/link/tls"))
        assert tls["root_ca_certificate"] and tls["enable_mtls"] is True


def test_readme_mavlink_connections_parse():
    from onboard.io.mavlink_link import parse_connection

    text = DEPLOY_README.read_text(encoding="utf-8")
    found = set(re.findall(r"\b((?:serial|udpin|udpout):[^\s`'\",)]+)", text))
    assert {"serial:/dev/autopilot:921600", "udpin:127.0.0.1:14540"} <= found
    for conn in found:
        parse_connection(conn)  # raises ConfigError naming the field otherwise


def test_readme_mavlink_router_block_targets_the_daemon(container_config):
    from onboard.io.mavlink_link import parse_connection

    (block,) = _fenced_blocks("ini")
    ini = configparser.ConfigParser()
    ini.read_string(block)
    udp = [ini[s] for s in ini.sections() if s.startswith("UdpEndpoint")]
    assert len(udp) == 1 and udp[0]["Mode"] == "Normal"  # client mode: mavlink-router sends first
    daemon = parse_connection(container_config.mavlink.connection)
    assert daemon.kind == "udpin"
    assert [udp[0]["Address"], udp[0]["Port"]] == daemon.device.split(":")[1:]
    assert any(s.startswith("UartEndpoint") for s in ini.sections())


@pytest.mark.integration
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_readme_tls_example_works_on_loopback(tmp_path, container_config):
    """Certificates from the README's script; router and ground configs from its JSON5 blocks with
    only paths and ports replaced; a daemon-like peer publishes status, the ground client gets it
    over mutual TLS; without a client certificate the ground client is refused."""
    import zenoh

    from onboard.io.zenoh_session import ZenohConfig, build_config, status_key

    (script,) = _fenced_blocks("sh")
    env = {**os.environ, "VEHICLE_DNS": "localhost", "VEHICLE_IP": "127.0.0.1"}
    done = subprocess.run(
        ["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT_S
    )
    assert done.returncode == 0, done.stderr
    tls_dir = tmp_path / "tls"
    assert {p.name for p in tls_dir.iterdir()} >= {"ca.pem", "router.pem", "router.key", "ground.pem", "ground.key"}

    router_block, ground_block = _fenced_blocks("json5")[:2]
    tls_port, tcp_port = free_tcp_port(), free_tcp_port()
    router_text = (
        router_block.replace("/zenoh/tls/", f"{tls_dir}/")
        .replace("tls/0.0.0.0:7448", f"tls/127.0.0.1:{tls_port}")
        .replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{tcp_port}")
    )
    ground_text = ground_block.replace("/etc/irtrack/tls/", f"{tls_dir}/").replace(
        "tls/uav1.irtrack.lan:7448", f"tls/localhost:{tls_port}"
    )
    assert router_text != router_block and ground_text != ground_block
    ground_no_cert = zenoh.Config.from_json5(ground_text)
    ground_no_cert.insert_json5("transport/link/tls/connect_certificate", "null")
    ground_no_cert.insert_json5("transport/link/tls/connect_private_key", "null")

    sessions = []
    try:
        sessions.append(zenoh.open(zenoh.Config.from_json5(router_text)))
        daemon_settings = ZenohConfig(connect=(f"tcp/127.0.0.1:{tcp_port}",), listen=container_config.zenoh.listen)
        sessions.append(daemon := zenoh.open(build_config(daemon_settings)))
        sessions.append(ground := zenoh.open(zenoh.Config.from_json5(ground_text)))
        assert _await_delivery(daemon, status_key(container_config.vehicle), ground, b'{"tls": true}')
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            sessions.append(zenoh.open(ground_no_cert))
    finally:
        for s in reversed(sessions):
            s.close()
