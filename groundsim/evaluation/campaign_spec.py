"""A campaign's spec (``SPEC.yaml``, schema in ``docs/campaigns.md``) and the geometry variants it sweeps.

:func:`load_spec` validates a spec completely before anything runs (errors are one line
``<spec>: <field>: expected <what>, got <value>``, exit 2).  Geometry variants (:func:`derive_scenario`)
are made from a reference scenario's motion models; their definitions are in
:mod:`groundsim.evaluation.campaign`'s docstring.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from groundsim.world.motion import KinematicState, Motion, Perturbed
from groundsim.world.noise_cases import load_noise_cases
from groundsim.world.scenario import (
    MIN_SEPARATION_M,
    SINGER_MARGIN_S,
    Scenario,
    VehicleSpec,
    check_apart,
    load_scenario,
    reference_scenario_paths,
)
from groundsim.world.sim import frame_count
from groundsim.world.spec import SpecFail, check_integer, check_mapping, check_number, check_string, read_spec_yaml
from onboard.core.errors import ConfigError
from onboard.estimation.map_estimator import MapConfig

__all__ = [
    "MODES",
    "NOISE_MODELS",
    "MAX_RUNS",
    "MAX_SEED",
    "Geometry",
    "REFERENCE_GEOMETRY",
    "ManoeuvreScaled",
    "MovedTarget",
    "derive_scenario",
    "CampaignSpec",
    "load_spec",
    "spec_from_dict",
]

log = logging.getLogger(__name__)

MODES = ("synthetic", "closed_loop")
NOISE_MODELS = ("case", "config")
MAX_RUNS = 100_000  # a spec expanding past this is a mistake, not a campaign
MAX_SEED = 2**63 - 1  # the table's seed column is a 64-bit integer (runs.parquet could not hold a larger one)
#: a geometry axis's random draws are tried at most this many times the draws asked for: far more than a range with
#: room for them needs to give distinct values at 4 significant digits, few enough to refuse a range without room fast
DRAW_ATTEMPTS_PER_DRAW = 20
GROUND_CLEARANCE_M = 1.0  # a derived path must stay this far above the origin's ground plane (NED d < -1 m)


# --------------------------------------------------------------------------- geometry variants (pure)


@dataclass(frozen=True)
class Geometry:
    """A variant of a scenario's geometry (module docstring): ``range_scale`` (> 0), ``aspect_deg``,
    ``manoeuvre_scale`` (>= 0)."""

    range_scale: float = 1.0
    aspect_deg: float = 0.0
    manoeuvre_scale: float = 1.0

    def __post_init__(self) -> None:
        fail = SpecFail("<Geometry>")
        check_number(self.range_scale, "range_scale", fail, lo=0.0, lo_open=True)
        check_number(self.aspect_deg, "aspect_deg", fail, lo=-360.0, hi=360.0, unit="deg")
        check_number(self.manoeuvre_scale, "manoeuvre_scale", fail, lo=0.0)

    @property
    def is_reference(self) -> bool:
        return self.range_scale == 1.0 and self.aspect_deg == 0.0 and self.manoeuvre_scale == 1.0

    @property
    def label(self) -> str:
        return f"r{self.range_scale:g}_a{self.aspect_deg:g}_m{self.manoeuvre_scale:g}"


REFERENCE_GEOMETRY = Geometry()


def _rot_z(yaw_rad: float) -> np.ndarray:
    """R rotating NED vectors about +d by ``yaw_rad`` (north towards east)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ManoeuvreScaled:
    """``base`` with its acceleration history times ``scale``, from the same start position and velocity:
    ``p(t) = p0 + v0 t + scale (p_base(t) - p0 - v0 t)`` (so ``a(t) = scale a_base(t)``)."""

    base: Motion
    scale: float

    def state(self, t_s) -> KinematicState:
        t = np.asarray(t_s, dtype=float)
        s0 = self.base.state(np.zeros(1))
        p0, v0 = s0.p_ned_m[0], s0.v_ned_mps[0]
        b = self.base.state(t)
        tt = t[..., None]
        line = p0 + v0 * tt
        k = float(self.scale)
        return KinematicState(line + k * (b.p_ned_m - line), v0 + k * (b.v_ned_mps - v0) + 0.0 * tt, k * b.a_ned_mps2)


@dataclass(frozen=True)
class MovedTarget:
    """``base`` rotated about the vertical through ``pivot_ned_m`` by ``yaw_rad`` (north towards east),
    then translated by ``offset_ned_m``."""

    base: Motion
    pivot_ned_m: tuple
    yaw_rad: float
    offset_ned_m: tuple

    def state(self, t_s) -> KinematicState:
        b = self.base.state(t_s)
        R = _rot_z(self.yaw_rad)
        pivot = np.asarray(self.pivot_ned_m, dtype=float)
        p = pivot + np.asarray(self.offset_ned_m, dtype=float) + (b.p_ned_m - pivot) @ R.T
        return KinematicState(p, b.v_ned_mps @ R.T, b.a_ned_mps2 @ R.T)


def derive_scenario(
    scenario: Scenario, geometry: Geometry, source: str = "<campaign>", field: str = "geometry"
) -> Scenario:
    """The variant of ``scenario`` with ``geometry`` (module docstring); the reference geometry returns
    ``scenario`` itself.  Raises :class:`~groundsim.world.scenario.ScenarioError` naming ``source`` (the spec)
    and ``field`` when the variant's commanded paths come closer than ``MIN_SEPARATION_M`` or go below the
    ground."""
    if geometry.is_reference:
        return scenario
    obs_ref = scenario.observer.motion
    observer = obs_ref if geometry.manoeuvre_scale == 1.0 else ManoeuvreScaled(obs_ref, float(geometry.manoeuvre_scale))
    base = scenario.target.base_motion
    p_t0 = np.asarray(base.state(np.zeros(1)).p_ned_m[0], dtype=float)
    p_o0 = np.asarray(obs_ref.state(np.zeros(1)).p_ned_m[0], dtype=float)
    offset = (geometry.range_scale - 1.0) * (p_t0 - p_o0)
    tgt_base = MovedTarget(
        base, tuple(float(x) for x in p_t0), math.radians(geometry.aspect_deg), tuple(float(x) for x in offset)
    )
    dist = scenario.target.disturbance
    if dist is None:
        target = VehicleSpec(tgt_base)
    else:  # the disturbance spec is kept: run r's realisation is drawn as for the reference scenario
        run0 = dist.realise(scenario.duration_s + SINGER_MARGIN_S, scenario.rng("target.disturbance", 0))
        target = VehicleSpec(Perturbed(tgt_base, run0), tgt_base, dist)
    name = f"{scenario.name}_{geometry.label}"
    fail = SpecFail(source)
    t = scenario.frame_times_s()
    with np.errstate(all="ignore"):
        po, pt = observer.state(t).p_ned_m, tgt_base.state(t).p_ned_m
    what = (
        f"{scenario.name} with range_scale {geometry.range_scale:g}, aspect_deg {geometry.aspect_deg:g}, "
        f"manoeuvre_scale {geometry.manoeuvre_scale:g}"
    )
    check_apart(fail, field, f"a geometry whose paths stay {MIN_SEPARATION_M:g} m apart", po, pt, t, f"{what}: ")
    for who, p in (("observer", po), ("target", pt)):
        k = int(np.argmax(p[:, 2]))
        if not p[k, 2] < -GROUND_CLEARANCE_M:
            fail.text(
                field,
                f"a geometry whose paths stay {GROUND_CLEARANCE_M:g} m above the ground",
                f"{what}: the {who} at {-p[k, 2]:.3g} m up at t = {t[k]:.2f} s",
            )
    return dataclasses.replace(
        scenario,
        name=name,
        description=f"{scenario.description} [{geometry.label}]",
        observer=VehicleSpec(observer),
        target=target,
    )


# --------------------------------------------------------------------------- the spec


@dataclass(frozen=True)
class CampaignSpec:
    """A validated campaign spec (``docs/campaigns.md``).  ``scenario_paths`` resolve ``scenarios``;
    ``geometries`` is the expanded list (grid x draws); ``seeds`` the run seeds."""

    name: str
    mode: str
    scenarios: tuple[str, ...]
    scenario_paths: tuple[Path, ...]
    noise: tuple[str, ...]
    algorithms: tuple[str, ...]
    seeds: tuple[int, ...]
    geometries: tuple[Geometry, ...]
    duration_s: float | None = None
    noise_model: str = "case"
    crb: bool = True
    workers: int | None = None
    onboard_config: Path | None = None
    source: str = "<dict>"

    @property
    def run_count(self) -> int:
        return len(self.scenarios) * len(self.geometries) * len(self.noise) * len(self.algorithms) * len(self.seeds)


_SPEC_KEYS = (
    "name",
    "description",
    "mode",
    "scenarios",
    "noise",
    "algorithms",
    "seeds",
    "geometry",
    "duration_s",
    "noise_model",
    "crb",
    "workers",
    "onboard_config",
)
_GEOMETRY_AXES = ("range_scale", "aspect_deg", "manoeuvre_scale")
_AXIS_BOUNDS = {
    "range_scale": dict(lo=0.0, lo_open=True, hi=100.0),
    "aspect_deg": dict(lo=-360.0, hi=360.0),
    "manoeuvre_scale": dict(lo=0.0, hi=100.0),
}


def _name_list(v, path, fail, what) -> tuple[str, ...]:
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, list) or not v:
        fail(path, f"a non-empty list of {what}", v)
    out = tuple(check_string(x, f"{path}[{i}]", fail, what=what) for i, x in enumerate(v))
    dup = [x for x in out if out.count(x) > 1]
    if dup:
        fail(path, f"a list of distinct {what}", dup[0])
    return out


def _geometries(d, path, fail) -> tuple[Geometry, ...]:
    """``geometry:`` -> the expanded list: the grid of list axes x ``draws`` random draws of the {min, max} axes."""
    if d is None:
        return (REFERENCE_GEOMETRY,)
    check_mapping(d, path, fail, _GEOMETRY_AXES + ("draws", "seed"))
    grid: dict[str, list[float]] = {}
    ranges: dict[str, tuple[float, float]] = {}
    for axis in _GEOMETRY_AXES:
        p = f"{path}.{axis}"
        v = d.get(axis, [REFERENCE_GEOMETRY.__dict__[axis]])
        b = _AXIS_BOUNDS[axis]
        if isinstance(v, dict):
            check_mapping(v, p, fail, ("min", "max"), ("min", "max"))
            lo = check_number(v["min"], f"{p}.min", fail, **b)
            hi = check_number(v["max"], f"{p}.max", fail, **b)
            if not hi > lo:
                fail(f"{p}.max", f"a number > min ({lo:g})", v["max"])
            ranges[axis] = (lo, hi)
        else:
            if not isinstance(v, list) or not v:
                fail(p, "a non-empty list of numbers (grid) or {min: .., max: ..} (random draws)", v)
            vals = [check_number(x, f"{p}[{i}]", fail, **b) for i, x in enumerate(v)]
            if len(set(vals)) != len(vals):
                fail(p, "distinct values", v)
            grid[axis] = vals
    draws = 1
    if "draws" in d:
        if not ranges:
            fail(f"{path}.draws", "no draws unless an axis is random ({min: .., max: ..})", d["draws"])
        draws = check_integer(d["draws"], f"{path}.draws", fail, lo=1, hi=MAX_RUNS)
    elif ranges:
        fail(f"{path}.draws", "a number of random draws (required when an axis is {min: .., max: ..})")
    seed = check_integer(d.get("seed", 0), f"{path}.seed", fail, lo=0, hi=MAX_SEED)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6E0]))
    out: list[Geometry] = []
    import itertools

    axes = list(grid)
    for combo in itertools.product(*(grid[a] for a in axes)):
        base = dict(zip(axes, combo))
        drawn: dict[Geometry, None] = {}
        # a draw that rounds to one already drawn is drawn again (the draws before it, and so a spec whose draws never
        # repeat, are unchanged); a range too narrow to give `draws` distinct values ends the search
        for _ in range(DRAW_ATTEMPTS_PER_DRAW * draws):
            if len(drawn) == draws:
                break
            g = dict(base)
            for axis, (lo, hi) in ranges.items():  # 4 significant digits: readable labels, stable hashes
                g[axis] = float(f"{rng.uniform(lo, hi):.4g}")
            drawn[Geometry(**g)] = None
        if len(drawn) < draws:
            spans = ", ".join(f"{a} [{lo:g}, {hi:g}]" for a, (lo, hi) in ranges.items())
            fail.text(
                f"{path}.draws",
                f"at most as many draws as the random axes give distinct values at 4 significant digits ({spans})",
                f"{draws} draws, {len(drawn)} distinct",
                "widen the range or ask for fewer draws",
            )
        out.extend(drawn)
    return tuple(out)


def _beside_spec(path: Path, spec_dir: Path) -> Path:
    """``path`` as the spec means it: relative to the spec's directory (not to wherever the command runs), resolved."""
    return (spec_dir / path).resolve()


def _resolve_scenario(text: str, spec_dir: Path) -> Path:
    """A scenario entry's file: a shipped scenario's name (``P1``, ``p1``: no suffix, no '/') or a path."""
    p = Path(text)
    if p.suffix or "/" in text:
        return _beside_spec(p, spec_dir)
    shipped = {name.lower(): path for name, path in reference_scenario_paths().items()}  # P1 or p1
    return shipped.get(text.lower(), _beside_spec(p, spec_dir))


def spec_from_dict(d, source="<dict>", spec_dir: Path | None = None) -> CampaignSpec:
    """Validate a parsed spec mapping (``docs/campaigns.md``); raises ScenarioError (a ConfigError) naming
    ``source`` and the field.  Scenario files, noise cases and plug-in names are checked too."""
    fail = SpecFail(source)
    spec_dir = spec_dir or Path(".")
    check_mapping(d, "", fail, _SPEC_KEYS, ("scenarios", "noise", "algorithms"))
    name = check_string(
        d.get("name", Path(str(source)).stem or "campaign"),
        "name",
        fail,
        what="a name of letters, digits, '_', '.', '-'",
    )
    from groundsim.world.spec import NAME_PATTERN

    if not NAME_PATTERN.match(name):
        fail("name", "a name of letters, digits, '_', '.', '-'", name)
    check_string(d.get("description", ""), "description", fail)
    mode = check_string(d.get("mode", "synthetic"), "mode", fail, choices=MODES)
    scenarios = _name_list(d["scenarios"], "scenarios", fail, "scenario names or files")
    paths = []
    for i, s in enumerate(scenarios):
        p = _resolve_scenario(s, spec_dir)
        if not p.is_file():
            known = ", ".join(reference_scenario_paths())
            fail.text(
                f"scenarios[{i}]",
                f"a shipped scenario ({known}) or a scenario file",
                f"{s!r} (no file {p}: scenario files are relative to the spec's folder)",
            )
        same = [j for j, q in enumerate(paths) if q.resolve() == p.resolve()]
        if same:  # P1, p1 and config/scenarios/P1.yaml are one scenario: its runs would share their run ids
            fail(f"scenarios[{i}]", f"a scenario not listed before (scenarios[{same[0]}] is the same file)", s)
        paths.append(p)
    noise = _name_list(d["noise"], "noise", fail, "noise-case names")
    cases = load_noise_cases()
    for i, n in enumerate(noise):
        check_string(n, f"noise[{i}]", fail, choices=tuple(cases))
    algorithms = _name_list(d["algorithms"], "algorithms", fail, "estimator plug-in names")
    from onboard.pipeline.plugins import load_factory

    for i, a in enumerate(algorithms):
        option = f"{source}: algorithms[{i}]"
        try:
            load_factory(a, option=option)  # an unknown plug-in fails here, before any run
        except ConfigError as exc:  # not every refusal names the option (a module:Attribute that is a module)
            if str(exc).startswith(option):
                raise
            raise ConfigError(f"{option}: {exc}") from None
    seeds_v = d.get("seeds", 1)
    if isinstance(seeds_v, list):
        if not seeds_v:
            fail("seeds", "a count >= 1 or a non-empty list of run seeds >= 0", seeds_v)
        seeds = tuple(check_integer(s, f"seeds[{i}]", fail, lo=0, hi=MAX_SEED) for i, s in enumerate(seeds_v))
        if len(set(seeds)) != len(seeds):
            fail("seeds", "distinct run seeds", seeds_v)
    else:
        seeds = tuple(range(check_integer(seeds_v, "seeds", fail, lo=1, hi=MAX_RUNS)))
    geometries = _geometries(d.get("geometry"), "geometry", fail)
    duration = d.get("duration_s")
    if duration is not None:
        duration = check_number(duration, "duration_s", fail, lo=0.0, lo_open=True, unit="s")
    noise_model = check_string(
        d.get("noise_model", "case" if mode == "synthetic" else "config"), "noise_model", fail, choices=NOISE_MODELS
    )
    if mode == "closed_loop" and noise_model != "config":
        fail("noise_model", "config in closed_loop mode (the daemon's configuration is what runs)", noise_model)
    crb = d.get("crb", True)
    if not isinstance(crb, bool):
        fail("crb", "true or false", crb)
    workers = d.get("workers")
    if workers is not None:
        workers = check_integer(workers, "workers", fail, lo=1, hi=1024)
    onboard = d.get("onboard_config")
    if onboard is not None:
        onboard = Path(check_string(onboard, "onboard_config", fail, what="a path to an onboard configuration file"))
        onboard = _beside_spec(onboard, spec_dir)
        if not onboard.is_file():
            fail("onboard_config", "an existing onboard configuration file", str(onboard))
    spec = CampaignSpec(
        name=name,
        mode=mode,
        scenarios=scenarios,
        scenario_paths=tuple(paths),
        noise=noise,
        algorithms=algorithms,
        seeds=seeds,
        geometries=geometries,
        duration_s=duration,
        noise_model=noise_model,
        crb=crb,
        workers=workers,
        onboard_config=onboard,
        source=str(source),
    )
    if spec.run_count > MAX_RUNS:
        fail("(document)", f"at most {MAX_RUNS} runs", f"{spec.run_count} runs")
    names: dict[str, int] = {}
    min_frames = MapConfig().min_frames
    for i, p in enumerate(paths):  # every scenario loads, every variant is a valid geometry, the duration fits
        sc = load_scenario(p)
        if sc.is_fleet:  # a case flies one observer: the others would be left out of its runs without a word
            fail.text(
                f"scenarios[{i}]",
                "a scenario of one observer (python -m bench.fleet measures a fleet)",
                f"{scenarios[i]!r}, a fleet of {len(sc.observers)} ({', '.join(o.name for o in sc.observers)})",
            )
        if sc.name in names:  # rows, run ids and the report are keyed by the scenario's name
            fail.text(
                f"scenarios[{i}]",
                f"a scenario whose name is not scenarios[{names[sc.name]}]'s",
                f"{scenarios[i]!r}, named {sc.name}",
            )
        names[sc.name] = i
        if duration is not None and duration > sc.duration_s + 1e-9:
            fail("duration_s", f"at most {sc.name}'s duration_s ({sc.duration_s:g} s)", duration)
        if duration is not None and frame_count(duration, sc.frame_rate_hz) < min_frames:
            fail(
                "duration_s",
                f"a duration of at least {min_frames} frames of {sc.name}, the fewest the estimators solve "
                f"(> {(min_frames - 1) / sc.frame_rate_hz:g} s at {sc.frame_rate_hz:g} Hz)",
                duration,
            )
        for g in geometries:
            derive_scenario(sc, g, source=str(source))
    return spec


def load_spec(path) -> CampaignSpec:
    """Read and validate a campaign spec file; one-line ConfigError (exit 2) on any problem."""
    p = Path(path)
    return spec_from_dict(read_spec_yaml(p), source=p, spec_dir=p.parent)
