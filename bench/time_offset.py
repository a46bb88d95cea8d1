"""The camera clock's offset against the autopilot's: detection, warning and compensation in lockstep runs.

    python -m bench.time_offset [--scenarios P1 P2] [--seeds 3] [--duration 40] [--offset-ms 50] [--workers 2]
    python -m bench.time_offset --zero-only --scenarios H2 --seeds 1 --duration 300   # the false-alarm run
    python -m bench.time_offset --scenarios P1 --seed 2 --workers 1                    # one seed again

Each (scenario, seed) is flown three times through :func:`groundsim.evaluation.eval.run_lockstep` (RTK
navigation noise, frames stamped ``--offset-ms`` late by ``--camera-time-offset-ms``): with no offset, with the
offset and ``time_offset.compensate`` on (the default), with the offset and compensation off.  Per run it
prints the offset estimate at the end with its sigma, when the estimate first became confident and when the
watchdog first raised ``camera_time_offset`` (seconds from the first frame with a measured target), and the
3-D error: RMS over the frames where both that run and the zero-offset run of the same seed have an observable
position (the same frames, so the ratio compares like with like), and the share of frames observable.

Numbers, no assertions; the goals (detected and warned within 10 s of tracking; 3-D error within 1.2x of the
zero-offset run with compensation; no warning in 5 minutes at 0 ms) are printed beside them, and a last line
counts the runs that meet each.  P1 and P2 fly ~43 s at most (their accelerating vehicle passes 25 m/s); H2 (a
target 500 m off, flying straight, the observer circling) flies 5 minutes.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from bench import run_benchmark
from bench.options import BenchParser, known_scenario, nonnegative_int, positive_float, positive_int

GOALS = "goals: detected and warned <= 10 s after tracking starts; 3-D RMS <= 1.2x the 0 ms run; no warning at 0 ms"


def _run(task: tuple) -> dict:
    """One lockstep run: (scenario, seed, offset_ms, compensate, duration_s) -> figures and per-frame errors."""
    from groundsim.evaluation.eval import EvalOptions, load_base_config, run_lockstep
    from groundsim.world.nav_errors import DEFAULT_NAV_NOISE, CameraClockError, InjectedErrors
    from groundsim.world.scenario import load_scenario, resolve_scenario_path

    name, seed, offset_ms, compensate, duration_s = task
    base = load_base_config(None)
    base = dataclasses.replace(base, time_offset=dataclasses.replace(base.time_offset, compensate=compensate))
    options = EvalOptions(
        duration_s=duration_s,
        batch=False,
        keep_frame=False,
        injected=InjectedErrors(DEFAULT_NAV_NOISE, camera_clock=CameraClockError(float(offset_ms))),
    )
    r = run_lockstep(load_scenario(resolve_scenario_path(name)), seed, options, base)
    err = np.linalg.norm(r.est_p_ned_m - r.truth_p_ned_m, axis=1)
    obs = r.has_estimate & r.observable
    return {"task": task, "time_offset": r.time_offset, "err_m": err, "observable": obs, "frames": r.frames}


def _since(t_s: float, t0_s: float) -> str:
    return "never" if t_s is None or math.isnan(t_s) else f"{t_s - t0_s:.1f} s"


def _warned_s(res: dict) -> float:
    to = res["time_offset"]
    return math.nan if math.isnan(to["warning_t_s"]) else to["warning_t_s"] - to["first_measurement_t_s"]


def _ratio(res: dict, zero: dict) -> float | None:
    """3-D RMS of ``res`` over that of ``zero`` on the frames observable in both (None: no such frame)."""
    n = min(res["err_m"].size, zero["err_m"].size)
    both = res["observable"][:n] & zero["observable"][:n]
    if not both.any():
        return None
    return float(np.sqrt(np.mean(res["err_m"][:n][both] ** 2)) / np.sqrt(np.mean(zero["err_m"][:n][both] ** 2)))


def _line(label: str, res: dict, zero: dict | None) -> str:
    to = res["time_offset"]
    t0 = to["first_measurement_t_s"]
    est = "-" if to["estimate_ms"] is None else f"{to['estimate_ms']:+.1f} +- {to['sigma_ms']:.1f} ms"
    text = (
        f"  {label:<14} estimate {est:<20} {to['state']:<10} compensated {to['compensated_ms']:5.1f} ms; "
        f"confident after {_since(to['confident_t_s'], t0):>7}, warned after {_since(to['warning_t_s'], t0):>7}; "
        f"max confident |estimate| {to['max_abs_confident_ms']:.1f} ms; observable {100 * res['observable'].mean():.0f} %"
    )
    if zero is not None:
        n = min(res["err_m"].size, zero["err_m"].size)
        both = res["observable"][:n] & zero["observable"][:n]
        if both.any():
            rms = float(np.sqrt(np.mean(res["err_m"][:n][both] ** 2)))
            rms0 = float(np.sqrt(np.mean(zero["err_m"][:n][both] ** 2)))
            text += f"; 3-D RMS {rms:.2f} m vs {rms0:.2f} m at 0 ms (x{rms / rms0:.2f}, {int(both.sum())} frames)"
        else:
            text += "; 3-D: no frame observable in both runs"
    return text


def main(argv=None) -> int:
    p = BenchParser(prog="python -m bench.time_offset", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="+", type=known_scenario, default=["P1", "P2"])
    p.add_argument("--seeds", type=positive_int, default=3, help="seeds 0 .. N-1 of each scenario (3)")
    p.add_argument(
        "--seed", type=nonnegative_int, nargs="+", default=None, help="these seeds only (instead of --seeds)"
    )
    p.add_argument("--duration", type=positive_float, default=40.0, help="seconds flown per run (40)")
    p.add_argument("--offset-ms", type=float, default=50.0, help="the injected offset, ms (50)")
    p.add_argument("--workers", type=positive_int, default=2)
    p.add_argument("--zero-only", action="store_true", help="only the 0 ms runs (the false-alarm check)")
    args = p.parse_args(argv)
    seeds = list(range(args.seeds)) if args.seed is None else sorted(set(args.seed))
    if any(seed < 0 for seed in seeds):
        p.error(f"--seed: seeds are integers >= 0, got {seeds}")
    tasks = []
    for name in args.scenarios:
        for seed in seeds:
            tasks.append((name, seed, 0.0, True, args.duration))
            if not args.zero_only:
                tasks += [
                    (name, seed, args.offset_ms, True, args.duration),
                    (name, seed, args.offset_ms, False, args.duration),
                ]
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        results = {r["task"]: r for r in pool.map(_run, tasks)}
    print(f"camera clock offset, RTK navigation, {args.duration:g} s per run ({GOALS})")
    warned, ratios, zero_warned = [], [], 0
    for name in args.scenarios:
        for seed in seeds:
            zero = results[(name, seed, 0.0, True, args.duration)]
            zero_warned += bool(zero["time_offset"]["warned"])
            print(f"{name} seed {seed}:")
            print(_line("0 ms", zero, None))
            if not args.zero_only:
                off = args.offset_ms
                comp = results[(name, seed, off, True, args.duration)]
                nocomp = results[(name, seed, off, False, args.duration)]
                warned += [_warned_s(comp), _warned_s(nocomp)]
                ratios.append(_ratio(comp, zero))
                print(_line(f"{off:g} ms comp", comp, zero))
                print(_line(f"{off:g} ms no comp", nocomp, zero))
    n_zero = len(args.scenarios) * len(seeds)
    summary = f"summary: 0 ms runs warned {zero_warned}/{n_zero} ({args.duration:g} s each)"
    if not args.zero_only:
        summary += (
            f"; {args.offset_ms:g} ms runs warned within 10 s {sum(w <= 10.0 for w in warned)}/{len(warned)}; "
            f"compensated 3-D RMS within 1.2x of 0 ms {sum(r is not None and r <= 1.2 for r in ratios)}/{len(ratios)}"
            f" ({sum(r is None for r in ratios)} without a frame observable in both)"
        )
        known = sorted(r for r in ratios if r is not None)
        if known:  # the ratio's spread over the seeds: one seed's ratio is not the estimator's whole story
            summary += f"; ratios x{known[0]:.2f} .. x{known[-1]:.2f}, median x{float(np.median(known)):.2f}"
    print(summary)
    print(f"  machine: {os.cpu_count()} cores, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} (shared)")
    return 0


if __name__ == "__main__":
    sys.exit(run_benchmark("time_offset", main))
