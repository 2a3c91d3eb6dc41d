"""What ``skidbench compare`` draws beyond the metrics, written by ``evaluate`` (the stage that has the fitted
model and its predictions) next to each per-window table, so that compare renders without reading a split,
loading a fit or predicting:

- ``<stem>.residuals.parquet`` (Fig. 5): the test split's measured and predicted yaw rate (rad/s) and the
  measured angular acceleration (rad/s², smoothed derivative), valid samples only;
- ``<stem>.surfaces.npz`` (Fig. 6): the model's yaw rate (rad/s) over a wheel-rate grid (rad/s) at the
  commanded angular accelerations of ``report_data.fig6_accels`` (a prediction on synthetic inputs);
- ``<stem>.trajectories.parquet`` (Fig. 7): true and predicted poses over the horizon of a few windows per
  test split, chosen from the ground truth alone (the same windows for every model);

with ``<stem>`` = ``<ds>/eval/<model>/<terrain>[.<inputs>]`` (:meth:`Layout.eval_stem`); and once per
terrain ``<ds>/eval/wheel_response/<terrain>.parquet``: the calibration's wheel response against the
encoders around the largest Train command step. The ``read_*`` functions are compare's side.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from skidbench.benchmark.report.settings import ReportDataSettings
from skidbench.benchmark.scoring.horizon import (
    EvaluationError,
    horizon_steps,
    window_errors,
    window_trajectory,
)
from skidbench.pipeline.calibrate.calibration import Calibrations, calibration_doc, wheel_response_of
from skidbench.pipeline.calibrate.wheel_response import wheel_response
from skidbench.pipeline.core.errors import SkidbenchError, one_line
from skidbench.pipeline.core.io import read_parquet_metadata, write_bytes_atomic, write_parquet_atomic
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.protocol import INPUT_COLUMNS
from skidbench.pipeline.core.schema import concat_sequences, read_split

log = logging.getLogger(__name__)

FIG5_SPLITS = ("ld", "cv")  # Fig. 5 shows the long drives, else the first test split there is
FIG7_SPLITS = ("cv", "ld")
FIG7_MIN_DISTANCE_M = 0.5  # Fig. 7 shows windows that go somewhere


class ReportDataError(EvaluationError):
    """What compare wants was not written by evaluate (or is unreadable)."""


def _path(stem: Path, what: str) -> Path:
    return stem.with_name(f"{stem.name}.{what}")


# -- evaluate's side ----------------------------------------------------------------------------------
def write_report_data(
    s: ReportDataSettings, layout: Layout, stem: Path, model: Any, terrain: str,
    tests: Mapping[str, Sequence[Any]], velocities: Mapping[str, Sequence[np.ndarray]], horizon_s: float,
) -> list[Path]:  # fmt: skip
    """Writes the three artifacts of one (model, terrain, protocol) (module docstring) and returns them.
    ``tests``: split -> the TestSequences evaluate scored; ``velocities``: split -> their (T, 3) predicted
    body velocities (m/s, m/s, rad/s); ``horizon_s``: the horizon of Fig. 7 (evaluate's first)."""
    accels, windows = list(s.fig6_accels), s.fig7_windows
    jobs = {
        "residuals.parquet": lambda: write_residuals(stem, tests, velocities),
        "trajectories.parquet": lambda: write_trajectories(stem, tests, velocities, horizon_s, windows),
        "surfaces.npz": lambda: write_surfaces(stem, model, layout, terrain, accels, s.fig6_grid),
    }
    out = []
    for what, write in jobs.items():
        try:
            out.append(write())
        except Exception as exc:  # a figure's data never fails the benchmark: compare says it is missing
            _path(stem, what).unlink(missing_ok=True)  # no stale data of an earlier run in its place
            log.warning("%s: %s not written: %s: %s", stem, what, type(exc).__name__, one_line(str(exc)))
    return out


def _smoothed_derivative(t: np.ndarray, y: np.ndarray, window_s: float = 0.3) -> np.ndarray:
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    k = max(1, int(round(window_s / dt)))
    ys = np.convolve(y, np.ones(k) / k, mode="same") if len(y) >= k else y
    return np.gradient(ys, t) if len(t) > 1 else np.zeros_like(y)


def write_residuals(stem: Path, tests: Mapping[str, Sequence[Any]], velocities) -> Path:
    """Fig. 5's series: ``wz_pred``, ``wz_meas`` (rad/s), ``accel`` (rad/s²) of the valid samples."""
    split = next((sp for sp in FIG5_SPLITS if sp in tests), next(iter(tests)))
    seqs = [q for q in tests[split] if len(q.table)]
    vel = [v for q, v in zip(tests[split], velocities[split], strict=True) if len(q.table)]
    acc = np.concatenate(
        [_smoothed_derivative(q.table["t"].to_numpy(float), q.table["wz"].to_numpy(float)) for q in seqs]
    )
    ok = np.concatenate([q.table["valid"].to_numpy(bool) for q in seqs])
    meas = np.concatenate([q.table["wz"].to_numpy(float) for q in seqs])
    pred = np.concatenate([np.asarray(v, float)[:, 2] for v in vel])
    table = pa.table({"wz_pred": pred[ok], "wz_meas": meas[ok], "accel": acc[ok]})
    path = _path(stem, "residuals.parquet")
    write_parquet_atomic(table, path, {"split": split})
    return path


def fig7_windows(seqs: Sequence[Any], horizon_s: float, n_windows: int) -> list[tuple[int, int]]:
    """The windows Fig. 7 shows of one split, from the ground truth alone: ``(sequence index, start)`` at
    the quantiles 0.5..0.97 of the turned angle among the windows that travel at least 0.5 m."""
    cands = []
    for i, q in enumerate(seqs):
        df = q.table
        t = df["t"].to_numpy(float)
        if len(df) <= horizon_steps(t, horizon_s):
            continue
        gt = df[["x", "y", "yaw"]].to_numpy(float)
        w = window_errors(t, gt, np.zeros((len(t), 3)), horizon_s, df["valid"].to_numpy(bool))
        w = w[w["distance"] >= FIG7_MIN_DISTANCE_M]
        if len(w):
            cands.append(w.assign(_f=i))
    if not cands or n_windows < 1:
        return []
    allw = pd.concat(cands, ignore_index=True)
    qs = np.linspace(0.5, 0.97, n_windows) if n_windows > 1 else [0.9]
    picked = allw.sort_values("rotation").iloc[[int(q * (len(allw) - 1)) for q in qs]]
    return [(int(r["_f"]), int(r["start"])) for _, r in picked.iterrows()]


def write_trajectories(
    stem: Path, tests: Mapping[str, Sequence[Any]], velocities, horizon_s: float, n_windows: int
) -> Path:
    """Fig. 7's poses: one row per (window, ``role`` truth|pred, step ``k``): ``split``, ``sequence``,
    ``window`` (order within the split), ``t0`` (s), ``x``, ``y`` (m), ``yaw`` (rad)."""
    frames = []
    for split in (sp for sp in FIG7_SPLITS if sp in tests):
        seqs = tests[split]
        for j, (i, s0) in enumerate(fig7_windows(seqs, horizon_s, n_windows)):
            df = seqs[i].table
            t = df["t"].to_numpy(float)
            gt = df[["x", "y", "yaw"]].to_numpy(float)
            n = horizon_steps(t, horizon_s)
            poses = {"truth": gt[s0 : s0 + n + 1],
                     "pred": window_trajectory(t, gt, velocities[split][i], s0, horizon_s)}  # fmt: skip
            for role, p in poses.items():
                frames.append(pd.DataFrame({"split": split, "sequence": seqs[i].name, "window": j,
                                            "t0": float(t[s0]), "role": role, "k": np.arange(len(p)),
                                            "x": p[:, 0], "y": p[:, 1], "yaw": p[:, 2]}))  # fmt: skip
    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(
        {c: [] for c in ("split", "sequence", "window", "t0", "role", "k", "x", "y", "yaw")}
    )  # fmt: skip
    path = _path(stem, "trajectories.parquet")
    write_parquet_atomic(pa.Table.from_pandas(table, preserve_index=False), path, {"horizon_s": horizon_s})
    return path


def _wheel_rate_limit(layout: Layout, terrain: str, default: float = 10.0) -> float:
    """Fig. 6's grid half-width (rad/s): the 95th percentile of |commanded wheel rate| in the terrain's
    first Train sequence."""
    try:
        files = layout.split_files(Manifest.read(layout.manifest), terrain, "train")
        df, _ = read_split(files[0])
    except (SkidbenchError, OSError, IndexError):
        return default
    return float(np.nanpercentile(np.abs(df[["cmd_wl", "cmd_wr"]].to_numpy(float)), 95)) or default


def write_surfaces(
    stem: Path, model: Any, layout: Layout, terrain: str, accels: Sequence[float], n: int = 31
) -> Path:
    """Fig. 6's surfaces: ``wl``, ``wr`` (n, n) wheel rates (rad/s), ``accels`` (k,) rad/s², ``wz`` (k, n, n)
    the model's yaw rate (rad/s; NaN where its solve did not converge), ``marked`` (k, n, n) points solved
    at a reduced acceleration or without a root, and ``counts`` (masked, no_root, reduced)."""
    robot = getattr(model, "robot", None)
    if robot is None:
        raise ReportDataError(f"model {getattr(model, 'name', type(model).__name__)} has no robot")
    lim = _wheel_rate_limit(layout, terrain)
    g = np.linspace(-lim, lim, n)
    wl, wr = np.meshgrid(g, g, indexing="xy")  # symmetric grid: the anti-diagonal is wr = -wl
    m = wl.size
    wz_all, marked = [], []
    has_marks = False
    masked = no_root = reduced = 0
    for a in accels:
        dwl, dwr = robot.wheel_rates_from_twist(0.0, float(a))  # pure angular acceleration
        v, w = robot.twist_from_wheel_rates(wl.ravel(), wr.ravel())
        dwl_a, dwr_a = np.full(m, float(dwl)), np.full(m, float(dwr))
        if hasattr(model, "velocities"):
            # the force balance at these wheel rates and accelerations themselves: the grid's rows are
            # independent points, not a time series a model's actuator (dead time, lag) could run over
            vel, sol = model.velocities((wl.ravel(), wr.ravel(), dwl_a, dwr_a))
            wz = np.asarray(vel, float)[:, 2].copy()
        else:
            table = pd.DataFrame({"t": np.arange(m) / 30.0, "sequence": "grid", "cmd_v": v, "cmd_w": w,
                                  "cmd_wl": wl.ravel(), "cmd_wr": wr.ravel(), "cmd_dwl": dwl_a,
                                  "cmd_dwr": dwr_a})  # fmt: skip
            wz = np.asarray(model.predict(table[list(INPUT_COLUMNS)]), float)[:, 2].copy()
            sol = getattr(model, "last_solve_", None)
        status = getattr(sol, "status", None)
        mark = np.zeros(m, bool)
        if status is not None and len(status) == m:  # the friction model's per-step solve status
            has_marks = True
            status = np.asarray(status)
            scale = getattr(sol, "accel_scale", None)
            reduced_here = np.asarray(scale) < 1 if scale is not None else np.zeros(m, bool)
            blank = (status == 0) & ~reduced_here  # not converged, no fallback: nothing to show
            wz[blank] = np.nan
            masked += int(np.sum(blank))
            no_root += int(np.sum((status == 2) & ~reduced_here))
            reduced += int(np.sum(reduced_here))
            mark = (status != 1) | reduced_here
        wz_all.append(wz.reshape(wl.shape))
        marked.append(mark.reshape(wl.shape))
    buf = io.BytesIO()
    np.savez_compressed(buf, wl=wl, wr=wr, accels=np.asarray(accels, float), wz=np.asarray(wz_all),
                        marked=np.asarray(marked), has_marks=has_marks,
                        counts=np.array([masked, no_root, reduced]))  # fmt: skip
    path = _path(stem, "surfaces.npz")
    write_bytes_atomic(path, buf.getvalue())
    return path


def wheel_response_path(layout: Layout, terrain: str) -> Path:
    return layout.eval / "wheel_response" / f"{terrain}.parquet"


def write_wheel_response_steps(cal: Calibrations, layout: Layout, terrain: str) -> Path:
    """The wheel response ``calibrate`` identified for ``terrain`` against the encoders around the largest
    step of the mean commanded wheel rate in its Train split (1 s before to 4 s after): columns ``t``
    (s from the step), ``cmd_wl``, ``cmd_wr``, ``enc_wl``, ``enc_wr``, ``resp_wl``, ``resp_wr`` (rad/s),
    the figure's title in the metadata; with no response (or no step), no rows and the ``reason``."""
    path = wheel_response_path(layout, terrain)
    try:
        cols, meta = _wheel_response_steps(cal, layout, terrain)
    except Exception as exc:  # the figure's data never fails the benchmark: compare shows the reason
        cols, meta = {}, {"reason": one_line(str(exc)) if isinstance(exc, SkidbenchError)
                          else f"{type(exc).__name__}: {one_line(str(exc))}"}  # fmt: skip
    names = ("t", "cmd_wl", "cmd_wr", "enc_wl", "enc_wr", "resp_wl", "resp_wr")
    table = pa.table({c: np.asarray(cols.get(c, []), float) for c in names})
    write_parquet_atomic(table, path, {"terrain": terrain, **meta})
    return path


def _wheel_response_steps(
    cal: Calibrations, layout: Layout, terrain: str
) -> tuple[dict[str, np.ndarray], dict]:
    doc = calibration_doc(cal, terrain) or {}
    resp = wheel_response_of(doc)
    if resp is None:
        why = (doc.get("wheel_response") or {}).get("reason", "no calibration")
        raise ReportDataError(f"terrain {terrain}: no wheel response identified ({why})")
    files = layout.split_files(Manifest.read(layout.manifest), terrain, "train")
    table = concat_sequences([read_split(p) for p in files])
    t = table["t"].to_numpy(float)
    cmd = table[["cmd_wl", "cmd_wr"]].to_numpy(float)
    enc = table[["enc_wl", "enc_wr"]].to_numpy(float, na_value=np.nan)
    seq = table["sequence"].astype(str).to_numpy()
    dt = float(np.median(np.diff(t)))
    before, after = int(round(1.0 / dt)), int(round(4.0 / dt))
    jump = np.abs(np.diff(cmd.mean(axis=1)))
    for k in np.argsort(jump)[::-1][:200] + 1:  # the largest step with encoders all around it
        a, b = k - before, k + after
        if a >= 0 and b <= len(t) and (seq[a:b] == seq[k]).all() and np.isfinite(enc[a:b]).all():
            break
    else:
        raise ReportDataError(f"terrain {terrain}: no command step with encoder readings around it in Train")
    pred = wheel_response(table, resp)[:, :2]
    wr = doc["wheel_response"]
    se = wr.get("param_se") or {}
    title = (
        f"{terrain}: wheel response `{wr['structure']}` (dead time {resp.delay_s:.2f}"
        + (f" +- {se['delay_s']:.2f}" if "delay_s" in se else "")
        + f" s, lag {resp.tau_s:.2f}"
        + (f" +- {se['tau_s']:.2f}" if "tau_s" in se else "")
        + f" s) vs encoders, largest Train command step; RMSE {wr['rmse_command']:.2f} -> "
        f"{wr['rmse_response']:.2f} rad/s"
    )
    cols = {"t": t[a:b] - t[k], "cmd_wl": cmd[a:b, 0], "cmd_wr": cmd[a:b, 1], "enc_wl": enc[a:b, 0],
            "enc_wr": enc[a:b, 1], "resp_wl": pred[a:b, 0], "resp_wr": pred[a:b, 1]}  # fmt: skip
    return cols, {"title": title}


# -- compare's side -----------------------------------------------------------------------------------
def _missing(path: Path, what: str) -> ReportDataError:
    return ReportDataError(
        f"{path}: no {what} written by `skidbench evaluate` (this model, terrain and protocol not evaluated, "
        "or evaluated before evaluate wrote report data: re-run `skidbench evaluate force=true`)"
    )


def _read_parquet(path: Path, what: str) -> tuple[pd.DataFrame, dict[str, Any]]:
    if not path.is_file():
        raise _missing(path, what)
    try:
        return pd.read_parquet(path), read_parquet_metadata(path)
    except (OSError, ValueError, SkidbenchError) as exc:
        raise ReportDataError(f"{path}: unreadable {what} ({one_line(str(exc))[:200]})") from None


def read_residuals(stem: Path) -> tuple[pd.DataFrame, str]:
    """Fig. 5's series (:func:`write_residuals`) and the split they come from."""
    df, meta = _read_parquet(_path(stem, "residuals.parquet"), "Fig. 5 residuals")
    return df, str(meta.get("split", "?"))


def read_surfaces(stem: Path) -> dict[str, Any]:
    """Fig. 6's grid and surfaces (:func:`write_surfaces`) as a dict of arrays."""
    path = _path(stem, "surfaces.npz")
    if not path.is_file():
        raise _missing(path, "Fig. 6 surfaces")
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise ReportDataError(f"{path}: unreadable Fig. 6 surfaces ({one_line(str(exc))[:200]})") from None


def read_trajectories(stem: Path) -> tuple[pd.DataFrame, float]:
    """Fig. 7's poses (:func:`write_trajectories`) and their horizon (s)."""
    df, meta = _read_parquet(_path(stem, "trajectories.parquet"), "Fig. 7 trajectories")
    return df, float(meta.get("horizon_s", np.nan))


def read_wheel_response_steps(layout: Layout, terrain: str) -> tuple[pd.DataFrame, str]:
    """The wheel-response step (:func:`write_wheel_response_steps`) and its title; ReportDataError with the
    reason when evaluate found none."""
    df, meta = _read_parquet(wheel_response_path(layout, terrain), "wheel-response step")
    if not len(df):
        raise ReportDataError(str(meta.get("reason") or f"terrain {terrain}: no wheel response step"))
    return df, str(meta.get("title", ""))
