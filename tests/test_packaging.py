"""Packaging: ``pip install .`` is the onboard service alone (the flight computer carries no simulator).

* pyproject: the runtime list carries none of the simulator's or the test tools' packages; the ``sim``
  and ``dev`` extras carry them; every third-party module imported anywhere under ``onboard/``
  (function-local imports included) is provided by a runtime dependency.
* ``python -m onboard --help`` / ``--check`` / ``--print-config`` and an import of every module under
  ``onboard/`` succeed in processes whose import system refuses the simulator's and the test tools'
  packages (a ``sitecustomize`` on ``PYTHONPATH`` installs a ``sys.meta_path`` finder that raises
  ModuleNotFoundError for them and records every attempt, so child processes are covered as well);
  an attempt that the code swallows still fails the test.  A control proves the refusal is active.
* The runtime list resolves to wheels for linux/aarch64 (pip's platform dry run, the glibc of the
  bookworm base image); skipped only when the package index cannot be reached, never on a
  resolution failure.
"""

from __future__ import annotations

import ast
import importlib.metadata
import json
import os
import re
import ssl
import subprocess
import sys
import textwrap
import tomllib
import urllib.error
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = REPO / "pyproject.toml"
ONBOARD = REPO / "onboard"

# what the airborne install must not carry: the simulator (and its plots) and the test tools
REFUSED = ("groundsim", "jsbsim", "matplotlib", "tqdm", "mavsdk")
SIM_DISTS = {"jsbsim", "matplotlib", "tqdm"}
DEV_DISTS = {"pytest", "hypothesis", "mavsdk", "evo", "pycocotools"}
FIRST_PARTY = {"onboard", "groundsim", "bench", "tests"}
# the one first-party import allowed under onboard/: replay --report (a desk tool) draws the eval
# report's plots with the simulator's code, lazily; the blocked-import runs below keep it out of the daemon
ALLOWED_FIRST_PARTY = {"onboard", "groundsim"}

SUBPROCESS_TIMEOUT_S = 120.0  # a guard against a hung child, not a measured property
RESOLVE_TIMEOUT_S = 900.0  # pip may download every wheel when the index serves no separate metadata
PROBE_TIMEOUT_S = 30.0

# glibc 2.36 (python:3.11-slim-bookworm, Raspberry Pi OS bookworm): every manylinux tag it runs
AARCH64_PLATFORMS = [f"manylinux_2_{minor}_aarch64" for minor in range(36, 16, -1)] + ["manylinux2014_aarch64"]
TARGET_PYTHON = "3.11"


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _req_name(req: str) -> str:
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
    assert m, req
    return _norm(m.group(1))


@pytest.fixture(scope="module")
def project() -> dict:
    return tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["project"]


def runtime_requirements(project: dict) -> list[str]:
    return list(project["dependencies"])


# ============================================================================ declared lists


def test_runtime_list_is_the_onboard_service_alone(project):
    runtime = {_req_name(r) for r in runtime_requirements(project)}
    assert runtime.isdisjoint(SIM_DISTS | DEV_DISTS), runtime & (SIM_DISTS | DEV_DISTS)
    assert {
        "numpy",
        "scipy",
        "opencv-contrib-python-headless",
        "pymavlink",
        "eclipse-zenoh",
        "pyyaml",
        "pymap3d",
        "pyserial",
        "av",
    } <= runtime
    extras = {name: {_req_name(r) for r in reqs} for name, reqs in project["optional-dependencies"].items()}
    assert SIM_DISTS <= extras["sim"]
    assert DEV_DISTS <= extras["dev"]
    assert "opencv-python" not in set().union(runtime, *extras.values()), "would shadow the contrib cv2"


def third_party_imports(source: str) -> set[str]:
    """Top-level names of every absolute import in ``source``, wherever it is (function bodies too)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != "__future__"}


def undeclared(imports: set[str], declared: set[str]) -> set[str]:
    """Imported top-level modules no declared distribution provides (first-party names aside)."""
    provided_by = importlib.metadata.packages_distributions()
    missing = set()
    for name in imports - ALLOWED_FIRST_PARTY:
        dists = {_norm(d) for d in provided_by.get(name, [])}
        if not dists & declared:
            missing.add(name)
    return missing


def test_undeclared_import_is_caught():
    """Control: the scan finds a function-local import of a package the runtime list lacks."""
    source = textwrap.dedent("""
        import os, numpy as np
        from onboard.core.frames import x
        def plot():
            import matplotlib.pyplot as plt
            from tqdm import tqdm
    """)
    imports = third_party_imports(source)
    assert imports == {"numpy", "matplotlib", "tqdm", "onboard"}
    assert undeclared(imports, {"numpy"}) == {"matplotlib", "tqdm"}


def test_every_import_under_onboard_is_a_runtime_dependency(project):
    declared = {_req_name(r) for r in runtime_requirements(project)}
    seen: dict[str, set[str]] = {}
    for path in sorted(ONBOARD.rglob("*.py")):
        for name in third_party_imports(path.read_text(encoding="utf-8")):
            seen.setdefault(name, set()).add(str(path.relative_to(REPO)))
    assert {"numpy", "cv2", "zenoh", "pymavlink"} <= set(seen), "the scan sees onboard's imports"
    missing = undeclared(set(seen), declared)
    assert not missing, {name: sorted(seen[name]) for name in missing}
    assert set(seen) & FIRST_PARTY <= ALLOWED_FIRST_PARTY, sorted(set(seen) & FIRST_PARTY)


# ============================================================================ running without the simulator


SITECUSTOMIZE = '''
"""Test harness (tests/test_packaging.py): refuse the simulator's and the test tools' packages."""
import importlib.abc
import os
import sys

_REFUSED = frozenset(os.environ["IRTRACK_TEST_REFUSED"].split(","))
_LOG = os.environ["IRTRACK_TEST_REFUSED_LOG"]


class _Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in _REFUSED:
            with open(_LOG, "a", encoding="utf-8") as f:
                f.write(f"{os.getpid()} {name}\\n")
            raise ModuleNotFoundError(f"No module named {name!r} (refused by tests/test_packaging.py)", name=name)
        return None


_already = sorted(m for m in sys.modules if m.partition(".")[0] in _REFUSED)
if _already:
    raise SystemExit(f"refused modules imported before sitecustomize: {_already}")
sys.meta_path.insert(0, _Refuse())
'''


@pytest.fixture
def refusing_env(tmp_path) -> tuple[dict[str, str], Path]:
    site_dir = tmp_path / "site"
    site_dir.mkdir()
    (site_dir / "sitecustomize.py").write_text(SITECUSTOMIZE, encoding="utf-8")
    log = tmp_path / "refused.log"
    log.touch()
    env = {k: v for k, v in os.environ.items() if not k.startswith("IRTRACK_")}
    env["PYTHONPATH"] = os.pathsep.join([str(site_dir), str(REPO)])
    env["IRTRACK_TEST_REFUSED"] = ",".join(REFUSED)
    env["IRTRACK_TEST_REFUSED_LOG"] = str(log)
    env["IRTRACK_HEALTH_FILE"] = str(tmp_path / "alive")
    return env, log


def _run(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT_S
    )


@pytest.mark.subprocess
@pytest.mark.parametrize("refused", REFUSED)
def test_control_the_refusal_is_active(refusing_env, refused):
    """Control: under the harness each refused package really fails to import (all are installed
    in the development venv, so without the harness these imports would succeed)."""
    env, log = refusing_env
    done = _run(["-c", f"import {refused}"], env)
    assert done.returncode != 0 and "refused by tests/test_packaging.py" in done.stderr, done.stderr
    assert log.read_text(encoding="utf-8").split()[1::2] == [refused]


@pytest.mark.subprocess
@pytest.mark.parametrize(
    "args",
    [
        ["--help"],
        ["--check", "--config", "config/onboard.yaml"],
        ["--check", "--config", "config/onboard_sim.yaml"],
        ["--print-config", "--config", "config/onboard.yaml"],
    ],
    ids=["help", "check", "check-sim-config", "print-config"],
)
def test_python_m_onboard_without_the_simulator(refusing_env, args):
    env, log = refusing_env
    done = _run(["-m", "onboard", *args], env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.strip(), "prints its usage / verdict / config"
    attempts = log.read_text(encoding="utf-8")
    assert attempts == "", f"python -m onboard {' '.join(args)} tried to import: {attempts}"


@pytest.mark.subprocess
def test_every_onboard_module_imports_without_the_simulator(refusing_env):
    """Import time of every module under onboard/ (desk tools included): nothing refused is touched."""
    env, log = refusing_env
    modules = sorted(
        ".".join(p.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__") for p in ONBOARD.rglob("*.py")
    )
    assert "onboard.app.service" in modules and "onboard.app.replay" in modules
    code = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module(m)\nprint(len(sys.argv) - 1)"
    done = _run(["-c", code, *modules], env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(len(modules))]
    assert log.read_text(encoding="utf-8") == "", "imported at import time: " + log.read_text(encoding="utf-8")


# ============================================================================ linux/aarch64 resolution


_CONNECTION_ERROR = re.compile(
    r"NewConnectionError|Failed to establish a new connection|Temporary failure in name resolution"
    r"|Name or service not known|Network is unreachable|No route to host|Connection refused"
    r"|ConnectTimeoutError|ProxyError|Could not fetch URL|connection broken by",
    re.I,
)


def index_unreachable(pip_output: str, probe_error: BaseException | None) -> bool:
    """True only when pip reported connection errors AND the index itself cannot be reached: a
    resolution failure with the index up (no wheel for the platform, a conflict) is never excused."""
    return probe_error is not None and bool(_CONNECTION_ERROR.search(pip_output))


def test_unreachable_index_is_told_from_a_resolution_failure():
    no_wheel = (
        "ERROR: Could not find a version that satisfies the requirement jsbsim<2,>=1.2 (from versions: none)\n"
        "ERROR: No matching distribution found for jsbsim<2,>=1.2\n"
    )
    offline = (
        "WARNING: Retrying (Retry(total=4, ...)) after connection broken by 'NewConnectionError(...: "
        "Failed to establish a new connection: [Errno -3] Temporary failure in name resolution')': /simple/numpy/\n"
        + no_wheel
    )
    down = urllib.error.URLError(OSError("Temporary failure in name resolution"))
    assert not index_unreachable(no_wheel, None)
    assert not index_unreachable(no_wheel, down), "no connection error in pip's output: a real failure"
    assert not index_unreachable(offline, None), "the index answers now: a real failure"
    assert index_unreachable(offline, down)


def _pip_config() -> dict[str, str]:
    done = subprocess.run(
        [sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT_S
    )
    out = {}
    for line in done.stdout.splitlines():
        key, sep, value = line.partition("=")
        if sep:
            out[key.split(".", 1)[-1]] = value.strip().strip("'\"")
    return out


def probe_index() -> BaseException | None:
    """None when the package index pip uses answers (its page for pip itself), else the error."""
    cfg = _pip_config()
    index = os.environ.get("PIP_INDEX_URL") or cfg.get("index-url") or "https://pypi.org/simple"
    cafile = os.environ.get("PIP_CERT") or cfg.get("cert")
    ctx = ssl.create_default_context(cafile=cafile if cafile and os.path.exists(cafile) else None)
    try:
        with urllib.request.urlopen(index.rstrip("/") + "/pip/", timeout=PROBE_TIMEOUT_S, context=ctx) as r:
            r.read(1)
    except (urllib.error.URLError, OSError) as exc:
        return exc
    return None


def _wheel_platform_ok(filename: str) -> bool:
    assert filename.endswith(".whl"), filename
    platform_tag = filename[:-4].split("-")[-1]
    return all(t == "any" or t in AARCH64_PLATFORMS for t in platform_tag.split("."))


@pytest.mark.subprocess
@pytest.mark.timeout(RESOLVE_TIMEOUT_S + 60)
def test_runtime_requirements_resolve_for_linux_aarch64(project, tmp_path):
    """``pip install --dry-run --only-binary=:all:`` of the runtime list for CPython 3.11 on
    linux/aarch64 (glibc 2.36): every requirement, and every dependency of theirs, has a wheel."""
    reqs = runtime_requirements(project)
    report = tmp_path / "report.json"
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "install",
        "--dry-run",
        "--ignore-installed",
        "--only-binary=:all:",
        "--python-version",
        TARGET_PYTHON,
        "--implementation",
        "cp",
        "--target",
        str(tmp_path / "target"),
        "--report",
        str(report),
        "--disable-pip-version-check",
        "--no-input",
    ]
    for platform in AARCH64_PLATFORMS:
        cmd += ["--platform", platform]
    done = subprocess.run([*cmd, *reqs], capture_output=True, text=True, timeout=RESOLVE_TIMEOUT_S)
    output = done.stdout + done.stderr
    if done.returncode != 0:
        if index_unreachable(output, probe_index()):
            pytest.skip("the package index cannot be reached: " + _CONNECTION_ERROR.search(output).group(0))
        pytest.fail(f"the onboard runtime does not resolve for linux/aarch64:\n{output[-4000:]}")
    installs = json.loads(report.read_text(encoding="utf-8"))["install"]
    resolved = {_norm(i["metadata"]["name"]): i["download_info"]["url"].rsplit("/", 1)[-1] for i in installs}
    assert {_req_name(r) for r in reqs} <= set(resolved), sorted({_req_name(r) for r in reqs} - set(resolved))
    wrong = {name: f for name, f in resolved.items() if not _wheel_platform_ok(f)}
    assert not wrong, f"wheels not for linux/aarch64: {wrong}"
