"""The selected target's 3-D in the reference scenes C1-C5, against each scene's clean-sky twin.

``python -m bench.scenes3d [--scenes C1 C2 C3 C4 C5] [--seeds N] [--duration S] [--nav-noise RTK]
[--chain objects|single] [--onboard-config FILE] [--noise-twins K] [--no-other-targets] [--workers N]
[--json FILE]``; ``--table-from FILE`` prints a ``--json`` file's runs and table again without running.

Each (scene, seed) is flown twice through the lockstep closed loop of ``groundsim eval``
(:func:`groundsim.evaluation.eval.run_lockstep`: the simulator's flight, renderer and MAVLink-quantised
telemetry with the run's navigation errors, RTK by default, into the daemon's :class:`FramePipeline`, its
image chain and sliding-window estimator, frame by frame, deterministic):

* the **scene** as shipped (``config/scenarios/C*.yaml``);
* its **clean-sky twin** (:func:`clean_twin`): the same scenario with its ``scene`` section set to the
  default (no clouds, terrain, distractors, nor camera model: every part off) and no ``other_targets``.
  Everything else is the scene's: the observer's and the target's flight, the gimbal's pointing, the
  camera, the ``ir`` section (band, NETD, haze, encoding: C4's twin is its dim target, mono16, on a clean
  sky), the scenario seed and so every random stream of the flight and of the navigation errors (streams
  are named, :meth:`Scenario.rng`, so switching the scene off shifts none of them).  Only the pixels
  differ, and the pixel noise with them (the renderer's own noise stream instead of the camera model's).
* with ``--noise-twins K``, K **noise twins** per seed (:func:`noise_twin`): the clean-sky twin again with
  nothing but its render-noise stream drawn from another name, so the same poses and navigation errors
  under other sensor noise.  Where range is unobservable (C2, C3: straight constant-velocity flights), the
  median error is where the estimate happens to sit inside its own wide sigma, and how far the twins' medians
  spread among themselves is the yardstick a scene/twin ratio has to be read against.

``--no-other-targets`` removes the scene's ``other_targets`` (C3's crossing second target) from every run,
keeping the rest of the scene: what the second target costs, alone.

Both go through the same daemon configuration: the shipped ``config/onboard.yaml`` with
``imaging.chain: objects``, the default (``--chain single`` for the one-blob chain, which locks clutter on C1-C4;
docs/perception.md), the scenario's camera and unobservable positions published (as ``groundsim eval``).

Per run and pooled over the seeds, per scene (definitions in :func:`run_figures` / :func:`pair_row`):
frames with a 3-D position, the median error of those positions (m, and per cent of the range) for the
scene and its twin and their ratio (asked: <= 1.5), the ratio on the frames where both have a position,
the share of positions beyond 3 sigma (asked: <= 1 %), the observable fraction and the share of visible
frames whose measured centre is on the target (within 3 px of its truth pixel: a wrong object selected
shows here first), the angular (cross-range) error's median and its scene / twin ratio (what the image
gives: the line of sight, without the range it cannot give), the twins' noise spread, the frames whose
measured centre is on the target but pulled more than 0.3 px off its truth pixel (a neighbour blended in),
and the estimator's resets.

Numbers only; nothing asserts.  Timing is not measured here (``python -m bench.onboard --scene C1``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
from dataclasses import dataclass, field
from typing import Annotated

from onboard.core.blas import single_thread_blas_env  # noqa: E402 - imports nothing but os

if __name__ == "__main__":  # one BLAS thread per process: must precede the numpy import
    single_thread_blas_env()

import numpy as np  # noqa: E402

from bench import run_benchmark, write_json  # noqa: E402
from bench.options import (  # noqa: E402
    BenchParser,
    json_runs,
    known_nav_noise,
    known_scenario,
    nonnegative_int,
    output_file,
    positive_float,
    positive_int,
)
from groundsim.world.scenario import Scenario, ScenarioError  # noqa: E402
from onboard.core.schema import Integer, config_dataclass  # noqa: E402

__all__ = [
    "SCENES",
    "RATIO_LIMIT",
    "BEYOND_3SIGMA_LIMIT",
    "ON_TARGET_PX",
    "PULLED_PX",
    "clean_twin",
    "noise_twin",
    "NoiseTwinScenario",
    "RunFigures",
    "run_figures",
    "pair_row",
    "format_table",
    "main",
]

SCENES = ("C1", "C2", "C3", "C4", "C5")
RATIO_LIMIT = 1.5  # the scene's median 3-D error at most this times its twin's (issue's figure)
BEYOND_3SIGMA_LIMIT = 0.01  # at most this share of published positions beyond 3 sigma
ON_TARGET_PX = 3.0  # a measured centre this close to the target's truth pixel is on the target
# an on-target centre farther than this from the truth pixel is "pulled": the chain's centroid error on a clean
# sky is ~0.05-0.1 px (docs/perception.md), so 0.3 px is something else in the blob (a crossing neighbour)
PULLED_PX = 0.3


def clean_twin(scenario):
    """``scenario``'s clean-sky twin: its ``scene`` section at the default (every part off) and no
    ``other_targets``; everything else, the seed included, unchanged (module docstring)."""
    from groundsim.world.render.scene_config import SceneConfig

    return dataclasses.replace(scenario, scene=SceneConfig(), other_targets=())


@config_dataclass(error=ScenarioError, kw_only=True)
class NoiseTwinScenario(Scenario):
    """A :class:`Scenario` whose ``"render.noise"`` stream (the renderer's sensor noise) is drawn from the name
    ``"render.noise/<render_noise_draw>"``; every other stream, and so the flight, the gimbal's pointing and the
    navigation errors, is the scenario's (streams are keyed by name: :meth:`Scenario.rng`).
    ``render_noise_draw`` 0: the scenario's own noise."""

    render_noise_draw: Annotated[int, Integer(0)] = 0

    def rng(self, stream: str, run_seed: int = 0) -> np.random.Generator:
        if stream == "render.noise" and self.render_noise_draw:
            stream = f"{stream}/{self.render_noise_draw}"
        return super().rng(stream, run_seed)


def noise_twin(scenario, draw: int):
    """``scenario``'s clean-sky twin (:func:`clean_twin`) with its render noise from draw ``draw`` >= 1
    (:class:`NoiseTwinScenario`): the same flight and navigation errors, other pixel noise.  ``draw`` 0: the twin."""
    twin = clean_twin(scenario)
    fields = {f.name: getattr(twin, f.name) for f in dataclasses.fields(twin)}
    return NoiseTwinScenario(**fields, render_noise_draw=int(draw))


@dataclass(frozen=True)
class RunFigures:
    """One lockstep run's 3-D figures.  Per published position (a finite 3-D estimate in the frame's track,
    observable or not, as the daemon publishes with ``output.unobservable_positions``): ``frame`` (index in
    the run), ``err_m`` (Euclidean error against the truth), ``err_range_pct`` (per cent of the true range),
    ``beyond_3sigma`` (``err_m > 3 sqrt(trace cov)``: the honesty test of ``groundsim eval``'s closed-loop
    figures), ``observable``, ``angle_mrad`` (the cross-range error: the angle at the true camera centre between
    the lines to the estimate and to the truth; times the true range it is the error across the line of sight).
    Per run: ``frames`` processed, ``visible`` frames (target in the image), ``on_target`` of them (measured centre
    within :data:`ON_TARGET_PX` of the truth pixel), ``pulled`` of those (farther than :data:`PULLED_PX`),
    ``max_pull_px`` (the largest on-target offset; NaN: none on target), ``resets`` (the pipeline's estimator
    resets, ``RunResult.counters["estimator_resets"]``), ``first_position_s`` (from the run's first frame; NaN:
    none), ``error`` (a failed run's one line, else None).  ``twin``: a clean-sky twin; ``noise_draw``: which
    (0 the twin, k >= 1 its k-th noise twin)."""

    scenario: str
    seed: int
    twin: bool
    frames: int
    visible: int
    on_target: int
    frame: np.ndarray
    err_m: np.ndarray
    err_range_pct: np.ndarray
    beyond_3sigma: np.ndarray
    observable: np.ndarray
    first_position_s: float = math.nan
    error: str | None = None
    noise_draw: int = 0
    angle_mrad: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pulled: int = 0
    max_pull_px: float = math.nan
    resets: int = 0

    @property
    def positions(self) -> int:
        return int(self.frame.size)


def run_figures(r, twin: bool, noise_draw: int = 0) -> RunFigures:
    """:class:`RunFigures` of a :class:`groundsim.evaluation.eval.RunResult` (or any object with its arrays)."""
    empty_f, empty_b = np.zeros(0), np.zeros(0, dtype=bool)
    if r.error is not None or r.frames == 0:
        return RunFigures(r.scenario, r.seed, twin, r.frames, 0, 0, np.zeros(0, int), empty_f, empty_f, empty_b, empty_b,
                          error=r.error or "no frame processed", noise_draw=noise_draw)  # fmt: skip
    est = np.asarray(r.est_p_ned_m, dtype=float)
    cov = np.asarray(r.est_cov_ned_m2, dtype=float)
    with np.errstate(invalid="ignore"):
        sig3 = 3.0 * np.sqrt(np.maximum(np.einsum("fii->f", cov), 0.0))
    pub = np.all(np.isfinite(est), axis=1) & np.isfinite(sig3)
    truth = np.asarray(r.truth_p_ned_m, dtype=float)
    e = np.linalg.norm(est - truth, axis=1)
    # the angle between the camera-to-estimate and camera-to-truth lines (atan2 of |a x b| and a . b: exact at
    # small angles, where the arccos of the normalised dot product is not)
    cam = np.asarray(r.cam_p_ned_m, dtype=float)
    a, b = est - cam, truth - cam
    angle_mrad = 1e3 * np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("fi,fi->f", a, b))
    visible = np.asarray(r.visible, dtype=bool)
    d_px = np.linalg.norm(np.asarray(r.uv_px, dtype=float) - np.asarray(r.truth_uv_px, dtype=float), axis=1)
    on = visible & np.asarray(r.measurement_valid, dtype=bool) & (d_px <= ON_TARGET_PX)  # NaN compares False
    t = np.asarray(r.t_s, dtype=float)
    counters = getattr(r, "counters", None) or {}
    return RunFigures(
        scenario=r.scenario,
        seed=int(r.seed),
        twin=twin,
        frames=int(r.frames),
        visible=int(visible.sum()),
        on_target=int(on.sum()),
        frame=np.flatnonzero(pub),
        err_m=e[pub],
        err_range_pct=100.0 * e[pub] / np.asarray(r.range_m, dtype=float)[pub],
        beyond_3sigma=e[pub] > sig3[pub],
        observable=np.asarray(r.observable, dtype=bool)[pub],
        first_position_s=float(t[pub][0] - t[0]) if pub.any() else math.nan,
        noise_draw=int(noise_draw),
        angle_mrad=angle_mrad[pub],
        pulled=int((on & (d_px > PULLED_PX)).sum()),
        max_pull_px=float(d_px[on].max()) if on.any() else math.nan,
        resets=int(counters.get("estimator_resets", 0)),
    )


def _median(a) -> float:
    return float(np.median(a)) if len(a) else math.nan


def _share(num: int, den: int) -> float:
    return num / den if den else math.nan


def pair_row(scene: list[RunFigures], twin: list[RunFigures], noise_twins: list[RunFigures] = ()) -> dict:
    """One scene's row, pooled over its seeds: every published position of every run counts once.

    ``positions`` (scene, twin), ``frames``; ``median_err_m`` / ``median_err_range_pct``: the median over
    the pooled positions (``median_err_observable_range_pct``: over those flagged observable only); ``ratio``: the scene's median error (per cent of range) over its twin's (asked
    <= :data:`RATIO_LIMIT`); ``ratio_common``: the same on the (seed, frame) pairs where both published a
    position (same frames, same ranges, same window age: what is left is the image); ``beyond_3sigma``: share
    of published positions (asked <= :data:`BEYOND_3SIGMA_LIMIT`); ``observable``: observable positions /
    frames processed; ``on_target``: on-target frames / visible frames; ``met``: both asks met by the scene
    (None when a ratio cannot be formed).  Runs are paired by seed; a failed run counts in ``failed``.

    ``median_angle_mrad``: the median cross-range error (:class:`RunFigures`), ``angular_ratio`` the scene's
    over the twin's; ``pulled`` (on-target frames pulled beyond :data:`PULLED_PX`) and ``resets``: sums over the
    runs.  ``noise_twins`` (the runs of ``--noise-twins``, any draws >= 1): ``noise_medians`` the median error
    (per cent of range) of each draw, the twin's first, each pooled over the seeds like the ratio;
    ``noise_spread`` their max / min (NaN without noise twins): a scene/twin ratio within [1 / spread, spread]
    is no farther from the twin than other sensor noise takes the twin itself."""

    def pooled(runs: list[RunFigures]) -> dict:
        ok = [f for f in runs if f.error is None]
        err_m = np.concatenate([f.err_m for f in ok]) if ok else np.zeros(0)
        pct = np.concatenate([f.err_range_pct for f in ok]) if ok else np.zeros(0)
        obs = np.concatenate([f.observable for f in ok]) if ok else np.zeros(0, dtype=bool)
        n_pos = int(err_m.size)
        frames = sum(f.frames for f in ok)
        return {
            "runs": len(runs),
            "failed": len(runs) - len(ok),
            "frames": frames,
            "positions": n_pos,
            "median_err_m": _median(err_m),
            "median_err_range_pct": _median(pct),
            "median_err_observable_range_pct": _median(pct[obs]) if n_pos else math.nan,
            "beyond_3sigma": _share(int(sum(int(f.beyond_3sigma.sum()) for f in ok)), n_pos),
            "observable": _share(int(sum(int(f.observable.sum()) for f in ok)), frames),
            "on_target": _share(sum(f.on_target for f in ok), sum(f.visible for f in ok)),
            "first_position_s": _median([f.first_position_s for f in ok if math.isfinite(f.first_position_s)]),
            "median_angle_mrad": _median(np.concatenate([f.angle_mrad for f in ok])) if ok else math.nan,
            "pulled": sum(f.pulled for f in ok),
            "resets": sum(f.resets for f in ok),
        }

    s, t = pooled(scene), pooled(twin)
    common_s, common_t = [], []
    twins = {f.seed: f for f in twin if f.error is None}
    for f in scene:
        g = twins.get(f.seed)
        if f.error is not None or g is None:
            continue
        _, i, j = np.intersect1d(f.frame, g.frame, assume_unique=True, return_indices=True)
        common_s.append(f.err_range_pct[i])
        common_t.append(g.err_range_pct[j])
    cs = np.concatenate(common_s) if common_s else np.zeros(0)
    ct = np.concatenate(common_t) if common_t else np.zeros(0)
    ratio = s["median_err_range_pct"] / t["median_err_range_pct"] if t["median_err_range_pct"] > 0 else math.nan
    ratio_common = _median(cs) / _median(ct) if ct.size and _median(ct) > 0 else math.nan
    angular_ratio = (
        s["median_angle_mrad"] / t["median_angle_mrad"] if t["median_angle_mrad"] > 0 else math.nan
    )  # NaN compares False
    noise_medians = [t["median_err_range_pct"]] + [
        pooled([f for f in noise_twins if f.noise_draw == k])["median_err_range_pct"]
        for k in sorted({f.noise_draw for f in noise_twins})
    ]
    finite = [m for m in noise_medians if math.isfinite(m) and m > 0]
    noise_spread = max(finite) / min(finite) if len(finite) > 1 else math.nan
    met = None
    if math.isfinite(ratio):
        met = bool(
            ratio <= RATIO_LIMIT and math.isfinite(s["beyond_3sigma"]) and s["beyond_3sigma"] <= BEYOND_3SIGMA_LIMIT
        )
    name = scene[0].scenario if scene else (twin[0].scenario if twin else "?")
    return {
        "scenario": name,
        "scene": s,
        "twin": t,
        "ratio": ratio,
        "common_positions": int(cs.size),
        "ratio_common": ratio_common,
        "angular_ratio": angular_ratio,
        "noise_medians": noise_medians,
        "noise_spread": noise_spread,
        "met": met,
    }


def _f(x: float, fmt: str, scale: float = 1.0) -> str:
    return "-" if x is None or not math.isfinite(x) else format(scale * x, fmt)


def format_run(f: RunFigures) -> str:
    """One line per run."""
    kind = (f"twin{f.noise_draw}" if f.noise_draw else "twin ") if f.twin else "scene"
    if f.error is not None:
        return f"   {f.scenario} s{f.seed} {kind}: failed: {f.error}"
    return (
        f"   {f.scenario} s{f.seed} {kind}: {f.frames} frames, {f.positions} with a 3-D position (first at"
        f" {_f(f.first_position_s, '.1f')} s); median error {_f(_median(f.err_m), '.1f')} m"
        f" ({_f(_median(f.err_range_pct), '.1f')} % of range); beyond 3 sigma"
        f" {_f(_share(int(f.beyond_3sigma.sum()), f.positions), '.1f', 100)} %; observable"
        f" {_f(_share(int(f.observable.sum()), f.frames), '.0f', 100)} % of frames; on target"
        f" {_f(_share(f.on_target, f.visible), '.1f', 100)} % of visible frames ({f.pulled} pulled > {PULLED_PX:g} px,"
        f" at most {_f(f.max_pull_px, '.2f')} px); angular error {_f(_median(f.angle_mrad), '.2f')} mrad;"
        f" {f.resets} estimator resets"
    )


def format_table(rows: list[dict]) -> str:
    """The per-scene table (markdown), scene / twin in each cell."""
    lines = [
        "| scene | seeds | frames with a 3-D position | median error, m | median error, % of range |"
        f" ratio (<= {RATIO_LIMIT:g}) | ratio, common frames | beyond 3 sigma (<= {100 * BEYOND_3SIGMA_LIMIT:g} %) |"
        " observable, % of frames | median error of observable positions, % of range | on target, % of visible"
        f" frames | pulled > {PULLED_PX:g} px, frames | estimator resets | angular error, mrad | angular ratio |"
        " noise spread (twins) | met |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        s, t = row["scene"], row["twin"]
        failed = f" ({s['failed']} + {t['failed']} failed)" if s["failed"] or t["failed"] else ""
        met = "-" if row["met"] is None else ("yes" if row["met"] else "no")
        if row["met"] is not None and not t["observable"]:  # two unobservable estimates: their ratio says little
            met += " (unobservable)"
        lines.append(
            f"| {row['scenario']} | {s['runs']}{failed} | {s['positions']} / {t['positions']} |"
            f" {_f(s['median_err_m'], '.1f')} / {_f(t['median_err_m'], '.1f')} |"
            f" {_f(s['median_err_range_pct'], '.1f')} / {_f(t['median_err_range_pct'], '.1f')} |"
            f" {_f(row['ratio'], '.2f')} | {_f(row['ratio_common'], '.2f')} ({row['common_positions']}) |"
            f" {_f(s['beyond_3sigma'], '.2f', 100)} / {_f(t['beyond_3sigma'], '.2f', 100)} % |"
            f" {_f(s['observable'], '.0f', 100)} / {_f(t['observable'], '.0f', 100)} |"
            f" {_f(s['median_err_observable_range_pct'], '.2f')} / {_f(t['median_err_observable_range_pct'], '.2f')} |"
            f" {_f(s['on_target'], '.1f', 100)} / {_f(t['on_target'], '.1f', 100)} |"
            f" {s['pulled']} / {t['pulled']} | {s['resets']} / {t['resets']} |"
            f" {_f(s['median_angle_mrad'], '.2f')} / {_f(t['median_angle_mrad'], '.2f')} |"
            f" {_f(row['angular_ratio'], '.2f')} | {_f(row['noise_spread'], '.2f')} ({len(row['noise_medians'])}) |"
            f" {met} |"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------- runs


def _job(args) -> RunFigures:
    """One lockstep run (in a pool worker or here), reduced to its figures; a run that cannot be made fails alone."""
    from groundsim.evaluation.eval import run_lockstep
    from groundsim.evaluation.parallel import report_progress
    from onboard.core.errors import IrtrackError

    # draw: None the scene, 0 its clean-sky twin, k >= 1 the twin's k-th noise twin
    scenario, seed, draw, options, cfg = args
    twin = draw is not None
    flown = scenario if draw is None else (clean_twin(scenario) if draw == 0 else noise_twin(scenario, draw))
    try:
        r = run_lockstep(flown, seed, options, cfg, report_progress)
    except IrtrackError as exc:
        from types import SimpleNamespace

        return run_figures(
            SimpleNamespace(scenario=scenario.name, seed=seed, frames=0, error=str(exc)), twin, draw or 0
        )
    return run_figures(r, twin, draw or 0)


def onboard_config(path: str | None, chain: str):
    """The daemon's configuration for both runs: ``path`` (default the shipped ``config/onboard.yaml``) with
    ``imaging.chain`` set to ``chain``."""
    from groundsim.evaluation.eval import DEFAULT_ONBOARD_CONFIG
    from onboard.app.config import load_config

    src = path if path is not None else (DEFAULT_ONBOARD_CONFIG if DEFAULT_ONBOARD_CONFIG.is_file() else None)
    return load_config(src, overrides={"imaging.chain": (chain, "bench.scenes3d --chain")}, environ={})


def figures_from_json(runs: list[dict]) -> list[RunFigures]:
    """The runs of a ``--json`` file back as :class:`RunFigures` (``--table-from``)."""
    arrays = {
        "frame": int,
        "err_m": float,
        "err_range_pct": float,
        "beyond_3sigma": bool,
        "observable": bool,
        "angle_mrad": float,
    }
    out = []
    for d in runs:
        kw = {k: (np.asarray(v, dtype=arrays[k]) if k in arrays else v) for k, v in d.items()}
        out.append(RunFigures(**kw))
    return out


def _runs_file(text: str) -> list[dict]:
    """``--table-from``: the runs of a ``--json`` file (:func:`json_runs`), one at least: a file of none would print
    an empty table and exit 0, as if it held results."""
    runs = json_runs(text)
    if not runs:
        raise argparse.ArgumentTypeError(f"{text!r}: no runs in it")
    return runs


def _report(figures: list[RunFigures], names: list[str]) -> list[dict]:
    """Print one line per run and the per-scene table; the rows."""
    for f in figures:
        print(format_run(f))
    rows = [
        pair_row(
            [f for f in figures if f.scenario == name and not f.twin],
            [f for f in figures if f.scenario == name and f.twin and not f.noise_draw],
            [f for f in figures if f.scenario == name and f.twin and f.noise_draw],
        )
        for name in names
    ]
    print(format_table(rows))
    return rows


def main(argv=None) -> int:
    from groundsim.evaluation.eval import EvalOptions
    from groundsim.evaluation.parallel import limit_blas_threads, progress_bar, quiet_run_logs, run_jobs
    from groundsim.world.nav_errors import InjectedErrors
    from groundsim.world.scenario import DEFAULT_NAV_NOISE, load_scenario, resolve_scenario_path
    from groundsim.world.sim import frame_count

    ap = BenchParser(prog="python -m bench.scenes3d", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", type=known_scenario, default=list(SCENES), help="scenarios (default C1-C5)")
    ap.add_argument("--seeds", type=positive_int, default=2, help="run seeds 0..N-1 per scene (default 2)")
    ap.add_argument(
        "--duration", type=positive_float, default=None, help="seconds flown (default the scenario's, 10 s)"
    )
    ap.add_argument(
        "--nav-noise", type=known_nav_noise, default=DEFAULT_NAV_NOISE, help="navigation-error case (default RTK)"
    )
    ap.add_argument("--chain", choices=("objects", "single"), default="objects", help="imaging.chain (default objects)")
    ap.add_argument("--onboard-config", default=None, help="the daemon's configuration (default config/onboard.yaml)")
    ap.add_argument(
        "--noise-twins",
        type=nonnegative_int,
        default=0,
        help="K more twins per seed, only the render noise changed (default 0)",
    )
    ap.add_argument("--no-other-targets", action="store_true", help="fly every run without the scene's other_targets")
    ap.add_argument("--workers", type=positive_int, default=1, help="processes (default 1: the machine is shared)")
    ap.add_argument(
        "--json", type=output_file, default=None, metavar="FILE", help="also write the rows and runs as JSON here"
    )
    ap.add_argument(
        "--table-from",
        type=_runs_file,
        default=None,
        metavar="FILE",
        help="run nothing: print the runs and table of this --json file",
    )
    args = ap.parse_args(argv)
    if args.table_from is not None:
        try:
            figures = figures_from_json(args.table_from)
        except (TypeError, ValueError) as exc:  # runs of another benchmark, or edited: fields missing or unknown
            ap.error(f"argument --table-from: not the runs of a bench.scenes3d --json file ({exc})")
        _report(figures, list(dict.fromkeys(f.scenario for f in figures)))
        return 0
    limit_blas_threads(1)
    with quiet_run_logs():
        scenarios = [load_scenario(resolve_scenario_path(n)) for n in args.scenes]
        if args.no_other_targets:
            scenarios = [dataclasses.replace(sc, other_targets=()) for sc in scenarios]
        options = EvalOptions(
            duration_s=args.duration, batch=False, keep_frame=False, injected=InjectedErrors(args.nav_noise)
        )
        cfg = onboard_config(args.onboard_config, args.chain)
        draws = (None, *range(args.noise_twins + 1))  # the scene, its twin, the twin's noise twins
        jobs = [(sc, seed, draw, options, cfg) for sc in scenarios for seed in range(args.seeds) for draw in draws]
        total = sum(frame_count(args.duration or sc.duration_s, sc.frame_rate_hz) for sc, *_ in jobs)
        print(
            f"bench.scenes3d: {', '.join(sc.name for sc in scenarios)} x {args.seeds} seed(s), each beside its clean-sky"
            f" twin and {args.noise_twins} noise twin(s){' (no other targets)' if args.no_other_targets else ''};"
            f" lockstep, navigation errors {args.nav_noise}, imaging.chain {args.chain};"
            f" {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}",
            flush=True,
        )
        bar = progress_bar(total, "frame", "scenes3d")
        try:
            figures = run_jobs(_job, jobs, min(args.workers, len(jobs)), bar.update)
        finally:
            bar.close()
    rows = _report(figures, [sc.name for sc in scenarios])
    if args.json:
        runs = [
            {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in dataclasses.asdict(f).items()}
            for f in figures
        ]
        write_json(args.json, {"rows": rows, "runs": runs, "options": vars(args)}, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(run_benchmark("scenes3d", main))
