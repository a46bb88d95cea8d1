"""Honest over minutes: the sliding-window estimator alone on long synthetic flights, per scenario family.

    python -m bench.honesty [--families circling,weaving,switching] [--minutes 2] [--seeds 4] [--first-seed 0]
                            [--workers 2] [--bin-s 30] [--monitor [--model-hold-s S]] [--json out/honesty.json]

Each run is a perfect-geometry flight (``groundsim.evaluation.synth``) under the RTK noise case, 15 frames
a second (every frame kept by the window), fed frame by frame to
:class:`~onboard.estimation.sliding.SlidingWindowEstimator` as the daemon's estimator worker feeds it; every
estimate it returns is a published position.  Families:

- ``circling``: the observer circles (40 m radius, 8 m/s), the target circles 220 m away (30 m radius,
  5 m/s): steady, the scene where 55 s flights showed 2.3-4.3 % beyond 3 sigma;
- ``weaving``: the observer follows a constant-velocity target (5 m/s, 200 m ahead) flying S-turns across
  the line of sight (30 m, 20 s period): the benign family of the verdict's recall;
- ``switching``: the observer circles, the target flies a racetrack (150 m legs, 50 m half-turns, 6 m/s):
  it changes motion model (constant velocity <-> constant turn) every ~25 s.

Printed: per family and flight length, a summary (the share beyond 3 sigma over all published positions,
in the worst time bin and in the worst run; how often the estimator saw a change of motion model); per
family, flight length and time bin, the published positions, the share beyond 3 sigma
(``||e|| > 3 sqrt(trace P)``, the honesty check of ``onboard.estimation.metrics``), the observable share
and the observable positions' median error / range; where the dishonest positions fall relative to the
last change of the selected motion model; and the verdict's recall on the ``weaving`` family at the end
of each flight (runs whose last position is within 2 % of range, and how many of them are called
observable).  Numbers are printed, never asserted.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass

from onboard.core.blas import single_thread_blas_env  # noqa: E402 - imports nothing but os

single_thread_blas_env()

import numpy as np  # noqa: E402

from bench import run_benchmark, write_json  # noqa: E402
from bench.options import (  # noqa: E402
    BenchParser,
    choices_list,
    json_runs,
    nonnegative_int,
    nonnegative_number,
    positive_float,
    positive_int,
)
from groundsim.evaluation.synth import Racetrack, Weave, estimator_noise_model, synthesize  # noqa: E402
from groundsim.world.motion import Circular, KinematicState  # noqa: E402
from groundsim.world.scenario import load_noise_cases, load_scenario, reference_scenario_paths  # noqa: E402
from onboard.estimation.sliding import (  # noqa: E402
    SlidingConfig,
    SlidingWindowEstimator,
    consistency_monitor,
    line_of_sight_unit_ned,
)

FAMILIES = ("circling", "weaving", "switching")
FRAME_RATE_HZ = 15.0
GOOD_PCT = 2.0  # the verdict's "good run": error / range at most this at the end


@dataclass(frozen=True)
class Shifted:
    """``base`` started ``dt_s`` into its path (a seed's phase)."""

    base: object
    dt_s: float

    def state(self, t_s) -> KinematicState:
        return self.base.state(np.asarray(t_s, dtype=float) + self.dt_s)  # type: ignore[attr-defined]


def family_motions(family: str, seed: int):
    """Observer and target motions of ``family`` for ``seed`` (random phases)."""
    rng = np.random.default_rng([seed, FAMILIES.index(family)])
    az0 = rng.uniform(0, 2 * np.pi)
    circling_observer = Circular((0.0, 0.0, -70.0), 40.0, az0, -0.2)
    if family == "circling":
        tgt = Circular((220.0, 0.0, -85.0), 30.0, rng.uniform(0, 2 * np.pi), 5.0 / 30.0)
        return circling_observer, tgt
    if family == "weaving":
        obs = Weave((0.0, 0.0, -70.0), (5.0, 0.0, 0.0), (0.0, 1.0, 0.0), 30.0, 20.0)
        obs = Shifted(obs, rng.uniform(0, 20.0))
        tgt = Weave((200.0, rng.uniform(-30, 30), -85.0), (5.0, 0.0, 0.0), (0.0, 1.0, 0.0), 0.0, 1.0)
        return obs, tgt
    if family == "switching":
        tgt = Shifted(Racetrack((230.0, 0.0, -85.0), 150.0, 50.0, 6.0), rng.uniform(0, 100.0))
        return circling_observer, tgt
    raise ValueError(f"unknown family {family!r}")


def run_flight(
    family: str,
    seed: int,
    duration_s: float,
    monitor: bool = False,
    model_hold_s: float = 0.0,
    noise: str = "RTK",
    in_estimator: bool = False,
) -> dict:
    """One flight: per published position its time, error, 3-sigma test, verdict, range and selected model.
    ``in_estimator``: the monitor the estimator runs itself (``SlidingConfig.consistency_check``) instead of
    the bench's own (the same numbers without ``model_hold_s``)."""
    nc = load_noise_cases()[noise]
    intr = load_scenario(reference_scenario_paths()["P1"]).camera.intrinsics
    obs_m, tgt_m = family_motions(family, seed)
    t = np.arange(0.0, duration_s, 1.0 / FRAME_RATE_HZ)
    truth, obs = synthesize(obs_m, tgt_m, t, intr, nc, np.random.default_rng([seed, 7]))
    # the estimator's own monitor (SlidingConfig.consistency_check) off: the bench compares the window alone
    # with the window through the monitor built here, whose hold after a model change can be varied
    sw = SlidingWindowEstimator(SlidingConfig(consistency_check=in_estimator), noise=estimator_noise_model(nc))
    mon = consistency_monitor(sw.noise, intr, model_hold_s) if monitor and not in_estimator else None
    rows = []
    t0 = time.thread_time()
    for i in range(t.size):
        est = sw.add(t[i], obs.uv_px[i], intr, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i])
        if est is None:
            continue
        if mon is not None:
            cam = obs.p_cam_ned_m[i]
            los = line_of_sight_unit_ned(obs.uv_px[i], intr, obs.q_ned_from_cam[i])
            est = mon.check(est, cam, los, lambda e, cam=cam: sw.carry(e, e.t_s, cam))
        e = est.p_ned_m - truth.p_target_ned_m[i]
        err = float(np.linalg.norm(e))
        sig = float(math.sqrt(max(np.trace(est.cov_p_ned_m2), 0.0)))
        rows.append(
            (
                float(t[i]),
                err,
                sig,
                bool(est.observable),
                float(truth.range_m[i]),
                est.model if est.motion_prior is None else f"{est.model}:{est.motion_prior.q_horizontal_m2ps3:.2g}",
                float(est.range_sigma_ratio),
            )
        )
    cpu = time.thread_time() - t0
    return {
        "family": family,
        "seed": seed,
        "duration_s": duration_s,
        "cpu_s": cpu,
        "monitor": monitor,
        "stats": dict(sw.stats),
        "rows": rows,
    }


def _run_one(args):
    return run_flight(*args)


def run_all(
    families, seeds, duration_s: float, workers: int, monitor: bool = False, model_hold_s: float = 0.0
) -> list[dict]:
    jobs = [(f, s, duration_s, monitor, model_hold_s) for f in families for s in seeds]
    out = []
    if workers > 1:
        import multiprocessing as mp

        from groundsim.evaluation.parallel import init_worker

        with mp.get_context("fork").Pool(workers, initializer=init_worker) as pool:
            for r in pool.imap_unordered(_run_one, jobs):
                out.append(r)
                print(f"\r  flights {len(out)}/{len(jobs)}", end="", file=sys.stderr, flush=True)
    else:
        for j in jobs:
            out.append(_run_one(j))
            print(f"\r  flights {len(out)}/{len(jobs)}", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return out


def _pct(x) -> str:
    return "-" if not math.isfinite(x) else f"{x:.2f} %"


def _groups(runs: list[dict]) -> dict[tuple[str, float], list[dict]]:
    """The runs by (family, flight minutes), in the order they first appear."""
    out: dict[tuple[str, float], list[dict]] = {}
    for r in runs:
        out.setdefault((r["family"], r["duration_s"] / 60.0), []).append(r)
    return out


def _group_rows(runs: list[dict]) -> Iterator[tuple[str, float, list[dict], np.ndarray]]:
    """Per (family, flight minutes) with published rows: the family, the minutes, its runs and their rows as
    an (N, 5) array of time, error, sigma, observable, range."""
    for (fam, minutes), rs in _groups(runs).items():
        rows = [row for r in rs for row in r["rows"]]
        if rows:
            yield fam, minutes, rs, np.array([row[:5] for row in rows], dtype=float)


def summary_table(runs: list[dict], bin_s: float) -> str:
    """Per family and flight length: the share beyond 3 sigma over all published positions, in the worst time
    bin and in the worst run; the observable share and median err/range; how often the estimator saw a change
    of motion model (``SlidingWindowEstimator.stats``: manoeuvres, inconsistent and unsteady selections) per minute."""
    lines = [
        "| family | minutes | runs | published | beyond 3 sigma | worst bin | worst run | observable | "
        "median err/range, observable | manoeuvres / min | inconsistent selections / min | unsteady selections / min |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for fam, minutes, rs, a in _group_rows(runs):
        bad = a[:, 1] > 3 * a[:, 2]
        bins = np.floor(a[:, 0] / bin_s)
        worst_bin = max(100 * float(np.mean(bad[bins == b])) for b in np.unique(bins))
        worst_run = max(100 * float(np.mean([row[1] > 3 * row[2] for row in r["rows"]])) for r in rs if r["rows"])
        obs = a[:, 3] > 0
        med = 100 * float(np.median(a[obs, 1] / a[obs, 4])) if obs.any() else math.nan
        total_min = sum(r["duration_s"] for r in rs) / 60.0
        man = sum(r.get("stats", {}).get("manoeuvres", 0) for r in rs) / total_min
        inc = sum(r.get("stats", {}).get("inconsistent_selections", 0) for r in rs) / total_min
        uns = sum(r.get("stats", {}).get("unsteady_selections", 0) for r in rs) / total_min
        lines.append(
            f"| {fam} | {minutes:g} | {len(rs)} | {len(a)} | {100 * bad.mean():.2f} % | {worst_bin:.2f} % | "
            f"{worst_run:.2f} % | {100 * obs.mean():.0f} % | {_pct(med)} | {man:.1f} | {inc:.1f} | {uns:.1f} |"
        )
    return "\n".join(lines)


def time_table(runs: list[dict], bin_s: float) -> str:
    """Per family, flight length and time bin: published, beyond 3 sigma, observable share, observable median
    err/range."""
    lines = [
        "| family | minutes | runs | time bin s | published | beyond 3 sigma | observable | median err/range, observable |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for fam, minutes, rs, a in _group_rows(runs):
        edges = np.arange(0.0, a[:, 0].max() + bin_s, bin_s)
        for lo in list(edges) + [None]:
            m = np.ones(len(a), bool) if lo is None else (a[:, 0] >= lo) & (a[:, 0] < lo + bin_s)
            if not m.any():
                continue
            b = a[m]
            beyond = 100 * np.mean(b[:, 1] > 3 * b[:, 2])
            obs = b[:, 3] > 0
            med = 100 * float(np.median(b[obs, 1] / b[obs, 4])) if obs.any() else math.nan
            label = "all" if lo is None else f"{lo:.0f}-{lo + bin_s:.0f}"
            lines.append(
                f"| {fam} | {minutes:g} | {len(rs)} | {label} | {int(m.sum())} | {beyond:.2f} % | {100 * obs.mean():.0f} % | {_pct(med)} |"
            )
    return "\n".join(lines)


def switch_table(runs: list[dict], near_s: float = 5.0) -> str:
    """Where the positions beyond 3 sigma fall: within ``near_s`` after a change of the selected model or not."""
    lines = [
        f"| family | model changes per minute | published within {near_s:g} s after a change | beyond 3 sigma there | elsewhere |",
        "|---|---|---|---|---|",
    ]
    for fam in dict.fromkeys(r["family"] for r in runs):
        near_n = near_b = far_n = far_b = changes = 0
        minutes = 0.0
        for r in runs:
            if r["family"] != fam:
                continue
            last_model, last_change = None, -math.inf
            minutes += r["duration_s"] / 60.0
            for t, err, sig, _obs, _rng, model, _ratio in r["rows"]:
                if last_model is not None and model != last_model:
                    changes += 1
                    last_change = t
                last_model = model
                bad = err > 3 * sig
                if t - last_change <= near_s:
                    near_n += 1
                    near_b += bad
                else:
                    far_n += 1
                    far_b += bad
        lines.append(
            f"| {fam} | {changes / max(minutes, 1e-9):.1f} | {near_n} | {_pct(100 * near_b / near_n if near_n else math.nan)} | "
            f"{_pct(100 * far_b / far_n if far_n else math.nan)} |"
        )
    return "\n".join(lines)


def recall_table(runs: list[dict], family: str = "weaving", last_s: float = 1.0) -> str:
    """The verdict at the end of each ``family`` flight (its last ``last_s`` of positions, median error):
    good runs (error <= GOOD_PCT), how many of them called observable, the observable runs' error and honesty."""
    rs = [r for r in runs if r["family"] == family and r["rows"]]
    if not rs:
        return f"(no {family} flights)"
    good = called = good_called = 0
    errs_called, honest_called, sig_ratio = [], 0, []
    for r in rs:
        t_end = r["rows"][-1][0]
        tail = [row for row in r["rows"] if row[0] >= t_end - last_s]
        err_pct = 100 * float(np.median([row[1] / row[4] for row in tail]))
        observable = tail[-1][3]
        sig_ratio.append(100 * tail[-1][6])
        good += err_pct <= GOOD_PCT
        called += observable
        good_called += observable and err_pct <= GOOD_PCT
        if observable:
            errs_called.append(err_pct)
            honest_called += np.mean([row[1] > 3 * row[2] for row in r["rows"]]) <= 0.01
    rec = 100 * good_called / good if good else math.nan
    return (
        f"{family}: {len(rs)} runs; err/range <= {GOOD_PCT:g} % at the end: {good}; of them called observable: "
        f"{good_called} (recall {_pct(rec)}); called observable: {called}, their median err/range "
        f"{_pct(float(np.median(errs_called)) if errs_called else math.nan)}, honest (<= 1 % beyond 3 sigma "
        f"over the flight) {honest_called}/{called}; reported range sigma at the end (median) "
        f"{float(np.median(sig_ratio)):.1f} %"
    )


def main(argv=None) -> int:
    ap = BenchParser(prog="python -m bench.honesty", description=__doc__.splitlines()[0])
    ap.add_argument("--families", type=choices_list(lambda: FAMILIES, "family"), default=list(FAMILIES))
    ap.add_argument("--minutes", type=positive_float, default=2.0)
    ap.add_argument("--seeds", type=positive_int, default=4)
    ap.add_argument("--first-seed", type=nonnegative_int, default=0)
    ap.add_argument("--workers", type=positive_int, default=2)
    ap.add_argument(
        "--monitor", action="store_true", help="publish through onboard.estimation.consistency.ConsistencyMonitor"
    )
    ap.add_argument(
        "--model-hold-s", type=nonnegative_number, default=0.0, help="with --monitor: demote after a model change"
    )
    ap.add_argument("--bin-s", type=positive_float, default=30.0)
    ap.add_argument("--json", default=None, help="write the per-position rows here (re-read with --from-json)")
    ap.add_argument(
        "--from-json",
        type=json_runs,
        default=None,
        nargs="+",
        metavar="FILE",
        help="print the tables of earlier runs, no flights",
    )
    args = ap.parse_args(argv)
    if args.from_json:
        runs = [r for file_runs in args.from_json for r in file_runs]  # each file's, read when parsed
    else:
        t0 = time.perf_counter()
        runs = run_all(
            args.families,
            range(args.first_seed, args.first_seed + args.seeds),
            60.0 * args.minutes,
            args.workers,
            args.monitor,
            args.model_hold_s,
        )
        cpu = [r["cpu_s"] / r["duration_s"] for r in runs]
        print(
            f"== {len(runs)} flights of {args.minutes:g} min ({time.perf_counter() - t0:.0f} s wall; estimator "
            f"{np.median(cpu):.3f} CPU s per s of flight, median) =="
        )
        if args.json:
            write_json(args.json, {"runs": runs})
    print(summary_table(runs, args.bin_s))
    print()
    print(time_table(runs, args.bin_s))
    print()
    print(switch_table(runs))
    print()
    print(recall_table(runs))
    return 0


if __name__ == "__main__":
    sys.exit(run_benchmark("honesty", main))
