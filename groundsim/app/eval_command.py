"""``python -m groundsim eval``: the command over :mod:`groundsim.evaluation.eval` (options from the command
line, the run, the report, TrackEval's scores of the MOT files, the tables printed)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

from groundsim.evaluation.eval import (
    DEFAULT_ONBOARD_CONFIG,
    EvalInterrupted,
    EvalOptions,
    keep_interrupted,
    load_base_config,
    run_eval,
)
from groundsim.evaluation.parallel import limit_blas_threads, pool_workers, quiet_run_logs
from groundsim.evaluation.report import make_out_dir
from groundsim.evaluation.scoring import format_gnss_dropout
from groundsim.io.stop_signals import print_interrupted
from groundsim.world.nav_errors import InjectedErrors
from groundsim.world.scenario import DEFAULT_NAV_NOISE
from onboard.core.errors import ConfigError

__all__ = ["cmd_eval", "add_mot_scores", "format_time_offset", "DEFAULT_EVAL_SCENARIOS"]

log = logging.getLogger("groundsim.evaluation.eval")  # the eval's own logger: its lines and its quiet levels


DEFAULT_EVAL_SCENARIOS = ("P1", "P2", "P3")


def add_mot_scores(out: Path, seqs: list[str]) -> None:
    """TrackEval's scores of the MOT files (groundsim.evaluation.mot.score_mot) into report.json: a top-level
    ``mot`` {SEQ: metrics} and each run row's ``mot``; printed one line a SEQ.  A scoring failure is logged
    and leaves report.json as it was (the 3-D report does not depend on it)."""
    import json

    from groundsim.evaluation.mot import score_mot, seq_name

    try:
        scores = score_mot(out, seqs)
    except Exception as exc:  # noqa: BLE001 - TrackEval's own errors are many; the report stands without them
        log.warning("MOT scoring failed: %s: %s", type(exc).__name__, exc)
        return
    if not scores:
        return
    path = Path(out) / "report.json"
    report = json.loads(path.read_text(encoding="utf-8"))
    report["mot"] = scores
    for row in report.get("runs", []):
        seq = seq_name(row.get("scenario", ""), row.get("nav_noise", ""), row.get("seed", 0))
        if seq in scores:
            row["mot"] = scores[seq]
    path.write_text(json.dumps(report, indent=1, allow_nan=False) + "\n", encoding="utf-8")
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
    """The ``eval`` command: run, write the report, print the table and the report's path."""
    import sys

    from groundsim.evaluation.report import format_closed_loop, format_table2, write_eval_report
    from groundsim.world.scenario import load_scenario, resolve_scenario_path

    limit_blas_threads(1)
    with quiet_run_logs():  # per-track chatter would drown the progress bar
        names = [n for group in (args.scenario or [list(DEFAULT_EVAL_SCENARIOS)]) for n in group]
        scenarios = [load_scenario(resolve_scenario_path(n)) for n in names]
        if isinstance(args.seeds, bool) or args.seeds < 1:
            raise ConfigError(f"--seeds: expected an integer >= 1, got {args.seeds}")
        workers = pool_workers(args.workers)
        nav_noises = list(dict.fromkeys(args.nav_noise or [DEFAULT_NAV_NOISE]))
        options = EvalOptions(
            duration_s=args.duration,
            pixel_sigma_px=args.pixel_sigma,
            batch=not args.no_batch,
            injected=InjectedErrors.from_options(
                nav_noises[0], getattr(args, "gnss_dropout", None), getattr(args, "camera_time_offset_ms", None)
            ),
            estimator=getattr(args, "estimator", None),
            guidance=bool(getattr(args, "guidance", False)),
        )
        for n in nav_noises[1:]:
            options.with_nav_noise(n)  # validates every name before anything runs
        base = load_base_config(args.onboard_config)
        source = args.onboard_config or (
            str(DEFAULT_ONBOARD_CONFIG) if DEFAULT_ONBOARD_CONFIG.is_file() else "built-in defaults"
        )
        out = make_out_dir(args.out)
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
            )
        except EvalInterrupted as exc:
            return print_interrupted(keep_interrupted(exc, out))
        files = write_eval_report(out, result)
        from groundsim.evaluation.mot import write_mot

        cameras = {
            sc.name: (sc.camera.intrinsics.width_px, sc.camera.intrinsics.height_px, sc.frame_rate_hz)
            for sc in scenarios
        }
        seqs = write_mot(out, result.runs, cameras)
        log.info("MOT files of %d run(s) under %s", len(seqs), out / "mot")
        add_mot_scores(out, seqs)
        descriptions = {sc.name: sc.description.split(":", 1)[-1].strip() for sc in scenarios}
        print(format_table2(result.summary, descriptions))
        print()
        print(format_closed_loop(result.summary))
        if options.guidance:
            from groundsim.evaluation.scoring import format_guidance_summary

            table = format_guidance_summary(result.runs)
            with open(files["report.md"], "a", encoding="utf-8") as f:
                f.write("\n## Observer guidance in the loop\n\n" + table + "\n")
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
            f"\n{len(result.runs)} runs ({failed} failed) in {result.wall_s:.1f} s, estimator {options.estimator or 'map'}; "
            f"report: {files['report.md']}"
        )
        sys.stdout.flush()
        return 0
