"""The figures of the compare report drawn from what evaluate wrote next to each run's per-window table
(benchmark/report/data.py): Figs. 5-7, the wheel response and the calibration curves, and the list of
figures a report draws (:func:`figure_jobs`), each skipped with a note when its data is absent
(:func:`draw_figures`). compare reads no split, loads no fit and predicts nothing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.benchmark.board.tables import SPLITS, CompareError
from skidbench.benchmark.report import data as rd
from skidbench.benchmark.report import figures as figs
from skidbench.benchmark.report.settings import FigureSettings
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR
from skidbench.pipeline.core.errors import one_line
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.runner.forked import map_forked

log = logging.getLogger(__name__)


# -- figures 5-7 and the wheel response: drawn from what evaluate wrote (benchmark/report/data.py) ----------
def figure5(layout: Layout, terrain: str, model_name: str, inputs: str, path: Path, dpi: int) -> Path:
    """Fig. 5 from the residual series evaluate wrote for ``model_name`` on ``terrain``."""
    df, split = rd.read_residuals(layout.eval_stem(model_name, terrain, inputs))
    return figs.residual_vs_acceleration(
        df["wz_pred"].to_numpy(float),
        df["wz_meas"].to_numpy(float),
        df["accel"].to_numpy(float),
        f"Yaw-rate residual of the {figs.label(model_name).lower()} model vs angular acceleration "
        f"({terrain}, {split.upper()} split)",
        path,
        dpi,
    )


def figure6(layout: Layout, terrain: str, model_name: str, inputs: str, path: Path, dpi: int) -> Path:
    """Fig. 6 from the yaw-rate surfaces evaluate computed with the fitted ``model_name``."""
    z = rd.read_surfaces(layout.eval_stem(model_name, terrain, inputs))
    accels = [float(a) for a in z["accels"]]
    surfaces = {a: z["wz"][i] for i, a in enumerate(accels)}
    marks = {a: z["marked"][i] for i, a in enumerate(accels)} if bool(z["has_marks"]) else {}
    masked, no_root, reduced = (int(c) for c in z["counts"])
    wl = z["wl"]
    title = (
        f"{figs.label(model_name)} model: predicted yaw rate at commanded angular accelerations ({terrain})"
    )
    if masked or no_root or reduced:
        title += (
            f"\nof {wl.size * len(accels)} grid points, marked: {reduced} balanced only at a reduced "
            f"acceleration (shown there), {no_root} with no root (least-squares), {masked} not converged"
        )
    return figs.yaw_rate_surfaces(wl, z["wr"], surfaces, title, path, dpi, no_root=marks)


def figure6_accels(layout: Layout, terrain: str, model_name: str, inputs: str) -> list[float]:
    """The commanded angular accelerations (rad/s²) of the surfaces evaluate wrote ([] when none)."""
    try:
        return [float(a) for a in rd.read_surfaces(layout.eval_stem(model_name, terrain, inputs))["accels"]]
    except rd.ReportDataError:
        return []


def figure7(
    layout: Layout, terrain: str, models: Sequence[str], inputs: str, horizon_s: float, path: Path, dpi: int
) -> Path:
    """Fig. 7 from the windows' true and predicted poses evaluate wrote for each model of ``terrain``."""
    samples: dict[tuple[str, int], dict[str, Any]] = {}
    for m in models:
        try:
            df, h = rd.read_trajectories(layout.eval_stem(m, terrain, inputs))
        except rd.ReportDataError as exc:
            log.warning("Fig. 7: %s/%s skipped (%s)", m, terrain, one_line(str(exc)))
            continue
        if not np.isclose(h, horizon_s):
            log.warning("Fig. 7: %s/%s has %g s windows, not %g s: skipped", m, terrain, h, horizon_s)
            continue
        for (split, j), w in df.groupby(["split", "window"], sort=False):
            w = w.sort_values("k")
            sample = samples.setdefault(
                (str(split), int(j)),
                {"split": str(split), "sequence": str(w["sequence"].iloc[0]), "t0": float(w["t0"].iloc[0]),
                 "truth": w[w["role"] == "truth"][["x", "y", "yaw"]].to_numpy(float), "pred": {}},
            )  # fmt: skip
            sample["pred"][m] = w[w["role"] == "pred"][["x", "y", "yaw"]].to_numpy(float)
    if not samples:
        raise CompareError(f"no {horizon_s:g} s test window written by evaluate for terrain {terrain}")
    order = {sp: i for i, sp in enumerate(SPLITS)}
    return figs.trajectories([samples[k] for k in sorted(samples, key=lambda k: (order.get(k[0], 9), k[1]))],
                             horizon_s, path, dpi)  # fmt: skip


def wheel_response_figure(layout: Layout, terrain: str, path: Path, dpi: int) -> Path:
    """The identified wheel response against the encoders around the largest Train command step, as
    evaluate extracted it (:func:`report_data.write_wheel_response_steps`)."""
    df, title = rd.read_wheel_response_steps(layout, terrain)
    cols = lambda p: df[[f"{p}_wl", f"{p}_wr"]].to_numpy(float)  # noqa: E731
    return figs.wheel_response_steps(df["t"].to_numpy(float), cols("cmd"), cols("enc"), cols("resp"), title,
                                     path, dpi)  # fmt: skip


def calibration_windows(
    layout: Layout, finished: pd.DataFrame, inputs: str = "commanded"
) -> dict[str, pd.DataFrame]:
    """Per model with a predictive covariance: its per-window uncertainty columns over every terrain
    (``<ds>/eval/<model>/<terrain>[.<inputs>].windows.parquet`` written by evaluate)."""
    out: dict[str, pd.DataFrame] = {}
    for model, g in finished.groupby("model", sort=False):
        frames = []
        for terrain in g["terrain"]:
            stem = layout.eval_stem(str(model), str(terrain), inputs)
            path = stem.with_name(stem.name + ".windows.parquet")
            try:
                w = pd.read_parquet(path)
            except (OSError, ValueError):
                continue
            if "pos_d2" in w:
                frames.append(w)
        if frames:
            out[str(model)] = pd.concat(frames, ignore_index=True)
    return out


def floor_of(standings: st.Standings | None, metric: mt.Metric) -> dict[tuple[str, str], float]:
    """``{(terrain, split): the floor's value}`` of a metric, for its bar chart."""
    if standings is None:
        return {}
    c = standings.cells
    c = c[(c["model"] == FLOOR) & (c["metric"] == metric.name)]
    return {(r.terrain, r.split): float(r.estimate) for r in c.itertuples(index=False)}


#: (file name, caption, draw(path) -> path)
FigureJob = tuple[str, str, Callable[[Path], Path]]


def figure_jobs(
    fs: FigureSettings,
    layout: Layout,
    board: pd.DataFrame,
    horizon: float,
    inputs: str,
    standings: st.Standings | None,
    decomp: pd.DataFrame,
    shown: Sequence[str],
) -> list[FigureJob]:
    """The figures of a report: every metric's bar chart (Figs. 3 and 4 and the others), the protocols side
    by side (when more than one is shown), the wheel response, Figs. 5-7 on one terrain and the calibration
    of the pose uncertainty (for models with a predictive covariance)."""
    dpi = fs.dpi
    jobs: list[FigureJob] = [
        (
            m.figure.file,
            m.figure.caption,
            lambda p, m=m: figs.metric_bars(board, m, horizon, SPLITS, p, dpi, floor_of(standings, m)),
        )
        for m in mt.METRICS
        if m.figure is not None
    ]
    if len(shown) > 1:
        jobs.append(
            ("fig_protocols.png",
             f"The input protocols side by side ({' / '.join(shown)}), {horizon:g} s errors, mean over "
             "terrains",
             lambda p: figs.protocol_bars(decomp, shown, f"{horizon:g} s errors per input protocol", p, dpi)),
        )  # fmt: skip
    finished = board[board["status"] == "FINISHED"]
    terrains = sorted(finished["terrain"].unique())
    terrain = fs.terrain if fs.terrain else (terrains[0] if terrains else None)
    if terrain is not None:
        jobs.append(
            ("fig_wheel_response.png",
             f"The wheel response `calibrate` identified vs the encoders ({terrain}, Train)",
             lambda p: wheel_response_figure(layout, terrain, p, dpi)),
        )  # fmt: skip
        jobs += _terrain_jobs(fs, layout, finished, terrain, horizon, inputs)
    calib = calibration_windows(layout, finished, inputs)
    if calib:
        jobs.append(
            ("calibration.png",
             f"Calibration of the {horizon:g} s pose uncertainty: nominal vs empirical coverage",
             lambda p: figs.calibration_curves(calib, horizon, p, dpi)),
        )  # fmt: skip
    return jobs


def _terrain_jobs(
    fs: FigureSettings, layout: Layout, finished: pd.DataFrame, terrain: str, horizon: float, inputs: str
) -> list[FigureJob]:
    """Figs. 5-7 on ``terrain``."""
    dpi = fs.dpi
    models = st.order_models(finished[finished["terrain"] == terrain]["model"].tolist())
    m5, m6 = figs.label(fs.fig5_model).lower(), figs.label(fs.fig6_model).lower()
    accels = figure6_accels(layout, terrain, fs.fig6_model, inputs)
    return [
        ("fig5_residual_vs_acceleration.png",
         f"Fig. 5: yaw-rate residual of the {m5} model against angular acceleration ({terrain})",
         lambda p: figure5(layout, terrain, fs.fig5_model, inputs, p, dpi)),
        ("fig6_yaw_rate_surfaces.png",
         f"Fig. 6: {m6} model's yaw rate over the wheel-velocity plane at commanded angular "
         f"accelerations {accels} rad/s² ({terrain})",
         lambda p: figure6(layout, terrain, fs.fig6_model, inputs, p, dpi)),
        ("fig7_trajectories.png",
         f"Fig. 7: true and predicted {horizon:g} s trajectories ({terrain})",
         lambda p: figure7(layout, terrain, models, inputs, horizon, p, dpi)),
    ]  # fmt: skip


#: the jobs of the :func:`draw_figures` call in progress, read by its forked workers (a job is a closure over
#: the board and the layout: the workers inherit it, it is not sent to them)
_JOBS: tuple[FigureJob, ...] = ()


def _draw_job(i: int, path: Path) -> tuple[Path | None, str | None]:
    """Draw job ``i`` of :data:`_JOBS` into ``path``: (the file, None), or (None, the note of why not)."""
    _, caption, draw = _JOBS[i]
    try:
        return draw(path), None
    except Exception as exc:  # a figure that needs local data we do not have: say so, go on
        return None, f"{caption.split(':')[0]} skipped: {type(exc).__name__}: {one_line(str(exc))[:300]}"


def draw_figures(jobs: Sequence[FigureJob], out: Path, files: list[Path], notes: list[str]) -> list[str]:
    """Draw each figure into ``out`` (appended to ``files``, in the order of ``jobs``); the report's Markdown
    of those drawn. A figure that needs data this root does not have is skipped with a note, and the others
    go on. The figures are independent (each reads what it draws and writes its own file): they are drawn
    in forked worker processes, one per core (:func:`~skidbench.pipeline.runner.forked.map_forked`), the same
    files as one after the other."""
    global _JOBS
    _JOBS = tuple(jobs)
    try:
        drawn = map_forked(_draw_job, [(i, out / name) for i, (name, _, _) in enumerate(_JOBS)])
    finally:
        _JOBS = ()
    fig_md: list[str] = []
    for (name, caption, _), (path, note) in zip(jobs, drawn, strict=True):
        if note is not None:
            log.warning("%s", note)
            notes.append(note)
            continue
        files.append(path)
        fig_md.append(f"### {caption}\n\n![{caption}]({name})\n")
    return fig_md
