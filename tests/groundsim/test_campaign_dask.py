"""groundsim.evaluation.campaign on a Dask distributed cluster (``--scheduler``): the same tables as the local process
pool, resumption after an interruption, the Parquet table, and the refusals (one line, naming the option)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.campaign import (
    LOG_NAME,
    check_workers,
    code_fingerprint,
    plan_runs,
    read_log,
    run_id,
)
from groundsim.evaluation.campaign_report import (
    PARQUET_NAME,
    TABLE_NAME,
    table_rows,
    write_table,
)
from groundsim.evaluation.campaign_spec import (
    load_spec,
)
from onboard.core.errors import ConfigError
from tests.groundsim.campaign_helpers import (
    campaign_cmd,
    comparable,
    interrupt_campaign,
    onboard_digest,
    resume_campaign,
    run_as_cli,
)

distributed = pytest.importorskip("distributed")

# every dimension a cluster could mix up: 2 scenarios x 2 noise cases x 3 algorithms x 2 seeds = 24 runs (8 jobs,
# more than the 2 workers take at once) of 2 s flights (flown three times: the pool's table, the cluster's, the
# interrupted and resumed one; every run still publishes estimates at 2 s, which the first test checks); a third
# seed would repeat the same paths at a third more cost
SPEC_TEXT = (
    "name: scaleout\nscenarios: [P1, P2]\nnoise: [RTK, px0.3]\nalgorithms: [map, paper, rpekf]\nseeds: 2\n"
    "duration_s: 2.0\n"
)
RUNS = 2 * 2 * 3 * 2


@pytest.fixture(scope="module")
def spec_path(tmp_path_factory):
    p = tmp_path_factory.mktemp("spec") / "scaleout.yaml"
    p.write_text(SPEC_TEXT)
    return p


@pytest.fixture(scope="module")
def pool_table(spec_path, tmp_path_factory):
    """The reference: the campaign on the local process pool (2 workers), as the CLI would run it."""
    out = tmp_path_factory.mktemp("pool")
    res = run_as_cli(spec_path, out, workers=2)
    assert res.ran == RUNS and res.failed == 0
    return pd.read_csv(out / TABLE_NAME)


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded worker processes and a scheduler, on 127.0.0.1 only (no dashboard)."""
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    ) as c:
        yield c


@pytest.mark.slow
@pytest.mark.integration
def test_a_dask_cluster_gives_the_pool_s_table_and_parquet_round_trips(spec_path, pool_table, cluster, tmp_path):
    out = tmp_path / "dask"
    res = run_as_cli(spec_path, out, scheduler=cluster.scheduler_address)
    assert res.ran == RUNS and res.failed == 0 and res.workers == 2 and not res.interrupted
    dask_table = pd.read_csv(out / TABLE_NAME)
    pd.testing.assert_frame_equal(comparable(pool_table), comparable(dask_table))
    # the numbers are real: every run published estimates, the bound is finite, all three algorithms ran
    assert (dask_table["published_frames"] > 0).all() and np.isfinite(dask_table["crb_rms_m"]).all()
    assert sorted(dask_table["algorithm"].unique()) == ["map", "paper", "rpekf"]
    # the log was written by the coordinator only: one line per run, in the table's run ids
    done, bad = read_log(out / LOG_NAME)
    assert bad == 0 and len(done) == RUNS and set(done) == set(dask_table["run_id"])
    # runs.parquet beside runs.csv holds the same table, with its types (CSV loses None vs "" and bools)
    assert PARQUET_NAME in res.files
    pq = pd.read_parquet(out / PARQUET_NAME)
    ids = [run_id(p) for p in plan_runs(load_spec(spec_path), onboard_digest())]
    pd.testing.assert_frame_equal(pq, table_rows([done[i] for i in ids]))
    # a rerun on the cluster reuses everything
    again = run_as_cli(spec_path, out, scheduler=cluster.scheduler_address)
    assert again.ran == 0 and again.reused == RUNS


@pytest.mark.slow
@pytest.mark.integration
def test_a_campaign_on_the_cluster_interrupted_resumes_to_the_pool_s_table(spec_path, pool_table, cluster, tmp_path):
    """``groundsim campaign SPEC --scheduler ADDR``, SIGINT once the first case is logged: exit 130, the finished
    runs kept; the same command runs only the rest, and the table equals the pool's."""
    out = tmp_path / "out"
    cmd = campaign_cmd(spec_path, out, "--scheduler", cluster.scheduler_address)
    # hang guard 240 s; SIGINT once one case (3 algorithms) of 8 is done
    done_before = interrupt_campaign(cmd, out, runs_logged=3, hang_s=240, stop_s=120)
    assert 3 <= done_before < RUNS

    stdout = resume_campaign(cmd, done_before, runs=RUNS, timeout_s=600)
    assert f"of {cluster.scheduler_address}" in stdout
    pd.testing.assert_frame_equal(comparable(pool_table), comparable(pd.read_csv(out / TABLE_NAME)))


# --------------------------------------------------------------------------- refusals and the table (fast)


@pytest.mark.parametrize(
    "extra, message",
    [
        (
            ["--scheduler", "127.0.0.1:8786"],
            r"--scheduler: expected an address tcp://HOST:PORT, got '127\.0\.0\.1:8786'",
        ),
        (["--scheduler", "tcp://127.0.0.1:8786", "--workers", "2"], r"--workers: not with --scheduler"),
    ],
)
def test_bad_scheduler_options_are_one_line_and_exit_2(spec_path, tmp_path, capsys, extra, message):
    import re

    assert cli_main(["campaign", str(spec_path), "--out", str(tmp_path / "o"), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and re.search(message, err), err


class _FakeClient:
    def __init__(self, fingerprints: dict):
        self.fp = fingerprints

    def nthreads(self):
        return {w: 1 for w in self.fp}

    def run(self, fn):
        assert fn is code_fingerprint
        return dict(self.fp)


def test_workers_running_other_code_or_no_workers_are_refused_naming_them():
    mine = code_fingerprint()
    assert len(mine) == 16 and mine == code_fingerprint()
    assert check_workers(_FakeClient({"tcp://10.0.0.2:1": mine, "tcp://10.0.0.3:1": mine}), "tcp://s:1") == 2
    with pytest.raises(
        ConfigError, match=r"--scheduler tcp://s:1: worker\(s\) tcp://10\.0\.0\.3:1 run other irtrack code"
    ):
        check_workers(_FakeClient({"tcp://10.0.0.2:1": mine, "tcp://10.0.0.3:1": "0" * 16}), "tcp://s:1")
    with pytest.raises(ConfigError, match=r"--scheduler tcp://s:1: the scheduler has no workers"):
        check_workers(_FakeClient({}), "tcp://s:1")


def test_the_parquet_table_round_trips_missing_values_bools_and_strings(tmp_path):
    pytest.importorskip("pyarrow")
    rows = [
        {
            "run_id": "a",
            "scenario": "P1",
            "seed": 0,
            "status": "ok",
            "err_range_final_pct": 1.25,
            "batch_observable": True,
            "error": "",
            "bound_note": "",
            "wall_s": 0.5,
        },
        {
            "run_id": "b",
            "scenario": "P2",
            "seed": 1,
            "status": "failed",
            "err_range_final_pct": None,
            "batch_observable": None,
            "error": "ValueError: x",
            "bound_note": "CRB failed",
            "wall_s": 0.25,
        },
    ]
    files = write_table(tmp_path, rows)
    back = pd.read_parquet(files[PARQUET_NAME])
    pd.testing.assert_frame_equal(back, table_rows(rows))
    assert back["batch_observable"].iloc[0] == True  # noqa: E712 - a bool survived (numpy or python)
    assert pd.isna(back["batch_observable"].iloc[1]) and math.isnan(back["err_range_final_pct"].iloc[1])
    assert back["error"].tolist() == ["", "ValueError: x"]
