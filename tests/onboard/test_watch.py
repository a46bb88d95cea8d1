"""``python -m onboard.watch``: its lines (unit) and the real command against a zenoh publisher on loopback."""

from __future__ import annotations

import dataclasses
import io
import json
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from onboard.app.watch import (
    DEFAULT_CONNECT,
    EXIT_CONFIG,
    EXIT_INTERRUPTED,
    EXIT_NO_TRACK,
    EXIT_OK,
    WatchCounts,
    build_parser,
    format_track,
    interrupted_line,
    main,
    summary_line,
    zenoh_config,
)
from onboard.core.track import LineOfSight, Track, track_from_json, track_to_bytes
from tests.fakes import positioned_track, tracking_track

REPO = Path(__file__).resolve().parents[2]
START_TIMEOUT_S = 30.0  # the watcher's imports and zenoh session on a busy 2-core machine
WATCH_SECONDS = 6.0  # the watcher's --seconds: long enough to receive what is published once it matches
EXIT_TIMEOUT_S = 30.0

LOS = LineOfSight((1.0, 0.0, 0.0), 0.0, -2.5, 0.08, 0.06, (0.0, 0.0, -50.0))


def los_track(**fields) -> Track:
    """A tracking Track with a line of sight and no position."""
    return tracking_track(los=LOS, **fields)


def sample_tracks() -> list[Track]:
    """What a flight shows, in order: searching, a line of sight only, a position not yet observable, an
    observable one."""
    return [
        Track(vehicle="uav1", seq=1, time_boot_us=1_033_333, state="searching", pose_valid=True),
        los_track(seq=2, time_boot_us=1_066_667),
        positioned_track(seq=3, time_boot_us=4_000_000, los=LOS, observable=False, range_sigma_ratio=0.5),
        positioned_track(seq=4, time_boot_us=16_000_000, los=LOS, range_sigma_ratio=0.021),
    ]


# ------------------------------------------------------------------------------------------ the lines


def test_a_searching_track_says_no_target():
    line = format_track(Track(vehicle="uav1", seq=1, time_boot_us=1_033_333, state="searching"))
    assert line.split() == ["t", "1.033", "s", "searching", "no", "target", "observable", "no"]


def test_a_track_without_position_shows_its_line_of_sight():
    line = format_track(los_track(time_boot_us=2_500_000))
    assert line.startswith("t    2.500 s  tracking ")
    assert "los az 0.00 el -2.50 deg (sigma 0.08 0.06), no position yet" in line
    assert line.endswith("observable no")


def test_a_track_without_pose_shows_its_pixel():
    line = format_track(tracking_track(pose_valid=False, u_px=321.34, v_px=200.46))
    assert "pixel 321.3 200.5 (no pose)" in line


def test_a_track_with_a_pose_but_no_line_of_sight_says_why_not_no_pose():
    # a frame stating a zoom camera.intrinsics are not for (or a camera/gimbal mismatch): pose, measurement, geometry
    # withheld; before, this line said "(no pose)" and sent the reader to the MAVLink link
    line = format_track(tracking_track(u_px=321.34, v_px=200.46))
    assert "pixel 321.3 200.5 (line of sight withheld: see the status's geometry)" in line
    coasting = format_track(tracking_track(state="coasting", measurement_valid=False, u_px=321.34, v_px=200.46))
    assert "pixel 321.3 200.5 (predicted, no line of sight)" in coasting


def test_a_positioned_track_shows_position_sigma_range_and_verdict():
    track = positioned_track(time_boot_us=16_000_000, range_sigma_ratio=0.021, cov_p_ned_m2=np.diag([4.0, 9.0, 1.0]))
    line = format_track(track)
    assert line.startswith("t   16.000 s  tracking ")
    assert "lat 32.001000 lon 118.800000 alt 80.0 m" in line
    assert "ned 100.0 0.0 -80.0 m" in line
    assert "sigma 2.0 3.0 1.0 m" in line
    assert "range 130 m +-2.1 %" in line
    assert line.endswith("observable yes")


def test_a_position_read_back_from_the_wire_reads_the_same():
    track = positioned_track(time_boot_us=16_000_000, range_sigma_ratio=0.021)
    assert format_track(track_from_json(track_to_bytes(track))) == format_track(track)


def test_counts_summary_and_interrupted_lines():
    counts = WatchCounts()
    for t in sample_tracks():
        counts.add(t)
    assert (counts.tracks, counts.with_los, counts.with_position, counts.observable) == (4, 3, 2, 1)
    assert (counts.first_position_s, counts.first_observable_s) == (4.0, 16.0)
    assert summary_line(counts, 40.0) == (
        "summary: 4 tracks in 40.0 s, 3 with line of sight, 2 with position (first at t 4.0 s), "
        "1 observable (first at t 16.0 s)"
    )
    assert interrupted_line(counts) == "interrupted: 4 tracks received, 2 with position, 1 observable"
    counts.bad = 2
    assert summary_line(counts, 1.0).endswith("; 2 payloads were not tracks")
    fleet = WatchCounts()
    fleet.add_fleet({"lat_deg": 32.0, "observable": True})  # the fusion's: no line of sight to count
    assert summary_line(fleet, 40.0) == "summary: 1 fleet tracks in 40.0 s, 1 with position, 1 observable"
    assert summary_line(WatchCounts(), 0.5) == (
        "summary: 0 tracks in 0.5 s, 0 with line of sight, 0 with position, 0 observable; nothing arrived: is the "
        "daemon running, and zenoh connected to it?"
    )


# ------------------------------------------------------------------------------------------ the options


@pytest.mark.parametrize(
    ("argv", "connect", "listen"),
    [
        ([], (DEFAULT_CONNECT,), ()),
        (["--zenoh-connect", "tcp/10.0.0.2:7447"], ("tcp/10.0.0.2:7447",), ()),
        (["--zenoh-listen", "tcp/127.0.0.1:7448"], (), ("tcp/127.0.0.1:7448",)),
    ],
)
def test_zenoh_defaults_to_the_sim_daemons_listener(argv, connect, listen):
    settings = zenoh_config(build_parser().parse_args(argv))
    assert (settings.connect, settings.listen, settings.multicast_scouting) == (connect, listen, None)


def test_options_and_defaults():
    args = build_parser().parse_args([])
    assert (args.vehicle, args.seconds, args.json) == ("uav1", 30.0, False)
    args = build_parser().parse_args(["--vehicle", "uav2", "--seconds", "0", "--json", "--no-zenoh-multicast-scouting"])
    assert (args.vehicle, args.seconds, args.json, args.zenoh_scouting) == ("uav2", 0.0, True, False)


@pytest.mark.parametrize("seconds", ["-1", "nan", "soon"])
def test_bad_seconds_exit_2_on_one_line(seconds, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["--seconds", seconds])
    assert exc.value.code == EXIT_CONFIG
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("argv", "words"),
    [(["--vehicle", "uav 1"], "argument --vehicle: vehicle name"), (["--zenoh-connect", "bogus"], "--zenoh-connect")],
)
def test_bad_zenoh_options_exit_2_on_one_line(argv, words, capsys):
    assert main([*argv, "--seconds", "1"]) == EXIT_CONFIG
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]


# ------------------------------------------------------------------------------------------ the command


class Publisher:
    """A zenoh session listening on a free loopback port with a publisher on irtrack/uav1/track; ``wait_matched``
    returns once a subscriber (the watcher) is reachable."""

    def __init__(self) -> None:
        from groundsim.io.ports import free_tcp_port
        from onboard.io.zenoh_session import TRACK_ENCODING, ZenohConfig, open_session, track_key

        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.session = open_session(ZenohConfig(listen=(self.endpoint,)))
        self.publisher = self.session.declare_publisher(track_key("uav1"), encoding=TRACK_ENCODING)
        self._matched = threading.Event()
        self._listener = self.publisher.declare_matching_listener(
            lambda status: self._matched.set() if status.matching else None
        )

    def wait_matched(self, timeout_s: float) -> bool:
        return self._matched.wait(timeout_s)

    def put(self, payload: bytes) -> None:
        self.publisher.put(payload)

    def close(self) -> None:
        self.session.close()


class Lines:
    """The lines a child process writes to one pipe, read by a thread; ``wait_for`` blocks on a condition."""

    def __init__(self, pipe) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self._thread.start()

    def _read(self, pipe) -> None:
        for line in pipe:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def wait_for(self, predicate, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self.lines), timeout_s)

    def join(self) -> list[str]:
        self._thread.join(EXIT_TIMEOUT_S)
        return self.lines


@pytest.fixture
def publisher():
    pub = Publisher()
    yield pub
    pub.close()


def start_watcher(endpoint: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "onboard.watch", "--zenoh-connect", endpoint, *extra],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def publish_samples(publisher: Publisher) -> list[bytes]:
    payloads = [track_to_bytes(t) for t in sample_tracks()]
    for p in payloads:
        publisher.put(p)
    return payloads


@pytest.fixture(scope="module")
def watched_for_seconds():
    """The two ``--seconds`` runs of the tests below, at once (each sleeps through its WATCH_SECONDS, so one after the
    other they cost twice): the text watcher and the ``--json`` one, each with a publisher of its own, which publishes
    the samples (and, to the ``--json`` one, a payload that is not a track) once its watcher has subscribed.  Returns
    per name (``"text"``, ``"json"``) the endpoint, the payloads published, the exit code, stdout and stderr."""
    runs: dict[str, dict] = {}
    try:
        for name, extra in (("text", ()), ("json", ("--json",))):
            runs[name] = {"pub": Publisher()}
            runs[name]["proc"] = start_watcher(runs[name]["pub"].endpoint, "--seconds", f"{WATCH_SECONDS:g}", *extra)
        runs["text"]["payloads"] = (
            publish_samples(runs["text"]["pub"]) if runs["text"]["pub"].wait_matched(START_TIMEOUT_S) else None
        )
        if runs["json"]["pub"].wait_matched(START_TIMEOUT_S):
            runs["json"]["payloads"] = publish_samples(runs["json"]["pub"])
            runs["json"]["pub"].put(b'{"schema": "something/else"}')
        else:
            runs["json"]["payloads"] = None
        out = {}
        for name, run in runs.items():
            stdout, stderr = run["proc"].communicate(timeout=WATCH_SECONDS + EXIT_TIMEOUT_S)
            out[name] = {
                "endpoint": run["pub"].endpoint,
                "payloads": run["payloads"],
                "returncode": run["proc"].returncode,
                "out": stdout,
                "err": stderr,
            }
    finally:
        for run in runs.values():
            if "proc" in run:
                run["proc"].kill()
            run["pub"].close()
    return out


@pytest.mark.integration
def test_the_watcher_prints_each_track_and_a_summary_then_exits_by_itself(watched_for_seconds):
    run = watched_for_seconds["text"]
    assert run["payloads"] is not None, "the watcher never subscribed"
    out, err = run["out"], run["err"]
    assert run["returncode"] == EXIT_OK, err
    lines = out.splitlines()
    assert lines[0] == f"watching irtrack/uav1/track on {run['endpoint']} for {WATCH_SECONDS:g} s (Ctrl-C stops sooner)"
    assert lines[1:-1] == [format_track(t) for t in sample_tracks()]
    assert lines[-1].startswith("summary: 4 tracks in ")
    assert lines[-1].endswith(
        " s, 3 with line of sight, 2 with position (first at t 4.0 s), 1 observable (first at t 16.0 s)"
    )
    assert err == ""


@pytest.mark.integration
def test_json_prints_the_payloads_as_received(watched_for_seconds):
    run = watched_for_seconds["json"]
    payloads = run["payloads"]
    assert payloads is not None, "the watcher never subscribed"
    out, err = run["out"], run["err"]
    assert run["returncode"] == EXIT_OK, err
    assert out.splitlines() == [p.decode() for p in payloads] + ['{"schema": "something/else"}']
    assert [json.loads(line)["seq"] for line in out.splitlines()[:4]] == [1, 2, 3, 4]
    info = err.splitlines()
    assert info[0].startswith("watching irtrack/uav1/track on ")
    assert info[-1].startswith("summary: 4 tracks in ") and info[-1].endswith("; 1 payloads were not tracks")


@pytest.mark.integration
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, EXIT_INTERRUPTED), (signal.SIGTERM, 128 + signal.SIGTERM)])
def test_ctrl_c_or_sigterm_exits_with_one_interrupted_line(publisher, sig, code):
    """SIGTERM (`timeout`, `kill`) ended the watcher with no line at all, its counts lost."""
    proc = start_watcher(publisher.endpoint, "--seconds", "0")
    try:
        out = Lines(proc.stdout)
        assert publisher.wait_matched(START_TIMEOUT_S), "the watcher never subscribed"
        publish_samples(publisher)
        assert out.wait_for(lambda lines: sum(line.startswith("t ") for line in lines) == 4, EXIT_TIMEOUT_S)
        proc.send_signal(sig)
        exit_code = proc.wait(EXIT_TIMEOUT_S)
        err = proc.stderr.read()
    finally:
        proc.kill()
    assert exit_code == code, err
    lines = out.join()
    assert lines[-1] == "interrupted: 4 tracks received, 2 with position, 1 observable"
    assert not any(line.startswith("summary") for line in lines)
    assert err == ""


def _fleet_payload(observable: bool) -> bytes:
    """An irtrack.fleet_track/1 as onboard.fuse publishes it (onboard.io.fleet_wire.fleet_track_json's keys)."""
    return json.dumps(
        {
            "schema": "irtrack.fleet_track/1",
            "seq": 7,
            "target_id": 3,
            "time_unix_us": 1_767_268_803_250_000,  # 2026-01-01T12:00:03.250Z
            "lat_deg": 32.001234,
            "lon_deg": 118.801234,
            "alt_m": 101.5,
            "ned_m": [136.8, 116.1, -101.5],
            "origin": {"lat_deg": 32.0, "lon_deg": 118.8, "alt_m": 0.0},
            "vel_ned_mps": [0.0, 5.0, 0.0],
            "sigma_ned_m": [0.4, 0.5, 0.3],
            "sigma_vel_ned_mps": [0.2, 0.2, 0.1],
            "cov_ned_m2": [[0.16, 0, 0], [0, 0.25, 0], [0, 0, 0.09]],
            "range_sigma_ratio": 0.002,
            "observable": observable,
            "vehicles": [{"vehicle": "uav1"}, {"vehicle": "uav2"}],
        }
    ).encode()


def test_the_fleet_key_shows_the_fusions_targets_one_line_each():
    """--vehicle fleet subscribes irtrack/fleet/track, where onboard.fuse publishes irtrack.fleet_track/1: each is a
    line (not 'not a track') and counts in the summary."""
    from onboard.app.watch import _receive, format_fleet_track

    line = format_fleet_track(json.loads(_fleet_payload(True)))
    assert line.startswith(
        "12:00:03.250 UTC  target 3  lat 32.001234 lon 118.801234 alt 101.5 m  ned 136.8 116.1 -101.5 m"
    )
    assert line.endswith("sigma 0.4 0.5 0.3 m  from uav1, uav2  observable yes")
    inbox: queue.Queue[bytes] = queue.Queue()
    for obs in (False, True):
        inbox.put(_fleet_payload(obs))
    counts, out, err = WatchCounts(), io.StringIO(), io.StringIO()
    # until both are counted (a short deadline alone lost the second on a loaded machine), 10 s at most
    done = threading.Event()

    def stop_when_both_counted() -> None:
        deadline = time.monotonic() + 10.0
        while counts.tracks < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        done.set()

    threading.Thread(target=stop_when_both_counted, daemon=True).start()
    _receive(inbox, counts, seconds=10.0, as_json=False, out=out, err=err, hint="", stop=done)
    assert out.getvalue().count("target 3") == 2 and err.getvalue() == ""
    assert (counts.tracks, counts.with_position, counts.observable, counts.bad) == (2, 2, 1, 0)


def test_a_fleet_track_with_fields_of_the_wrong_types_is_counted_bad_not_a_crash():
    """Any peer may publish on the key: a payload nested too deep, a string for a number, 1e30 microseconds, a number
    for a list ended the watcher with a traceback (exit 1, which says "no track")."""
    from onboard.app.watch import _receive

    good = json.loads(_fleet_payload(True))
    payloads = [b"[" * 100_000] + [
        json.dumps({**good, **change}).encode()
        for change in ({"lat_deg": "x"}, {"time_unix_us": 1e30}, {"ned_m": 5}, {"vehicles": 5}, {"time_unix_us": "a"})
    ]
    inbox: queue.Queue[bytes] = queue.Queue()
    for p in payloads:
        inbox.put(p)
    counts, out, err = WatchCounts(), io.StringIO(), io.StringIO()
    done = threading.Event()

    def stop_when_all_seen() -> None:
        deadline = time.monotonic() + 10.0
        while counts.bad < len(payloads) and time.monotonic() < deadline:
            time.sleep(0.01)
        done.set()

    threading.Thread(target=stop_when_all_seen, daemon=True).start()
    _receive(inbox, counts, seconds=10.0, as_json=False, out=out, err=err, hint="", stop=done)
    assert counts.bad == len(payloads) and counts.tracks == 0 and out.getvalue() == ""
    assert err.getvalue().count("not a fleet track") == 5 and err.getvalue().count("not a track") == 1


def test_a_summary_of_nothing_says_what_to_check():
    assert summary_line(WatchCounts(), 2.0).endswith(
        "; nothing arrived: is the daemon running, and zenoh connected to it?"
    )


@pytest.mark.integration
def test_nothing_received_exits_1_so_a_script_sees_a_silent_daemon(capsys):
    """A watcher whose ``--seconds`` pass without a track (no daemon at the endpoint) exits 1, not 0: ``onboard.watch
    --seconds 30 && ...`` must not pass a flow that published nothing."""
    import socket

    with socket.socket() as s:  # a loopback port nobody listens on: zenoh retries it quietly
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(["--seconds", "0.5", "--zenoh-connect", f"tcp/127.0.0.1:{port}"])
    out = capsys.readouterr().out
    assert code == EXIT_NO_TRACK, out
    assert out.splitlines()[-1].startswith("summary: 0 tracks in ")
    assert out.splitlines()[-1].endswith("nothing arrived: is the daemon running, and zenoh connected to it?")


# a Ctrl-C during the entry point's imports: KeyboardInterrupt raised inside one of them (zenoh's, which comes late,
# so numpy and the project's modules are half imported by then), as the signal's handler raises it there
_INTERRUPTED_IMPORT = """
import runpy, sys
class CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name == "zenoh":
            raise KeyboardInterrupt
        return None
sys.meta_path.insert(0, CtrlC())
sys.argv = ["onboard.watch", *sys.argv[1:]]
runpy.run_module("onboard.watch", run_name="__main__", alter_sys=True)
"""


@pytest.mark.subprocess
@pytest.mark.parametrize("json_output", [False, True])
def test_ctrl_c_during_the_imports_is_the_interrupted_line_and_130(json_output):
    """A Ctrl-C in the watcher's first second printed a traceback and ended by SIGINT (status -2), not 130."""
    from onboard.watch import EXIT_INTERRUPTED, INTERRUPTED_STARTING

    extra = ["--json"] if json_output else []
    r = subprocess.run(
        [sys.executable, "-c", _INTERRUPTED_IMPORT, "--seconds", "1", *extra],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == EXIT_INTERRUPTED, r.stderr[-2000:]
    line, other = (r.stderr, r.stdout) if json_output else (r.stdout, r.stderr)
    assert line == INTERRUPTED_STARTING + "\n" and other == "", (r.stdout, r.stderr)
    assert INTERRUPTED_STARTING == interrupted_line(WatchCounts())  # the same line as a Ctrl-C later, nothing received


def _watch_all(payloads: list[bytes]) -> tuple[WatchCounts, str, str]:
    """``_receive`` over ``payloads`` until each is counted (10 s at most)."""
    from onboard.app.watch import _receive

    inbox: queue.Queue[bytes] = queue.Queue()
    for p in payloads:
        inbox.put(p)
    counts, out, err = WatchCounts(), io.StringIO(), io.StringIO()
    done = threading.Event()

    def stop_when_all_counted() -> None:
        deadline = time.monotonic() + 10.0
        while counts.tracks + counts.bad < len(payloads) and time.monotonic() < deadline:
            time.sleep(0.01)
        done.set()

    threading.Thread(target=stop_when_all_counted, daemon=True).start()
    _receive(inbox, counts, seconds=10.0, as_json=False, out=out, err=err, hint="", stop=done)
    return counts, out.getvalue(), err.getvalue()


def _searching(seq: int, t_us: int) -> bytes:
    return track_to_bytes(Track(vehicle="uav1", seq=seq, time_boot_us=t_us, state="searching", pose_valid=True))


@pytest.mark.parametrize(
    "case",
    ["one camera, two daemons", "two cameras", "two cameras, seq and time ordered oppositely"],
)
def test_two_publishers_interleaving_on_the_track_key_are_said_once(case):
    """Two daemons named uav1 publish on one key: of one camera, each frame comes twice; of two, two numberings and
    clocks alternate.  The watcher says once that the lines mix two publishers, and the summary repeats it."""
    from onboard.app.watch import summary_line

    if case == "one camera, two daemons":
        payloads = [_searching(k, 1_000_000 + 33_333 * k) for k in range(20) for _ in range(2)]
    elif case == "two cameras, seq and time ordered oppositely":  # the higher seq, the earlier time: went unsaid
        payloads = [
            p for k in range(20) for p in (_searching(500 + k, 1_000_000 + k), _searching(k, 9_000_000 + 33_333 * k))
        ]
    else:
        payloads = [
            p for k in range(20) for p in (_searching(k, 1_000_000 + 33_333 * k), _searching(500 + k, 9_000_000 + k))
        ]
    counts, out, err = _watch_all(payloads)
    assert counts.tracks == 40 and out.count("\n") == 40
    assert err.count("go back and forth") == 1 and "two daemons named uav1" in err and "name_clash" in err
    assert "two publishers on the key" in summary_line(counts, 10.0)


def test_a_publisher_that_restarts_once_is_no_second_publisher():
    """A camera or daemon restarted: its numbering goes back once, then forward again."""
    from onboard.app.watch import summary_line

    payloads = [_searching(k, 20_000_000 + 33_333 * k) for k in range(10)]
    payloads += [_searching(k, 1_000_000 + 33_333 * k) for k in range(10)]
    counts, _out, err = _watch_all(payloads)
    assert counts.returns == 1 and err == ""
    assert "publishers" not in summary_line(counts, 10.0)


def test_a_daemon_restarted_under_a_running_camera_is_said_once_by_its_new_run_id():
    """The camera's numbering goes on through the daemon's restart, so only the run_id tells it: said once on
    stderr, and the summary lists the runs."""
    from onboard.app.watch import summary_line

    def tracked(seq: int, run: str) -> bytes:
        t = Track(vehicle="uav1", seq=seq, time_boot_us=1_000_000 + 33_333 * seq, state="searching", pose_valid=True)
        return track_to_bytes(dataclasses.replace(t, run_id=run))

    a, b = "0123456789abcdef", "fedcba9876543210"
    counts, _out, err = _watch_all([tracked(k, a) for k in range(10)] + [tracked(k, b) for k in range(10, 20)])
    assert err.count("new daemon run") == 1 and f"run_id {b} after {a}" in err and "start again" in err
    assert counts.runs == [a, b] and f"2 daemon runs (run_id {a}, {b})" in summary_line(counts, 10.0)
    counts, _out, err = _watch_all([tracked(k, a) for k in range(10)])  # one run: nothing said
    assert err == "" and "daemon runs" not in summary_line(counts, 10.0)
