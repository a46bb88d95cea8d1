"""A campaign's folder as its resume state: the append-only run log (``runs.jsonl``: rows appended and fsynced as
they come, read back line by line, damaged lines skipped) and the record of which campaign the folder holds
(``campaign.json``).  :mod:`groundsim.evaluation.campaign` describes resuming.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from groundsim.evaluation.campaign_report import (
    COLUMN_ORDER,
    FIGURE_NAME,
    PARQUET_NAME,
    REPORT_NAME,
    TABLE_NAME,
)
from groundsim.evaluation.campaign_runs import RunParams, run_id
from groundsim.evaluation.campaign_spec import CampaignSpec
from groundsim.evaluation.out_dir import write_replacing
from onboard.core.errors import ConfigError

__all__ = [
    "LOG_NAME",
    "MARK_NAME",
    "read_log",
    "reusable_rows",
    "skipped_text",
    "append_rows",
    "check_outputs",
    "check_same_campaign",
    "mark_campaign",
]

LOG_NAME = "runs.jsonl"
MARK_NAME = "campaign.json"  # which campaign's runs the folder's log holds: {"name": ..., "spec": ...}


# --------------------------------------------------------------------------- the append-only log


#: columns of a log row that hold text, and flags (true, false or null); the table's other columns hold numbers or
#: null: the report sorts, compares and takes medians of them, so a row with another type there is not reused
_TEXT_COLUMNS = frozenset(
    {"run_id", "mode", "scenario", "geometry", "noise", "algorithm", "noise_model", "status", "error", "bound_note"}
    | {"scenario_digest", "noise_digest", "onboard_digest"}
)
_FLAG_COLUMNS = frozenset({"crb", "batch_observable"})
_NUMBER_COLUMNS = frozenset(COLUMN_ORDER) - _TEXT_COLUMNS - _FLAG_COLUMNS
_STATUSES = ("ok", "failed")
_PARAM_FIELDS = tuple(f.name for f in dataclasses.fields(RunParams))
#: at most this many line numbers are listed in the warning about skipped lines (the count is always given)
_LINES_SHOWN = 10


def _not_a_row(row: Any) -> bool:
    """Whether a parsed log line is not a row :func:`append_rows` could have written: an object whose ``run_id``
    is text, and whose known columns hold their type (other keys are left alone: a newer version's columns)."""
    if not isinstance(row, dict) or not isinstance(row.get("run_id"), str):
        return True
    for key, value in row.items():
        if key in _TEXT_COLUMNS:
            ok = isinstance(value, str) and (key != "status" or value in _STATUSES)
        elif key in _FLAG_COLUMNS:
            ok = value is None or isinstance(value, bool)
        elif key in _NUMBER_COLUMNS:
            ok = value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
        else:
            continue
        if not ok:
            return True
    return False


def _is_row_of(row: dict, rid: str) -> bool:
    """Whether ``row`` is the result of run ``rid``: it carries the run's parameters, which hash to ``rid``, and the
    columns every row of the table and the report has."""
    if any(key not in row for key in (*_PARAM_FIELDS, "geometry", "status")):
        return False
    return run_id(RunParams(**{key: row[key] for key in _PARAM_FIELDS})) == rid


def _scan_log(path: Path, planned: frozenset[str] = frozenset()) -> tuple[dict[str, dict], list[int]]:
    """``runs.jsonl`` -> ({run_id: row}, [numbers of the lines skipped]); a later row of a run replaces an earlier
    one (``--retry-failed`` appends).  Read as bytes, line by line, so a line that is not UTF-8, not JSON or not a
    row (:func:`_not_a_row`) is skipped without stopping the others; a row under a ``planned`` run id must be that
    run's (:func:`_is_row_of`), so a damaged one cannot replace a good one before it."""
    done: dict[str, dict] = {}
    bad: list[int] = []
    if not path.is_file():
        return done, bad
    try:
        with path.open("rb") as f:
            for number, raw in enumerate(f, start=1):
                if not raw.strip():
                    continue
                try:
                    row = json.loads(raw.decode("utf-8"))
                except (ValueError, RecursionError):  # not UTF-8 (UnicodeDecodeError is one), not JSON, too deep
                    bad.append(number)
                    continue
                if _not_a_row(row) or (row["run_id"] in planned and not _is_row_of(row, row["run_id"])):
                    bad.append(number)
                    continue
                done[row["run_id"]] = row
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return done, bad


def read_log(path: Path) -> tuple[dict[str, dict], int]:
    """``runs.jsonl`` -> ({run_id: row}, lines skipped).  A torn or foreign line is skipped, not fatal."""
    done, bad = _scan_log(path)
    return done, len(bad)


def reusable_rows(path: Path, planned_ids: Iterable[str]) -> tuple[dict[str, dict], list[int]]:
    """The rows of the log a campaign of ``planned_ids`` can reuse, and the numbers of the lines skipped: those
    :func:`read_log` skips, and rows under a planned run id that are not that run's (:func:`_is_row_of`)."""
    return _scan_log(path, frozenset(planned_ids))


def skipped_text(path: Path, lines: list[int]) -> str:
    shown = ", ".join(map(str, lines[:_LINES_SHOWN])) + (", ..." if len(lines) > _LINES_SHOWN else "")
    return (
        f"{path}: {len(lines)} line(s) skipped, not a run's row (line {shown}): cut short by an interruption, "
        "damaged or written by something else; any run they held is run again"
    )


def append_rows(path: Path, rows: Iterable[dict]) -> None:
    """Append rows to the log, one JSON line each, flushed and fsynced (a kill loses no finished run).
    An OSError (the log unwritable, the disk full) is a one-line ConfigError naming the file."""
    try:
        with path.open("a+b") as f:
            # a line cut short by a kill has no newline: ended here, so the row written next is a line of its
            # own (glued onto the fragment it was lost with it, and reading the log skipped both)
            if f.seek(0, os.SEEK_END) > 0:
                f.seek(-1, os.SEEK_END)
                if f.read(1) != b"\n":
                    f.write(b"\n")
        with path.open("a", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(row, sort_keys=True, allow_nan=False) + "\n")
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write: {exc.strerror or exc}") from None


def check_outputs(out: Path) -> None:
    """Refuses, before any run, outputs that could not be written after the runs: the log must open for
    appending, and the table, the report and the figure must not be directories (one-line ConfigError)."""
    for name in (LOG_NAME, MARK_NAME, TABLE_NAME, PARQUET_NAME, REPORT_NAME, FIGURE_NAME):
        if (out / name).is_dir():
            raise ConfigError(f"{out / name}: cannot write: Is a directory")
    append_rows(out / LOG_NAME, ())


def _held_campaign(out: Path) -> tuple[str, str] | None:
    """(name, spec file) of the campaign whose runs ``out``'s log holds, None when it holds none (no log, or one
    emptied by ``--fresh``): read from :data:`MARK_NAME`, or, in a folder written before it existed, from the
    report's title (the spec file then unknown)."""
    log_path = out / LOG_NAME
    if not log_path.is_file() or log_path.stat().st_size == 0:
        return None
    try:
        mark = json.loads((out / MARK_NAME).read_text(encoding="utf-8"))
        if isinstance(mark, dict) and isinstance(mark.get("name"), str):
            return mark["name"], str(mark.get("spec", "?"))
    except (OSError, ValueError):
        pass
    try:
        with (out / REPORT_NAME).open(encoding="utf-8") as f:
            title = f.readline().strip()
    except (OSError, ValueError):
        return None
    prefix = "# Campaign "
    return (title[len(prefix) :], "unknown") if title.startswith(prefix) else None


def check_same_campaign(out: Path, spec: CampaignSpec) -> None:
    """ConfigError naming ``out`` and both campaigns when its log holds another campaign's runs: its table and
    report would be this one's while its log held both, and each campaign run there in turn would overwrite the
    other's.  A campaign is its name (what names its default folder): a spec edited (a seed added) or moved
    keeps resuming its folder."""
    held = _held_campaign(out)
    if held is None or held[0] == spec.name:
        return
    raise ConfigError(
        f"--out {out}: holds the runs of campaign {held[0]!r} (spec {held[1]}), not of {spec.name!r} "
        f"(spec {spec.source}); give another --out, or --fresh to forget the runs of {held[0]!r} and start "
        f"{spec.name!r} there"
    )


def mark_campaign(out: Path, spec: CampaignSpec) -> None:
    """Record in ``out`` that its log is ``spec``'s campaign's (:func:`check_same_campaign` reads it)."""
    text = json.dumps({"name": spec.name, "spec": str(spec.source)}, indent=1) + "\n"
    try:
        write_replacing(out / MARK_NAME, lambda p: p.write_text(text, encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{out / MARK_NAME}: cannot write: {exc.strerror or exc}") from None
