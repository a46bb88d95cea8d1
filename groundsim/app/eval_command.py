"""``python -m groundsim eval``: the command over :mod:`groundsim.evaluation.eval` (options from the command
line, the run, the report, TrackEval's scores of the MOT files, the tables printed)."""

from __future__ import annotations

import logging
import math
import signal
from pathlib import Path

from groundsim.evaluation.eval import (
    DEFAULT_ONBOARD_CONFIG,
    EvalInterrupted,
    EvalOptions,
    keep_interrupted,
    load_base_config,
    run_eval,
)
from groundsim.evaluation.mot import write_mot
from groundsim.evaluation.out_dir import make_out_dir, refuse_foreign_out, writing
from groundsim.evaluation.parallel import check_run_timeout, limit_blas_threads, pool_workers, quiet_run_logs
from groundsim.evaluation.report import SCHEMA, holds_eval_report
from groundsim.evaluation.scoring import format_gnss_dropout
from groundsim.io.stop_signals import finish_despite_signals, first_signal_stops, print_interrupted
from groundsim.world.nav_errors import InjectedErrors, run_nav_case
from groundsim.world.scenario import refuse_duplicate_scenarios
from onboard.core.errors import ConfigError

__all__ = [
    "cmd_eval",
    "add_mot_scores",
    "format_time_offset",
    "check_out_paths",
    "DEFAULT_EVAL_SCENARIOS",
    "EXIT_FAILED",
    "MAX_EVAL_RUNS",
]

log = logging.getLogger("groundsim.evaluation.eval")  # the eval's own logger: its lines and its quiet levels


DEFAULT_EVAL_SCENARIOS = ("P1", "P2", "P3")
EXIT_FAILED = 1  # every run failed: a report of errors only (bad input is the command line's EXIT_ERROR, 2)
# eval keeps every run's per-frame columns in memory until the report; the campaign, which streams its runs to
# disk, allows MAX_RUNS (campaign_spec) and is the tool for more
MAX_EVAL_RUNS = 1000


def add_mot_scores(out: Path, seqs: list[str]) -> None:
    """TrackEval's scores of the MOT files (groundsim.evaluation.mot.score_mot) into report.json: a top-level
    ``mot`` {SEQ: metrics} and each run row's ``mot``; a table of them at the end of report.md; printed one line a
    SEQ.  A scoring failure, or no TrackEval installed, is logged and leaves both reports as they were (the 3-D
    report does not depend on it)."""
    import json

    from groundsim.evaluation.mot import score_mot, seq_name

    if not seqs:  # every run failed: TrackEval has nothing to read (it would fail on the empty seqmap)
        return
    try:
        scores = score_mot(out, seqs)
    except Exception as exc:  # noqa: BLE001 - TrackEval's own errors are many; the report stands without them
        log.warning("MOT scoring failed: %s: %s", type(exc).__name__, exc)
        return
    if not scores:
        log.warning(
            "MOT files written under %s, not scored: TrackEval is not installed (the dev extra installs it; "
            "scripts/install.sh .venv sim,dev)",
            Path(out) / "mot",
        )
        return
    path = Path(out) / "report.json"
    report = json.loads(path.read_text(encoding="utf-8"))
    report["mot"] = scores
    for row in report.get("runs", []):
        seq = seq_name(row.get("scenario", ""), row.get("nav_noise", ""), row.get("seed", 0))
        if seq in scores:
            row["mot"] = scores[seq]
    path.write_text(json.dumps(report, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    from groundsim.evaluation.mot import format_mot_scores

    with open(Path(out) / "report.md", "a", encoding="utf-8") as f:
        f.write("\n## Multi-object tracking, TrackEval (MOT Challenge 2-D boxes under mot/)\n\n")
        f.write(format_mot_scores(scores) + "\n")
    for seq, m in scores.items():
        print(
            f"MOT {seq}: HOTA {m['HOTA']:.3f} DetA {m['DetA']:.3f} AssA {m['AssA']:.3f} MOTA {m['MOTA']:.3f}"
            f" IDF1 {m['IDF1']:.3f} IDSW {m['IDSW']}"
        )


def format_time_offset(runs: list) -> str:
    """One line per run: the camera clock offset's estimate at the end, and when (seconds after the first frame with a
    measured target) it first became confident and the watchdog first raised ``camera_time_offset``."""

    def since(t_s: float, t0_s: float) -> str:
        return "never" if t_s is None or math.isnan(t_s) or math.isnan(t0_s) else f"{t_s - t0_s:.1f} s"

    lines = [
        "Camera clock offset (time_offset): injected, estimated at the end, confident and warned after tracking began"
    ]
    for r in runs:
        to = getattr(r, "time_offset", None)
        name = f"{r.scenario} s{r.seed}"
        if not to:
            lines.append(f"{name:<14} no estimate (time_offset.enabled false, or the run failed)")
            continue
        est = "-" if to["estimate_ms"] is None else f"{to['estimate_ms']:+.1f} +- {to['sigma_ms']:.1f} ms"
        t0 = to["first_measurement_t_s"]
        lines.append(
            f"{name:<14} injected {to['injected_ms']:g} ms, estimate {est} ({to['state']}), compensated "
            f"{to['compensated_ms']:.1f} ms; confident after {since(to['confident_t_s'], t0)}, warned after "
            f"{since(to['warning_t_s'], t0)}"
        )
    return "\n".join(lines)


def cmd_eval(args) -> int:
    """The ``eval`` command: run, write the report, print the table and the report's path.

    Exit codes: 0; :data:`EXIT_FAILED` when every run failed (the report holds their errors); the command
    line's EXIT_ERROR for bad input (a ConfigError); EXIT_INTERRUPTED after Ctrl-C or SIGTERM during the runs.
    Once the runs are done, Ctrl-C (or SIGTERM) no longer stops the writing: the finished work is written, then
    (after Ctrl-C) the interrupted line says where."""
    from groundsim.world.scenario import load_scenario, resolve_scenario_path
    from groundsim.world.sim import check_duration_s

    limit_blas_threads(1)
    # per-track chatter would drown the progress bar; a second stop signal must not cut the report short
    with quiet_run_logs(), first_signal_stops("the report"):
        names = [n for group in (args.scenario or [list(DEFAULT_EVAL_SCENARIOS)]) for n in group]
        paths = [resolve_scenario_path(n) for n in names]
        scenarios = [load_scenario(p) for p in paths]
        refuse_duplicate_scenarios(names, paths, [sc.name for sc in scenarios], "one report row and one set of files")
        for sc in scenarios:
            sc.refuse_fleet("eval runs one pipeline for one observer: python -m bench.fleet measures a fleet")
        if isinstance(args.seeds, bool) or args.seeds < 1:
            raise ConfigError(f"--seeds: expected an integer >= 1, got {args.seeds}")
        workers = pool_workers(args.workers)
        run_timeout = check_run_timeout(getattr(args, "run_timeout", None))
        # no --nav-noise: each scenario flies its own nav_noise, as groundsim run, demo and dataset do (None)
        nav_noises: list[str | None] = list(dict.fromkeys(args.nav_noise)) if args.nav_noise else [None]
        runs = len(scenarios) * len(nav_noises) * args.seeds
        if runs > MAX_EVAL_RUNS:
            raise ConfigError(
                f"--seeds: at most {MAX_EVAL_RUNS} runs in one eval (scenarios x navigation cases x seeds), got "
                f"{len(scenarios)} x {len(nav_noises)} x {args.seeds} = {runs}; groundsim campaign runs more"
            )
        options = EvalOptions(
            duration_s=args.duration,
            pixel_sigma_px=args.pixel_sigma,
            batch=not args.no_batch,
            injected=InjectedErrors.from_options(
                nav_noises[0], getattr(args, "gnss_dropout", None), getattr(args, "camera_time_offset_ms", None)
            ),
            estimator=getattr(args, "estimator", None),
            tracker=getattr(args, "tracker", None),
            guidance=bool(getattr(args, "guidance", False)),
            gimbal_frame=getattr(args, "gimbal_frame", "earth"),
        )
        for n in nav_noises[1:]:
            options.with_nav_noise(n)  # validates every name before anything runs
        # the duration and what must fall within it, checked before --out is made (a refused run leaves nothing)
        for sc in scenarios:
            d = check_duration_s(args.duration, sc)
            if options.injected.gnss_dropout is not None:
                options.injected.gnss_dropout.check_within(d)
        base = load_base_config(args.onboard_config)
        source = args.onboard_config or (
            str(DEFAULT_ONBOARD_CONFIG) if DEFAULT_ONBOARD_CONFIG.is_file() else "built-in defaults"
        )
        # the report replaces an earlier eval's files by name, and its MOT files whole folders: a folder of
        # anything else (a home folder, a TrackEval tree of the user's) is refused before it is touched
        refuse_foreign_out(args.out, holds_eval_report, "groundsim eval", f"report.json of schema {SCHEMA}")
        out = make_out_dir(args.out)
        flown = [(sc, run_nav_case(sc, n).name) for n in nav_noises for sc in scenarios]
        # the report's folders: <scenario>_<case> once the runs fly more than one case (write_eval_report)
        labels = [f"{sc.name}_{n}" for sc, n in flown] if len({n for _, n in flown}) > 1 else []
        check_out_paths(out, labels or [sc.name for sc in scenarios])
        cameras = {
            sc.name: (sc.camera.intrinsics.width_px, sc.camera.intrinsics.height_px, sc.frame_rate_hz)
            for sc in scenarios
        }
        log.info(
            "eval: %d scenario(s) x %d seed(s), %d worker(s), onboard config %s",
            len(scenarios),
            args.seeds,
            workers,
            source,
        )
        try:
            result = run_eval(
                scenarios,
                range(args.seeds),
                options,
                base,
                workers=workers,
                progress=not args.no_progress,
                config_source=source,
                nav_noises=nav_noises,
                run_timeout_s=run_timeout,
            )
        except EvalInterrupted as exc:
            with finish_despite_signals():
                kept = writing(out, keep_interrupted, exc, out)
                if exc.result.runs:
                    writing(out, write_mot, out, exc.result.runs, cameras)
                    kept += f"; MOT files in {out / 'mot'}"
            return print_interrupted(kept)
        with finish_despite_signals() as received:
            return _report(out, result, options, scenarios, cameras, received)


def _report(out: Path, result, options: EvalOptions, scenarios, cameras: dict, received: list[int]) -> int:
    """Everything after the runs: files, MOT scores, tables; the exit code.  ``received``: the signals that
    arrived meanwhile (they only skip the MOT scoring, the one step that may take long)."""
    import sys

    from groundsim.evaluation.report import format_closed_loop, format_table2, write_eval_report

    files = writing(out, write_eval_report, out, result)
    seqs = writing(out, write_mot, out, result.runs, cameras)
    log.info("MOT files of %d run(s) under %s", len(seqs), out / "mot")
    if not received:
        add_mot_scores(out, seqs)
    descriptions = {sc.name: sc.description.split(":", 1)[-1].strip() for sc in scenarios}
    print(format_table2(result.summary, descriptions))
    print()
    print(format_closed_loop(result.summary))
    if options.guidance:
        from groundsim.evaluation.scoring import format_guidance_summary

        table = format_guidance_summary(result.runs)

        def append() -> None:
            with open(files["report.md"], "a", encoding="utf-8") as f:
                f.write("\n## Observer guidance in the loop\n\n" + table + "\n")

        writing(out, append)
        print()
        print(table)
    if options.injected.gnss_dropout is not None:
        print()
        print(format_gnss_dropout(result.runs))
    if options.injected.camera_clock is not None:
        print()
        print(format_time_offset(result.runs))
    failed = sum(1 for s in result.scores if "error" in s)
    print(
        f"\n{len(result.runs)} runs ({failed} failed) in {result.wall_s:.1f} s, estimator {options.estimator or 'map'}, "
        f"image chain {', '.join(sorted({r.tracker for r in result.runs})) or options.tracker or '-'}; "
        f"report: {files['report.md']}"
    )
    sys.stdout.flush()
    if signal.SIGINT in received:
        n = len(result.runs)
        return print_interrupted(f"{n} of {n} runs done; report in {files['report.md']}; MOT files in {out / 'mot'}")
    if result.runs and failed == len(result.runs):
        print(
            f"groundsim eval: every run failed ({failed} of {failed}); their errors in {files['report.md']}",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return 0


def check_out_paths(out: Path, labels: list[str]) -> None:
    """Before the runs: ``out/mot`` created, and no ``out/<label>`` (a scenario's TUM folder) that is not a
    folder, so that a path the report cannot use fails now, in one line naming --out, not after the runs."""
    make_out_dir(out / "mot", "--out")
    for label in labels:
        p = out / label
        if p.exists() and not p.is_dir():
            raise ConfigError(f"--out {out}: {p} is not a directory (the report writes {label}/seed<N>/ there)")
