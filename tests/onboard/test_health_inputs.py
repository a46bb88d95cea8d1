"""The liveness probe and ``--check`` on liveness paths that hold something the daemon does not write there: a
folder, a device, a file with content (the daemon's own file is an empty regular file it touches)."""

from __future__ import annotations

import os
import time

import pytest

from onboard.app import health
from onboard.core.errors import ConfigError


@pytest.fixture
def with_content(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("important\n")
    return path


@pytest.mark.parametrize(
    "target, foreign",
    [("folder", "is a folder"), ("device", "is a device"), ("with_content", "holds 10 bytes")],
)
def test_the_probe_calls_a_path_the_daemon_never_writes_not_alive_naming_it(
    target, foreign, tmp_path, with_content, capsys
):
    path = {"folder": str(tmp_path), "device": os.devnull, "with_content": str(with_content)}[target]
    now_s = time.time()
    os.utime(path, (now_s, now_s))  # touched just now, as /tmp is by every process that writes into it
    verdict = health.check_liveness(path)
    assert (verdict.alive, verdict.reason, verdict.age_s, verdict.foreign) == (False, "foreign", None, foreign)
    assert health.main(["--file", path]) == health.EXIT_UNHEALTHY
    out = capsys.readouterr().out
    assert out.startswith(f"NOT alive: {path} {foreign}: ") and "empty regular file" in out and out.count("\n") == 1


def test_an_empty_regular_file_touched_now_is_still_alive(tmp_path):
    path = tmp_path / "alive"
    health.mark_alive(str(path))
    assert health.check_liveness(str(path)).alive


def test_a_foreign_verdict_says_what_the_path_holds_and_nothing_else():
    with pytest.raises(ValueError, match="foreign"):
        health.Liveness(False, "foreign", None, 5.0)
    with pytest.raises(ValueError, match="foreign"):
        health.Liveness(False, "missing", None, 5.0, "is a folder")
    with pytest.raises(ValueError, match="age_s"):
        health.Liveness(False, "foreign", 1.0, 5.0, "is a folder")


@pytest.mark.parametrize("target", ["folder", "with_content"])
def test_check_refuses_a_liveness_path_the_daemon_would_refuse_at_start(target, tmp_path, with_content, capsys):
    from onboard.app.main import main

    path = {"folder": tmp_path, "with_content": with_content}[target]
    with pytest.raises(ConfigError) as start:  # the daemon's own check at start
        health.claim_health_file(str(path))
    assert main(["--set", f"output.health_file={path}", "--check"]) == 2
    err = capsys.readouterr().err
    assert err == f"(defaults): {start.value}\n"
    assert main(["--set", f"output.health_file={tmp_path / 'alive'}", "--check"]) == 0
