"""``python -m groundsim campaign SPEC.yaml``: a sweep of runs, one tidy table, resumable, and its report.

A campaign crosses scenarios (and variants of their geometry), navigation-noise cases
(``config/noise_cases.yaml``), trajectory-estimator plug-ins (``onboard.pipeline.plugins``) and run seeds.
The spec file's schema is in ``docs/campaigns.md``; :func:`load_spec` validates it completely before
anything runs (errors are one line ``<spec>: <field>: expected <what>, got <value>``, exit 2).

Geometry variants (:func:`derive_scenario`) are made from a reference scenario's motion models, so
every model (straight, accelerating, cubic, circle, figure-eight, waypoints, Singer-disturbed) works:

- ``range_scale`` k: the target's whole path is moved along the initial line of sight, by
  ``(k - 1) (p_target(0) - p_observer(0))``: the initial range is k times the reference's, the
  target's motion (speed, turns) unchanged, so the bearing rates shrink roughly as 1/k;
- ``aspect_deg`` psi: the target's path is rotated about the vertical through its start point by psi
  (positive from north towards east): the same speed and manoeuvre, another heading relative to the
  line of sight (the aspect);
- ``manoeuvre_scale`` m: the observer's acceleration history is multiplied by m, from the same start
  position and velocity: ``p(t) = p0 + v0 t + m (p_ref(t) - p0 - v0 t)``.  m = 0 is the straight line
  at constant velocity (no range information from the observer's motion), m = 1 the reference.

``(1, 0, 1)`` is the reference scenario itself, unchanged (same name, same runs as ``groundsim eval``).

Modes.  ``synthetic`` (default; fast): the analytic truth and noisy observations of
:func:`groundsim.evaluation.synth.synthesize_scenario` (the noise case's pixel and navigation errors) fed frame by
frame to the plug-in through its step interface (``add``), exactly as the daemon's pipeline would feed
it; the estimator assumes the noise case (``noise_model: case``, the pixel sigma floored at
:data:`MIN_ASSUMED_PIXEL_SIGMA_PX`) or the onboard configuration's model (``noise_model: config``).
``closed_loop``: :func:`groundsim.evaluation.eval.run_lockstep` (JSBSim, rendered frames, the image chain, the
noise case as the telemetry's navigation errors, the shipped daemon configuration).

Metrics of a run (:func:`score_track`, the same for both modes; the closed-loop windows of the eval):
median err/range on observable frames, median err/range of every published (finite) estimate after
5 s (half the run when it is shorter than 10 s: :func:`settle_s`), err/range at the last frame, RMSE,
observable share after that, honesty (fraction of published
estimates beyond 3 sqrt(trace cov); a run is honest at <= 1 %), mean NEES, first observable time.
The bound: the Bayesian CRB (``onboard.estimation.crb``) of the case's window, at the truth, with the
motion prior a whole-window MAP solve selects (synthetic: computed once per case and shared by its
algorithms; closed loop: ``groundsim eval``'s batch columns); ``crb_range_sigma_pct`` is the smallest
range sigma an estimator knowing the motion model could report.

Resumability.  A run is identified by :func:`run_id`, a SHA-256 of its parameters (scenario and the
digest of what its file says (:func:`~groundsim.world.scenario.scenario_digest`: not its comments or layout), geometry, noise case and the digest of its numbers, algorithm, seed, mode, duration,
noise model, the onboard configuration's digest, :data:`RESULT_SCHEMA`).  Each finished run is appended
to ``OUT/runs.jsonl`` as one line, flushed and fsynced, the moment its result arrives; a new invocation
reads it (a line cut short by a kill, damaged, or not a run's row is skipped, one warning names the
lines, and their runs are redone) and runs only what is missing.  A folder holds one campaign (its name, recorded in
``OUT/campaign.json``): another campaign's is refused before anything is written (:func:`check_same_campaign`),
unless ``--fresh``.  The log and that record are :mod:`groundsim.evaluation.campaign_log`; a run's identity,
figures and job :mod:`groundsim.evaluation.campaign_runs`.  ``runs.csv`` (and
``runs.parquet`` when pyarrow is installed), ``report.md`` and ``manoeuvre.png`` are rebuilt from the
log every time, in the spec's order, so the table does not depend on the order runs finished in, nor
on interruptions.

Execution.  One *job* is a case (scenario variant, noise case, seed): it synthesises once, computes the
bound once and runs each pending algorithm.  :func:`run_job` is a pure function of a picklable job.
Jobs go to a local process pool (forkserver, one BLAS thread per worker), or, with ``--workers 1``, run
in this process, or, with ``--scheduler tcp://HOST:PORT``, to the workers of a Dask distributed cluster
(``dask scheduler`` / ``dask worker``; docs/campaigns.md).  Pool and cluster take one path: every job
submitted as a future, the rows taken as each completes and appended by this process (the coordinator)
with :func:`append_rows`; workers never see the output directory, so the log, the resumption and the
table are the same whichever executor ran the jobs.  Before submitting, the coordinator asks every
connected worker for its :func:`code_fingerprint` and refuses workers running other irtrack code.
A tqdm bar counts runs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from groundsim.evaluation.campaign_log import (
    LOG_NAME,
    MARK_NAME,
    append_rows,
    check_outputs,
    check_same_campaign,
    mark_campaign,
    read_log,
    reusable_rows,
    skipped_text,
)
from groundsim.evaluation.campaign_report import (
    FIGURE_NAME,
    REPORT_NAME,
    TABLE_NAME,
    write_report,
    write_table,
)
from groundsim.evaluation.campaign_runs import (
    RESULT_SCHEMA,
    Job,
    RunParams,
    plan_runs,
    run_id,
    run_job,
    run_row,
    score_track,
    short_digest,
)
from groundsim.evaluation.campaign_spec import CampaignSpec, derive_scenario, load_spec
from groundsim.evaluation.out_dir import make_out_dir, refuse_foreign_out
from groundsim.evaluation.parallel import (
    auto_deadline_s,
    check_run_timeout,
    finish_pool,
    limit_blas_threads,
    pool_results,
    pool_workers,
    progress_bar,
    quiet_run_logs,
    start_pool,
    stop_pool,
)
from groundsim.io.stop_signals import finish_despite_signals, first_signal_stops, signals_held
from groundsim.world.noise_cases import load_noise_cases
from groundsim.world.scenario import load_scenario
from onboard.core.errors import ConfigError

# the run log and the runs are their own modules (campaign_log, campaign_runs); their names stay importable from here
__all__ = [
    "LOG_NAME",
    "MARK_NAME",
    "check_same_campaign",
    "RESULT_SCHEMA",
    "Job",
    "RunParams",
    "run_id",
    "plan_runs",
    "score_track",
    "run_job",
    "read_log",
    "reusable_rows",
    "append_rows",
    "check_outputs",
    "run_campaign",
    "CampaignResult",
    "cmd_campaign",
    "code_fingerprint",
    "check_workers",
    "check_scheduler_address",
]

log = logging.getLogger(__name__)

SCHEDULER_CONNECT_TIMEOUT_S = 10.0  # --scheduler: how long to wait for the Dask scheduler to answer

# --------------------------------------------------------------------------- execution


#: what the campaign's fork server imports once for its workers
CAMPAIGN_PRELOAD = ("groundsim.evaluation.campaign", "groundsim.evaluation.eval", "onboard.estimation.sliding")


@dataclass(frozen=True)
class CampaignResult:
    """What one invocation did: ``planned`` runs, ``reused`` from the log, ``ran`` now (``failed`` of
    them), ``wall_s`` of the runs' execution, ``workers``, ``interrupted``, and the files written."""

    planned: int
    reused: int
    ran: int
    failed: int
    wall_s: float
    workers: int
    interrupted: bool
    files: dict = field(default_factory=dict)


def _jobs(spec: CampaignSpec, runs: list[RunParams], base_config) -> list[Job]:
    """The runs as jobs: a synthetic case's algorithms in one (they share its observations and bound), a closed-loop
    run alone (its flight is its own: one job a case had a plug-in that hangs or ends its worker lose the case's
    other algorithms' finished runs with its own)."""
    cases = load_noise_cases()
    scen = {}
    for p in spec.scenario_paths:
        sc = load_scenario(p)
        scen[sc.name] = sc
    groups: dict[tuple, list[RunParams]] = {}
    for r in runs:
        key = r.case_key() if r.mode != "closed_loop" else (r.case_key(), r.algorithm)
        groups.setdefault(key, []).append(r)
    jobs = []
    for rs in groups.values():
        r0 = rs[0]
        variant = derive_scenario(scen[r0.scenario], r0.geometry)
        jobs.append(Job(variant, cases[r0.noise], tuple(rs), base_config))
    return jobs


def check_scheduler_address(scheduler: str) -> None:
    """ConfigError naming ``--scheduler`` unless it is ``PROTOCOL://HOST:PORT`` with a port 1-65535 (an IPv6
    host in brackets): dask reads a malformed one as an address it cannot reach, so the mistake surfaced as a
    timeout after 20 s, as a traceback."""
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(scheduler)
        port = parts.port
    except ValueError as exc:  # a port that is not a number or beyond 65535, an unclosed IPv6 bracket
        why = str(exc)
    else:
        checks = (
            ("://" in scheduler, "no protocol"),
            (bool(parts.hostname), "no host"),
            (port is not None and 1 <= port <= 65535, "no port in 1-65535"),
            (not (parts.path or parts.query or parts.fragment), "more after the port"),
        )
        why = next((w for ok, w in checks if not ok), "")
    if why:
        raise ConfigError(f"--scheduler: expected an address tcp://HOST:PORT, got {scheduler!r} ({why})")


def _cluster_client(scheduler: str):
    """A ``distributed.Client`` on ``scheduler`` (``tcp://HOST:PORT``); ConfigError naming ``--scheduler``
    when dask is missing, the address is malformed or nothing answers there."""
    check_scheduler_address(scheduler)
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--scheduler: needs dask.distributed (pip install 'irtrack[sim]')") from None
    try:
        client = Client(scheduler, timeout=SCHEDULER_CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ConfigError(
            f"--scheduler {scheduler}: no scheduler answered within {SCHEDULER_CONNECT_TIMEOUT_S:g} s "
            f"({type(exc).__name__}: {' '.join(str(exc).split())})"
        ) from None
    return client


def code_fingerprint() -> str:
    """Digest of the irtrack code a process runs (every ``.py`` under ``onboard/`` and ``groundsim/`` as
    imported, path and bytes), so a coordinator can refuse cluster workers running other code."""
    import onboard

    h = hashlib.sha256()
    groundsim_root = Path(__file__).resolve().parents[1]  # this module is groundsim/evaluation/campaign.py
    for root in (Path(onboard.__file__).resolve().parent, groundsim_root):
        for f in sorted(root.rglob("*.py")):
            h.update(str(f.relative_to(root.parent)).encode("utf-8") + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def _remote_job(job: Job) -> list[dict]:
    """:func:`run_job` on a cluster worker, with one BLAS thread (as the local pool's initializer sets)."""
    limit_blas_threads(1)
    return run_job(job)


def check_workers(client, scheduler: str) -> int:
    """Threads the cluster offers; ConfigError when it has none or a worker runs other irtrack code."""
    nthreads = client.nthreads()
    if not nthreads:
        raise ConfigError(
            f"--scheduler {scheduler}: the scheduler has no workers (start some: dask worker {scheduler})"
        )
    mine = code_fingerprint()
    theirs = client.run(code_fingerprint)
    other = sorted(w for w, fp in theirs.items() if fp != mine)
    if other:
        raise ConfigError(
            f"--scheduler {scheduler}: worker(s) {', '.join(other)} run other irtrack code than this "
            f"coordinator (fingerprint {mine}); install the same checkout there"
        )
    return sum(nthreads.values())


def _deadline_s(job: Job, run_timeout_s: float | None) -> float:
    """A job's deadline on a pool: ``--run-timeout``, else the automatic one for its runs' flights."""
    if run_timeout_s is not None:
        return run_timeout_s
    d = job.runs[0].duration_s
    return auto_deadline_s(job.scenario.duration_s if d is None else d, len(job.runs))


def _lost_rows(job: Job, why: str) -> list[dict]:
    """The failed rows of a job whose pool worker ended under it (a plug-in's os._exit, a crash)."""
    return [
        run_row(p, {"status": "failed", "error": f"WorkerLost in algorithm {p.algorithm}: {why}"}) for p in job.runs
    ]


def run_campaign(
    spec: CampaignSpec,
    out: Path,
    workers: int = 2,
    progress: bool = True,
    fresh: bool = False,
    retry_failed: bool = False,
    base_config=None,
    onboard_digest: str = "defaults",
    scheduler: str | None = None,
    run_timeout_s: float | None = None,
) -> CampaignResult:
    """Plan, skip what the log has, run the rest, append each case's rows as they come, then rebuild the
    table and the report.  Ctrl-C stops cleanly: the runs finished so far are kept, the table and report
    show them, and the same command resumes.

    Executors: ``workers`` processes of a local pool (1 = in this process), or, with ``scheduler``
    (``tcp://HOST:PORT``), the workers of a Dask distributed cluster (``workers`` is then the threads the
    cluster offers).  Pool and cluster share one path: every job is submitted as a future, results are
    taken as they complete and appended here; workers never touch ``out``.  ``run_timeout_s``: each job's
    wall-clock deadline on a local pool, its runs failed past it (None: per run 20 x its simulated seconds + 120 s,
    summed over the job's runs); not enforced in this process or on a cluster."""
    run_timeout_s = check_run_timeout(run_timeout_s)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / LOG_NAME
    check_outputs(out)
    if not fresh:  # before anything runs or is written: another campaign's folder is refused as it is
        check_same_campaign(out, spec)
    planned = plan_runs(spec, onboard_digest)
    ids = [run_id(p) for p in planned]
    client = None
    if scheduler is not None:  # before --fresh removes anything: a wrong address or cluster changes nothing
        client = _cluster_client(scheduler)
        try:
            workers = check_workers(client, scheduler)
        except BaseException:
            client.close()
            raise
    try:
        if fresh and log_path.exists():
            # emptied, not removed: the folder stays a campaign's (refuse_foreign_out reads the log's presence),
            # so the same command run again after an interruption before the first result still resumes it
            log_path.write_bytes(b"")
        mark_campaign(out, spec)
        done, bad = reusable_rows(log_path, ids)
        if bad:  # said once: the log is read again below for the table, its skipped lines not repeated
            log.warning("%s", skipped_text(log_path, bad))
        if retry_failed:
            done = {k: v for k, v in done.items() if v.get("status") == "ok"}
        pending = [p for p, i in zip(planned, ids) if i not in done]
        reused = len(planned) - len(pending)
        jobs = _jobs(spec, pending, base_config)
    except BaseException:
        if client is not None:
            client.close()
        raise
    limit_blas_threads(1)
    if client is not None:
        where = f"the cluster at {scheduler}"
    else:
        workers = max(1, min(workers, len(jobs))) if jobs else 1
        where = "this process" if workers == 1 else "a local process pool"
    log.info(
        "campaign %s: %d runs planned, %d already done, %d to run in %d jobs on %d worker(s) (%s)",
        spec.name,
        len(planned),
        reused,
        len(pending),
        len(jobs),
        workers,
        where,
    )
    bar = None
    ran = failed = 0
    interrupted = False
    t0 = time.perf_counter()
    pool = None
    futures: list = []
    received: list[int] = []
    with contextlib.ExitStack() as finishing:
        try:
            if progress and pending:
                bar = progress_bar(len(pending), "run", f"campaign {spec.name} ({workers} worker(s))")
            if client is not None:  # submit every job, take them as they complete
                import uuid

                from distributed import as_completed

                batch = uuid.uuid4().hex[:8]
                futures = [
                    client.submit(_remote_job, j, key=f"irtrack-{spec.name}-{batch}-{k}", pure=False)
                    for k, j in enumerate(jobs)
                ]
                results = (f.result() for f in as_completed(futures, loop=client.loop))
            elif workers > 1:  # the same, on a local pool
                # every worker started before Ctrl-C is taken (a half-started forkserver worker printed a traceback)
                pool, _ = start_pool(workers, CAMPAIGN_PRELOAD, progress=False)
                results = (
                    rows
                    for _, rows in pool_results(
                        pool, run_job, jobs, on_lost=_lost_rows, deadline_s=lambda j: _deadline_s(j, run_timeout_s)
                    )
                )
            else:
                results = (run_job(j) for j in jobs)
            for rows in results:
                with signals_held():  # logged and counted together: the interrupted line's count is the log's
                    append_rows(log_path, rows)
                    ran += len(rows)
                    failed += sum(1 for r in rows if r.get("status") != "ok")
                if bar is not None:
                    bar.update(len(rows))
                    bar.set_postfix_str(
                        f"{rows[0]['scenario']} {rows[0]['geometry']} {rows[0]['noise']} seed {rows[0]['seed']}"
                    )
            if pool is not None:
                finish_pool(pool)
                pool = None
        except KeyboardInterrupt:
            interrupted = True
        finally:
            # from here on a signal is noted, not raised: a second Ctrl-C (or a SIGTERM) had cut the table short
            # and lost the finished runs' report; the runs it stops are already stopped
            received = finishing.enter_context(finish_despite_signals("the table and the report"))
            # interrupted or failed: drop what is still queued or running (its runs are redone on resume)
            if pool is not None:
                stop_pool(pool)
            if client is not None:
                try:
                    if futures:
                        client.cancel(futures)
                finally:
                    client.close()
            if bar is not None:
                bar.close()
        wall = time.perf_counter() - t0
        done, _ = reusable_rows(log_path, ids)
        rows = [done[i] for i in ids if i in done]
        result = CampaignResult(len(planned), reused, ran, failed, wall, workers, interrupted)
        try:
            files = write_table(out, rows)
            files.update(write_report(out, spec, rows, dataclasses.asdict(result)))  # the report states these counts
        except OSError as exc:
            raise ConfigError(f"{out}: cannot write the table or the report: {exc}") from None
    # a Ctrl-C while writing ends the command as one during the runs would (the interrupted line, its exit code);
    # a SIGTERM then, as in eval, only waited for the writing: every run is done and written
    return dataclasses.replace(result, files=files, interrupted=interrupted or signal.SIGINT in received)


# --------------------------------------------------------------------------- command line


def _all_failed(name: str, table_path) -> int:
    """1, with one line on stderr naming the first error, when every run of the table failed (nothing came of the
    campaign: a plug-in that cannot run, say), else 0.  Some failed runs are results, said in the table and report."""
    import csv

    if table_path is None or not os.path.isfile(table_path):
        return 0
    with open(table_path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or any(r.get("status") != "failed" for r in rows):
        return 0
    print(
        f"error: campaign {name}: every one of its {len(rows)} runs failed; the first: {rows[0].get('error', '?')}",
        file=sys.stderr,
    )
    return 1


def cmd_campaign(args) -> int:
    """``groundsim campaign SPEC``: validate, run what is missing, write table + report, print the summary.
    Ctrl-C or SIGTERM: the runs done are kept and in the table, the interrupted line, exit 130."""
    from groundsim.evaluation.eval import DEFAULT_ONBOARD_CONFIG, load_base_config

    # the first SIGTERM, or Ctrl-C, stops it cleanly; a later one cannot cut that stop short, even one arriving as the
    # first is caught.  SIGINT ignored on entry (started with & by a non-interactive shell) stays ignored
    with quiet_run_logs("groundsim.evaluation.eval"), first_signal_stops("the table and the report"):
        spec = load_spec(args.spec)
        scheduler = getattr(args, "scheduler", None)
        if scheduler is not None:  # before --out is made
            check_scheduler_address(scheduler)
        if scheduler is not None and args.workers is not None:
            raise ConfigError(
                f"--workers: not with --scheduler (the cluster's workers run the jobs), got --workers {args.workers}"
            )
        workers = pool_workers(args.workers if args.workers is not None else spec.workers)
        run_timeout = check_run_timeout(getattr(args, "run_timeout", None))
        cfg_path = spec.onboard_config
        if cfg_path is None and DEFAULT_ONBOARD_CONFIG.is_file():
            cfg_path = DEFAULT_ONBOARD_CONFIG
        base = load_base_config(cfg_path)
        digest = short_digest(Path(cfg_path).read_bytes()) if cfg_path is not None else "defaults"
        out_path = Path(args.out) if args.out else Path("out/campaigns") / spec.name
        # a campaign reads its folder's runs.jsonl as its own, removes it with --fresh and overwrites its table and
        # report: a folder of anything else is refused before it is touched
        refuse_foreign_out(out_path, lambda o: (o / LOG_NAME).is_file(), "groundsim campaign", LOG_NAME)
        out = make_out_dir(out_path)
        res = run_campaign(
            spec,
            out,
            workers=workers,
            progress=not args.no_progress,
            fresh=args.fresh,
            retry_failed=args.retry_failed,
            base_config=base,
            onboard_digest=digest,
            scheduler=scheduler,
            run_timeout_s=run_timeout,
        )
        load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
        rate = 60.0 * res.ran / res.wall_s if res.ran and res.wall_s > 0 else math.nan
        print(
            f"campaign {spec.name}: {res.planned} runs planned, {res.reused} reused from {out / LOG_NAME}, "
            f"{res.ran} run now ({res.failed} failed) in {res.wall_s:.1f} s on {res.workers} worker(s)"
            f"{f' of {scheduler}' if scheduler else ''}"
            f"{f' = {rate:.1f} runs/min' if math.isfinite(rate) else ''} (load {load1:.1f})"
        )
        print(
            f"table: {res.files.get(TABLE_NAME)}; report: {res.files.get(REPORT_NAME)}"
            f"{'; figure: ' + str(res.files[FIGURE_NAME]) if FIGURE_NAME in res.files else ''}"
        )
        sys.stdout.flush()
        if res.interrupted:
            print(
                f"interrupted: {res.reused + res.ran} of {res.planned} runs done; the same command resumes",
                file=sys.stderr,
            )
            return 130
        return _all_failed(spec.name, res.files.get(TABLE_NAME))
