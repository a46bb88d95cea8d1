"""Benchmark of ``python -m onboard.reconstruct`` on long files: CPU, peak memory and accuracy, in windows
(the command's ``--window-s``, default 60 s) and as one problem over the whole file (its ``--window-s 0``, run here
for the spans up to ``--whole-up-to``).

``python -m bench.reconstruct [--durations 20 40 80 160 600] [--whole-up-to 160] [--rate-hz 30]``.  Each file is a
flight that stays observable however long it lasts: the camera circling as in H1 (40 m at 8 m/s, 70 m up), the
target circling 160 m away (30 m at 6 deg/s, 85 m up), 0.3 px pixel noise, perfect navigation.  Each
reconstruction runs as its own child process (the command as a user runs it, one BLAS thread); its CPU seconds
(user + system) and peak resident memory come from the kernel's accounting of that child (``os.wait4``).  The
whole-file problem's cost grows with the span cubed: ``--whole-up-to`` bounds the spans it is run on.
Numbers only: nothing here asserts.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from onboard.core.blas import single_thread_blas_env  # noqa: E402 - imports nothing but os

single_thread_blas_env()

import numpy as np  # noqa: E402

from bench import run_benchmark  # noqa: E402
from bench.options import BenchParser, nonnegative_number, positive_float  # noqa: E402
from groundsim.evaluation.synth import synthesize  # noqa: E402
from groundsim.world.motion import Circular  # noqa: E402
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths  # noqa: E402
from onboard.app.reconstruct import DEFAULT_WINDOW_S, OBS_COLUMNS  # noqa: E402


def write_flight(path: Path, duration_s: float, rate_hz: float) -> np.ndarray:
    """The circling flight's OBS.csv at ``path``; returns the target's true positions, one per row."""
    sc = load_scenario(reference_scenario_paths()["H1"])
    target = Circular((160.0, 0.0, -85.0), 30.0, 0.0, math.radians(6.0))
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    truth, obs = synthesize(
        sc.observer_motion(), target, t, sc.camera.intrinsics, load_noise_cases()["px0.3"], np.random.default_rng(5)
    )
    columns = np.column_stack(
        [obs.t_s, obs.uv_px, obs.fx_px, obs.fy_px, obs.cx_px, obs.cy_px, obs.p_cam_ned_m, obs.q_ned_from_cam]
    )
    with open(path, "w", encoding="ascii", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(OBS_COLUMNS)
        w.writerows([[repr(float(v)) for v in row] for row in columns])
    return truth.p_target_ned_m


def run_reconstruct(src: Path, out: Path, summary: Path, window_s: float) -> tuple[int, float, float, str]:
    """``python -m onboard.reconstruct`` on ``src``: exit code, CPU s, peak RSS in MB, its stdout line."""
    cmd = [sys.executable, "-m", "onboard.reconstruct", str(src), "-o", str(out), "--summary-json", str(summary)]
    cmd += ["--window-s", f"{window_s:g}"]
    # the files' own noise: 0.3 px on the pixels, perfect navigation (the command assumes an RTK drone's otherwise)
    cmd += ["--pixel-sigma", "0.3", "--attitude-sigma-deg", "0", "--attitude-bias-deg", "0", "--position-sigma-m", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    line = proc.stdout.read().strip()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0, line


def score(out: Path, truth: np.ndarray) -> tuple[float, float]:
    """Median position error (m) and the share of rows with an axis beyond 3 of its sigmas."""
    a = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
    err = a[:, 1:4] - truth
    return float(np.median(np.linalg.norm(err, axis=1))), float(np.mean(np.any(np.abs(err) > 3 * a[:, 4:7], axis=1)))


def main(argv: list[str] | None = None) -> int:
    ap = BenchParser(prog="python -m bench.reconstruct", description=__doc__.split("\n\n")[0])
    ap.add_argument("--durations", type=positive_float, nargs="+", default=[20.0, 40.0, 80.0, 160.0, 600.0])
    ap.add_argument("--whole-up-to", type=nonnegative_number, default=160.0, metavar="S")
    ap.add_argument("--window-s", type=positive_float, default=DEFAULT_WINDOW_S, metavar="S")
    ap.add_argument("--rate-hz", type=positive_float, default=30.0)
    args = ap.parse_args(argv)
    print("| span s | rows | --window-s | windows | CPU s | peak MB | median error m | beyond 3 sigma | observable |")
    print("|---|---|---|---|---|---|---|---|---|")
    failed = 0
    with tempfile.TemporaryDirectory(prefix="bench_reconstruct_") as d:
        for duration in args.durations:
            src = Path(d) / f"obs_{duration:g}.csv"
            truth = write_flight(src, duration, args.rate_hz)
            for window_s in [args.window_s] + ([0.0] if duration <= args.whole_up_to else []):
                out, summary = Path(d) / "out.csv", Path(d) / "summary.json"
                rc, cpu_s, peak_mb, _ = run_reconstruct(src, out, summary, window_s)
                if rc != 0:
                    print(f"| {duration:g} | {len(truth)} | {window_s:g} | exit {rc} | | | | | |")
                    failed += 1
                    continue
                s = json.loads(summary.read_text())
                median_m, beyond = score(out, truth)
                observable = f"{100 * s.get('observable_rows_fraction', float(s['observable'])):.0f} % of rows"
                print(
                    f"| {duration:g} | {len(truth)} | {window_s:g} | {s['windows']} | {cpu_s:.1f} | {peak_mb:.0f} | "
                    f"{median_m:.3f} | {100 * beyond:.2f} % | {observable} |",
                    flush=True,
                )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(run_benchmark("reconstruct", main))
