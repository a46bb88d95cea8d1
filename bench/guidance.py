"""Benchmark of observer guidance (onboard.estimation.guidance): the cost of one advice update.

``python -m bench.guidance [--updates 200]``.  Draws random observer states and unobservable target posteriors
(100-400 m, range sigma 50 % of the range, the RTK noise model of ``config/onboard.yaml``) and prints, per
:meth:`GuidancePlanner.advise` call with the shipped ``guidance`` section, the CPU ms of the calling thread
(``time.thread_time``: what the work costs, not how long a loaded machine took to schedule it; BLAS on one thread)
and the wall ms, median / p90 / max, and how the updates were answered.  The daemon runs one update per
``guidance.update_interval_s`` (1 s).  Numbers only: nothing here asserts on time.
"""

from __future__ import annotations

import collections
import math
import sys
import time

from onboard.core.blas import single_thread_blas_env  # noqa: E402 - imports nothing but os

single_thread_blas_env()

import numpy as np  # noqa: E402

from bench import run_benchmark  # noqa: E402
from bench.options import BenchParser, positive_int  # noqa: E402
from onboard.app.config import OnboardConfig  # noqa: E402
from onboard.estimation.guidance import GuidanceConfig, GuidancePlanner, ObserverState, TargetPosterior  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = BenchParser(prog="python -m bench.guidance", description=__doc__.split("\n\n")[0])
    ap.add_argument("--updates", type=positive_int, default=200)
    args = ap.parse_args(argv)
    cfg = OnboardConfig()
    k = cfg.camera.intrinsics
    planner = GuidancePlanner.for_noise(GuidanceConfig(), cfg.estimator.noise_model(), (k.fx_px, k.fy_px))
    rng = np.random.default_rng(0)
    cpu_ms, wall_ms = [], []
    outcome: collections.Counter[str] = collections.Counter()
    for i in range(args.updates):
        speed = rng.uniform(0.0, 10.0)
        heading = rng.uniform(-math.pi, math.pi)
        obs = ObserverState(
            float(i), [0.0, 0.0, -rng.uniform(40.0, 120.0)], [speed * math.cos(heading), speed * math.sin(heading), 0.0]
        )
        r = rng.uniform(100.0, 400.0)
        az, el = rng.uniform(-math.pi, math.pi), rng.uniform(-0.3, 0.1)
        u = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), -math.sin(el)])
        p = obs.p_ned_m + r * u
        cov = 4.0 * np.eye(3) + (0.5 * r) ** 2 * np.outer(u, u)
        tgt = TargetPosterior.from_track(
            float(i), p, rng.uniform(-5.0, 5.0, 3) * [1, 1, 0.2], cov, (1.0, 1.0, 0.5), obs.p_ned_m, obs.v_ned_mps
        )
        c0, w0 = time.thread_time(), time.perf_counter()
        advice = planner.advise(obs, tgt)
        cpu_ms.append((time.thread_time() - c0) * 1e3)
        wall_ms.append((time.perf_counter() - w0) * 1e3)
        outcome[advice.status] += 1
    n_cand = len(planner.candidates(obs, tgt))
    print(
        f"guidance: {args.updates} updates, {n_cand} candidates each, horizon {planner.config.horizon_s:g} s sampled every {planner.config.sample_interval_s:g} s"
    )
    for name, xs in (("cpu", cpu_ms), ("wall", wall_ms)):
        a = np.asarray(xs)
        print(
            f"  {name:4s} ms per update: median {np.median(a):6.2f}  p90 {np.percentile(a, 90):6.2f}  max {a.max():6.2f}"
        )
    print("  outcomes: " + ", ".join(f"{k} {v}" for k, v in sorted(outcome.items())))


if __name__ == "__main__":
    sys.exit(run_benchmark("guidance", main))
