"""Every compiled kernel, the daemon's and the simulator's, compiled once into numba's cache.

numba compiles a kernel the first time a process calls it and caches the machine code beside its source
(``__pycache__``), where every later process loads it in well under a second. After an install nothing is cached
yet: the first daemon spends ~13 s of CPU on its kernels before it serves, and the first simulator ~10-20 s before
its first frame, so a newcomer's first demo showed a silent simulator and the daemon's ``no_frames`` and
``no_mavlink`` warnings. ``make demo`` runs this module once per install (and again when a kernel's source
changes): the daemon's kernels in one process, the simulator's in another, side by side on two cores.

The simulator's kernels are compiled by rendering the first two frames of the shipped scenes that use them (the
clean sky, the clouds, terrain, distractors and camera model of C1-C5) through :class:`~groundsim.world.sim.SimCore`,
as ``groundsim run`` does: the kernels see the argument types a real run passes, and nothing here lists them a
second time. numba checks each cached entry against its source file and this CPU, so a stale cache costs only the
compile it would have saved.

``python -m groundsim.app.warm``: prints one line per part and the seconds it took; exit status 1 when a part
failed (its error printed).
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import ProcessPoolExecutor

__all__ = ["SCENES", "warm_onboard", "warm_simulator", "main"]

#: the shipped scenes whose frames exercise every renderer path: the clean sky, then clouds, terrain, crossing
#: targets and birds, a hazy dim target, a real camera's artefacts
SCENES = ("P1", "C1", "C2", "C3", "C4", "C5")
FRAMES = 2  # the second frame too: what a renderer keeps from the first (its background, the camera's state)


def warm_onboard() -> str:
    """The daemon's kernels (the estimator's window problem, the image chain's passes)."""
    from onboard.estimation import kernels as estimation_kernels
    from onboard.imaging import kernels as imaging_kernels

    estimation_kernels.warm()
    imaging_kernels.warm()
    return "the daemon's kernels (estimator, image chain)"


def warm_simulator(names: tuple[str, ...] = SCENES) -> str:
    """The simulator's kernels: :data:`FRAMES` frames of each named shipped scenario rendered."""
    from groundsim.world.scenario import load_scenario, reference_scenario_paths
    from groundsim.world.sim import SimCore

    paths = reference_scenario_paths()
    unknown = [n for n in names if n not in paths]
    if unknown:
        raise ValueError(f"no shipped scenario {', '.join(unknown)} (config/scenarios has {', '.join(paths)})")
    for name in names:
        core = SimCore(load_scenario(paths[name]), 0, duration_s=1.0)
        for k in range(min(FRAMES, core.frame_count)):
            core.frame(k)
    return f"the simulator's kernels ({', '.join(names)} rendered)"


def main(scenes: tuple[str, ...] = SCENES) -> int:
    print("compiling the numba kernels once into their cache (later runs load them)", flush=True)
    t0 = time.perf_counter()
    failed = False
    # two processes, one a part: each compiles what the other does not need, so neither waits on the other
    with ProcessPoolExecutor(2) as pool:
        parts = [pool.submit(warm_onboard), pool.submit(warm_simulator, scenes)]
        for part in parts:
            try:
                what = part.result()
            except Exception as exc:  # noqa: BLE001 - printed, and the exit status says it
                print(f"warm: failed: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
                failed = True
            else:
                print(f"warm: {what}, {time.perf_counter() - t0:.1f} s", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
