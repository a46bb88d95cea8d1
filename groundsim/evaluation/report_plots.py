"""The evaluation's PNG plots: a run's trajectory, its error over time with the reported sigma, a frame with the
chain's and the truth's marks, and the performance panel (:mod:`groundsim.evaluation.report` writes them; the demo and
``groundsim report`` draw the same).  matplotlib's object API on the Agg canvas (``matplotlib.figure.Figure``): no
pyplot state, no display needed."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = [
    "PERFORMANCE_STAGES",
    "PNG_DPI",
    "plot_errors",
    "plot_frame",
    "plot_objects",
    "plot_performance",
    "plot_trajectory",
]

PNG_DPI = 110


def _figure(w_in: float, h_in: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(w_in, h_in), layout="constrained")


def _enu(p_ned):
    """(east, north, up) columns of NED points, for plots that read like a map."""
    p = np.asarray(p_ned, dtype=float)
    return p[:, 1], p[:, 0], -p[:, 2]


def _lbl(label: str, *values) -> str:
    """``label`` when any of ``values`` has a finite number (the series is drawn), else matplotlib's
    "no legend" label: a legend lists only what is drawn."""
    for v in values:
        a = np.asarray(v, dtype=float)
        if a.size and np.isfinite(a).any():
            return label
    return "_nolegend_"


def _legend(ax, **kw) -> None:
    """A legend when something labelled is drawn (an empty one warns and shows a blank box)."""
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(**kw)


def plot_trajectory(path, run, title: str = "") -> Path:
    """Fig. 8 analogue: 3-D and top view of the target's truth, the online reconstruction (observable
    frames; all frames with an estimate faint), the batch reconstruction and the observer's path."""
    import mpl_toolkits.mplot3d  # noqa: F401 - registers the 3-D projection

    fig = _figure(12.0, 5.4)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    has = np.all(np.isfinite(run.est_p_ned_m), axis=1)
    obs = has & run.observable
    series = [
        (run.truth_p_ned_m, dict(color="k", lw=2.0, label="target truth")),
        (run.observer_p_ned_m, dict(color="0.55", lw=1.5, ls="--", label="observer (camera) path")),
    ]
    for p, kw in series:
        e, n, u = _enu(p)
        ax3.plot(e, n, u, **kw)
        ax2.plot(e, n, **kw)
    if (has & ~obs).any():
        e, n, u = _enu(run.est_p_ned_m[has & ~obs])
        ax3.scatter(e, n, u, s=4, color="tab:orange", alpha=0.25, label="online, not observable")
        ax2.scatter(e, n, s=4, color="tab:orange", alpha=0.25, label="online, not observable")
    if obs.any():
        e, n, u = _enu(run.est_p_ned_m[obs])
        ax3.scatter(e, n, u, s=5, color="tab:red", label="online track (observable)")
        ax2.scatter(e, n, s=5, color="tab:red", label="online track (observable)")
    b = (run.batch or {}).get("pipeline") or {}
    if b.get("p_ned_m") is not None:
        e, n, u = _enu(b["p_ned_m"])
        ax3.plot(e, n, u, color="tab:blue", lw=1.2, label="batch (whole flight)")
        ax2.plot(e, n, color="tab:blue", lw=1.2, label="batch (whole flight)")
    e0, n0, _ = _enu(run.truth_p_ned_m[:1])
    ax2.scatter(e0, n0, marker="o", color="k", s=20, zorder=5)
    ax2.annotate("target start", (e0[0], n0[0]), textcoords="offset points", xytext=(5, 5), fontsize=8)
    eo, no, _ = _enu(run.observer_p_ned_m[:1])
    ax2.annotate("observer start", (eo[0], no[0]), textcoords="offset points", xytext=(5, -12), fontsize=8)
    ax3.set_xlabel("east m", labelpad=8)
    ax3.set_ylabel("north m", labelpad=8)
    ax3.set_zlabel("up m", labelpad=10)  # the default pad puts the label on the tick labels
    ax3.set_title("3-D (local frame about the scenario origin)")
    ax2.set_xlabel("east m")
    ax2.set_ylabel("north m")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.grid(True, alpha=0.3)
    ax2.set_title("top view")
    _legend(ax2, fontsize=8, loc="best")
    fig.suptitle(title or f"{run.scenario} seed {run.seed}: truth vs reconstruction")
    return _save(fig, path)


def plot_errors(path, run, title: str = "") -> Path:
    """Error over time: per NED axis with the reported 1-sigma band, and the range-normalised error of
    the online track, the perfect-centroid baseline and the batch reconstruction."""
    fig = _figure(11.0, 8.0)
    axes = fig.subplots(4, 1, sharex=True)
    t = run.t_s - run.t_s[0]
    has = np.all(np.isfinite(run.est_p_ned_m), axis=1)
    obs = has & run.observable
    e = run.est_p_ned_m - run.truth_p_ned_m
    with np.errstate(invalid="ignore"):
        sig = np.sqrt(np.maximum(np.einsum("fii->fi", run.est_cov_ned_m2), 0.0))  # NaN where no estimate
    for k, name in enumerate(("north", "east", "down")):
        ax = axes[k]
        ek = np.where(has, e[:, k], np.nan)
        sk = np.where(has, sig[:, k], np.nan)
        ax.fill_between(t, -sk, sk, color="tab:red", alpha=0.15, lw=0, label=_lbl("reported 1 sigma", sk))
        e_obs, e_not = np.where(obs, ek, np.nan), np.where(has & ~obs, ek, np.nan)
        ax.plot(t, e_obs, color="tab:red", lw=1.2, label=_lbl("error, observable", e_obs))
        ax.plot(t, e_not, color="tab:orange", lw=0.8, alpha=0.7, label=_lbl("error, not observable", e_not))
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(f"{name} m")
        shown = np.abs(ek[obs]) if obs.any() else np.abs(ek[has])
        finite = shown[np.isfinite(shown)]  # none where no estimated frame has truth (a truth cut short)
        lim = max(1.0, 3.0 * float(np.percentile(finite, 95))) if finite.size else 1.0
        ax.set_ylim(-lim, lim)
        _mark_clipped(ax, t, ek, lim, "m", "observable" if obs.any() else "estimated")
        with np.errstate(invalid="ignore"):
            wide = int(np.sum(sk > lim))
        if wide:  # the band runs off the axis: said, so a cut band is not read as its edge
            ax.text(
                0.995,
                0.04,
                f"1 sigma beyond the axis on {wide} frame{'s' if wide > 1 else ''} (up to {np.nanmax(sk):.3g} m)",
                transform=ax.transAxes,
                ha="right",
                fontsize=7,
                color="tab:red",
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.7", alpha=0.85),
                zorder=5,
            )
        ax.grid(True, alpha=0.3)
    _legend(axes[0], fontsize=8, loc="upper right", ncol=3)
    ax = axes[3]
    rng = run.range_m
    en = np.linalg.norm(e, axis=1) / rng * 100.0
    en_obs, en_not = np.where(obs, en, np.nan), np.where(has & ~obs, en, np.nan)
    ax.plot(t, en_obs, color="tab:red", lw=1.2, label=_lbl("online track (observable)", en_obs))
    ax.plot(t, en_not, color="tab:orange", lw=0.8, alpha=0.7, label=_lbl("online, not observable", en_not))
    bh = np.all(np.isfinite(run.base_p_ned_m), axis=1) & run.base_observable
    eb = np.where(bh, np.linalg.norm(run.base_p_ned_m - run.truth_p_ned_m, axis=1) / rng * 100.0, np.nan)
    ax.plot(t, eb, color="tab:green", lw=1.0, label=_lbl("perfect centroids (observable)", eb))
    b = (run.batch or {}).get("pipeline") or {}
    if b.get("p_ned_m") is not None:
        idx = b["frames"]
        ebt = np.linalg.norm(b["p_ned_m"] - run.truth_p_ned_m[idx], axis=1) / rng[idx] * 100.0
        ax.plot(t[idx], ebt, color="tab:blue", lw=1.0, label=_lbl("batch (whole flight)", ebt))
    ax.set_yscale("log")
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _pos: f"{y:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_ylabel("||e|| / range %")
    ax.set_xlabel("time s")
    ax.grid(True, which="both", alpha=0.3)
    _legend(ax, fontsize=8, loc="upper right", ncol=2)
    fig.suptitle(title or f"{run.scenario} seed {run.seed}: reconstruction error")
    return _save(fig, path)


def _mark_clipped(ax, t, e, lim: float, unit: str, basis: str) -> int:
    """Errors beyond the axis limit ``lim`` (3 x the 95th percentile of the ``basis`` errors, so the
    spikes of unobservable estimates would otherwise be cut off unseen): a triangle on the edge at each
    one's time and a note of the limit.  Returns how many were beyond."""
    with np.errstate(invalid="ignore"):
        above, below = e > lim, e < -lim
    n = int(above.sum() + below.sum())
    if n == 0:
        return 0
    for sel, y, marker in ((above, lim, "^"), (below, -lim, "v")):
        if sel.any():
            ax.scatter(t[sel], np.full(int(sel.sum()), y), marker=marker, s=14, color="0.25", clip_on=False, zorder=4)
    ax.text(
        0.005,
        0.04,
        f"axis clipped at \u00b1{lim:.3g} {unit} (3 x the 95th percentile of the {basis} errors): "
        f"{n} error{'s' if n > 1 else ''} beyond, marked \u25b2\u25bc on the edge",
        transform=ax.transAxes,
        fontsize=7,
        color="0.25",
        bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.7", alpha=0.85),
        zorder=5,
    )
    return n


def plot_frame(path, frame: dict, title: str = "") -> Path:
    """One IR frame with the track box and the true target pixel, and a zoom on the target."""
    from matplotlib.patches import Rectangle

    img = np.asarray(frame["pixels"])
    fig = _figure(11.0, 4.6)
    gs = fig.add_gridspec(1, 3)
    ax = fig.add_subplot(gs[0, :2])
    az = fig.add_subplot(gs[0, 2])
    tu, tv = frame.get("truth_uv_px") or (math.nan, math.nan)
    half = 24
    # display stretch only (the grey values are not changed): whole frame 0.5-99.95 %, zoom min-max
    lo, hi = np.percentile(img, [0.5, 99.95])
    zlo, zhi = lo, hi
    if math.isfinite(tu):
        u0, v0 = int(max(tu - half, 0)), int(max(tv - half, 0))
        patch = img[v0 : int(tv + half) + 1, u0 : int(tu + half) + 1]
        if patch.size:
            zlo, zhi = float(patch.min()), float(patch.max())
    for a, (vlo, vhi) in ((ax, (lo, hi)), (az, (zlo, zhi))):
        a.imshow(
            img,
            cmap="gray",
            vmin=vlo,
            vmax=max(vhi, vlo + 1),
            interpolation="nearest",
            extent=(0, img.shape[1], img.shape[0], 0),
        )
    box = frame.get("bbox")
    if box is not None:
        for a in (ax, az):
            a.add_patch(Rectangle((box[0], box[1]), box[2], box[3], fill=False, ec="tab:red", lw=1.5))
    if frame.get("uv_px") is not None:
        for a in (ax, az):
            a.plot(*frame["uv_px"], "+", color="tab:red", ms=10, mew=1.5, label="track centre")
    if math.isfinite(tu):
        for a in (ax, az):
            a.plot(tu, tv, "x", color="tab:cyan", ms=8, mew=1.5, label="true target pixel")
        az.set_xlim(tu - half, tu + half)
        az.set_ylim(tv + half, tv - half)
    _legend(az, fontsize=8, loc="lower right")
    for a in (ax, az):
        a.set_xlabel("u px")
        a.set_ylabel("v px")
    az.set_title("zoom on the target")
    ax.set_title(
        f"frame {frame['k']} at t = {frame['t_s']:.2f} s, state {frame.get('state')}, range {frame['range_m']:.0f} m"
        " (contrast stretched for display)",
        fontsize=10,
    )
    fig.suptitle(title)
    return _save(fig, path)


#: The stacked stages of the performance plot: key of ``<key>_ms_per_frame``, colour, legend label.
PERFORMANCE_STAGES = (
    ("flight", "0.6", "flight (JSBSim, both vehicles)"),
    ("render", "tab:purple", "render (the IR frame)"),
    ("pipeline", "tab:red", "pipeline (FramePipeline.process: the daemon's work)"),
    (
        "baseline",
        "tab:green",
        "perfect-centroid baseline (evaluation only:\nthe same estimator on true pixels + noise)",
    ),
)


def plot_performance(path, summary_perf: list[dict], latencies: dict[str, np.ndarray], title: str = "") -> Path:
    """Fig. 9 analogue: per-frame processing latency distribution, and wall ms per frame by stage."""
    fig = _figure(12.0, 4.6)
    a1, a2 = fig.subplots(1, 2)
    for name, lat in latencies.items():
        lat = np.asarray(lat, dtype=float)
        if lat.size:
            a1.hist(
                lat,
                bins=np.logspace(np.log10(max(lat.min(), 0.05)), np.log10(max(lat.max(), 1.0)), 40),
                histtype="step",
                lw=1.5,
                label=f"{name} (p50 {np.percentile(lat, 50):.1f} ms)",
            )
    a1.set_xscale("log")
    # plain numbers on the log axis (1, 2, 5, 10 ms), not matplotlib's minor labels "3x10^0"
    from matplotlib.ticker import FuncFormatter

    a1.xaxis.set_major_formatter(FuncFormatter(lambda x, _pos: f"{x:g}"))
    a1.xaxis.set_minor_formatter(FuncFormatter(lambda x, _pos: f"{x:g}" if f"{x:.1g}"[0] in "25" else ""))
    a1.set_xlabel("pipeline processing per frame, ms (imaging + pose + estimator)")
    a1.set_ylabel("frames")
    a1.grid(True, which="both", alpha=0.3)
    _legend(a1, fontsize=8)
    names = [r["scenario"] for r in summary_perf]
    bottom = np.zeros(len(names))
    bars = []
    for st, c, label in PERFORMANCE_STAGES:
        vals = np.array([r.get(f"{st}_ms_per_frame") or 0.0 for r in summary_perf])
        bars.append(a2.bar(names, vals, bottom=bottom, color=c, label=label))
        bottom += vals
    budget_ms = 1000.0 / 30.0
    budget = a2.axhline(budget_ms, color="k", ls="--", lw=1, label=f"30 fps budget ({budget_ms:.1f} ms)")
    a2.set_ylim(0.0, 1.75 * max(budget_ms, float(bottom.max(initial=0.0))))  # room for the legend above
    a2.set_ylabel("wall ms per frame (lockstep, one process)")
    a2.set_title("time per frame by stage (the daemon does only the pipeline)", fontsize=9)
    a2.legend(handles=[budget, *bars[::-1]], fontsize=7, loc="upper left")  # top to bottom, as stacked
    a2.grid(True, axis="y", alpha=0.3)
    fig.suptitle(title or "performance")
    return _save(fig, path)


#: false tracks drawn in a row each at most; the rest share one row
MAX_FALSE_ROWS = 8


def _runs(frames: list[int], keys: list) -> list[tuple[int, int, object]]:
    """Consecutive frames with the same key as ``(first frame, frames, key)``: a gap in the frames ends a run."""
    out: list[tuple[int, int, object]] = []
    for f, k in zip(frames, keys):
        if out and out[-1][2] == k and out[-1][0] + out[-1][1] == f:
            out[-1] = (out[-1][0], out[-1][1] + 1, k)
        else:
            out.append((f, 1, k))
    return out


def plot_objects(path, gt_text: str, tracker_text: str, t_s, title: str = "") -> Path:
    """Who was tracked when, from a run's MOT files (:func:`groundsim.evaluation.mot.object_timeline`): a row per
    true object, pale where it is in the image and visible, grey where hidden; over it, coloured by the tracked id
    paired with it (within 3 px: a change of colour is an id switch), the frames it was tracked; red ticks where it
    was visible and nothing tracked it.  Below, each tracked id paired with no object (a false track) on its
    frames.  ``t_s``: the time of each frame (frame k of the files is ``t_s[k - 1]``)."""
    import matplotlib
    from matplotlib.patches import Patch

    from groundsim.evaluation.mot import object_timeline

    tl = object_timeline(gt_text, tracker_text)
    t = np.asarray(t_s, dtype=float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0 / 30.0

    def span(first: int, n: int) -> tuple[float, float]:
        i = min(max(first - 1, 0), t.size - 1) if t.size else 0
        start = float(t[i]) if t.size else (first - 1) * dt
        return start, n * dt

    objects, false = tl["objects"], tl["false"]
    false_rows = list(false.items())[:MAX_FALSE_ROWS]
    rest = sorted(f for _, frames in list(false.items())[MAX_FALSE_ROWS:] for f in frames)
    rows = len(objects) + len(false_rows) + (1 if rest else 0)
    fig = _figure(11.0, 1.6 + 0.32 * max(rows, 1))
    ax = fig.add_subplot(1, 1, 1)
    # tab10 without its red and grey, which mean "missed" and "hidden" here
    palette = [c for i, c in enumerate(matplotlib.colormaps["tab10"].colors) if i not in (3, 7)]
    colour_of: dict[int, object] = {}
    labels: list[str] = []
    y = rows - 1
    for gid, frames_states in objects.items():
        frames = [f for f, _, _ in frames_states]
        for first, n, visible in _runs(frames, [v for _, v, _ in frames_states]):
            ax.broken_barh([span(first, n)], (y - 0.4, 0.8), color="0.93" if visible else "0.72", lw=0)
        named = None  # the id last written on this row: written again only when another takes over
        for first, n, tid in _runs(frames, [tid for _, _, tid in frames_states]):
            if tid is None:
                continue
            c = colour_of.setdefault(tid, palette[len(colour_of) % len(palette)])
            ax.broken_barh([span(first, n)], (y - 0.25, 0.5), color=c, lw=0)
            if tid != named:
                ax.text(span(first, n)[0], y + 0.3, f"#{tid}", fontsize=6, va="bottom", clip_on=True)
                named = tid
        missed = [f for f, visible, tid in frames_states if visible and tid is None]
        if missed:
            ax.vlines([span(f, 1)[0] + dt / 2 for f in missed], y - 0.4, y + 0.4, color="tab:red", lw=0.6)
        labels.append("target" if gid == 1 else f"object {gid}")
        y -= 1
    for tid, frames in false_rows:
        for first, n, _ in _runs(frames, [0] * len(frames)):
            ax.broken_barh([span(first, n)], (y - 0.25, 0.5), color="tab:red", alpha=0.6, lw=0)
        labels.append(f"false #{tid}")
        y -= 1
    if rest:
        for first, n, _ in _runs(rest, [0] * len(rest)):
            ax.broken_barh([span(first, n)], (y - 0.25, 0.5), color="tab:red", alpha=0.4, lw=0)
        labels.append(f"{len(false) - MAX_FALSE_ROWS} more false")
    ax.set_yticks(range(rows - 1, -1, -1), labels, fontsize=8)
    ax.set_ylim(-0.7, rows - 0.3)
    if t.size:
        ax.set_xlim(float(t[0]), float(t[-1]) + dt)
    ax.set_xlabel("time since the scenario's start (s)")
    ax.grid(True, axis="x", alpha=0.3)
    ax.legend(
        handles=[
            Patch(color="0.93", label="visible (any contrast)"),
            Patch(color="0.72", label="hidden (cloud, edge)"),
            Patch(color=palette[0], label="tracked (colour: its id)"),
            Patch(color="tab:red", label="visible, not tracked / false track"),
        ],
        fontsize=7,
        loc="upper left",
        bbox_to_anchor=(1.0, 1.0),
    )
    fig.suptitle(title or "objects tracked")
    return _save(fig, path)


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=PNG_DPI)
    return path
