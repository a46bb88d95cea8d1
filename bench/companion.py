"""``python -m bench.companion --cpu-quota 0.5``: the realistic flow with the daemon under a CFS CPU quota,
beside the same flow unconstrained, one run after the other.

The flow is ``python -m groundsim demo``'s (:mod:`groundsim.evaluation.demo`): the daemon with the
container's configuration (``deploy/onboard.container.yaml``, with the scenario's camera and loopback
endpoints) and ``groundsim run`` in real time (P2, RTK, 20 s by default), scored against the truth.

The quota: the daemon (and the estimator worker and fork server it starts, which inherit the group)
runs in a cgroup of its own created by this bench, cgroup v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``
with a 100 ms period, as ``deploy.resources.limits.cpus`` does in a container.  Creating it needs write
access to the cgroup tree (root, or a delegated subtree); when that fails the bench says so in one line
and **emulates** the quota: a thread reads the CPU of the daemon's process tree every 5 ms
(``/proc/<pid>/task/*/schedstat``, nanoseconds) and stops the tree (SIGSTOP) for the rest of each 100 ms
period once it has used ``quota x period``, then continues it (SIGCONT).  That is the CFS rule, at a 5 ms
granularity and with the bench's own sampling cost; rows measured so are labelled ``(emulated)``.

Per row: ``tracks`` (track messages of the ~600 frames simulated), ``position coverage`` (of those,
with a 3-D position, from the first one on), ``observable after 5 s`` (frames simulated after 5 s whose track says observable),
``honest`` (published positions within 3 sqrt(trace(cov)) of the truth), ``overload`` (seconds from the
daemon's first dropped frame or withheld position to its ``overload`` WARNING, from its log), the
daemon's CPU (its process tree's CPU seconds per wall second over the run) and the CPU it was refused
(the cgroup's throttled time per wall second; the emulation's stopped time).

CPU figures are noisy on a shared machine: run a row twice before trusting a difference.
"""

from __future__ import annotations

import calendar
import contextlib
import dataclasses
import json
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from groundsim.evaluation.proc_cpu import children_by_parent
from onboard.core.cpu_accounting import parse_cgroup_cpu_stat, parse_proc_cgroup
from onboard.core.errors import ConfigError, InputError, IrtrackError

CFS_PERIOD_US = 100_000
EMULATION_POLL_S = 0.005
DEFAULT_CONFIG = "deploy/onboard.container.yaml"
OBSERVABLE_AFTER_S = 5.0
CGROUP_ROOT = Path("/sys/fs/cgroup")
EXIT_BAD_INPUT = 2  # an option or a file refused: the exit code of every irtrack command's bad input

# the daemon's log lines (onboard/app/logs.py): text ``<ts> level=.. logger=.. msg="word: ..."`` or JSON
_LOG_LINE = re.compile(r'^(\S+) level=\S+ logger=\S+ msg="(.*)"$')
_TS = re.compile(r"^(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)\.(\d{3})Z$")


class QuotaUnavailable(IrtrackError):
    """No cgroup with a CPU quota can be created here (the message says why)."""


@dataclass
class Limit:
    """How the daemon is limited: ``prefix`` puts it in a cgroup; ``throttled_s()`` the time refused so far."""

    label: str
    prefix: tuple[str, ...]
    cgroup_dir: Path | None = None
    emulator: EmulatedQuota | None = None

    def throttled_s(self) -> float | None:
        if self.emulator is not None:
            return self.emulator.stopped_s
        if self.cgroup_dir is None:
            return None
        try:
            th = parse_cgroup_cpu_stat((self.cgroup_dir / "cpu.stat").read_text())
        except OSError:
            return None
        return None if th is None else th.throttled_s


def _cgroup_prefix(d: Path) -> tuple[str, ...]:
    # the shell joins the cgroup, then becomes the daemon: every process it starts is in the group from birth
    return ("sh", "-c", 'echo $$ > "$0/cgroup.procs" && exec "$@"', str(d))


@contextlib.contextmanager
def cfs_cgroup(quota_cores: float, root: Path = CGROUP_ROOT) -> Iterator[Path]:
    """A new cgroup (v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``) under this process's own, removed after."""
    where = parse_proc_cgroup(Path("/proc/self/cgroup").read_text())
    if where is None:
        raise QuotaUnavailable("no cgroup with a CPU controller in /proc/self/cgroup")
    version, path = where
    rel = path.lstrip("/")
    name = f"irtrack-companion-{os.getpid()}"
    quota_us = max(1000, round(quota_cores * CFS_PERIOD_US))
    if version == 1:
        parent = next((d for d in (root / "cpu" / rel, root / "cpu,cpuacct" / rel) if d.is_dir()), None)
        if parent is None:
            raise QuotaUnavailable(f"no v1 cpu hierarchy for {path} under {root}")
        files = {"cpu.cfs_period_us": str(CFS_PERIOD_US), "cpu.cfs_quota_us": str(quota_us)}
    else:
        parent = root / rel
        files = {"cpu.max": f"{quota_us} {CFS_PERIOD_US}"}
        try:
            if "cpu" not in (parent / "cgroup.subtree_control").read_text().split():
                (parent / "cgroup.subtree_control").write_text("+cpu")
        except OSError as exc:
            raise QuotaUnavailable(f"cannot enable the cpu controller in {parent}: {exc.strerror}") from exc
    d = parent / name
    try:
        d.mkdir()
    except OSError as exc:
        raise QuotaUnavailable(f"cannot create cgroup {d}: {exc.strerror}") from exc
    try:
        for f, v in files.items():
            (d / f).write_text(v)
        yield d
    except OSError as exc:
        raise QuotaUnavailable(f"cannot set the quota in {d}: {exc.strerror}") from exc
    finally:
        _remove_cgroup(d)


def _remove_cgroup(d: Path) -> None:
    for _ in range(50):  # the daemon's children may take a moment to be reaped
        try:
            d.rmdir()
            return
        except FileNotFoundError:
            return
        except OSError:
            time.sleep(0.1)
    print(f"bench.companion: cgroup {d} still holds processes; remove it by hand (rmdir)", file=sys.stderr)


def _tree(pid: int) -> list[int]:
    kids = children_by_parent()
    out, frontier = [pid], [pid]
    while frontier:
        below = kids.get(frontier.pop(), [])
        out += below
        frontier += below
    return out


def _tree_cpu_ns(pids: list[int]) -> int:
    total = 0
    for pid in pids:
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            continue
        for tid in tids:
            try:
                with open(f"/proc/{pid}/task/{tid}/schedstat", encoding="ascii") as f:
                    total += int(f.read().split()[0])
            except (OSError, ValueError, IndexError):
                continue
    return total


class EmulatedQuota:
    """The CFS rule applied from outside (module docstring): the daemon's tree may use ``quota x period``
    of CPU per period; past that it is stopped until the period ends.  Finds the daemon as this process's
    child running ``-m onboard``."""

    def __init__(self, quota_cores: float, period_s: float = CFS_PERIOD_US / 1e6, find_pid=None) -> None:
        self.budget_ns = int(quota_cores * period_s * 1e9)
        self._find_pid = find_pid or self._daemon_pid
        self.period_s = period_s
        self.stopped_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="emulated-quota", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)

    def _daemon_pid(self) -> int | None:
        for pid in children_by_parent().get(os.getpid(), []):
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"onboard" in cmd and b"-m" in cmd:
                return pid
        return None

    def _signal(self, pids: list[int], sig: int) -> None:
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)

    def _run(self) -> None:
        root = None
        while root is None and not self._stop.wait(EMULATION_POLL_S):
            root = self._find_pid()
        pids: list[int] = []
        next_tree = 0.0
        while not self._stop.is_set():
            period_end = time.monotonic() + self.period_s
            if time.monotonic() >= next_tree:
                pids, next_tree = _tree(root), time.monotonic() + 0.5  # the worker is started (and restarted) late
            used0 = _tree_cpu_ns(pids)
            while time.monotonic() < period_end and not self._stop.is_set():
                if _tree_cpu_ns(pids) - used0 >= self.budget_ns:
                    self._signal(pids, signal.SIGSTOP)
                    t0 = time.monotonic()
                    self._stop.wait(max(period_end - t0, 0.0))
                    self._signal(pids, signal.SIGCONT)
                    self.stopped_s += time.monotonic() - t0
                    break
                time.sleep(EMULATION_POLL_S)
            if not pids or not os.path.exists(f"/proc/{root}"):
                return
        self._signal(pids, signal.SIGCONT)


@contextlib.contextmanager
def daemon_limit(quota_cores: float | None, emulate: bool, say) -> Iterator[Limit]:
    """The :class:`Limit` for one row: none, a cgroup, or (when no cgroup can be made, or ``emulate``)
    the emulation."""
    if quota_cores is None:
        yield Limit("unlimited", ())
        return
    if not emulate:
        try:
            with cfs_cgroup(quota_cores) as d:
                yield Limit(f"{quota_cores:g} core", _cgroup_prefix(d), cgroup_dir=d)
            return
        except QuotaUnavailable as exc:
            say(
                f"bench.companion: no CFS quota here ({exc}); the {quota_cores:g} core row is EMULATED with SIGSTOP/SIGCONT"
            )
    em = EmulatedQuota(quota_cores)
    em.start()
    try:
        yield Limit(f"{quota_cores:g} core (emulated)", (), emulator=em)
    finally:
        em.close()


def score_row(a: dict, t0_us: int | None) -> dict:
    """The table's figures from :func:`groundsim.evaluation.demo.aligned_arrays` (module docstring)."""
    tracked = a["tracked"]
    has = np.all(np.isfinite(a["est_p"]), axis=1) & tracked
    n_tracks = int(tracked.sum())
    first = int(np.argmax(has)) if has.any() else 0  # coverage counts from the first position on
    late = a["t_us"] >= (a["t_us"][0] if a["t_us"].size else 0) + int(OBSERVABLE_AFTER_S * 1e6)
    obs = has & a["observable"]
    P = a["est_P"]
    ok = has & np.all(np.isfinite(P.reshape(len(P), 9)), axis=1) if len(P) else has
    err = np.linalg.norm(a["est_p"] - a["truth_p"], axis=1)
    sig3 = 3.0 * np.sqrt(np.abs(np.trace(P, axis1=1, axis2=2))) if len(P) else err
    return {
        "frames": int(a["t_us"].size),
        "tracks": n_tracks,
        "coverage": float(has[first:].sum() / tracked[first:].sum()) if has.any() else 0.0,
        "observable_after_5s": float((obs & late).sum() / late.sum()) if late.any() else float("nan"),
        "honest": float(np.mean(err[ok] <= sig3[ok])) if ok.any() else float("nan"),
        "positions": int(ok.sum()),
    }


def _log_event(line: str) -> tuple[float, str] | None:
    """(UTC seconds, the message's first word) of a daemon log line, text or JSON (onboard/app/logs.py)."""
    if line.startswith("{"):
        try:
            obj = json.loads(line)
            ts, msg = str(obj["ts"]), str(obj["msg"])
        except (ValueError, KeyError, TypeError):
            return None
    else:
        m = _LOG_LINE.match(line)
        if not m:
            return None
        ts, msg = m.group(1), m.group(2)
    m = _TS.match(ts)
    if not m:
        return None
    t = calendar.timegm(time.strptime(m.group(1), "%Y-%m-%dT%H:%M:%S")) + int(m.group(2)) / 1000.0
    return t, msg.split(":", 1)[0]


def overload_delay_s(log_text: str) -> tuple[float | None, float | None]:
    """From the daemon's log: (seconds from its first dropped frame or withheld position to its first
    ``overload`` warning, seconds from the daemon's first log line to that first cause); Nones when absent."""
    first_line = first_cause = warned = None
    for line in log_text.splitlines():
        ev = _log_event(line)
        if ev is None:
            continue
        t, word = ev
        first_line = t if first_line is None else first_line
        if word in ("dropped_queue", "estimate_stale") and first_cause is None:
            first_cause = t
        elif word == "overload" and warned is None:
            warned = t
    if first_cause is None:
        return None, None
    return (None if warned is None else warned - first_cause), first_cause - (first_line or first_cause)


def _set_chain(path: Path, chain: str) -> None:
    """Set ``imaging.chain`` in the daemon's generated configuration ``path`` (checked as the daemon reads it)."""
    import yaml

    from onboard.app.config import load_config

    text = path.read_text(encoding="utf-8")
    raw = yaml.safe_load(text)
    raw.setdefault("imaging", {})["chain"] = chain
    head = "".join(line + "\n" for line in text.splitlines() if line.startswith("#"))
    path.write_text(
        head + f"# bench.companion --chain {chain}\n" + yaml.safe_dump(raw, sort_keys=False), encoding="utf-8"
    )
    load_config(path, environ={})


def run_row(args, quota: float | None, out_root: Path, say) -> dict:
    from groundsim.evaluation.demo import TruthTail, aligned_arrays, plan_demo, run_demo

    name = "unlimited" if quota is None else f"quota{quota:g}"
    # planned before the limit is made: a bad option is refused before a cgroup or an emulation starts
    plan = plan_demo(
        args.scenario, args.duration, args.seed, out_root / name, args.config, args.nav_noise, config_option="--config"
    )
    if args.chain is not None:
        _set_chain(plan.onboard_config_path, args.chain)
    with daemon_limit(quota, args.emulate, say) as limit:
        plan = dataclasses.replace(plan, daemon_prefix=limit.prefix)
        th0 = limit.throttled_s()
        wall0 = time.time()
        outcome = run_demo(plan, out=lambda s: None)
        wall = time.time() - wall0
        th1 = limit.throttled_s()
    truth = TruthTail(plan.truth_path)
    truth.poll()
    tracks = [json.loads(line) for line in (plan.out_dir / "tracks.jsonl").read_text().splitlines() if line.strip()]
    row = score_row(aligned_arrays(truth, tracks, plan.scenario.origin), None)
    log_text = (plan.out_dir / "onboard.log").read_text(encoding="utf-8", errors="replace")
    delay, first_cause = overload_delay_s(log_text)
    row.update(
        label=limit.label,
        overload_s=delay,
        first_cause_s=first_cause,
        daemon_cpu=outcome.cpu_share.get("daemon"),
        throttled=None if th0 is None or th1 is None else (th1 - th0) / max(wall, 1e-9),
        error=outcome.error,
        status_cpu=(outcome.last_status or {}).get("cpu"),
        daemon_exit=outcome.daemon_exit,
        wall_s=wall,
    )
    return row


def _f(x, fmt=".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)


def _overload(r: dict) -> str:
    if r["first_cause_s"] is None:
        return "no drop, no warning"
    return "NOT warned" if r["overload_s"] is None else f"{r['overload_s']:.1f}"


def format_table(rows: list[dict]) -> str:
    lines = [
        "| daemon CPU quota | tracks | position coverage | observable after 5 s | honest (within 3 sigma) | "
        "overload warned (s after the first drop) | daemon CPU (cores) | refused (s/s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['tracks']} of {r['frames']} | {_f(r['coverage'])} | {_f(r['observable_after_5s'])} | "
            f"{_f(r['honest'], '.3f')} ({r['positions']}) | {_overload(r)} | {_f(r['daemon_cpu'])} | "
            f"{_f(r['throttled'])} |"
        )
    return "\n".join(lines)


def usable_cores() -> int:
    """The cores this process may run on (its affinity, which ``taskset`` narrows), else the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _quota_problem(quotas: list[float]) -> str | None:
    """Why ``--cpu-quota`` cannot be measured here, or None.  A quota above the usable cores never throttles: its
    row would be an unconstrained run labelled as a limited one, so it is refused rather than warned about in a
    long run's output."""
    if any(not (q > 0 and np.isfinite(q)) for q in quotas):
        return f"--cpu-quota: expected positive numbers of cores, got {' '.join(f'{q:g}' for q in quotas)}"
    cores = usable_cores()
    over = [q for q in quotas if q > cores]
    if over:
        return (
            f"--cpu-quota {' '.join(f'{q:g}' for q in over)}: more than the {cores} core(s) this process may use; "
            f"such a quota never throttles the daemon, so its row would be an unconstrained run: expected at most {cores}"
        )
    return None


def _row_name(q: float | None) -> str:
    return "daemon unlimited" if q is None else f"daemon quota {q:g} core"


def main(argv=None) -> int:
    from bench.options import BenchParser, known_nav_noise, known_scenario, nonnegative_int, positive_float

    ap = BenchParser(prog="python -m bench.companion", description=__doc__.split("\n\n")[0])
    ap.add_argument("--cpu-quota", type=float, nargs="+", default=[0.5], help="cores (repeatable list; default 0.5)")
    ap.add_argument("--scenario", type=known_scenario, default="P2", help="scenario name or file (default P2)")
    ap.add_argument("--duration", type=positive_float, default=20.0, help="simulated seconds (default 20)")
    ap.add_argument("--seed", type=nonnegative_int, default=0)
    ap.add_argument("--nav-noise", type=known_nav_noise, default="RTK", help="navigation-error case (default RTK)")
    ap.add_argument("--config", default=DEFAULT_CONFIG, help=f"the daemon's configuration (default {DEFAULT_CONFIG})")
    ap.add_argument("--out", default="out/companion", help="run directories (logs, tracks, truth)")
    ap.add_argument("--no-unlimited", action="store_true", help="skip the unconstrained row")
    ap.add_argument(
        "--chain",
        choices=("objects", "single"),
        help="the daemon's imaging.chain (default: the configuration's, objects): size cpus for the chain you fly",
    )
    ap.add_argument("--emulate", action="store_true", help="emulate the quota even where a cgroup could be made")
    args = ap.parse_args(argv)
    problem = _quota_problem(args.cpu_quota)
    if problem is not None:
        print(f"bench.companion: {problem}", file=sys.stderr)
        return EXIT_BAD_INPUT

    def say(s: str) -> None:
        print(s, flush=True)

    quotas: list[float | None] = ([] if args.no_unlimited else [None]) + list(args.cpu_quota)
    rows = []
    load0 = os.getloadavg()[0]
    for i, q in enumerate(quotas, start=1):
        say(
            f"bench.companion: row {i} of {len(quotas)}, {_row_name(q)}: {args.scenario} {args.nav_noise}"
            f" {args.duration:g} s, imaging.chain {args.chain or 'as configured'} ..."
        )
        try:
            row = run_row(args, q, Path(args.out), say)
        except (ConfigError, InputError) as exc:  # an option or a file of the user's: refused, as the CLIs do
            print(f"bench.companion: {' '.join(str(exc).split())}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except IrtrackError as exc:
            print(f"bench.companion: {' '.join(str(exc).split())}", file=sys.stderr)
            return 1
        say(
            f"bench.companion: row {i} of {len(quotas)}, {_row_name(q)}: done in {row['wall_s']:.1f} s,"
            f" {row['tracks']} tracks of {row['frames']} frames{'; run problem: ' + row['error'] if row['error'] else ''}"
        )
        rows.append(row)
    say("")
    say(format_table(rows))
    say(
        f"\nload average {load0:.2f} before, {os.getloadavg()[0]:.2f} after, {os.cpu_count()} cores: CPU figures "
        "are noisy on a shared machine; repeat a row before trusting a difference."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
