"""The campaign's figure: reconstruction error against the observer's manoeuvre (``manoeuvre.png``).

Pure drawing over the rows of :func:`groundsim.evaluation.campaign.manoeuvre_rows`; matplotlib's object
API on the Agg canvas (no pyplot state, no display).  Every algorithm keeps its colour in every panel;
the reference lines (the Cramer-Rao bound, the "works" threshold) are black and grey, so no reference
line can be read as an algorithm's.
"""

from __future__ import annotations

import math
from pathlib import Path

from groundsim.evaluation.report_plots import PNG_DPI

__all__ = ["THRESHOLD_STYLE", "CRB_STYLE", "plot_manoeuvre"]

#: The "works" threshold line: neutral grey, dash-dot (the algorithms are coloured, solid or dotted).
THRESHOLD_STYLE = {"color": "0.45", "ls": "-.", "lw": 1.2}
#: The Cramer-Rao bound: black, dashed.
CRB_STYLE = {"color": "k", "ls": "--", "lw": 1.0}


def plot_manoeuvre(path: Path, mrows: list[dict], good_err_pct: float, settle_after_s: float) -> bool:
    """Error vs observer manoeuvre: one panel per (scenario, noise), one colour per algorithm (settled
    median solid, last frame dotted), the CRB and the ``good_err_pct`` threshold; one legend for the
    figure, with the definition of "settled" (estimates from ``settle_after_s`` on, half the run when
    it is shorter than twice that).  False (no file) when fewer than two manoeuvre levels were swept."""
    if len({r["manoeuvre_scale"] for r in mrows}) < 2:
        return False
    from matplotlib.figure import Figure

    panels = list(dict.fromkeys((r["scenario"], r["noise"]) for r in mrows))
    algos = list(dict.fromkeys(r["algorithm"] for r in mrows))
    colours = {a: f"C{i % 10}" for i, a in enumerate(algos)}
    ncol = 2 if len(panels) == 4 else min(3, len(panels))  # 2 x 2 rather than a row of 3 and a lone panel
    nrow = math.ceil(len(panels) / ncol)
    fig = Figure(figsize=(4.2 * ncol, 3.4 * nrow + 1.0), layout="constrained")
    axes = fig.subplots(nrow, ncol, squeeze=False)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    legend: dict[str, object] = {}  # label -> handle, in drawing order, over every panel
    for ax, (s, n) in zip(axes.flat, panels):
        for a in algos:
            rs = sorted(
                (r for r in mrows if (r["scenario"], r["noise"], r["algorithm"]) == (s, n, a)),
                key=lambda r: r["accel_perp_mps2"],
            )
            if not rs:
                continue
            x = [r["accel_perp_mps2"] for r in rs]
            (settled,) = ax.plot(x, [r["err_pub"] for r in rs], marker="o", color=colours[a])
            (last,) = ax.plot(x, [r["err_final"] for r in rs], marker="o", mfc="none", ls=":", color=colours[a])
            legend.setdefault(f"{a}: settled (median)", settled)
            legend.setdefault(f"{a}: last frame", last)
        rs = sorted(
            (r for r in mrows if (r["scenario"], r["noise"]) == (s, n) and r["algorithm"] == algos[0]),
            key=lambda r: r["accel_perp_mps2"],
        )
        (crb,) = ax.plot([r["accel_perp_mps2"] for r in rs], [r["crb_pct"] for r in rs], **CRB_STYLE)
        legend.setdefault("Cramer-Rao bound (RMS / range)", crb)
        good = ax.axhline(good_err_pct, **THRESHOLD_STYLE)
        legend.setdefault(f"{good_err_pct:g} % of range: the 'works' threshold", good)
        ax.set_yscale("log")
        ax.set_title(f"{s}, {n}", fontsize=10)
        ax.set_xlabel("observer acceleration normal to LOS, RMS (m/s$^2$)")
        ax.set_ylabel("median err / range (%)")
        ax.grid(True, which="both", alpha=0.3)
    fig.legend(
        list(legend.values()),
        list(legend.keys()),
        loc="outside lower center",
        ncol=min(4, len(legend)),
        fontsize=8,
        title=(
            f"settled: the published (finite) estimates from {settle_after_s:g} s on (half the run when it is "
            f"shorter than {2 * settle_after_s:g} s); last frame: the final estimate; medians over seeds"
        ),
        title_fontsize=8,
    )
    fig.suptitle("Reconstruction error vs observer manoeuvre (measured)", fontsize=11)
    path = Path(path)
    fig.savefig(path, dpi=PNG_DPI)
    return True
