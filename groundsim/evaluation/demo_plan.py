"""The demo's plan (:mod:`groundsim.evaluation.demo`): everything checked and written before either child starts
-- the scenario extended to the demo's duration as ``groundsim run`` extends it, the daemon's configuration in
OUT/onboard.yaml, the free loopback ports -- and the two children's command lines.  A mistake raises ConfigError
before OUT is created."""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

from groundsim.evaluation.out_dir import make_out_dir, refuse_foreign_out
from groundsim.io.ports import free_tcp_port, free_udp_port
from groundsim.world.nav_errors import GnssDropout, InjectedErrors, run_nav_case
from groundsim.world.scenario import DEFAULT_NAV_NOISE
from onboard.core.checks import is_positive_number
from onboard.core.errors import ConfigError

__all__ = ["DEFAULT_DEMO_ONBOARD_CONFIG", "DEMO_OUTPUTS", "DemoPlan", "daemon_command", "plan_demo", "sim_command"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoPlan:
    """Everything the two children need.  Paths are inside ``out_dir``."""

    scenario: object  # groundsim.world.scenario.Scenario (the possibly extended one)
    scenario_path: Path
    duration_s: float
    seed: int
    out_dir: Path
    mavlink_port: int
    zenoh_port: int
    vehicle: str
    onboard_config_path: Path
    truth_path: Path
    python: str = sys.executable
    # the simulator's navigation-error case (RTK by default), GNSS dropout ...: passed to its groundsim run
    injected: InjectedErrors = field(default_factory=lambda: InjectedErrors(DEFAULT_NAV_NOISE))
    live_view_port: int | None = None  # passed to the daemon as --live-view PORT (Foxglove WebSocket on 127.0.0.1)
    daemon_prefix: tuple[str, ...] = ()  # run the daemon through this (bench.companion: into a CPU-limited cgroup)
    onboard_config_source: str = "(defaults)"  # the daemon's base configuration: a file, or the built-in defaults
    mount_as_configured: bool = False  # the daemon keeps that configuration's camera mount

    @property
    def zenoh_endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.zenoh_port}"


DEFAULT_DEMO_ONBOARD_CONFIG = "config/onboard.yaml"
DEFAULT_DEMO_DURATION_S = 20.0  # --duration not given: this long, or as long as the scenario can fly
CAP_STEP_S = 0.1  # a capped default duration is a multiple of this past the scenario's duration_s
PORT_MIN, PORT_MAX = 1, 65535  # --live-view: a TCP port (the daemon's live_view.port)


def _longest_extension_s(scenario, duration_s: float) -> float:
    """The longest duration up to ``duration_s`` that :func:`groundsim.world.sim.extend_scenario` accepts for
    ``scenario`` (its own ``duration_s`` at least), in ``CAP_STEP_S`` steps.  Bisection: an extension that is
    refused stays refused when longer (its checks cover the added time)."""
    from groundsim.world.sim import extend_scenario

    lo, hi = 0, max(0, math.floor((duration_s - scenario.duration_s) / CAP_STEP_S))
    while lo < hi:
        mid = (lo + hi + 1) // 2
        try:
            extend_scenario(scenario, scenario.duration_s + mid * CAP_STEP_S)
            lo = mid
        except ConfigError:
            hi = mid - 1
    return round(scenario.duration_s + lo * CAP_STEP_S, 6)


def _demo_scenario(scenario: str, duration_s: float | None):
    """The scenario (``--scenario``) extended to the demo's duration, its file and the duration, checked as
    ``groundsim run`` checks them (:func:`groundsim.world.sim.check_duration_s`, ``extend_scenario``).  A
    duration it cannot fly is refused naming ``--duration``; without ``--duration`` the default
    ``DEFAULT_DEMO_DURATION_S`` is capped at what the scenario can fly, with a note."""
    from groundsim.world.scenario import load_scenario, resolve_scenario_path
    from groundsim.world.sim import check_duration_s, extend_scenario

    path = resolve_scenario_path(scenario)
    sc = load_scenario(path)
    if sc.is_fleet:
        names = ", ".join(o.name for o in sc.observers)
        raise ConfigError(
            f"--scenario: {sc.name} has several observers ({names}); the demo runs one daemon for one observer:"
            " expected a scenario of one observer"
        )
    if duration_s is None:
        d = check_duration_s(DEFAULT_DEMO_DURATION_S, sc)
        try:
            return extend_scenario(sc, d), path, d
        except ConfigError as exc:
            capped = _longest_extension_s(sc, d)
            print(f"demo: {sc.name} flies at most {capped:g} s ({exc}); flying {capped:g} s", flush=True)
            return extend_scenario(sc, capped), path, capped
    d = check_duration_s(duration_s, sc)
    return extend_scenario(sc, d), path, d


def _check_live_view_port(port) -> int | None:
    if port is None:
        return None
    if isinstance(port, bool) or not isinstance(port, int) or not PORT_MIN <= port <= PORT_MAX:
        raise ConfigError(f"--live-view: expected a TCP port {PORT_MIN}..{PORT_MAX}, got {port!r}")
    return port


def plan_demo(
    scenario: str,
    duration_s: float | None,
    seed: int,
    out_dir,
    onboard_config: str | None,
    nav_noise: str | None = None,
    mount_as_configured: bool = False,
    gnss_dropout: GnssDropout | None = None,
    live_view_port: int | None = None,
    config_option: str = "--onboard-config",
) -> DemoPlan:
    """Load and check everything, then write OUT/onboard.yaml and pick the ports; a mistake raises
    ConfigError before OUT is created.  ``duration_s`` None: ``DEFAULT_DEMO_DURATION_S`` or as long as the
    scenario can fly (:func:`_demo_scenario`).  ``config_option``: the option that gave ``onboard_config``, which
    its errors name (another front end of the demo calls it otherwise).
    ``nav_noise``: the simulator's navigation-error case (None: the scenario's, RTK by default);
    ``gnss_dropout``: one for the simulator to inject (None: none);
    ``mount_as_configured``: the daemon keeps the configuration's camera mount (gimballed or not, angles)
    instead of the scenario's: what an operator's wrong mount configuration does;
    ``live_view_port``: the daemon's ``--live-view`` port (None: none)."""
    import yaml

    from groundsim.evaluation.eval import onboard_config_for
    from onboard.app.config import OnboardConfig, config_to_dict, load_config
    from onboard.io.zenoh_session import ZenohConfig

    if duration_s is not None and not is_positive_number(duration_s):
        raise ConfigError(f"--duration: expected a positive number of seconds, got {duration_s!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"--seed: expected an integer >= 0, got {seed!r}")
    live_view_port = _check_live_view_port(live_view_port)
    sc, sc_path, duration = _demo_scenario(scenario, duration_s)
    if gnss_dropout is not None:
        gnss_dropout.check_within(duration)
    if onboard_config == DEFAULT_DEMO_ONBOARD_CONFIG and not Path(onboard_config).is_file():
        # run from another folder: the shipped file of the installed tree, as eval and campaign take it, not the
        # built-in defaults without a word
        from groundsim.evaluation.eval import DEFAULT_ONBOARD_CONFIG

        if DEFAULT_ONBOARD_CONFIG.is_file():
            onboard_config = str(DEFAULT_ONBOARD_CONFIG)
    if onboard_config is not None and Path(onboard_config).is_file():
        base = load_config(onboard_config, environ={})
        config_source = str(onboard_config)
    elif onboard_config is not None and Path(onboard_config).is_dir():
        raise ConfigError(
            f"{config_option} {onboard_config}: a directory, not a file; give the daemon's configuration (a YAML file)"
        )
    elif onboard_config is not None and onboard_config != DEFAULT_DEMO_ONBOARD_CONFIG:
        raise ConfigError(f"{config_option} {onboard_config}: no such file")
    else:
        base = OnboardConfig()
        config_source = "(defaults)"
    nav = run_nav_case(sc, nav_noise).name
    cfg = onboard_config_for(sc, base)
    if mount_as_configured:
        cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, mount=base.camera.mount))
    # a demo writes its onboard.yaml, report, truth, logs and plots by name: in a folder of anything else (a user's
    # own onboard.yaml or report.md) it would replace them; an earlier demo's folder it clears first (below)
    refuse_foreign_out(out_dir, _earlier_demo, "groundsim demo", "onboard.yaml of a demo")
    out = make_out_dir(out_dir)
    earlier = _earlier_demo(out)  # read before this demo's onboard.yaml replaces the earlier one's
    mav, zport = free_udp_port(), free_tcp_port()
    raw = config_to_dict(cfg)
    raw["mavlink"]["connection"] = f"udpin:127.0.0.1:{mav}"
    raw["zenoh"] = config_to_dict(ZenohConfig(listen=(f"tcp/127.0.0.1:{zport}",)))
    raw["output"]["health_file"] = str((out / "onboard.alive").resolve())
    path = out / "onboard.yaml"
    header = (
        f"{DEMO_MARK} from {config_source}:\n"
        f"# scenario {sc.name}'s camera, {'the configured mount' if mount_as_configured else 'mount'} and origin; "
        "loopback endpoints; positions published even when unobservable\n"
    )
    path.write_text(header + yaml.safe_dump(raw, sort_keys=False), encoding="utf-8")
    load_config(path, environ={})  # what the daemon will read must be valid
    if earlier:  # every check passed: this demo runs, and the earlier one's results must not pass for its
        _clear_earlier_demo(out)
    return DemoPlan(
        sc,
        Path(sc_path),
        duration,
        int(seed),
        out,
        mav,
        zport,
        cfg.vehicle,
        path,
        out / "truth.csv",
        injected=InjectedErrors(nav, gnss_dropout),
        live_view_port=live_view_port,
        onboard_config_source=config_source,
        mount_as_configured=bool(mount_as_configured),
    )


#: what a demo writes in OUT (its live run's files, the children's logs; ``eval/`` the evaluation's folder)
DEMO_OUTPUTS = (
    "report.json",
    "report.md",
    "tracks.jsonl",
    "truth.csv",
    "truth.tum",
    "estimate.tum",
    "trajectory.png",
    "error.png",
    "onboard.log",
    "sim.log",
)


#: the first words of the onboard.yaml a demo writes in OUT: what marks a folder as a demo's
DEMO_MARK = "# generated by `python -m groundsim demo`"


def _earlier_demo(out: Path) -> bool:
    """Whether ``out`` holds an earlier demo's results: its generated onboard.yaml is there."""
    try:
        with open(out / "onboard.yaml", encoding="utf-8") as f:
            return f.read(len(DEMO_MARK)) == DEMO_MARK
    except (OSError, UnicodeDecodeError):
        return False


def _clear_earlier_demo(out: Path) -> None:
    """An earlier demo's results in ``out`` go before this one starts: an interrupted run, or one without the
    evaluation, must not leave them beside its own as if they were its (a report of another run, a stale eval/).
    Called only for a folder an earlier demo wrote (:func:`_earlier_demo`), once this one's checks have passed;
    only the demo's own file names (and an ``eval/`` holding an evaluation's report) are removed, and said."""
    import shutil

    gone = [name for name in DEMO_OUTPUTS if (out / name).is_file()]
    for name in gone:
        (out / name).unlink()
    ev = out / "eval"
    if ev.is_dir() and ((ev / "report.json").is_file() or (ev / "report.md").is_file()):
        shutil.rmtree(ev)
        gone.append("eval/")
    if gone:
        log.warning("%s held an earlier demo's results; removed: %s", out, ", ".join(gone))


def daemon_command(plan: DemoPlan) -> list[str]:
    live = [] if plan.live_view_port is None else ["--live-view", str(int(plan.live_view_port))]
    return [*plan.daemon_prefix, plan.python, "-m", "onboard", "--config", str(plan.onboard_config_path), *live]


def sim_command(plan: DemoPlan) -> list[str]:
    return [
        plan.python,
        "-m",
        "groundsim",
        "run",
        "--scenario",
        str(plan.scenario_path),
        "--seed",
        str(plan.seed),
        "--duration",
        f"{plan.duration_s:g}",
        "--rate",
        "realtime",
        "--mavlink",
        f"udpout:127.0.0.1:{plan.mavlink_port}",
        "--zenoh-connect",
        plan.zenoh_endpoint,
        "--zenoh-connect-timeout",
        "10",
        "--vehicle",
        plan.vehicle,
        "--truth",
        str(plan.truth_path),
        *plan.injected.run_options(),
    ]
