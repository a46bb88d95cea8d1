"""onboard.app.health: the liveness probe the container's HEALTHCHECK runs."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from onboard.app import health
from onboard.core.errors import ConfigError
from tests.process_helpers import run_module

REPO = Path(__file__).resolve().parents[2]
PROBE_TIMEOUT_S = 20.0  # generous: a cold interpreter on a loaded 2-core box
MTIME_ATOL_S = 0.05  # filesystem mtime granularity is far finer; this is slack for the clock read


def _run_probe(*args: str, env_file: str | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != health.HEALTH_FILE_ENV}
    if env_file is not None:
        env[health.HEALTH_FILE_ENV] = env_file
    return run_module("onboard.health", *args, timeout_s=PROBE_TIMEOUT_S, env=env)


# ----------------------------------------------------------------------------- pure verdict


@pytest.mark.parametrize(
    "age_s, alive, reason",
    [
        (0.0, True, "ok"),
        (4.9, True, "ok"),
        (5.0, True, "ok"),  # the limit itself is still alive
        (5.01, False, "stale"),
        (3600.0, False, "stale"),
        (-0.5, True, "ok"),  # a touch a little "ahead" (clock read order, coarse mtimes)
        (-1.0, True, "ok"),
        (-1.01, False, "future"),  # clock stepped back
    ],
)
def test_judge_liveness_boundaries(age_s, alive, reason):
    now_s = 1_700_000_000.0
    v = health.judge_liveness(now_s - age_s, now_s, max_age_s=5.0)
    assert v.alive is alive
    assert v.reason == reason
    assert v.age_s == pytest.approx(age_s, abs=1e-6)


def test_judge_liveness_missing_file():
    v = health.judge_liveness(None, 100.0)
    assert (v.alive, v.reason, v.age_s, v.max_age_s) == (False, "missing", None, health.DEFAULT_MAX_AGE_S)


@given(
    now_s=st.floats(min_value=0.0, max_value=4e9, allow_nan=False),
    age_s=st.floats(min_value=-1e6, max_value=1e6, allow_nan=False),
    max_age_s=st.floats(min_value=1e-3, max_value=1e4, allow_nan=False),
)
def test_judge_liveness_is_the_documented_interval(now_s, age_s, max_age_s):
    mtime_s = now_s - age_s
    v = health.judge_liveness(mtime_s, now_s, max_age_s)
    real_age_s = now_s - mtime_s  # what the function sees after rounding
    assert v.alive == (-health.FUTURE_TOLERANCE_S <= real_age_s <= max_age_s)
    assert v.age_s == real_age_s


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), True, "5"])
def test_bad_max_age_is_a_config_error_naming_it(bad):
    with pytest.raises(ConfigError, match="max_age_s"):
        health.judge_liveness(1.0, 2.0, max_age_s=bad)


@pytest.mark.parametrize("field, mtime_s, now_s", [("mtime_s", float("nan"), 1.0), ("now_s", 1.0, float("inf"))])
def test_non_finite_times_are_rejected_by_name(field, mtime_s, now_s):
    with pytest.raises(ConfigError, match=field):
        health.judge_liveness(mtime_s, now_s)


def test_liveness_rejects_contradictions():
    with pytest.raises(ValueError, match="contradicts"):
        health.Liveness(True, "stale", 9.0, 5.0)
    with pytest.raises(ValueError, match="age_s"):
        health.Liveness(False, "missing", 1.0, 5.0)


# ----------------------------------------------------------------------------- path and file


def test_health_file_path_default_env_and_empty():
    assert health.health_file_path({}) == "/tmp/irtrack-alive"
    assert health.health_file_path({"IRTRACK_HEALTH_FILE": "/run/x"}) == "/run/x"
    with pytest.raises(ConfigError, match="IRTRACK_HEALTH_FILE"):
        health.health_file_path({"IRTRACK_HEALTH_FILE": "  "})


def test_mark_alive_creates_then_refreshes(tmp_path):
    path = tmp_path / "alive"
    health.mark_alive(str(path))
    assert path.exists()
    old_s = time.time() - 60.0
    os.utime(path, (old_s, old_s))
    assert not health.check_liveness(str(path)).alive
    before_s = time.time()
    health.mark_alive(str(path))
    assert path.stat().st_mtime >= before_s - MTIME_ATOL_S
    assert health.check_liveness(str(path)).reason == "ok"


def test_mark_alive_uses_env_path(tmp_path, monkeypatch):
    path = tmp_path / "from-env"
    monkeypatch.setenv(health.HEALTH_FILE_ENV, str(path))
    health.mark_alive()
    assert path.exists()


def test_mark_alive_raises_when_directory_missing(tmp_path):
    path = str(tmp_path / "no-such-dir" / "alive")
    with pytest.raises(OSError) as e:
        health.mark_alive(path)
    # the service logs the error and reports its strerror under the path: both must say what and where
    assert (e.value.errno, e.value.strerror, e.value.filename) == (errno.ENOENT, os.strerror(errno.ENOENT), path)
    assert not os.path.exists(os.path.dirname(path))  # nothing created on the way


def test_check_liveness_uses_mtime(tmp_path):
    path = tmp_path / "alive"
    path.write_text("")
    t_s = 1_000_000.0
    os.utime(path, (t_s, t_s))
    assert health.check_liveness(str(path), 5.0, now_s=t_s + 4.0).alive
    stale = health.check_liveness(str(path), 5.0, now_s=t_s + 6.0)
    assert (stale.alive, stale.reason, stale.age_s) == (False, "stale", pytest.approx(6.0))
    assert health.check_liveness(str(tmp_path / "absent")).reason == "missing"


# ----------------------------------------------------------------------------- the probe as Docker runs it


def test_main_in_process(tmp_path, capsys):
    path = tmp_path / "alive"
    assert health.main(["--file", str(path)]) == health.EXIT_UNHEALTHY
    assert "does not exist" in capsys.readouterr().out
    health.mark_alive(str(path))
    assert health.main(["--file", str(path)]) == health.EXIT_HEALTHY
    assert capsys.readouterr().out.startswith("alive: ")


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--max-age-s", "abc"], "usage error (the daemon's liveness was not checked)"),
        (["--max-age-s", "0"], "max_age_s"),
        (["--bogus"], "usage error (the daemon's liveness was not checked)"),
        (["/var/run/irtrack-alive"], "usage error"),  # the file as a positional argument: a usage mistake
    ],
)
def test_bad_options_are_unhealthy_never_docker_reserved_2(args, needle, capsys):
    assert health.main(args) == health.EXIT_UNHEALTHY
    out = capsys.readouterr().out.strip()
    assert needle in out and "\n" not in out


@pytest.mark.subprocess
def test_probe_subprocess_fresh_stale_missing(tmp_path):
    """The HEALTHCHECK command itself, through IRTRACK_HEALTH_FILE as the image sets it."""
    path = tmp_path / "alive"
    missing = _run_probe(env_file=str(path))
    assert missing.returncode == 1, missing.stdout + missing.stderr
    health.mark_alive(str(path))
    fresh = _run_probe(env_file=str(path))
    assert fresh.returncode == 0, fresh.stdout + fresh.stderr
    assert fresh.stdout.count("\n") == 1 and fresh.stderr == ""
    old_s = time.time() - 30.0
    os.utime(path, (old_s, old_s))
    stale = _run_probe(env_file=str(path))
    assert stale.returncode == 1
    assert "30." in stale.stdout or "29." in stale.stdout  # the age is reported
    assert _run_probe("--max-age-s", "60", env_file=str(path)).returncode == 0


@pytest.mark.subprocess
def test_probe_imports_only_the_standard_library():
    """The probe runs every few seconds on the drone: it must not drag numpy/zenoh/cv2 in."""
    code = (
        "import sys, onboard.app.health; "
        "heavy = {'numpy', 'zenoh', 'cv2', 'scipy', 'pymavlink', 'yaml'} & set(sys.modules); "
        "print(sorted(heavy))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S
    )
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_a_liveness_path_on_a_real_file_is_refused_and_left_alone(tmp_path):
    """The daemon touches its liveness file and deletes it when it stops: a path set by mistake onto a file that
    holds anything is refused at start, naming the field, and the file keeps its bytes; an empty one (a dead
    daemon's) is taken over and removed at the end; release leaves a file someone wrote into meanwhile."""
    victim = tmp_path / "flight-notes.txt"
    victim.write_text("important\n")
    with pytest.raises(ConfigError, match=r"output.health_file: .*flight-notes.txt exists and holds 10 bytes"):
        health.claim_health_file(str(victim))
    with pytest.raises(
        ConfigError, match=r"output.health_file: .* exists and is a folder: a liveness file is an empty"
    ):
        health.claim_health_file(str(tmp_path))
    health.claim_health_file(str(tmp_path / "absent"))  # nothing there: fine
    stale = tmp_path / "alive"
    stale.touch()
    health.claim_health_file(str(stale))
    health.release_health_file(str(stale))
    assert not stale.exists()
    health.release_health_file(str(victim))
    assert victim.read_text() == "important\n"


def test_the_daemon_refuses_a_liveness_path_on_a_real_file_and_keeps_it(tmp_path):
    from groundsim.io.ports import free_udp_port

    victim = tmp_path / "victim.txt"
    victim.write_text("important\n")
    proc = run_module(
        "onboard",
        "--mavlink",
        f"udpin:127.0.0.1:{free_udp_port()}",
        "--set",
        f"output.health_file={victim}",
        timeout_s=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert "output.health_file" in proc.stderr and "holds 10 bytes" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert victim.read_text() == "important\n"
