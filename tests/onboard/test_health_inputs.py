"""The liveness probe and ``--check`` on liveness paths that hold something the daemon does not write there: a
folder, a device, a file with content (the daemon's own file is an empty regular file it touches)."""

from __future__ import annotations

import errno
import os
import time

import pytest

from onboard.app import health
from onboard.core.errors import ConfigError
from tests.integration_helpers import ONBOARD_CONFIG


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


@pytest.mark.parametrize("where", ["missing", "read_only_file_system"])
def test_check_refuses_a_liveness_file_in_a_folder_where_none_can_be_made(where, tmp_path, monkeypatch, capsys):
    """A folder the daemon cannot create its file in (a read-only root: /var/irtrack-alive) passed --check; the daemon
    then ran with no liveness file and its container's health check called it dead."""
    import tempfile

    from onboard.app.main import main

    folder = tmp_path / ("gone" if where == "missing" else "ro")
    if where == "read_only_file_system":  # what the image's user meets on the read-only root (root too: no skip)
        folder.mkdir()
        real = tempfile.NamedTemporaryFile

        def refused(*args, **kwargs):
            if os.fspath(kwargs.get("dir", "")) == str(folder):
                raise OSError(errno.EROFS, os.strerror(errno.EROFS))
            return real(*args, **kwargs)

        monkeypatch.setattr(tempfile, "NamedTemporaryFile", refused)
    path = folder / "alive"
    assert main(["--set", f"output.health_file={path}", "--check"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"(defaults): output.health_file: cannot make {path}: {folder}: ") and err.count("\n") == 1
    expected = {"missing": "no such folder", "read_only_file_system": "Read-only file system"}
    assert expected[where] in err, err
    assert main(["--set", f"output.health_file={tmp_path / 'alive'}", "--check"]) == 0
    assert not [p for p in tmp_path.rglob(".irtrack-check-*")]  # the check's own file is gone


def test_the_check_says_what_it_checked(tmp_path, capsys, monkeypatch):
    """'ok' alone did not say what was checked, nor that no link was tried."""
    from onboard.app.main import main

    alive = tmp_path / "alive"
    assert main(["--set", f"output.health_file={alive}", "--check"]) == 0
    out = capsys.readouterr().out
    assert out == (
        "(defaults) with output.health_file (--set): ok (every field, zenoh config, output.health_file writable;"
        " no link opened)\n"
    ), out
    record = tmp_path / "r.mcap"
    assert main(["--set", "output.health_file=null", "--record", str(record), "--live-view", "8765", "--check"]) == 0
    out = capsys.readouterr().out
    assert out == (
        "(defaults) with output.health_file (--set), record.path (--record), live_view.port (--live-view): ok (every"
        " field, zenoh config, record.path writable, live_view.host resolves; no link opened)\n"
    ), out
    # a disk with less free than record.min_free_mb: the daemon would fly unrecorded, and the check says so
    import onboard.io.record_files as record_files

    monkeypatch.setattr(record_files, "free_disk_bytes", lambda path: 5_000_000)
    assert main(["--set", "output.health_file=null", "--record", str(record), "--check"]) == 0
    out = capsys.readouterr().out
    assert "record.path writable but 5 MB free, under record.min_free_mb (200): the daemon would fly unrecorded" in out


def test_the_check_names_the_variables_and_options_it_checked_beside_the_file(monkeypatch, capsys):
    """The ok line named only the file: the same file checked in another environment (the container's) is another
    configuration."""
    from onboard.app.main import main

    monkeypatch.setenv("IRTRACK_ESTIMATOR_WINDOW_S", "10")
    argv = [
        "--config",
        str(ONBOARD_CONFIG),
        "--set",
        "follow.enabled=true",
        "--set",
        "output.health_file=null",
        "--check",
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out == (
        f"{ONBOARD_CONFIG} with estimator.window_s (env IRTRACK_ESTIMATOR_WINDOW_S), follow.enabled (--set),"
        " output.health_file (--set): ok (every field, zenoh config; no link opened)\n"
    ), out


@pytest.mark.parametrize("case", ["under_a_file", "symlink_loop"])
def test_the_probe_says_why_a_path_cannot_be_looked_at_not_that_it_is_missing(case, tmp_path, with_content, capsys):
    """A path the probe may not stat (a folder it may not search, ...) was reported as 'does not exist'. Root may
    search any folder, so the errors here are ones root meets too; the words are the system's either way."""
    if case == "under_a_file":
        path, words = with_content / "alive", os.strerror(errno.ENOTDIR)
    else:
        loop = tmp_path / "loop"
        loop.symlink_to(loop)
        path, words = loop, os.strerror(errno.ELOOP)
    verdict = health.check_liveness(str(path))
    assert (verdict.alive, verdict.reason, verdict.age_s, verdict.error) == (False, "unreadable", None, words)
    assert health.main(["--file", str(path)]) == health.EXIT_UNHEALTHY
    assert capsys.readouterr().out == f"NOT alive: cannot look at {path}: {words}\n"
    missing = health.check_liveness(str(tmp_path / "absent"))  # the control: a path that is not there is missing
    assert (missing.reason, missing.error) == ("missing", None)


def test_an_unreadable_verdict_says_why_and_nothing_else():
    with pytest.raises(ValueError, match="error"):
        health.Liveness(False, "unreadable", None, 5.0)
    with pytest.raises(ValueError, match="error"):
        health.Liveness(False, "missing", None, 5.0, error="Permission denied")
    with pytest.raises(ValueError, match="age_s"):
        health.Liveness(False, "unreadable", 1.0, 5.0, error="Permission denied")
