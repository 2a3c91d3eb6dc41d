"""The benchmark's figures (matplotlib, Agg): the paper's Figs. 3-7 and a per-run error figure.

Every function takes plain arrays/tables and a path, writes one PNG atomically and returns the path, so
the figures can be drawn from MLflow results, from local files or from tests alike.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from skidbench.benchmark.scoring.metrics import HEADLINE, Metric  # noqa: E402
from skidbench.benchmark.scoring.standings import PAPER_MODELS, order_models  # noqa: E402
from skidbench.pipeline.core.io import atomic_path  # noqa: E402

#: display names of the built-in models
MODEL_LABELS = {
    "ideal": "Ideal DD",
    "edd": "Extended DD",
    "full_linear": "Full linear",
    "roc": "ROC-based",
    "enhanced": "Enhanced kin.",
    "friction": "Friction-based",
}
SPLIT_LABELS = {"cv": "Constant velocity (CV)", "ld": "Long distance (LD)", "train": "Train"}
_PALETTE = plt.get_cmap("tab10").colors


def model_color(model: str, models: Sequence[str]) -> tuple:
    if model in PAPER_MODELS:
        return _PALETTE[PAPER_MODELS.index(model)]
    extra = [m for m in order_models(models) if m not in PAPER_MODELS]
    return _PALETTE[(len(PAPER_MODELS) + extra.index(model)) % len(_PALETTE)]


def label(model: str) -> str:
    return MODEL_LABELS.get(model, model)


def _save(fig, path: Path, dpi: int = 130, *, kept: bool = False) -> Path:
    """``fig`` as a PNG at ``path``, written atomically, then closed; ``kept``: a figure kept for the
    process with fixed margins (:func:`_window_axes`): saved as laid out, and left open."""
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches=None if kept else "tight", format="png")
    if not kept:
        plt.close(fig)
    return path


# -- Figs. 3 and 4 (and every metric with a figure) ----------------------------------------------------
def metric_bars(
    board: pd.DataFrame,
    metric: Metric,
    horizon_s: float,
    splits: Sequence[str],
    path: Path,
    dpi: int = 130,
    floor: Mapping[tuple[str, str], float] | None = None,
) -> Path:
    """Bar chart of a metric (Fig. 3: translational RMSRE, Fig. 4: rotational; ``metric.figure``) per model
    (bars) and terrain (groups), one panel per test split, each bar with its 95 % interval as an error bar
    when the board has it (:meth:`Metric.interval_keys`), and the floor (``floor[(terrain, split)]``: a
    perfect model against the ground truth, docs/intervals.md) as a black line across each terrain's group.

    ``board``: one row per (model, terrain) with columns ``model``, ``terrain``, ``status`` and the
    metric's columns named by :meth:`Metric.metric_key`. FAILED runs are marked, not dropped."""
    fig_spec = metric.figure
    digits = fig_spec.digits if fig_spec else 1
    small = 0.5 * 10.0**-digits
    models = order_models(board["model"].unique().tolist())
    terrains = sorted(board["terrain"].unique().tolist())
    nm, nt = len(models), len(terrains)
    width = 0.8 / max(nm, 1)
    fig, axes = plt.subplots(
        1, len(splits), figsize=(1.2 + 1.9 * len(splits) * max(nt, 1.5), 3.8), squeeze=False
    )
    for ax, split in zip(axes[0], splits, strict=True):
        col = metric.metric_key(split, horizon_s)
        lo_col, hi_col, _ = metric.interval_keys(split, horizon_s)
        top = 0.0
        for i, m in enumerate(models):
            xs, ys, los, his = [], [], [], []
            for j, ter in enumerate(terrains):
                row = board[(board["model"] == m) & (board["terrain"] == ter)]
                x = j + (i - (nm - 1) / 2) * width
                v = (
                    float(row[col].iloc[0])
                    if len(row) and col in row and pd.notna(row[col].iloc[0])
                    else np.nan
                )
                failed = len(row) and str(row["status"].iloc[0]) != "FINISHED"
                if failed:
                    ax.text(x, 0, "failed", rotation=90, ha="center", va="bottom", fontsize=7, color="0.3")
                xs.append(x)
                ys.append(v)
                los.append(float(row[lo_col].iloc[0]) if len(row) and lo_col in row else np.nan)
                his.append(float(row[hi_col].iloc[0]) if len(row) and hi_col in row else np.nan)
            ys_arr = np.array(ys)
            lo_arr, hi_arr = np.array(los), np.array(his)
            top = max(top, np.nanmax(ys_arr) if np.isfinite(ys_arr).any() else 0.0)
            bars = ax.bar(
                xs, np.nan_to_num(ys_arr), width * 0.92, label=label(m), color=model_color(m, models)
            )
            top = max(top, _error_bars(ax, np.array(xs), ys_arr, lo_arr, hi_arr))
            for b, y in zip(bars, ys_arr, strict=True):
                if np.isfinite(y):
                    txt = f"{y:.{digits}f}" if y >= small else f"<{10.0**-digits:g}"
                    xy = (b.get_x() + b.get_width() / 2, b.get_height())
                    ax.annotate(txt, xy, xytext=(0, 2), textcoords="offset points", ha="center", va="bottom",
                                fontsize=6, rotation=90)  # fmt: skip
        _floor_lines(ax, terrains, split, floor or {})
        ax.set_xticks(range(nt), [t.capitalize() for t in terrains])
        ax.set_title(SPLIT_LABELS.get(split, split), fontsize=10)
        ax.set_ylabel(fig_spec.axis if fig_spec else metric.column_label(""))
        ax.set_ylim(0, top * 1.18 if top > 0 else 1.0)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    handles, labels_ = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels_, loc="lower center", ncol=min(nm, 6), fontsize=8, frameon=False)
    title = fig_spec.title if fig_spec else metric.description
    fig.suptitle(f"{title}, {horizon_s:g} s horizon", fontsize=11)
    fig.tight_layout(rect=(0, 0.08 if nm <= 6 else 0.14, 1, 1))
    return _save(fig, path, dpi)


def _error_bars(ax, xs: np.ndarray, ys: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Each bar's 95 % interval (block bootstrap) as an error bar, as the paper's Figs. 3-4 would have it;
    returns the highest upper bound (0 without one)."""
    has = np.isfinite(ys) & np.isfinite(lo) & np.isfinite(hi)
    if not has.any():
        return 0.0
    err = np.vstack([ys[has] - lo[has], hi[has] - ys[has]]).clip(min=0.0)
    ax.errorbar(xs[has], ys[has], yerr=err, fmt="none", ecolor="0.15", elinewidth=0.8, capsize=1.5)
    # an interval of a cell on a block or two can reach 1000x its value: the axis keeps the bars readable
    # (at most 3x the highest bar) and such a bar's error bar runs off the top
    return float(min(np.nanmax(hi[has]), 3.0 * np.nanmax(ys[has])))


def _floor_lines(ax, terrains: Sequence[str], split: str, floor: Mapping[tuple[str, str], float]) -> None:
    """The floor (a perfect model against the ground truth) as a black line across each terrain's group."""
    for j, ter in enumerate(terrains):
        fv = floor.get((ter, split))
        if fv is not None and np.isfinite(fv):
            ax.hlines(fv, j - 0.42, j + 0.42, colors="k", linewidth=1.2,
                      label="floor (ground truth)" if j == 0 else None)  # fmt: skip


# -- Fig. 5 -----------------------------------------------------------------------------------------
def residual_vs_acceleration(
    wz_pred: np.ndarray, wz_meas: np.ndarray, accel: np.ndarray, title: str, path: Path, dpi: int = 130
) -> Path:
    """(a) measured yaw rate against the linear model's prediction (the side view of the model's plane),
    coloured by angular acceleration; (b) the residual against angular acceleration, with binned means
    and a least-squares line (the paper's Fig. 5)."""
    wz_pred, wz_meas, accel = (np.asarray(a, float) for a in (wz_pred, wz_meas, accel))
    ok = np.isfinite(wz_pred) & np.isfinite(wz_meas) & np.isfinite(accel)
    wz_pred, wz_meas, accel = wz_pred[ok], wz_meas[ok], accel[ok]
    res = wz_meas - wz_pred
    lim = np.nanpercentile(np.abs(accel), 98) if accel.size else 1.0
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10.5, 4.2))
    order = np.argsort(np.abs(accel))  # large |accel| on top
    sc = a1.scatter(wz_pred[order], wz_meas[order], c=accel[order], s=3, cmap="coolwarm", vmin=-lim, vmax=lim)
    if wz_pred.size:
        lo, hi = np.nanpercentile(np.r_[wz_pred, wz_meas], [0.5, 99.5])
        a1.plot([lo, hi], [lo, hi], "k-", lw=1, label="model plane (measured = predicted)")
        a1.legend(loc="upper left", fontsize=8)
    a1.set_xlabel(r"predicted $\omega_z$ (rad/s)")
    a1.set_ylabel(r"measured $\omega_z$ (rad/s)")
    a1.set_title("(a) side view of the model's plane", fontsize=10)
    fig.colorbar(sc, ax=a1, label=r"angular acceleration (rad/s$^2$)")
    a2.scatter(accel, res, s=2, alpha=0.25, color="0.45", rasterized=True)
    if accel.size > 10:
        edges = np.linspace(-lim, lim, 17)
        idx = np.digitize(accel, edges)
        centers, means = [], []
        for k in range(1, len(edges)):
            sel = idx == k
            if sel.sum() >= 5:
                centers.append(0.5 * (edges[k - 1] + edges[k]))
                means.append(np.mean(res[sel]))
        a2.plot(centers, means, "o-", color="C3", ms=4, label="binned mean")
        slope, icpt = np.polyfit(accel, res, 1)
        r = np.corrcoef(accel, res)[0, 1]
        xx = np.array([-lim, lim])
        a2.plot(xx, slope * xx + icpt, "k--", lw=1, label=f"fit: {slope:+.3f} s, r = {r:+.2f}")
        a2.legend(loc="upper right", fontsize=8)
        ylim = np.nanpercentile(np.abs(res), 99.5) * 1.1
        a2.set_ylim(-ylim, ylim)
    a2.set_xlim(-lim * 1.05, lim * 1.05)
    a2.axhline(0, color="k", lw=0.5)
    a2.set_xlabel(r"measured angular acceleration (rad/s$^2$)")
    a2.set_ylabel(r"residual $\delta\omega_z$ = measured - predicted (rad/s)")
    a2.set_title("(b) residual against angular acceleration", fontsize=10)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, path, dpi)


# -- Fig. 6 -----------------------------------------------------------------------------------------
def _accel_styles(accels: list[float]) -> tuple[dict, dict, dict]:
    """(colour, line style, label) per commanded angular acceleration: diverging and colour-blind-safe
    (negative blue, zero grey, positive orange-red), a sequential map with more than one per sign."""
    base = {-1: "#1f5fbf", 0: "#4d4d4d", 1: "#d9541e"}
    colors = {a: base[int(np.sign(a))] for a in accels}
    if len(set(colors.values())) < len(accels):  # more than one acceleration per sign: a sequential map
        cmap = plt.get_cmap("coolwarm")
        colors = {a: cmap(0.05 + 0.9 * k / max(len(accels) - 1, 1)) for k, a in enumerate(accels)}
    styles = {a: ("-", "--", ":", "-.")[k % 4] for k, a in enumerate(accels)}
    lab = {a: rf"$\dot\omega_{{cmd}}$ = {a:+g} rad/s$^2$" for a in accels}
    return colors, styles, lab


def _draw_surfaces(ax, wl, wr, surfaces, no_root, colors, lab) -> None:
    """Fig. 6 (a): one surface (and wireframe) per acceleration on the 3D axes ``ax``, its no-root cells
    as dots, and the colour legend."""
    accels = sorted(surfaces)
    stride = max(1, wl.shape[0] // 15)
    for a in accels:
        z = np.asarray(surfaces[a], float)
        if no_root[a] is not None:
            z = np.where(no_root[a], np.nan, z)  # NaN, not a masked array: plot_wireframe ignores masks
            ax.scatter(
                wl[no_root[a]],
                wr[no_root[a]],
                surfaces[a][no_root[a]],
                color=colors[a],
                s=2,
                alpha=0.5,
                depthshade=False,
            )
        ax.plot_surface(wl, wr, z, color=colors[a], alpha=0.45, linewidth=0, antialiased=True, shade=False)
        ax.plot_wireframe(wl, wr, z, color=colors[a], linewidth=0.6, rstride=stride, cstride=stride)
    ax.set_xlabel(r"$\omega_l$ (rad/s)", fontsize=9, labelpad=4)
    ax.set_ylabel(r"$\omega_r$ (rad/s)", fontsize=9, labelpad=4)
    ax.set_zlabel(r"predicted $\omega_z$ (rad/s)", fontsize=9, labelpad=4)
    ax.tick_params(labelsize=7, pad=0)
    ax.view_init(elev=22, azim=-128)
    ax.set_box_aspect((1, 1, 0.75))
    ax.legend(
        [Line2D([], [], color=colors[a], lw=6, alpha=0.7) for a in accels],
        [lab[a] for a in accels],
        loc="upper left",
        fontsize=8,
        frameon=True,
    )
    ax.set_title("(a) yaw rate over the wheel-velocity plane", fontsize=10)


def _surface_slices(wl, wr, surfaces, no_root) -> list[tuple]:
    """Fig. 6's slices, each (x, yaw rate per acceleration, no-root cells per acceleration, x label,
    title): the spot-turn diagonal (w_r = -w_l, when the grid is symmetric) and a fixed left wheel rate."""
    accels = sorted(surfaces)
    n = wl.shape[0]
    diag = np.arange(n)
    anti = n - 1 - diag
    symmetric = wl.shape == wr.shape and np.allclose(wl[anti, diag], -wr[anti, diag])
    slices = []
    if symmetric:
        slices.append(
            (
                wr[anti, diag],
                {a: surfaces[a][anti, diag] for a in accels},
                {a: None if no_root[a] is None else no_root[a][anti, diag] for a in accels},
                r"$\omega_r = -\omega_l$ (rad/s)",
                "(b) slice: turning in place",
            )
        )
    # a fixed left wheel rate (about half the range, forward), the right wheel rate varying
    col = int(np.argmin(np.abs(wl[0] - 0.5 * np.nanmax(wl))))
    slices.append(
        (
            wr[:, col],
            {a: surfaces[a][:, col] for a in accels},
            {a: None if no_root[a] is None else no_root[a][:, col] for a in accels},
            r"$\omega_r$ (rad/s)",
            f"({'c' if symmetric else 'b'}) slice: " + r"$\omega_l$ = " + f"{wl[0, col]:.1f} rad/s",
        )
    )
    return slices


def _draw_slice(a2, piece: tuple, colors, styles, lab) -> bool:
    """One slice of Fig. 6 on ``a2`` (no-root cells as open dots, the line broken there); returns whether
    it has any."""
    x, sl, nr, xlabel, sub = piece
    any_nr = False
    for a in sl:
        y = np.asarray(sl[a], float)
        if nr[a] is not None and nr[a].any():
            any_nr = True
            a2.plot(x[nr[a]], y[nr[a]], "o", ms=3.5, mfc="none", color=colors[a], alpha=0.8)
            y = np.where(nr[a], np.nan, y)
        a2.plot(x, y, styles[a], color=colors[a], lw=2, label=lab[a])
    a2.axhline(0, color="k", lw=0.5)
    a2.axvline(0, color="k", lw=0.5)
    a2.set_xlabel(xlabel, fontsize=9)
    a2.set_ylabel(r"predicted $\omega_z$ (rad/s)", fontsize=9)
    a2.tick_params(labelsize=8)
    a2.grid(alpha=0.3)
    a2.set_title(sub, fontsize=10)
    return any_nr


def yaw_rate_surfaces(
    wl: np.ndarray,
    wr: np.ndarray,
    surfaces: Mapping[float, np.ndarray],
    title: str,
    path: Path,
    dpi: int = 130,
    no_root: Mapping[float, np.ndarray] | None = None,
) -> Path:
    """The paper's Fig. 6. (a) 3D: the model's yaw rate over the wheel-velocity plane, one surface per
    commanded angular acceleration (distinct colours, shared colour legend); (b) the slice through the
    spot-turn diagonal (w_r = -w_l) and (c) the slice at a fixed left wheel rate, where the surfaces'
    ordering (higher commanded angular acceleration -> lower yaw rate) reads off directly. NaN cells (no
    prediction) are left blank. ``no_root`` (bool grids, optional): cells where the force balance has no root
    at the commanded acceleration (the prediction there is the model's fallback: the solution at a reduced
    acceleration, or the least-squares solution of eq. 12); the surfaces show roots only and these cells
    are drawn as dots, so a missing patch of surface reads as "no force balance", not as a solver failure."""
    accels = sorted(surfaces)
    no_root = {a: np.asarray(no_root[a], bool) if no_root and a in no_root else None for a in accels}
    colors, styles, lab = _accel_styles(accels)
    fig = plt.figure(figsize=(13, 6.2))
    gs = fig.add_gridspec(2, 2, width_ratios=(1.35, 1.0), hspace=0.42, wspace=0.12)
    _draw_surfaces(fig.add_subplot(gs[:, 0], projection="3d"), wl, wr, surfaces, no_root, colors, lab)
    slices = _surface_slices(wl, wr, surfaces, no_root)
    for k, piece in enumerate(slices):
        a2 = fig.add_subplot(gs[k, 1]) if len(slices) == 2 else fig.add_subplot(gs[:, 1])
        any_nr = _draw_slice(a2, piece, colors, styles, lab)
        if k == 0:  # the legend, on the first slice
            h, lb = a2.get_legend_handles_labels()
            if any_nr:
                h.append(Line2D([], [], ls="", marker="o", mfc="none", color="0.3", ms=4))
                lb.append("no root at the commanded\nacceleration (fallback shown)")
            a2.legend(h, lb, fontsize=7.5)
    fig.suptitle(title, fontsize=11)
    fig.subplots_adjust(left=0.0, right=0.98, top=0.86, bottom=0.09)
    return _save(fig, path, dpi)


# -- Fig. 7 -----------------------------------------------------------------------------------------
def trajectories(samples: Sequence[Mapping], horizon_s: float, path: Path, dpi: int = 130) -> Path:
    """Predicted and true trajectories of sample windows: one panel per window. Each sample: ``split``,
    ``sequence``, ``t0``, ``truth`` (n+1, 3) and ``pred`` {model: (n+1, 3)}."""
    splits = list(dict.fromkeys(s["split"] for s in samples))
    ncol = max(sum(s["split"] == sp for s in samples) for sp in splits)
    fig, axes = plt.subplots(len(splits), ncol, figsize=(3.3 * ncol, 3.3 * len(splits) + 0.6), squeeze=False)
    all_models = order_models(sorted({m for s in samples for m in s["pred"]}))
    for r, sp in enumerate(splits):
        row = [s for s in samples if s["split"] == sp]
        for c in range(ncol):
            ax = axes[r][c]
            if c >= len(row):
                ax.axis("off")
                continue
            s = row[c]
            origin = s["truth"][0]
            ca, sa = np.cos(origin[2]), np.sin(origin[2])

            def local(p, origin=origin, ca=ca, sa=sa):  # start pose at (0, 0) heading +x
                dx, dy = p[:, 0] - origin[0], p[:, 1] - origin[1]
                return ca * dx + sa * dy, -sa * dx + ca * dy

            for m in all_models:
                if m in s["pred"]:
                    x, y = local(s["pred"][m])
                    ax.plot(x, y, "-", lw=1.3, color=model_color(m, all_models), label=label(m))
            x, y = local(s["truth"])
            ax.plot(x, y, "k-", lw=2.4, label="ground truth")
            ax.plot([0], [0], "ko", ms=4)
            ax.set_aspect("equal", adjustable="datalim")
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
            ax.set_title(f"{SPLIT_LABELS.get(sp, sp)}\n{s['sequence']} t={s['t0']:.0f} s", fontsize=8)
            if c == 0:
                ax.set_ylabel("y (m), start frame", fontsize=8)
            if r == len(splits) - 1:
                ax.set_xlabel("x (m), start frame", fontsize=8)
    handles, labels_ = [], []
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels_:
                handles.append(h)
                labels_.append(lab)
    fig.legend(handles, labels_, loc="lower center", ncol=min(len(labels_), 7), fontsize=8, frameon=False)
    fig.suptitle(f"True and predicted {horizon_s:g} s trajectories", fontsize=11)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return _save(fig, path, dpi)


# -- per run ----------------------------------------------------------------------------------------
def window_error_figure(windows: pd.DataFrame, title: str, path: Path, dpi: int = 110) -> Path:
    """Relative translational and rotational error of every window over time, per test split (first
    horizon), for one (model, terrain) run. Drawn for every run of every evaluate, so cheaply: one figure
    per number of splits is made once (:func:`_window_axes`, fixed margins) and redrawn with each run's
    points; the PNG is the one a new figure would give."""
    h = float(windows["horizon_s"].iloc[0])
    w = windows[windows["horizon_s"] == h]
    splits = list(dict.fromkeys(w["split"]))
    fig, axes = _window_axes(len(splits))
    for c, sp in enumerate(splits):
        ws = w[w["split"] == sp]
        for r, (col, name) in enumerate((("rel_trans", "translational"), ("rel_rot", "rotational"))):
            ax = axes[r][c]
            for k, (seq, g) in enumerate(ws.groupby("sequence", sort=True)):
                ax.plot(g["t0"], 100 * g[col], ".", ms=1.5, color=_PALETTE[k % 10], label=seq)
            ax.set_ylabel(f"{name} rel. error (%)", fontsize=8)
            if r == 0:
                ax.set_title(SPLIT_LABELS.get(sp, sp), fontsize=9)
            else:
                ax.set_xlabel("window start (s)", fontsize=8)
    fig.suptitle(f"{title}: per-window errors, {h:g} s horizon", fontsize=10)
    return _save(fig, path, dpi, kept=True)


#: the fixed margins of :func:`window_error_figure` (inches): room for the y tick labels and label on the
#: left, the suptitle and the split's title on top, the x tick labels and label below, each column's
#: y label between the columns
_WINDOW_MARGINS_IN = {"left": 0.75, "right": 0.15, "bottom": 0.5, "top": 0.62, "wspace": 0.45,
                      "hspace": 0.35}  # fmt: skip
_WINDOW_FIGURES: dict[int, tuple] = {}  # number of splits -> (figure, axes), made once per process


def _window_axes(n_splits: int) -> tuple:
    """The figure and (2, ``n_splits``) axes of :func:`window_error_figure` (rows share y), emptied of the
    last run's points with their data limits reset. A :class:`~matplotlib.figure.Figure` of no pyplot
    window: made once, kept for the process (making the axes and their ticks is most of a figure's cost)."""
    from matplotlib.figure import Figure

    if n_splits not in _WINDOW_FIGURES:
        width, height, m = 4.2 * n_splits, 4.6, _WINDOW_MARGINS_IN
        fig = Figure(figsize=(width, height))
        axes = fig.subplots(2, n_splits, squeeze=False, sharey="row")
        fig.subplots_adjust(left=m["left"] / width, right=1 - m["right"] / width, bottom=m["bottom"] / height,
                            top=1 - m["top"] / height, wspace=m["wspace"] / (width / n_splits),
                            hspace=m["hspace"] / (height / 2))  # fmt: skip
        for ax in axes.flat:
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
        _WINDOW_FIGURES[n_splits] = (fig, axes)
    fig, axes = _WINDOW_FIGURES[n_splits]
    for ax in axes.flat:
        for line in list(ax.lines):
            line.remove()
        ax.relim()
    return fig, axes


# -- the input protocols side by side, and the wheel response ----------------------------------------
PROTOCOL_LABELS = {
    "commanded": "commanded (paper)",
    "response": "wheel response",
    "measured": "measured (oracle)",
}


def protocol_bars(
    values: pd.DataFrame, protocols: Sequence[str], title: str, path: Path, dpi: int = 130
) -> Path:
    """Per model, one bar per input protocol, one panel per metric: what the wheel response explains
    (commanded -> response) and what remains when the wheels are known (response -> measured).

    ``values``: one row per model, column ``model`` and ``_<metric>_<split>_<protocol>`` (the headline
    metrics of :mod:`skidbench.benchmark.scoring.metrics`)."""
    models = order_models(values["model"].tolist())
    panels = [(m, s) for m in HEADLINE for s in ("cv", "ld")]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.8), squeeze=False)
    width = 0.8 / max(len(protocols), 1)
    shades = {"commanded": "0.25", "response": "tab:blue", "measured": "tab:green"}
    for ax, (metric, split) in zip(axes[0], panels, strict=True):
        for i, p in enumerate(protocols):
            col = f"_{metric.name}_{split}_{p}"
            ys = [
                float(values.loc[values["model"] == m, col].iloc[0]) if col in values else np.nan
                for m in models
            ]
            xs = np.arange(len(models)) + (i - (len(protocols) - 1) / 2) * width
            ax.bar(xs, np.nan_to_num(ys), width * 0.92, color=shades.get(p, _PALETTE[i]),
                   label=PROTOCOL_LABELS.get(p, p))  # fmt: skip
        ax.set_xticks(range(len(models)), [label(m) for m in models], rotation=45, ha="right", fontsize=7)
        ax.set_title(f"{metric.short} {split.upper()}", fontsize=10)
        ax.set_ylabel(metric.figure.axis if metric.figure else metric.column_label(""))
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    handles, labels_ = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels_, loc="lower center", ncol=len(protocols), fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return _save(fig, path, dpi)


def wheel_response_steps(
    t: np.ndarray, command: np.ndarray, measured: np.ndarray, response: np.ndarray, title: str, path: Path,
    dpi: int = 130,
) -> Path:  # fmt: skip
    """The wheels' response to a command step: the commanded, the measured (encoders) and the identified
    response's wheel rates (rad/s) of the left and right wheel (``(T, 2)`` each) against time (s)."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharex=True, squeeze=False)
    for j, (ax, side) in enumerate(zip(axes[0], ("left", "right"), strict=True)):
        ax.step(t, command[:, j], where="post", color="0.55", lw=1.2, label="commanded")
        ax.plot(t, measured[:, j], color="tab:red", lw=1.4, label="measured (encoders)")
        ax.plot(t, response[:, j], color="tab:blue", lw=1.4, ls="--", label="identified response")
        ax.set_title(f"{side} wheel", fontsize=10)
        ax.set_xlabel("time from the command step (s)")
        ax.set_ylabel("wheel rate (rad/s)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, dpi)


def calibration_curves(
    windows: Mapping[str, pd.DataFrame], horizon_s: float, path: Path, dpi: int = 130
) -> Path:
    """Nominal vs empirical coverage of the predicted h-second end position (2-dof Gaussian region,
    left) and yaw (right), one line per model and test split (solid CV, dashed LD). A calibrated model
    follows the diagonal; below it, over-confident. ``windows``: model -> windows with ``horizon_s``,
    ``split``, ``pos_d2``, ``yaw_z2`` columns (benchmark/scoring/horizon.py)."""
    from scipy.stats import chi2

    nominal = np.linspace(0.01, 0.99, 50)
    models = order_models(list(windows))
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 4.4), sharey=True)
    for ax, col, dof, what in ((axes[0], "pos_d2", 2, "position"), (axes[1], "yaw_z2", 1, "yaw")):
        ax.plot([0, 1], [0, 1], color="0.6", lw=1)
        q = chi2.ppf(nominal, dof)
        for m in models:
            w = windows[m]
            w = w[np.isclose(w["horizon_s"], horizon_s)] if "horizon_s" in w else w
            for split, ls in (("cv", "-"), ("ld", "--")):
                d = np.sort(w.loc[w["split"] == split, col].to_numpy(float)) if "split" in w else np.array([])
                if not len(d):
                    continue
                emp = np.searchsorted(d, q, side="right") / len(d)
                ax.plot(nominal, emp, ls, color=model_color(m, models), label=f"{label(m)} {split.upper()}")
        ax.axvline(0.95, color="0.85", lw=0.8)
        ax.set_xlabel("nominal coverage")
        ax.set_title(f"{what} at {horizon_s:g} s")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
    axes[0].set_ylabel("empirical coverage")
    axes[1].legend(fontsize=7, loc="lower right")
    return _save(fig, path, dpi)
