"""Offline reconstruction: ``python -m onboard.reconstruct OBS.csv -o OUT.csv [options]``.

Reads timestamped target pixels with the camera's pose, reconstructs the target's 3-D path with
the MAP estimator (default) or the paper's closed form, and writes one position (and 1-sigma) per
input row.

Input (OBS.csv)
    UTF-8 text (a byte-order mark is allowed), comma-separated, a header line, then one row per
    observation.  Required columns, in any order::

        t_s,u_px,v_px,fx_px,fy_px,cx_px,cy_px,cam_n_m,cam_e_m,cam_d_m,q_w,q_x,q_y,q_z

    ``t_s`` seconds, strictly increasing (uneven steps and gaps are fine); ``u_px, v_px`` the
    target pixel (ideal pinhole, no lens distortion); ``fx_px .. cy_px`` that row's intrinsics;
    ``cam_*_m`` the camera centre in a local NED frame (metres); ``q_*`` ``q_ned_from_cam``
    (Hamilton, w first) rotating camera-frame vectors (x right, y down, z forward) into NED,
    unit norm within ``onboard.core.frames.QUAT_NORM_TOL`` (renormalised).  See ``onboard.core.frames``.
    Optional: ``width_px,height_px``, the image's size, which then bounds each pixel exactly; without
    them a pixel more than 15 % of a side outside the image (taken as twice the principal point) is
    refused.  Unknown extra columns are ignored, with one warning naming them.  Blank lines are skipped.
    Cells may carry surrounding spaces.  Sanity bounds (anything beyond is an error, not an
    overflow later): ``|t_s| <= 1e9``, pixels and intrinsics within ``1e6`` px (focal lengths
    > 0), camera coordinates within ``1e7`` m.  ``t_s`` may start anywhere (a Unix time, beyond the bound, needs
    the first row's time subtracted); an error on rows whose median step is over 1 s asks whether ``t_s`` is in
    milliseconds.

Output (OUT.csv)
    Header, then ``t_s,n_m,e_m,d_m,sigma_n_m,sigma_e_m,sigma_d_m``: one row per input row, in input
    order, ``t_s`` echoed exactly.  Sigmas are the estimator's marginal 1-sigma per NED axis; the
    paper's closed form has no noise model and therefore no covariance: its sigmas are ``nan``.

Summary (--summary-json)
    ``observable``, ``method``, ``frames`` and diagnostics (no truth needed): the MAP analysis'
    ``range_sigma_ratio`` (the observability verdict's input: the median over the window of the posterior range
    sigma over range, before an unobservable solution's range floor), ``range_sigma_median_ratio`` and
    ``range_sigma_max_ratio`` (the range sigma over range of OUT.csv's rows, from the covariance whose diagonal
    its sigmas are, floor included: their median and largest; for ``--method paper`` the MAP analysis'),
    ``model_fits`` (the estimator's residual adequacy test passed: false when the motion model cannot explain
    the pixels, which makes ``observable`` false whatever the geometry), ``adequacy_p`` (that test's p-value) and
    ``residual_rms_norm`` (the residuals' RMS over their assumed noise, about 1 when the model fits), its
    motion ``model`` (``cv``/``ca``/``ct``), ``q_horizontal_m2ps3``, ``turn_rate_radps``, ``iterations``,
    ``converged``, ``solve_ms``; for ``--method paper`` also ``delta``, ``order``, ``paper_cost``,
    ``paper_solver``, ``paper_refinement_rel`` and ``map_solve_ms``.  ``observable`` always comes
    from the MAP observability analysis run on the same rows (``observability_source: "map"``):
    the closed form has none.  Non-finite numbers are written as ``null``.  ``windows``: how many MAP
    problems were solved (``window_s``, below); with more than one, ``observable`` is true only when every
    window is, ``observable_rows_fraction`` the share of rows taken from observable windows,
    ``range_sigma_ratio`` the largest, ``model_fits`` when every window's does, ``model`` the windows' common
    choice (``null`` when they differ),
    ``iterations`` summed, ``converged`` when every window did, and ``window_results`` each window's own
    figures (its rows and times, the rows taken from it, and the fields above); the fields of one solution
    (``q_horizontal_m2ps3``, ``q_vertical_m2ps3``, ``turn_rate_radps``, ``map_cost``, ``attitude_bias_ned_deg``,
    ``adequacy_p``, ``residual_rms_norm``) are then in ``window_results`` only.

Report (stdout)
    On success one line: ``OUT.csv: N rows, method M, observable yes|no, range sigma median R % of range, max
    X %`` (R and X are ``range_sigma_median_ratio`` and ``range_sigma_max_ratio`` in percent: OUT.csv's rows' own;
    for ``--method paper`` the last two come from the MAP analysis and say so), and, when the file was solved in
    several windows, ``, K windows of at most W s (observable: P % of rows)``.

Long files (``--window-s``, default 60 s)
    The MAP problem over a span is dense in its spline's controls, so its time and memory grow with the span
    cubed.  A file spanning more than ``--window-s`` is solved in windows that long, starting every half
    window (the last one ending at the last row), each row taken from the window whose middle is nearest to
    it; rows more than half a window apart from the others are solved apart.  A window or a stretch with fewer
    rows than needed (below) is refused naming its times.  On a terminal a progress line counts the windows.
    ``--window-s 0``: one problem over the whole file.

Unobservable geometry (e.g. a straight, constant-velocity observer) is not an error: the command
exits 0, writes the (unreliable) estimate with its large sigmas, reports ``observable no`` (and
``observable: false`` in the summary) and prints one ``WARNING`` line on stderr: the range is not
determined, the camera must move across the line of sight.  Observations the motion model cannot explain
(the estimator's residual adequacy test fails: corrupt pixels, poses or times, or far too little noise assumed)
are ``observable no`` too, with another ``WARNING`` line instead: the model does not fit the observations, how
far the residuals are beyond their assumed noise, what to check.

Exit codes and errors
    0 success; 2 the input or the arguments are rejected (among them an output path that exists
    and is not a regular file, one in a folder that is missing or cannot be written, tried before
    the solve, and -o and --summary-json naming one file), or the rows cannot be reconstructed;
    1 the outputs cannot be written after the solve after all, or an internal error; 130 interrupted (Ctrl-C or
    SIGTERM) before the outputs were renamed into place: nothing written.  An error prints
    exactly one line on stderr and no traceback (``-v`` logs the traceback of an internal error).
    Row-level errors name the line and the column: ``line N`` is the physical line number in the
    file, counting the header as line 1 (so the first data row is line 2), e.g.
    ``error: obs.csv line 7, column q_w..q_z: quaternion norm 1.02 is not 1 within 0.001``.
    Outputs are written atomically: each to a temporary file beside it (mode 0666 less the umask,
    as a new file gets), and the temporary files renamed over OUT.csv and S.json only once both
    are written, so a failed run leaves no partial OUT.csv (and leaves a previous run's files
    untouched: trust the exit code, not the file).  Through a symbolic link the file it points to
    is replaced, the link kept.

Rows needed: both methods need at least ``MapConfig.min_frames`` (10) rows, because the MAP
observability analysis runs on the same rows.

Performance note: OpenBLAS threads contend badly on small shared machines (a MAP solve took
~9x longer with default threading under load); set ``OPENBLAS_NUM_THREADS=1`` there.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import logging
import math
import os
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from onboard.app.cli_args import OneLineParser, nonnegative_float, sigterm_as_interrupt
from onboard.app.output_files import create_beside, output_target, same_file_clash
from onboard.core.errors import InputError, IrtrackError
from onboard.core.frames import QUAT_NORM_TOL
from onboard.estimation.map_estimator import (
    EstimationError,
    MapConfig,
    MapEstimator,
    MapResult,
    NoiseModel,
    range_sigma_ratios,
)
from onboard.estimation.observations import Observations
from onboard.estimation.paper import PaperConfig, PaperEstimator, PaperResult
from onboard.estimation.window_problem import (
    SHIPPED_ATTITUDE_BIAS_SIGMA_DEG,
    SHIPPED_ATTITUDE_WHITE_SIGMA_DEG,
    SHIPPED_CAMERA_POSITION_WHITE_SIGMA_M,
    SHIPPED_PIXEL_SIGMA_PX,
)
from onboard.estimation.windows import DEFAULT_WINDOW_S, WindowedSolution, solve_in_windows

__all__ = [
    "OBS_COLUMNS",
    "OUT_COLUMNS",
    "ReconstructOptions",
    "Reconstruction",
    "parse_observations_csv",
    "read_observations_csv",
    "reconstruct",
    "format_output_csv",
    "main",
]

log = logging.getLogger(__name__)

OBS_COLUMNS = (
    "t_s",
    "u_px",
    "v_px",
    "fx_px",
    "fy_px",
    "cx_px",
    "cy_px",
    "cam_n_m",
    "cam_e_m",
    "cam_d_m",
    "q_w",
    "q_x",
    "q_y",
    "q_z",
)
OUT_COLUMNS = ("t_s", "n_m", "e_m", "d_m", "sigma_n_m", "sigma_e_m", "sigma_d_m")
QUAT_COLUMNS = ("q_w", "q_x", "q_y", "q_z")

#: |value| bounds per column: beyond them a value is an input error (no overflow downstream)
ABS_LIMITS = {
    "t_s": 1e9,
    "u_px": 1e6,
    "v_px": 1e6,
    "fx_px": 1e6,
    "fy_px": 1e6,
    "cx_px": 1e6,
    "cy_px": 1e6,
    "width_px": 1e6,
    "height_px": 1e6,
    "cam_n_m": 1e7,
    "cam_e_m": 1e7,
    "cam_d_m": 1e7,
    "q_w": 2.0,
    "q_x": 2.0,
    "q_y": 2.0,
    "q_z": 2.0,
}

EXIT_OK, EXIT_OUTPUT, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


class CsvInputError(InputError):
    """A rejected OBS.csv; the message already names the file, line and column."""


# --------------------------------------------------------------------------- parsing (pure)


def _number(cell: str, source: str, line: int, column: str) -> float:
    text = cell.strip()
    if not text:
        raise CsvInputError(f"{source} line {line}, column {column}: empty cell")
    try:
        value = float(text)
    except ValueError:
        shown = text if len(text) <= 30 else text[:27] + "..."
        raise CsvInputError(f"{source} line {line}, column {column}: {shown!r} is not a number") from None
    if not math.isfinite(value):
        raise CsvInputError(f"{source} line {line}, column {column}: {text!r} is not finite")
    if abs(value) > ABS_LIMITS[column]:
        # a Unix time (about 1.8e9 s) is the usual cause: the bound is no help without the way out
        hint = "; t_s is seconds from any origin: subtract the first row's time" if column == "t_s" else ""
        raise CsvInputError(
            f"{source} line {line}, column {column}: {value:g} is beyond the sanity bound "
            f"|{column}| <= {ABS_LIMITS[column]:g}{hint}"
        )
    return value


def parse_observations_csv(text: str, source: str = "<csv>") -> Observations:
    """Parse OBS.csv text (see the module docstring) into :class:`Observations`.

    Pure; raises :class:`CsvInputError` (one line naming ``source``, the line and the column) on
    the first problem.  Unknown columns are ignored with one warning.
    """
    if not text.strip():
        raise CsvInputError(f"{source}: empty file; expected a header line {','.join(OBS_COLUMNS)}")
    reader = csv.reader(io.StringIO(text, newline=""))
    header: list[str] | None = None
    header_line = 0
    index: dict[str, int] = {}
    size_index: list[int] | None = None
    rows: list[list[float]] = []
    lines: list[int] = []
    prev_line_num = 0
    try:
        for record in reader:
            line = prev_line_num + 1  # first physical line of this record
            prev_line_num = reader.line_num
            if not record or all(not c.strip() for c in record):
                continue  # blank line
            if header is None:
                header, header_line = [c.strip() for c in record], line
                seen: dict[str, int] = {}
                for i, name in enumerate(header):
                    if name in seen and name:
                        raise CsvInputError(
                            f"{source} line {line} (header): column {name!r} appears twice "
                            f"(columns {seen[name] + 1} and {i + 1})"
                        )
                    seen[name] = i
                missing = [c for c in OBS_COLUMNS if c not in seen]
                if missing:
                    hint = " (is the file comma-separated?)" if len(header) == 1 else ""
                    raise CsvInputError(f"{source} line {line} (header): missing column(s) {', '.join(missing)}{hint}")
                extra = [c for c in header if c not in OBS_COLUMNS + SIZE_COLUMNS]
                if extra:
                    log.warning("%s: ignoring unknown column(s) %s", source, ", ".join(repr(c) for c in extra))
                index = {c: seen[c] for c in OBS_COLUMNS}
                size_index = [seen[c] for c in SIZE_COLUMNS] if all(c in seen for c in SIZE_COLUMNS) else None
                continue
            if len(record) != len(header):
                raise CsvInputError(
                    f"{source} line {line}: {len(record)} cells, the header (line {header_line}) has {len(header)}"
                )
            vals = [_number(record[index[c]], source, line, c) for c in OBS_COLUMNS]
            t, fx, fy = vals[0], vals[3], vals[4]
            if fx <= 0:
                raise CsvInputError(f"{source} line {line}, column fx_px: focal length must be > 0, got {fx:g}")
            if fy <= 0:
                raise CsvInputError(f"{source} line {line}, column fy_px: focal length must be > 0, got {fy:g}")
            size = None
            if size_index is not None:
                size = (
                    _number(record[size_index[0]], source, line, SIZE_COLUMNS[0]),
                    _number(record[size_index[1]], source, line, SIZE_COLUMNS[1]),
                )
            _check_on_image(vals, source, line, size)
            qn = math.sqrt(sum(v * v for v in vals[10:14]))
            if abs(qn - 1.0) > QUAT_NORM_TOL:
                raise CsvInputError(
                    f"{source} line {line}, column q_w..q_z: quaternion norm {qn:.6g} is not 1 within {QUAT_NORM_TOL:g}"
                )
            if rows and not t > rows[-1][0]:
                raise CsvInputError(
                    f"{source} line {line}, column t_s: {t!r} is not after {rows[-1][0]!r} "
                    f"(line {lines[-1]}); times must strictly increase"
                )
            rows.append(vals)
            lines.append(line)
    except csv.Error as e:
        raise CsvInputError(f"{source} line {reader.line_num}: malformed CSV: {e}") from None
    if header is None:
        raise CsvInputError(f"{source}: empty file; expected a header line {','.join(OBS_COLUMNS)}")
    if not rows:
        raise CsvInputError(f"{source}: no data rows after the header (line {header_line})")
    a = np.asarray(rows, dtype=float)
    try:
        return Observations(
            t_s=a[:, 0],
            uv_px=a[:, 1:3],
            fx_px=a[:, 3],
            fy_px=a[:, 4],
            cx_px=a[:, 5],
            cy_px=a[:, 6],
            p_cam_ned_m=a[:, 7:10],
            q_ned_from_cam=a[:, 10:14],
        )
    except IrtrackError as e:  # every check above should have caught it first
        raise CsvInputError(f"{source}: {e}") from None


#: how far outside the image a row's pixel may lie, as a share of the image's side, when the CSV has no image size:
#: the image is then taken as twice the principal point, which a calibrated camera's centre misses by a few per cent
OFF_IMAGE_MARGIN = 0.15
#: optional columns: the image's size, which then bounds a row's pixel exactly (for pixels measured on the image;
#: a distorted camera's pixels undistorted, as ``groundsim dataset``'s obs.csv holds them, can lie past its edge)
SIZE_COLUMNS = ("width_px", "height_px")


def _check_on_image(vals: list[float], source: str, line: int, size_px: tuple[float, float] | None = None) -> None:
    """A pixel outside the image is no camera's measurement: a corrupt row, refused.  One such row (u 700 px on a
    640 px image) made a 20 s reconstruction wrong by 76 m, its warning blaming the flight's geometry; the
    estimator has no robust loss to shrug it off.  With the image's size (``width_px``, ``height_px``) the bound
    is the image itself; without it, the image taken as twice the principal point with ``OFF_IMAGE_MARGIN``."""
    for k, (i, c, name) in enumerate(((1, 5, "u_px"), (2, 6, "v_px"))):
        if size_px is not None:
            side = size_px[k]
            if side <= 0 or not 0.0 <= vals[i] <= side:
                raise CsvInputError(
                    f"{source} line {line}, column {name}: {vals[i]:g} is outside the image ({size_px[0]:g} x "
                    f"{size_px[1]:g} px, its {SIZE_COLUMNS[k]}): not a pixel a camera measured"
                )
            continue
        side = 2.0 * vals[c]
        if side <= 0:
            continue
        margin = OFF_IMAGE_MARGIN * side
        if not -margin <= vals[i] <= side + margin:
            raise CsvInputError(
                f"{source} line {line}, column {name}: {vals[i]:g} is outside the image (about"
                f" {2 * vals[5]:.0f} x {2 * vals[6]:.0f} px from cx_px, cy_px, {100 * OFF_IMAGE_MARGIN:g} % of a side"
                f" allowed beyond; columns {', '.join(SIZE_COLUMNS)} give the image's own size): not a pixel a camera"
                " measured"
            )


def read_observations_csv(path) -> Observations:
    """Read and parse OBS.csv; unreadable or non-UTF-8 files raise :class:`CsvInputError`."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise CsvInputError(f"cannot read {p}: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise CsvInputError(f"{p}: not UTF-8 text (byte offset {e.start})") from None
    if "\x00" in text:
        line = text.count("\n", 0, text.index("\x00")) + 1
        raise CsvInputError(f"{p} line {line}: contains a NUL byte (binary file?)")
    return parse_observations_csv(text, str(p))


# --------------------------------------------------------------------------- reconstruction (pure)


@dataclass(frozen=True)
class ReconstructOptions:
    """What to run: ``method`` "map" or "paper"; the MAP noise model; the paper's delta and order."""

    method: str = "map"
    noise: NoiseModel = field(default_factory=NoiseModel)
    paper: PaperConfig = field(default_factory=PaperConfig)
    map_config: MapConfig = field(default_factory=MapConfig)
    #: the longest span the MAP estimator solves as one problem; a longer file is solved in windows
    #: (:func:`plan_windows`); 0: one problem whatever the span
    window_s: float = DEFAULT_WINDOW_S

    def __post_init__(self) -> None:
        if self.method not in ("map", "paper"):
            raise InputError(f"ReconstructOptions.method must be 'map' or 'paper', got {self.method!r}")
        if not (math.isfinite(self.window_s) and self.window_s >= 0):
            raise InputError(f"ReconstructOptions.window_s must be a finite number >= 0, got {self.window_s!r}")

    @property
    def min_frames(self) -> int:
        return max(self.map_config.min_frames, self.paper.min_frames if self.method == "paper" else 0)


@dataclass(frozen=True)
class Reconstruction:
    """Positions (F, 3) and 1-sigmas (F, 3, NaN for the paper) per observation, plus the summary."""

    t_s: np.ndarray
    p_ned_m: np.ndarray
    sigma_ned_m: np.ndarray
    summary: dict


def _finite_or_none(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _map_summary(res: MapResult, solve_ms: float, adequacy_p_min: float) -> dict:
    return {
        "observable": bool(res.observable),
        "observability_source": "map",
        "range_sigma_ratio": _finite_or_none(res.range_sigma_ratio),
        # the estimator's adequacy test, one of its verdict's conditions: False when the motion model cannot
        # explain the pixels (corrupt pixels, poses or times), which no geometry would cure
        "model_fits": bool(res.adequacy_p >= adequacy_p_min),
        "adequacy_p": _finite_or_none(res.adequacy_p),
        "residual_rms_norm": _finite_or_none(res.residual_rms_norm),
        "model": res.model,
        "q_horizontal_m2ps3": _finite_or_none(res.prior.q_horizontal_m2ps3),
        "q_vertical_m2ps3": _finite_or_none(res.prior.q_vertical_m2ps3),
        "turn_rate_radps": _finite_or_none(res.turn_rate_radps),
        "iterations": int(res.iterations),
        "converged": bool(res.converged),
        "map_cost": _finite_or_none(res.cost),
        "map_solve_ms": round(solve_ms, 3),
    }


def reconstruct(
    obs: Observations,
    options: ReconstructOptions | None = None,
    progress: Callable[[int, int, float, float], None] | None = None,
) -> Reconstruction:
    """Run the chosen method (and the MAP observability analysis) on ``obs``: the MAP estimator over each of
    :func:`plan_windows`' windows (one, unless the rows span more than ``options.window_s``), the paper's closed
    form over every row.  ``progress(k, n, t_first_s, t_last_s)`` is called before the k-th (from 1) of n windows.

    Raises :class:`EstimationError` when the rows cannot be reconstructed (too few, degenerate, apart from the
    others, or a non-finite result).
    """
    options = options or ReconstructOptions()
    F = len(obs)
    if F < options.min_frames:
        raise EstimationError(
            f"{F} data rows; --method {options.method} needs at least {options.min_frames}"
            + (" (the MAP observability analysis runs on the same rows)" if options.method == "paper" else "")
        )
    estimator = MapEstimator(options.map_config, options.noise)
    solution = solve_in_windows(
        lambda part: _guarded(lambda: estimator.solve(part), "map"), obs, options.window_s, options.min_frames, progress
    )
    map_ms = sum(solution.solve_ms)
    summary = {"method": options.method, "frames": F}
    p_min = options.map_config.adequacy_p_min
    if len(solution.windows) == 1:
        summary.update(_map_summary(solution.results[0], map_ms, p_min))
    else:
        summary.update(_windows_summary(obs, solution, map_ms, options.noise.attitude_bias_sigma_rad > 0, p_min))
    summary.update(_range_sigma_summary(obs, solution.p_ned_m, solution.cov_p_ned_m2))
    summary["windows"] = len(solution.windows)
    summary["window_s"] = options.window_s
    summary["noise"] = {k: float(v) for k, v in vars(options.noise).items()}
    if len(solution.windows) == 1:
        summary.update(_bias_summary(solution.results[0], options.noise.attitude_bias_sigma_rad > 0))
    if options.method == "map":
        p, sigma = solution.p_ned_m, solution.sigma_ned_m
        summary["solve_ms"] = round(map_ms, 3)
    else:
        pr: PaperResult = _guarded(lambda: PaperEstimator(options.paper).solve(obs), "paper")
        p, sigma = pr.p_ned_m, pr.sigma_ned_m
        summary.update(
            {
                "delta": pr.delta,
                "order": pr.order,
                "paper_cost": _finite_or_none(pr.cost),
                "paper_solver": pr.solver,
                "paper_refinement_rel": _finite_or_none(pr.refinement_rel),
                "solve_ms": round(pr.solve_ms, 3),
            }
        )
    if not np.all(np.isfinite(p)):
        raise EstimationError(f"the {options.method} reconstruction is not finite (degenerate geometry)")
    if options.method == "map" and not np.all(np.isfinite(sigma)):
        raise EstimationError("the MAP covariance is not finite (degenerate geometry)")
    return Reconstruction(
        t_s=obs.t_s.copy(), p_ned_m=np.array(p, dtype=float), sigma_ned_m=np.array(sigma, dtype=float), summary=summary
    )


def _range_sigma_summary(obs: Observations, p_ned_m: np.ndarray, cov_p_ned_m2: np.ndarray) -> dict:
    """The MAP solution's range sigma over range per row, from the covariance whose diagonal OUT.csv's sigmas are
    (after an unobservable solution's range floor): its median and its largest.  ``range_sigma_ratio`` is the
    verdict's input instead, a window's median before that floor, and would understate what the file holds."""
    with np.errstate(all="ignore"):
        ratio = range_sigma_ratios(cov_p_ned_m2, np.asarray(p_ned_m, dtype=float), obs.p_cam_ned_m)
    finite = bool(np.all(np.isfinite(ratio)))
    return {
        "range_sigma_median_ratio": float(np.median(ratio)) if finite else None,
        "range_sigma_max_ratio": float(np.max(ratio)) if finite else None,
    }


def _bias_summary(res: MapResult, estimated: bool) -> dict:
    """``attitude_bias_ned_deg`` of a solution, when the bias was estimated (``--attitude-bias-deg`` > 0)."""
    if not estimated:
        return {}
    return {"attitude_bias_ned_deg": [_finite_or_none(math.degrees(v)) for v in res.attitude_bias_rad]}


def _windows_summary(
    obs: Observations, solution: WindowedSolution, map_ms: float, attitude_bias: bool, adequacy_p_min: float
) -> dict:
    """The summary's MAP part over several windows (the module docstring's ``Summary``): the solution's verdicts
    over all windows, iterations summed, and each window's own figures in ``window_results`` (its rows, times, the
    rows taken from it, and :func:`_map_summary`'s fields)."""
    return {
        "observable": solution.observable,
        "observable_rows_fraction": solution.observable_rows_fraction,
        "observability_source": "map",
        "range_sigma_ratio": _finite_or_none(solution.range_sigma_ratio),
        "model_fits": all(r.adequacy_p >= adequacy_p_min for r in solution.results),
        "model": solution.model,
        "iterations": int(sum(r.iterations for r in solution.results)),
        "converged": all(r.converged for r in solution.results),
        "map_solve_ms": round(map_ms, 3),
        "window_results": [
            {
                "rows": w.stop - w.first,
                "t_first_s": float(obs.t_s[w.first]),
                "t_last_s": float(obs.t_s[w.stop - 1]),
                "rows_taken": w.take_stop - w.take_first,
                "t_taken_first_s": float(obs.t_s[w.take_first]),
                "t_taken_last_s": float(obs.t_s[w.take_stop - 1]),
                **_map_summary(r, ms, adequacy_p_min),
                **_bias_summary(r, attitude_bias),
            }
            for w, r, ms in zip(solution.windows, solution.results, solution.solve_ms)
        ],
    }


def _guarded(fn, what: str):
    """Run a solver; numerical failures on valid-but-degenerate rows become EstimationError."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return fn()
        except EstimationError:
            raise
        except (np.linalg.LinAlgError, ValueError, FloatingPointError, OverflowError, ZeroDivisionError) as e:
            raise EstimationError(f"the {what} solver failed on these rows: {type(e).__name__}: {e}") from e


def _fmt_m(x: float) -> str:
    return f"{x:.6f}" if math.isfinite(x) else "nan"


def format_output_csv(t_s: np.ndarray, p_ned_m: np.ndarray, sigma_ned_m: np.ndarray) -> str:
    """OUT.csv text: header and one row per observation (t_s echoed exactly, metres to 1 um)."""
    out = io.StringIO()
    out.write(",".join(OUT_COLUMNS) + "\n")
    for t, p, s in zip(t_s, p_ned_m, sigma_ned_m):
        out.write(",".join([repr(float(t))] + [_fmt_m(float(v)) for v in p] + [_fmt_m(float(v)) for v in s]) + "\n")
    return out.getvalue()


# --------------------------------------------------------------------------- entry point (I/O)


class _Parser(OneLineParser):
    error_format = "error: {prog}: {message}"  # as this command's other errors ("error: ...")


def _nonneg(name):
    return nonnegative_float(f"{name} must be a number", f"{name} must be a finite number >= 0")


def _positive(name):
    base = _nonneg(name)

    def conv(text):
        v = base(text)
        if v <= 0:
            raise argparse.ArgumentTypeError(f"{name} must be > 0, got {text!r}")
        return v

    return conv


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m onboard.reconstruct",
        description="Reconstruct a target's 3-D path (local NED) from one moving camera's observations.",
        epilog="Errors name 'line N' = physical line in OBS.csv (header = line 1). Exit 0 ok, 2 bad input/"
        "arguments or not reconstructable, 1 cannot write outputs / internal error. "
        "Unobservable geometry exits 0, says observable no and warns on stderr.",
    )
    p.add_argument(
        "obs_csv",
        metavar="OBS.csv",
        help=f"observations: a header line with (any order) {','.join(OBS_COLUMNS)}; cam_* the camera centre "
        "in local NED (m), q_* q_ned_from_cam (w first, camera x right/y down/z forward); times strictly "
        "increasing",
    )
    p.add_argument("-o", "--output", metavar="OUT.csv", required=True, help="reconstructed positions and sigmas")
    p.add_argument(
        "--summary-json", metavar="S.json", help="write a JSON summary (observable, method, frames, diagnostics)"
    )
    p.add_argument(
        "--method",
        choices=("map", "paper"),
        default="map",
        help="MAP estimator (default) or the paper's closed form (no noise model: its sigmas are nan)",
    )
    p.add_argument(
        "--pixel-sigma",
        type=_positive("--pixel-sigma"),
        default=SHIPPED_PIXEL_SIGMA_PX,
        metavar="PX",
        help="pixel noise, 1 sigma per axis (default %(default)s)",
    )
    for option, default, metavar, help_text in (
        ("--attitude-sigma-deg", SHIPPED_ATTITUDE_WHITE_SIGMA_DEG, "DEG", "white attitude noise per axis, 1 sigma"),
        (
            "--attitude-bias-deg",
            SHIPPED_ATTITUDE_BIAS_SIGMA_DEG,
            "DEG",
            "prior sigma of a constant attitude bias per axis, estimated (0: none)",
        ),
        ("--position-sigma-m", SHIPPED_CAMERA_POSITION_WHITE_SIGMA_M, "M", "white camera-position noise per axis"),
    ):
        p.add_argument(
            option,
            type=_nonneg(option),
            default=default,
            metavar=metavar,
            help=f"{help_text} (default %(default)g: the daemon's shipped configuration, an RTK-class drone's "
            "navigation; 0 for exact navigation)",
        )
    p.add_argument(
        "--delta",
        type=_positive("--delta"),
        default=PaperConfig().delta,
        help="paper: smoothness weight (default %(default)s)",
    )
    p.add_argument(
        "--order",
        type=int,
        choices=(1, 2),
        default=PaperConfig().order,
        help="paper: finite-difference order of D (default %(default)s)",
    )
    p.add_argument(
        "--window-s",
        type=_nonneg("--window-s"),
        default=DEFAULT_WINDOW_S,
        metavar="S",
        help="the longest span the MAP estimator solves as one problem; longer files are solved in windows S long, "
        "every S/2, each row from the window it is most central in, and rows more than S/2 apart from the others "
        "solved apart (0: one problem over the whole file, whose time and memory grow with its span cubed; default "
        "%(default)g)",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log progress (and tracebacks of internal errors)")
    return p


def _check_output_paths(outputs: list[tuple[str, str]]) -> None:
    """Refuse (:class:`InputError`) an output ``(option, path)`` that exists and is not a regular file, which the
    rename would replace (a device such as ``/dev/null`` among them), one whose folder cannot take the temporary
    file it is written through (tried here, before the solve: a long file's solve takes minutes, and a missing
    folder found after it lost them), and two options naming one file."""
    seen: dict[str, str] = {}
    for option, path in outputs:
        target, refused = output_target(path)
        if refused is not None:
            raise InputError(f"{option} {path}: {refused}")
        if target in seen:
            raise InputError(f"{seen[target]} and {option} name the same file {path}")
        seen[target] = option
        try:
            tmp, fd = create_beside(target)
        except OSError as exc:
            raise InputError(f"{option} {path}: cannot write there: {exc.strerror or exc}") from None
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)


class _OutputWriteError(Exception):
    """An output not written: the message names the user's path and which outputs were replaced."""


def _write_outputs(outputs: list[tuple[str, str]]) -> None:
    """Write each ``(path, text)`` to a temporary file beside ``path``, then, only when all are written, rename
    them over their paths in the given order.  On an ``OSError`` the temporary files left are removed and
    :class:`_OutputWriteError` names the path and says which outputs were replaced (none, unless a rename
    after the first failed)."""
    staged: list[tuple[str, str, str]] = []  # (path as given, the file it names, temporary file)

    def remove(entries: list[tuple[str, str, str]]) -> None:
        for _, _, tmp in entries:
            with contextlib.suppress(OSError):
                os.unlink(tmp)

    for path, text in outputs:
        try:
            target = os.path.realpath(path)  # through a symbolic link: the link is kept, its file replaced
            tmp, fd = create_beside(target)
            staged.append((path, target, tmp))
            with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
                f.write(text)
        except OSError as e:
            remove(staged)
            raise _OutputWriteError(f"cannot write {path}: {e.strerror or e}; no output written") from None
        except BaseException:  # Ctrl-C while writing: no temporary file left beside the outputs
            remove(staged)
            raise
    for k, (path, target, tmp) in enumerate(staged):
        try:
            os.replace(tmp, target)
        except OSError as e:
            remove(staged[k:])
            replaced = ", ".join(p for p, _, _ in staged[:k])
            what = f"only {replaced} replaced" if replaced else "no output written"
            raise _OutputWriteError(f"cannot write {path}: {e.strerror or e}; {what}") from None


def main(argv=None) -> int:
    """Entry point; returns the exit code (see the module docstring)."""
    handler = logging.StreamHandler(sys.stderr)  # the stderr of this call (tests redirect it)
    handler.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(handler)
    try:
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as e:
            return int(e.code) if isinstance(e.code, int) else EXIT_INPUT
        root.setLevel(logging.DEBUG if args.verbose else logging.WARNING)
        handler.setLevel(logging.DEBUG if args.verbose else logging.WARNING)
        try:
            with sigterm_as_interrupt():
                return _run(args)
        except KeyboardInterrupt:
            print(f"interrupted: no output written ({args.output} is as it was, or was not created)", file=sys.stderr)
            return EXIT_INTERRUPTED
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)


def _run(args) -> int:
    try:
        options = ReconstructOptions(
            method=args.method,
            noise=NoiseModel(
                pixel_sigma_px=args.pixel_sigma,
                attitude_white_sigma_rad=math.radians(args.attitude_sigma_deg),
                attitude_bias_sigma_rad=math.radians(args.attitude_bias_deg),
                camera_position_white_sigma_m=args.position_sigma_m,
            ),
            paper=PaperConfig(delta=args.delta, order=args.order),
            window_s=args.window_s,
        )
        outputs = [("-o", args.output)] + ([("--summary-json", args.summary_json)] if args.summary_json else [])
        _check_output_paths(outputs)
        clash = same_file_clash(outputs, [("OBS.csv", args.obs_csv)])
        if clash is not None:
            raise InputError(clash)
        obs = read_observations_csv(args.obs_csv)
        log.info("%s: %d observations, %.3f s to %.3f s", args.obs_csv, len(obs), obs.t_s[0], obs.t_s[-1])
        progress = _Progress(args.obs_csv, args.verbose)
        try:
            rec = reconstruct(obs, options, progress)
        except EstimationError as e:
            raise CsvInputError(f"{args.obs_csv}: cannot reconstruct: {e}{_time_unit_hint(obs.t_s)}") from None
        finally:
            progress.close()
        summary = {"input": str(args.obs_csv), **rec.summary}
        texts = []
        if args.summary_json:  # renamed first: a new OUT.csv always has its own summary beside it
            texts.append((args.summary_json, json.dumps(summary, indent=2, allow_nan=False) + "\n"))
        texts.append((args.output, format_output_csv(rec.t_s, rec.p_ned_m, rec.sigma_ned_m)))
    except IrtrackError as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except Exception as e:  # noqa: BLE001 - an entry point never shows a traceback
        log.debug("internal error", exc_info=True)
        print(f"error: internal error: {type(e).__name__}: {e}", file=sys.stderr)
        return EXIT_OUTPUT
    try:
        _write_outputs(texts)
    except _OutputWriteError as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_OUTPUT
    print(_report_line(args.output, len(rec.t_s), summary))
    if not summary["converged"]:
        print(
            f"WARNING: {args.obs_csv}: the solve did not converge within its iterations: the positions in"
            f" {args.output} and their sigmas may be off (the summary's converged: false)",
            file=sys.stderr,
        )
    # printed as the errors are, not logged: they are the run's verdict, whatever handlers the caller's logging has
    misfit = _where(summary, lambda w: not w["model_fits"])
    if misfit is not None:
        windows = summary.get("window_results", [summary])
        worst = _worst_fit([w for w in windows if not w["model_fits"]])
        p_min = options.map_config.adequacy_p_min
        print(
            f"WARNING: {args.obs_csv}: the motion model does not fit the observations (observable no){misfit}: their"
            f" residuals are {_fmt_g(worst['residual_rms_norm'], 3)} times the assumed noise (RMS; about 1 when it"
            f" fits) and fail the adequacy test (p {_fmt_g(worst['adequacy_p'])} < {p_min:g});"
            " check the pixels, the camera poses, their times and the noise options; the positions in"
            f" {args.output} are unreliable (see their sigmas)",
            file=sys.stderr,
        )
    geometry = _where(summary, lambda w: not w["observable"] and w["model_fits"])
    if geometry is not None:
        print(
            f"WARNING: {args.obs_csv}: range not determined (observable no){geometry}: the camera must move across"
            f" the line of sight to the target; the positions in {args.output} lie along the bearings at an"
            " unreliable range (see their sigmas)",
            file=sys.stderr,
        )
    return EXIT_OK


def _where(summary: dict, failed: Callable[[dict], bool]) -> str | None:
    """None when no solution ``failed`` (a predicate on :func:`_map_summary`'s fields); else where: "" for one
    solution over the file, " for t_s ..." naming the rows taken from each window that failed."""
    if "window_results" not in summary:
        return "" if failed(summary) else None
    spans = [f"{w['t_taken_first_s']:.3f}..{w['t_taken_last_s']:.3f} s" for w in summary["window_results"] if failed(w)]
    if not spans:
        return None
    return f" for t_s {', '.join(spans[:5])}{' ...' if len(spans) > 5 else ''}"


def _worst_fit(window_results: list[dict]) -> dict:
    """The solution whose residuals fit their noise worst."""
    return max(window_results, key=lambda w: -math.inf if w["residual_rms_norm"] is None else w["residual_rms_norm"])


def _fmt_g(x: float | None, digits: int = 2) -> str:
    return "nan" if x is None else f"{x:.{digits}g}"


#: a median step between rows above this is no camera's frame rate: t_s likely counts milliseconds
SLOW_ROWS_STEP_S = 1.0


def _time_unit_hint(t_s: np.ndarray) -> str:
    """A hint for an error on rows whose median step is over ``SLOW_ROWS_STEP_S``: t_s in milliseconds (a 30 Hz
    camera's 33 ms steps read as 33 s) spreads the rows so thin that the windows' errors blame their spacing."""
    if t_s.size < 2:
        return ""
    step_s = float(np.median(np.diff(t_s)))
    if step_s <= SLOW_ROWS_STEP_S:
        return ""
    return f" (the rows are {step_s:.3g} s apart, median: is t_s in milliseconds? it must be in seconds)"


class _Progress:
    """A windowed reconstruction's progress: one line per window logged (``-v``), or else, on a terminal, one line
    on stderr rewritten in place, erased when done (a pipe or a log file gets nothing: its one-line errors stay one
    line; the log's lines are not written over a line without its end)."""

    def __init__(self, source: str, verbose: bool = False) -> None:
        self._source = source
        self._live = sys.stderr.isatty() and not verbose
        self._shown = False

    def __call__(self, k: int, n: int, t_first_s: float, t_last_s: float) -> None:
        if n == 1:
            return
        text = f"{self._source}: window {k} of {n} (t_s {t_first_s:.3f}..{t_last_s:.3f} s)"
        log.info("%s", text)
        if self._live:
            sys.stderr.write("\r\x1b[K" + text)
            sys.stderr.flush()
            self._shown = True

    def close(self) -> None:
        if self._shown:
            sys.stderr.write("\r\x1b[K")
            sys.stderr.flush()
            self._shown = False


def _pct(ratio: float) -> str:
    pct = 100.0 * ratio
    return f"{pct:.2g}" if pct < 10 else f"{pct:.0f}"


def _report_line(output: str, rows: int, summary: dict) -> str:
    """The success line on stdout (the module docstring's ``Report``)."""
    median, largest = summary["range_sigma_median_ratio"], summary["range_sigma_max_ratio"]
    if median is None or largest is None:
        sigma = "range sigma not finite"
    else:
        sigma = f"range sigma median {_pct(median)} % of range, max {_pct(largest)} %"
    analysis = "" if summary["method"] == "map" else "MAP analysis: "
    observable = "yes" if summary["observable"] else "no"
    line = f"{output}: {rows} rows, method {summary['method']}, {analysis}observable {observable}, {sigma}"
    if summary.get("windows", 1) > 1:
        line += (
            f", {summary['windows']} windows of at most {summary['window_s']:g} s"
            f" (observable: {100.0 * summary['observable_rows_fraction']:.0f} % of rows)"
        )
    return line


if __name__ == "__main__":
    sys.exit(main())
