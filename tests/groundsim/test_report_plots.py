"""The report plots say what they show, and the report texts state the configuration's defaults truly.

The figures are taken where they are saved (``Figure.savefig`` patched to keep them) and read back:
legends, texts, colours and markers, not pixels.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure

from groundsim.evaluation.campaign_plots import THRESHOLD_STYLE, plot_manoeuvre
from groundsim.evaluation.flight_report import FlightRun
from groundsim.evaluation.report import DEFINITIONS
from groundsim.evaluation.report_plots import plot_errors, plot_performance, plot_trajectory
from onboard.app.config import OutputConfig

REPO = Path(__file__).resolve().parents[2]
REPORT_SOURCES = [
    REPO / "groundsim" / "evaluation" / name for name in ("report.py", "demo.py", "eval.py", "flight_report.py")
]
SPIKE_M = 50.0  # unobservable error spikes, far beyond an axis scaled to the observable errors
SMALL_ERR_M = 0.2
N_SPIKES = 4
ZLABEL_PAD_MIN = 10  # points between the 3-D axis' tick labels and its label


@pytest.fixture
def saved(monkeypatch):
    """The figures the plot functions save, in order (nothing is written)."""
    figures: list[Figure] = []
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: figures.append(self))
    return figures


def _run(F: int = 60) -> FlightRun:
    """Observable frames with a small error, and a few unobservable ones with large spikes."""
    t = np.arange(F) / 30.0
    truth = np.column_stack([100.0 + 2.0 * t, 50.0 - t, -80.0 + 0.0 * t])
    cam = np.column_stack([0.0 * t, 4.0 * t, -60.0 + 0.0 * t])
    est = truth + SMALL_ERR_M
    obs = np.ones(F, bool)
    spikes = np.arange(5, 5 + 2 * N_SPIKES, 2)
    est[spikes, 0] += np.where(np.arange(N_SPIKES) % 2 == 0, SPIKE_M, -SPIKE_M)
    obs[spikes] = False
    cov = np.broadcast_to(np.eye(3) * 0.25, (F, 3, 3)).copy()
    rng = np.linalg.norm(truth - cam, axis=1)
    nan3 = np.full((F, 3), np.nan)
    return FlightRun("T", "0", t, est, cov, obs, truth, cam, rng, nan3, np.zeros(F, bool))


def test_error_plot_marks_every_error_beyond_its_axis_and_says_where_it_clips(saved, tmp_path):
    plot_errors(tmp_path / "error.png", _run())
    north = saved[0].axes[0]
    lo, hi = north.get_ylim()
    assert hi < SPIKE_M  # the axis follows the observable errors: the spikes are beyond it
    notes = [t.get_text() for t in north.texts if "clipped" in t.get_text()]
    assert len(notes) == 1 and f"\u00b1{hi:.3g} m" in notes[0] and f"{N_SPIKES} errors beyond" in notes[0]
    marked = np.concatenate([c.get_offsets()[:, 1] for c in north.collections if len(c.get_offsets())])
    assert np.count_nonzero(np.isclose(np.abs(marked), hi)) == N_SPIKES
    east = saved[0].axes[1]  # nothing clipped there: no note
    assert not [t for t in east.texts if "clipped" in t.get_text()]


def test_trajectory_plot_keeps_the_up_label_off_its_ticks(saved, tmp_path):
    plot_trajectory(tmp_path / "trajectory.png", _run())
    ax3 = next(ax for ax in saved[0].axes if ax.name == "3d")
    assert ax3.zaxis.labelpad >= ZLABEL_PAD_MIN


def test_performance_plot_names_every_stage_and_the_baseline_as_evaluation_only(saved, tmp_path):
    perf = [
        {
            "scenario": "P1",
            "flight_ms_per_frame": 0.6,
            "render_ms_per_frame": 2.0,
            "pipeline_ms_per_frame": 5.0,
            "baseline_ms_per_frame": 2.5,
        }
    ]
    plot_performance(tmp_path / "performance.png", perf, {"P1": np.array([1.0, 1.2, 5.0])})
    stages = saved[0].axes[1]
    labels = [t.get_text() for t in stages.get_legend().get_texts()]
    assert labels[0].startswith("30 fps budget")
    assert [lab.split(" ")[0] for lab in labels[1:]] == ["perfect-centroid", "pipeline", "render", "flight"]
    assert "evaluation only" in labels[1]  # top of the stack first, as drawn


def _mrows() -> list[dict]:
    rows = []
    for s, n in (("P1", "RTK"), ("P2", "RTK"), ("P1", "px0.3"), ("P2", "px0.3")):
        for a, scale in zip(("map", "paper", "rpekf"), (1.0, 10.0, 100.0)):
            for m in (0.5, 1.0, 2.0):
                rows.append(
                    {
                        "algorithm": a,
                        "scenario": s,
                        "noise": n,
                        "manoeuvre_scale": m,
                        "accel_perp_mps2": 0.45 * m,
                        "err_pub": scale / m,
                        "err_final": scale / (2 * m),
                        "crb_pct": 0.5 / m,
                    }
                )
    return rows


def test_manoeuvre_plot_has_one_legend_defining_settled_and_a_neutral_threshold(saved, tmp_path):
    assert plot_manoeuvre(tmp_path / "manoeuvre.png", _mrows(), 2.0, 5.0)
    fig = saved[0]
    assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
    legend = fig.legends[0]
    assert "settled: the published (finite) estimates from 5 s on" in legend.get_title().get_text()
    labels = [t.get_text() for t in legend.get_texts()]
    assert any("'works' threshold" in lab for lab in labels) and any("Cramer-Rao" in lab for lab in labels)
    threshold = to_rgba(THRESHOLD_STYLE["color"])
    for ax in fig.axes:
        lines = ax.get_lines()
        algo_colours = {to_rgba(ln.get_color()) for ln in lines if ln.get_marker() == "o"}
        assert len(algo_colours) == 3 and threshold not in algo_colours
        drawn = [ln for ln in lines if to_rgba(ln.get_color()) == threshold]
        assert len(drawn) == 1 and drawn[0].get_linestyle() == "-."


def test_manoeuvre_plot_is_skipped_with_one_level(saved, tmp_path):
    rows = [r for r in _mrows() if r["manoeuvre_scale"] == 1.0]
    assert not plot_manoeuvre(tmp_path / "manoeuvre.png", rows, 2.0, 5.0) and not saved


def test_report_texts_state_the_default_of_unobservable_positions_truly():
    default = str(OutputConfig().unobservable_positions).lower()
    stated = re.compile(
        r"default[^;]{0,40}?unobservable_positions:? `?(true|false)|unobservable_positions:? "
        r"`?(true|false)`?[^;]{0,20}?the default"
    )
    found = []
    for path in REPORT_SOURCES:
        text = " ".join(path.read_text(encoding="utf-8").split())
        found += [(path.name, m.group(1) or m.group(2)) for m in stated.finditer(text)]
    found += [("DEFINITIONS", m.group(1) or m.group(2)) for m in stated.finditer(" ".join(DEFINITIONS.values()))]
    assert len(found) >= 3 and all(value == default for _, value in found), found


def test_an_out_directory_that_is_a_file_is_called_one(tmp_path):
    from groundsim.evaluation.out_dir import make_out_dir
    from onboard.core.errors import ConfigError

    afile = tmp_path / "results.txt"
    afile.write_text("kept\n")
    with pytest.raises(ConfigError, match=r"^--out .*results.txt: a file, not a directory; give a directory"):
        make_out_dir(afile)
    assert afile.read_text() == "kept\n" and make_out_dir(tmp_path / "new" / "deeper").is_dir()
