"""``groundsim demo``: the pure pieces (plan, status line, truth tail, track store, scoring) and one
real run of both processes on 127.0.0.1, stopped with SIGINT part-way (bounded in time)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from groundsim.evaluation.demo import (
    DemoOutcome,
    TrackStore,
    TruthTail,
    aligned_arrays,
    daemon_command,
    format_demo_table,
    plan_demo,
    score_demo,
    sim_command,
    status_line,
)
from groundsim.evaluation.proc_cpu import ProcCpu
from groundsim.world.nav_errors import GnssDropout
from groundsim.world.scenario import load_scenario, scenarios_dir
from groundsim.world.truth import TruthWriter, truth_row
from onboard.app.config import load_config
from onboard.core.errors import ConfigError
from onboard.core.frames import geodetic_from_ned, quat_from_euler
from tests.process_helpers import REPO

pytestmark = pytest.mark.timeout(90)

P1 = scenarios_dir() / "P1.yaml"
DEMO_WALL_LIMIT_S = 60.0  # the whole real demo test, start to exit (the pytest timeout's basis: a hang guard)
SIGINT_AFTER_LINES = 2  # live status lines with frames flowing before Ctrl-C
# ... the last of which counts more simulated frames than this: the frames the score must hold (truth rows
# are only added, so a slow simulator delays the Ctrl-C instead of leaving fewer frames than the test asks)
SIGINT_AFTER_FRAMES = 30
STOP_LIMIT_S = 10.0  # SIGINT -> the demo has stopped both children, printed its table and exited (a hang guard)
CHILD_CPU_S = 0.5  # of the 0.6 s a child burns, counted for its parent


# --------------------------------------------------------------------------- plan


def test_plan_writes_a_valid_daemon_config_and_extends_the_scenario(tmp_path):
    plan = plan_demo("P1", 25.0, 2, tmp_path, None)
    sc = load_scenario(P1)
    assert plan.scenario.duration_s == 25.0 and plan.duration_s == 25.0
    assert plan.scenario_path == P1  # extended by the simulator as `groundsim run --duration 25` extends it
    t = np.array([0.0, 5.0, 9.9])
    np.testing.assert_array_equal(plan.scenario.observer.motion.state(t).p_ned_m, sc.observer.motion.state(t).p_ned_m)
    cfg = load_config(plan.onboard_config_path, environ={})
    assert cfg.mavlink.connection == f"udpin:127.0.0.1:{plan.mavlink_port}"
    assert cfg.zenoh.listen == (f"tcp/127.0.0.1:{plan.zenoh_port}",) and cfg.zenoh.multicast_scouting is False
    assert cfg.camera.mount.gimballed is True and cfg.camera.mount.pitch_deg == pytest.approx(-10.0, abs=1e-9)
    assert cfg.pose.geodetic_origin() == sc.origin
    assert cfg.output.health_file == str((tmp_path / "onboard.alive").resolve())
    d, s = daemon_command(plan), sim_command(plan)
    assert d[1:] == ["-m", "onboard", "--config", str(plan.onboard_config_path)]
    assert ["--rate", "realtime"] == s[s.index("--rate") : s.index("--rate") + 2]
    assert f"udpout:127.0.0.1:{plan.mavlink_port}" in s and plan.zenoh_endpoint in s and "--truth" in s


def test_plan_keeps_a_long_enough_scenario_and_rejects_bad_options(tmp_path):
    plan = plan_demo("P1", 4.0, 0, tmp_path, None)
    assert plan.scenario_path == P1 and plan.duration_s == 4.0
    with pytest.raises(ConfigError, match="--duration"):
        plan_demo("P1", -1.0, 0, tmp_path, None)
    with pytest.raises(ConfigError, match="--seed"):
        plan_demo("P1", 4.0, -3, tmp_path, None)
    with pytest.raises(ConfigError, match="--onboard-config nope.yaml: no such file"):
        plan_demo("P1", 4.0, 0, tmp_path, "nope.yaml")


def test_an_onboard_config_that_is_a_directory_is_called_one_before_out_is_made(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(ConfigError) as err:
        plan_demo("P1", 4.0, 0, out, str(tmp_path))
    assert str(err.value) == (
        f"--onboard-config {tmp_path}: a directory, not a file; give the daemon's configuration (a YAML file)"
    )
    assert not out.exists()


def test_the_configuration_errors_name_the_option_the_caller_took_it_from(tmp_path):
    """bench.companion takes the daemon's configuration as --config: its errors must not name --onboard-config."""
    with pytest.raises(ConfigError, match=r"^--config nope\.yaml: no such file$"):
        plan_demo("P1", 4.0, 0, tmp_path / "out", "nope.yaml", config_option="--config")


def test_a_duration_the_scenario_cannot_fly_is_refused_before_out_is_made(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=r"--duration: .*expected --duration at most 15\.4 s"):
        plan_demo("P3", 20.0, 0, out, None)
    with pytest.raises(ConfigError, match=r"--duration: expected at most \d+ s, got 1e\+09"):
        plan_demo("P1", 1e9, 0, out, None)
    assert not out.exists()


def test_the_default_duration_is_capped_at_what_the_scenario_can_fly(tmp_path, capsys):
    plan = plan_demo("P3", None, 0, tmp_path, None)
    assert 10.0 < plan.duration_s <= 15.4 and plan.scenario.duration_s == plan.duration_s
    note = capsys.readouterr().out.strip()
    assert "\n" not in note and f"flying {plan.duration_s:g} s" in note
    s = sim_command(plan)
    assert s[s.index("--duration") + 1] == f"{plan.duration_s:g}"
    assert plan_demo("P1", None, 0, tmp_path, None).duration_s == 20.0


@pytest.mark.parametrize(
    "scenario, options, match",
    [
        ("F1", {}, r"--scenario: F1 has several observers"),
        ("P1", {"live_view_port": 99999}, r"--live-view: expected a TCP port 1\.\.65535, got 99999"),
        ("P1", {"live_view_port": -5}, r"--live-view: expected a TCP port 1\.\.65535, got -5"),
        ("nope", {}, r"nope"),
        ("P1", {"gnss_dropout": GnssDropout(4.0, 1.0)}, r"--gnss-dropout: expected a start before the run's end"),
    ],
)
def test_what_the_children_would_refuse_is_refused_up_front(tmp_path, scenario, options, match):
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=match):
        plan_demo(scenario, 4.0, 0, out, None, **options)
    assert not out.exists()


def test_the_follow_up_evaluation_uses_the_demo_seed_config_and_errors(tmp_path, monkeypatch, capsys):
    import groundsim.evaluation.eval as ev
    from groundsim.evaluation.demo import _quick_eval

    cfg = REPO / "config" / "onboard.yaml"
    plan = plan_demo(
        "P1", 4.0, 7, tmp_path, str(cfg), "exact", mount_as_configured=True, gnss_dropout=GnssDropout(1.0, 2.0)
    )
    seen = {}

    class Stop(Exception):
        pass

    def fake_run_eval(scenarios, seeds, options, base_config, workers, config_source):
        seen.update(seeds=seeds, injected=options.injected, base=base_config, source=config_source)
        raise Stop

    monkeypatch.setattr(ev, "run_eval", fake_run_eval)
    with pytest.raises(Stop):
        _quick_eval(tmp_path / "eval", threading.Event(), plan)
    assert seen["seeds"] == [7] and seen["source"] == str(cfg)
    assert seen["injected"].nav_noise == "exact" and seen["injected"].gnss_dropout == GnssDropout(1.0, 2.0)
    assert seen["base"] == load_config(cfg, environ={})
    line = capsys.readouterr().out
    assert "seed 7" in line and str(cfg) in line and "not --mount-as-configured" in line


# --------------------------------------------------------------------------- collectors and formatting


def _truth_file(path: Path, n: int):
    sc = load_scenario(P1)
    rows = []
    with TruthWriter(path) as w:
        for k in range(n):
            t = k / 30.0
            p_t = np.array([120.0 - 4 * t, 30.0 - 3 * t, -85.0])
            p_c = np.array([0.0, 4 * t, -60.0])
            r = truth_row(
                k,
                1_000_000 + round(t * 1e6),
                t,
                sc.origin,
                sc.camera.intrinsics,
                p_t,
                [-4, -3, 0],
                p_c,
                p_c,
                quat_from_euler(0.0, 0.3, 0.2),
            )
            w.write(r)
            rows.append(r)
    return sc, rows


def test_truth_tail_reads_whole_lines_only(tmp_path):
    path = tmp_path / "truth.csv"
    _, rows = _truth_file(path, 5)
    text = path.read_text()
    cut = text.index("\n", text.index("\n", text.index("\n") + 1) + 1) + 10  # header, 2 rows, 10 chars of the third
    partial = tmp_path / "partial.csv"
    partial.write_text(text[:cut])
    tail = TruthTail(partial)
    assert tail.poll() == 2
    with open(partial, "a") as f:
        f.write(text[cut:])
    assert tail.poll() == 3
    assert tail.order == [r.time_boot_us for r in rows]
    assert tail.rows[rows[4].time_boot_us]["range_m"] == pytest.approx(rows[4].range_m, rel=1e-15)
    assert TruthTail(tmp_path / "missing.csv").poll() == 0


def _track_msg(row, err_ned=(0.0, 0.0, 0.0), observable=True, origin=None, with_position=True) -> dict:
    msg = {
        "schema": "irtrack.track/1",
        "vehicle": "uav1",
        "seq": row.seq,
        "time_boot_us": row.time_boot_us,
        "track_id": 1,
        "state": "tracking",
        "measurement_valid": True,
        "u_px": 320.0,
        "v_px": 256.0,
        "bbox": [312, 248, 16, 16],
        "pose_valid": True,
        "observable": observable,
        "window_frames": 40,
    }
    if with_position:
        p = np.array([row.target_n_m, row.target_e_m, row.target_d_m]) + np.asarray(err_ned)
        lat, lon, alt = geodetic_from_ned(p, origin)
        msg.update(
            lat_deg=float(lat),
            lon_deg=float(lon),
            alt_m=float(alt),
            ned_m=p.tolist(),
            origin={"lat_deg": origin.lat_deg, "lon_deg": origin.lon_deg, "alt_m": origin.alt_m},
            vel_ned_mps=[0.0, 0.0, 0.0],
            cov_ned_m2=np.eye(3).tolist(),
            range_m=float(row.range_m),
            range_sigma_ratio=0.01,
            model="cv",
        )
    return msg


def test_track_store_validates_messages():
    store = TrackStore()
    store.on_track(b"not json")
    store.on_track(json.dumps({"schema": "irtrack.track/1"}).encode())  # missing keys
    store.on_status(b"{")
    assert store.bad == 3 and store.tracks == [] and not store.ready.is_set()
    store.on_status(json.dumps({"frames": {"processed": 3}}).encode())
    assert store.ready.is_set() and store.snapshot()[1]["frames"]["processed"] == 3


def test_scoring_matches_truth_by_capture_time(tmp_path):
    path = tmp_path / "truth.csv"
    sc, rows = _truth_file(path, 30)
    tail = TruthTail(path)
    tail.poll()
    store = TrackStore()
    for r in rows[:5]:  # no 3-D yet
        store.on_track(json.dumps(_track_msg(r, with_position=False)).encode())
    for r in rows[5:15]:  # 3-D, not yet observable, 2 m off
        store.on_track(json.dumps(_track_msg(r, (2.0, 0.0, 0.0), observable=False, origin=sc.origin)).encode())
    for r in rows[15:]:  # observable, 0.5 m off
        store.on_track(json.dumps(_track_msg(r, (0.0, 0.3, 0.4), observable=True, origin=sc.origin)).encode())
    assert store.bad == 0
    a = aligned_arrays(tail, store.tracks, sc.origin)
    s = score_demo(a)
    assert (s["frames"], s["frames_with_estimate"], s["frames_observable"]) == (30, 25, 15)
    assert s["continuity"] == pytest.approx(0.5)
    assert s["observable"]["rmse_m"] == pytest.approx(0.5, abs=1e-6)  # geodetic round trip: micrometres
    assert s["observable"]["mean_nees"] == pytest.approx(0.25, abs=1e-5)
    expect_all = np.sqrt((10 * 4.0 + 15 * 0.25) / 25)
    assert s["all"]["rmse_m"] == pytest.approx(expect_all, abs=1e-6)
    out = DemoOutcome(
        "P1",
        0,
        1.0,
        1.0,
        30,
        30,
        False,
        0,
        0,
        cpu_share={"sim": 0.3, "daemon": 0.25, "demo": 0.02},
        last_status={"processing_ms": {"p50": 4.2, "p99": 30.0}},
    )
    table = format_demo_table(s, out)
    assert "| observable frames (published with observable: true) | 15 |" in table
    assert "continuity 50 %" in table and "daemon 25 %" in table and "p50 4.2 ms" in table


def test_status_line_shows_error_and_observability():
    line = status_line(
        3.0,
        90,
        600,
        {"frames": {"processed": 88, "dropped": 1}, "processing_ms": {"p50": 5.25}},
        {"state": "tracking", "track_id": 2, "lat_deg": 32.0, "observable": False},
        101.5,
        100.0,
        2.0,
        0.31,
        None,
    )
    assert line.startswith(
        "[  3.0 s] | sim 90/600 frames | daemon 88 processed, 1 dropped, p50 5.2 ms/frame | tracking #2"
    )
    assert "range 101.5 m (truth 100.0 m)" in line and "err 2.00 m (2.00 % of range) unobservable" in line
    assert line.endswith("CPU sim 31 %, daemon - %")
    assert "track -" in status_line(0.5, 0, 600, None, None, None, None, None, None, None)
    assert "no 3-D yet (7 frames in the window)" in status_line(
        1, 1, 2, None, {"state": "coasting", "window_frames": 7}, None, None, None, None, None
    )


def test_proc_cpu_reads_this_process():
    meter = ProcCpu(os.getpid())
    t0 = time.process_time()
    while time.process_time() - t0 < 0.05:  # burn a little CPU
        pass
    share = meter.share_since_last()
    if share is None:
        pytest.skip("no /proc on this system")
    assert share > 0.0 and meter.share_overall() is not None
    assert ProcCpu(2**22 + 12345).cpu_s() is None  # no such process


@pytest.mark.integration
def test_proc_cpu_counts_child_processes():
    meter = ProcCpu(os.getpid())
    if meter.cpu_s() is None:
        pytest.skip("no /proc on this system")
    own0 = time.process_time()
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import time\nt=time.process_time()\nwhile time.process_time()-t<0.6: pass\ntime.sleep(30)",
        ]
    )
    try:
        t_end = time.monotonic() + 30
        while time.monotonic() < t_end:  # until the child's busy loop shows (bounded)
            theirs = meter.cpu_s() - meter.cpu0 - (time.process_time() - own0)
            if theirs >= CHILD_CPU_S:
                break
            time.sleep(0.1)
        assert theirs >= CHILD_CPU_S
    finally:
        child.kill()
        child.wait()


# --------------------------------------------------------------------------- the real thing


@pytest.mark.integration
@pytest.mark.timeout(DEMO_WALL_LIMIT_S + 30)
def test_demo_runs_both_processes_and_stops_cleanly_on_sigint(tmp_path):
    """A real demo (daemon + realtime simulator on loopback): live lines, then Ctrl-C -> table, exit 130."""
    out = tmp_path / "demo"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable,
        "-m",
        "groundsim",
        "demo",
        "--duration",
        "30",
        "--out",
        str(out),
        "--no-eval",
        "--log-level",
        "warning",
    ]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines: list[str] = []
    try:
        # live lines once frames flow; a demo that hangs is caught by the test's timeout.  Ctrl-C once the daemon
        # too has processed that many frames: on a loaded machine it starts seconds behind the simulator, and the
        # share of frames with a track below is the pipeline's, not its start-up's
        live = sim_frames = daemon_frames = 0
        while live < SIGINT_AFTER_LINES or min(sim_frames, daemon_frames) <= SIGINT_AFTER_FRAMES:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line.rstrip("\n"))
            if line.startswith("[") and "| sim " in line and not line.split("| sim ")[1].startswith("0/"):
                live += 1
                sim_frames = int(line.split("| sim ")[1].split("/")[0])
                daemon_frames = int(line.split("| daemon ")[1].split(" processed")[0])
        if live < SIGINT_AFTER_LINES or min(sim_frames, daemon_frames) <= SIGINT_AFTER_FRAMES:
            text = "\n".join(lines)
            if "exited with code" in text or "published no status" in text:
                pytest.fail(f"a demo child crashed or never started:\n{text}")  # a failure, never a skip
            pytest.fail(f"no live status lines:\n{text}")
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=STOP_LIMIT_S)  # a guard against a hang, not a measured property
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = "\n".join(lines) + "\n" + rest
    assert proc.returncode == 130, text  # Ctrl-C: the interrupted line and 130, after the table and the files
    assert f"interrupted: the live run's report in {out / 'report.md'}" in text, text
    assert "daemon ready" in text and "| online track vs truth |" in text and "report: " in text, text
    rep = json.loads((out / "report.json").read_text())
    assert rep["stopped_early"] is True
    # both children were reaped (exit codes known) and ended by our SIGTERM (or the terminal's SIGINT): 0 or -15
    assert rep["exit_codes"]["daemon"] in (0, -signal.SIGTERM) and rep["exit_codes"]["sim"] in (0, -signal.SIGTERM)
    s = rep["scores"]
    assert s["frames"] > SIGINT_AFTER_FRAMES and s["frames_with_track_message"] > 0.5 * s["frames"], s
    assert rep["daemon_status"]["frames"]["processed"] > 0
    assert (out / "truth.csv").is_file() and (out / "tracks.jsonl").stat().st_size > 0
    cfg = yaml.safe_load((out / "onboard.yaml").read_text())
    assert not Path(cfg["output"]["health_file"]).exists()  # the daemon removed its liveness file on exit


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_a_demo_stopped_by_a_signal_is_interrupted_not_a_success(tmp_path, monkeypatch, capsys, signum):
    """SIGTERM (a job's limit, ``timeout``) cut the run short and skipped the evaluation, yet exited 0 without a
    word: it is an interruption as Ctrl-C is (one line, 130)."""
    import types

    import groundsim.evaluation.demo as demo
    from groundsim.app import cli

    def stopped_run(plan, stop):
        os.kill(os.getpid(), signum)  # as a terminal or a job's limit sends it mid-run
        for _ in range(100):
            if stop.is_set():
                break
            time.sleep(0.01)
        return types.SimpleNamespace(files={}, error=None)

    def never(*_a, **_k):
        raise AssertionError("the evaluation ran after the run was cut short")

    monkeypatch.setattr(demo, "run_demo", stopped_run)
    monkeypatch.setattr(demo, "_quick_eval", never)
    args = cli.build_parser().parse_args(["demo", "--duration", "5", "--out", str(tmp_path / "d")])
    assert demo.cmd_demo(args) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "interrupted: nothing written"


def test_an_earlier_demos_results_go_before_a_new_demo_starts(tmp_path, caplog):
    """An interrupted demo, or one without the evaluation, left the earlier run's report, TUM files, plots and eval/
    beside its own; a user's own files stay."""
    from groundsim.evaluation.demo_plan import DEMO_OUTPUTS

    for name in DEMO_OUTPUTS:
        (tmp_path / name).write_text("an earlier run's\n")
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "report.md").write_text("an earlier evaluation\n")
    (tmp_path / "notes.txt").write_text("mine\n")
    theirs = tmp_path / "not_a_demo"  # the same names in a folder no demo wrote: the user's, refused and kept
    theirs.mkdir()
    (theirs / "report.md").write_text("my report\n")
    (theirs / "onboard.yaml").write_text("vehicle: mine\n")
    with pytest.raises(ConfigError, match="not empty and not an earlier groundsim demo's folder"):
        plan_demo("P1", 4.0, 0, theirs, None)  # the run would have written its own report.md and onboard.yaml there
    assert (theirs / "report.md").read_text() == "my report\n" and (
        theirs / "onboard.yaml"
    ).read_text() == "vehicle: mine\n"
    plan_demo("P1", 4.0, 0, tmp_path / "first", None)  # an earlier demo's onboard.yaml marks the folder
    (tmp_path / "onboard.yaml").write_text((tmp_path / "first" / "onboard.yaml").read_text())
    plan_demo("P1", 4.0, 0, tmp_path, None)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["first", "not_a_demo", "notes.txt", "onboard.yaml"], left
    assert any("held an earlier demo's results; removed: report.json" in r.getMessage() for r in caplog.records)


def test_the_default_onboard_config_is_the_shipped_file_from_any_folder(tmp_path, monkeypatch):
    """Run from another folder, the default --onboard-config (config/onboard.yaml) silently became the built-in
    defaults; it is the installed tree's file, as eval's and campaign's are."""
    from groundsim.evaluation.demo_plan import DEFAULT_DEMO_ONBOARD_CONFIG
    from groundsim.evaluation.eval import DEFAULT_ONBOARD_CONFIG

    monkeypatch.chdir(tmp_path)
    plan = plan_demo("P1", 4.0, 0, tmp_path / "d", DEFAULT_DEMO_ONBOARD_CONFIG)
    assert plan.onboard_config_source == str(DEFAULT_ONBOARD_CONFIG)
