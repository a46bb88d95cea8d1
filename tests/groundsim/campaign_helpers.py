"""Helpers of the campaign tests (tests/groundsim/test_campaign.py, test_campaign_dask.py): the timing-free
table, the onboard configuration's digest, and the CLI campaign interrupted by SIGINT and then resumed."""

from __future__ import annotations

import hashlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

from groundsim.evaluation.campaign import LOG_NAME, read_log, run_campaign
from groundsim.evaluation.campaign_report import TABLE_NAME, TIMING_COLUMNS
from groundsim.evaluation.campaign_spec import load_spec
from groundsim.evaluation.eval import load_base_config

REPO = Path(__file__).resolve().parents[2]
ONBOARD = REPO / "config/onboard.yaml"


def comparable(df: pd.DataFrame) -> pd.DataFrame:
    """The campaign table without its wall-clock columns (what two runs of one campaign share)."""
    return df.drop(columns=[c for c in TIMING_COLUMNS if c in df.columns]).reset_index(drop=True)


def onboard_digest() -> str:
    """What cmd_campaign records for config/onboard.yaml."""
    return hashlib.sha256(ONBOARD.read_bytes()).hexdigest()[:12]


def campaign_cmd(spec_path: Path, out: Path, *options: str) -> list[str]:
    """``python -m groundsim campaign SPEC --out OUT OPTIONS... --no-progress --log-level warning``."""
    return [
        sys.executable,
        "-m",
        "groundsim",
        "campaign",
        str(spec_path),
        "--out",
        str(out),
        *options,
        "--no-progress",
        "--log-level",
        "warning",
    ]


def interrupt_campaign(cmd: list[str], out: Path, runs_logged: int, hang_s: float, stop_s: float) -> int:
    """Start ``cmd`` and send it SIGINT once ``runs_logged`` runs are in its log: it exits 130 saying how to
    resume, the partial table beside the log.  Returns how many runs it logged."""
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log_path = out / LOG_NAME
    deadline = time.monotonic() + hang_s  # hang guard only
    while time.monotonic() < deadline and proc.poll() is None:
        if log_path.is_file() and len(read_log(log_path)[0]) >= runs_logged:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the campaign finished before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=stop_s)
    assert proc.returncode == 130, err
    done_before = len(read_log(log_path)[0])
    assert "the same command resumes" in err
    assert len(pd.read_csv(out / TABLE_NAME)) == done_before  # the partial table is there too
    return done_before


def resume_campaign(cmd: list[str], done_before: int, runs: int, timeout_s: float) -> str:
    """Run ``cmd`` again to the end: it reuses the ``done_before`` runs and runs the rest.  Returns its stdout."""
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout_s)
    assert res.returncode == 0, res.stderr
    assert f"{done_before} reused" in res.stdout and f"{runs - done_before} run now" in res.stdout
    return res.stdout


def run_as_cli(spec_path: Path, out: Path, **how):
    """run_campaign on the spec file as ``groundsim campaign`` runs it (config/onboard.yaml, its digest, no
    progress bar); ``how``: workers= or scheduler=."""
    return run_campaign(
        load_spec(spec_path),
        out,
        progress=False,
        base_config=load_base_config(ONBOARD),
        onboard_digest=onboard_digest(),
        **how,
    )
