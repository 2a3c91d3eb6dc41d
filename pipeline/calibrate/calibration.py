"""Robot calibration from its own data: the effective wheel radius and the effective track width (ICR
spread) a terrain's Train split implies, with confidence intervals (the ``calibrate`` stage; the one home
of the concept).

Identification, per terrain, on the Train split's valid, *settled* rows (the wheel commands unchanged for
``settle_s``, so the velocity controller and the smoothed ground-truth velocities have caught up):

* **radius** (straight rows: ``|wr - wl| <= straight_ratio * |wl + wr| / 2``, mean wheel rate above
  ``min_wheel_rate``): the regression through the origin of the ground-truth ``vx`` on ``(wl + wr) / 2``;
  its slope is ``r_eff``. With fewer than ``min_rows`` settled straight rows, the same regression on the
  *low-turn* rows, settled or not (``|wr - wl| <= LOW_TURN_RATIO * |wl + wr| / 2``: turning radius at
  least ``B / LOW_TURN_RATIO``), with the commanded mean wheel acceleration as a second regressor (it takes
  what a lag or an acceleration slip moves between the command and the speed while the wheels change
  speed); the slope on ``(wl + wr) / 2`` is ``r_eff`` (``method`` says which rows gave it);
* **track width** (turning rows: ``|wr - wl| >= min_turn_rate``): the regression through the origin of
  the ground-truth ``wz`` on ``r_eff (wr - wl)``; its slope is ``1 / B_eff``. ``B_eff`` is the effective
  track of the skid-steer literature (Mandow et al. 2007: the ICR spread), larger than the physical track
  because the wheels skid in a turn.

``wl, wr`` are the encoders' wheel rates (``enc_wl``, ``enc_wr``). Data without encoders (``amrl_txt``)
uses the commanded rates on settled straight rows for the radius, which is identifiable there because a
velocity controller holds a straight-line command with light motor load; its track width is *not*
identified (in a turn the motors carry the skid torque, and without encoders a wheel that falls short of
its command cannot be told from a wider effective track; the ICR coefficient of ``edd``/``roc`` carries
it) and the document says so. A quantity with fewer than ``min_rows`` rows is not identified either.

Confidence intervals: a block bootstrap over contiguous ``block_s`` pieces of the Train sequences (rows
within a few seconds are correlated, so a per-row standard error would be far too small); the percentile
interval at ``ci`` and the bootstrap standard error.

How the models take the constants (:func:`robot_for_model`): a model class lists the constants it takes
from the calibration in ``calibrated_constants`` (``models/base.py``: the radius by default), and keeps
the spec sheet's value of the others, which its own parameters absorb (each model says how in its
``calibration_usage``; the calibration knows no model). ``calibrate.use=false``: every model gets the
spec sheet's robot.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from skidbench.pipeline.calibrate.settings import CalibrationSettings
from skidbench.pipeline.calibrate.wheel_response import ResponseFit, WheelResponse, identify_response
from skidbench.pipeline.core.cache import StaleInputError, Stamp, stamp_file
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.io import write_json_atomic
from skidbench.pipeline.core.layout import Layout, layout_from_cfg
from skidbench.pipeline.core.robot import Robot, robot_from_hydra
from skidbench.pipeline.core.schema import concat_sequences, read_split

log = logging.getLogger("skidbench.calibrate")

CALIBRATION_SCHEMA = 2  # 2: the wheel response (pipeline/calibrate/wheel_response.py) next to the constants
CONSTANTS = ("wheel_radius", "track_width")


class CalibrationError(SkidbenchError):
    pass


#: the radius's fallback rows: |wr - wl| <= this * |mean wheel rate| (turn radius >= 2 tracks)
LOW_TURN_RATIO = 0.5
SEED = 0  # of the block bootstrap's draws


def identification(s: CalibrationSettings) -> dict[str, Any]:
    """What identifies a calibration (its document's ``settings``, part of its stamp): the settings but
    ``use`` (which only says whether fits take the result), and the fixed constants."""
    d = dataclasses.asdict(s)
    return {"min_wheel_rate": d["min_wheel_rate"], "straight_ratio": d["straight_ratio"],
            "low_turn_ratio": LOW_TURN_RATIO, "min_turn_rate": d["min_turn_rate"], "settle_s": d["settle_s"],
            "command_change": d["command_change"], "min_rows": d["min_rows"], "block_s": d["block_s"],
            "bootstrap": d["bootstrap"], "ci": d["ci"], "seed": SEED}  # fmt: skip


# -- identification -------------------------------------------------------------------------------------
def _settled(t: np.ndarray, seq: np.ndarray, changing: np.ndarray, settle_s: float) -> np.ndarray:
    """True where the last command change of the row's sequence is at least ``settle_s`` ago (rows
    before the first change of a sequence count from its start)."""
    out = np.zeros(len(t), bool)
    starts = np.flatnonzero(np.r_[True, seq[1:] != seq[:-1]])
    ends = np.r_[starts[1:], len(t)]
    for a, b in zip(starts, ends, strict=True):
        tt = t[a:b]
        idx = np.where(changing[a:b], np.arange(b - a), -1)
        last = np.maximum.accumulate(idx)
        since = np.where(last >= 0, tt - tt[np.maximum(last, 0)], tt - tt[0])
        out[a:b] = since >= settle_s
    return out


def _blocks(t: np.ndarray, seq: np.ndarray, block_s: float) -> np.ndarray:
    """Contiguous block id of every row (``block_s`` pieces of each sequence)."""
    out = np.zeros(len(t), np.int64)
    starts = np.flatnonzero(np.r_[True, seq[1:] != seq[:-1]])
    ends = np.r_[starts[1:], len(t)]
    nxt = 0
    for a, b in zip(starts, ends, strict=True):
        k = np.floor((t[a:b] - t[a]) / max(block_s, 1e-9)).astype(np.int64)
        out[a:b] = nxt + k
        nxt += int(k.max()) + 1 if b > a else 0
    return out


def _slope_with_ci(
    x: np.ndarray, y: np.ndarray, blocks: np.ndarray, s: CalibrationSettings
) -> dict[str, Any]:
    """Slope of y = k x through the origin, with a block-bootstrap percentile interval and s.e."""
    k = float(x @ y / (x @ x))
    ub, inv = np.unique(blocks, return_inverse=True)
    sxy = np.bincount(inv, x * y, len(ub))
    sxx = np.bincount(inv, x * x, len(ub))
    rng = np.random.default_rng(SEED)
    if len(ub) >= 2:
        draws = rng.integers(0, len(ub), size=(s.bootstrap, len(ub)))
        ks = sxy[draws].sum(axis=1) / np.maximum(sxx[draws].sum(axis=1), 1e-300)
        a = (1.0 - s.ci) / 2.0
        lo, hi = np.quantile(ks, [a, 1.0 - a])
        se = float(np.std(ks, ddof=1))
    else:
        lo = hi = se = float("nan")
    resid = y - k * x
    return {
        "slope": k,
        "ci": [float(lo), float(hi)],
        "se": se,
        "n_rows": len(x),
        "n_blocks": len(ub),
        "residual_rms": float(np.sqrt(np.mean(resid**2))),
    }


@dataclasses.dataclass(frozen=True)
class _Rows:
    """What the identification reads of a Train table: the wheel rates it uses (``source``: the encoders
    where nearly every valid row has them, else the commands), their mean and difference, the targets
    (vx, wz), bootstrap blocks, and the settled straight and turning rows."""

    source: str
    valid: np.ndarray
    mean_rate: np.ndarray
    diff: np.ndarray
    target: np.ndarray
    blocks: np.ndarray
    straight: np.ndarray
    turning: np.ndarray
    low_turn: np.ndarray  # low-turn rows, settled or not (the radius's fallback)
    mean_accel: np.ndarray  # commanded mean wheel acceleration (rad/s^2)


def _rows(table: pd.DataFrame, s: CalibrationSettings) -> _Rows:
    need = ["t", "cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr", "enc_wl", "enc_wr", "vx", "wz", "valid"]
    missing = [c for c in need if c not in table.columns]
    if missing:
        raise CalibrationError(f"calibration: the Train table lacks column(s) {missing}")
    seq = pd.factorize(table["sequence"])[0] if "sequence" in table else np.zeros(len(table), np.int64)
    t = table["t"].to_numpy(float)
    enc = table[["enc_wl", "enc_wr"]].to_numpy(float, na_value=np.nan)
    cmd = table[["cmd_wl", "cmd_wr"]].to_numpy(float)
    # encoders where (nearly) every valid row has them; else the commanded rates
    valid = table["valid"].to_numpy(bool)
    has_enc = valid.any() and np.mean(np.all(np.isfinite(enc[valid]), axis=1)) >= 0.9
    wheels = enc if has_enc else cmd
    target = table[["vx", "wz"]].to_numpy(float)
    changing = np.any(np.abs(table[["cmd_dwl", "cmd_dwr"]].to_numpy(float)) > s.command_change, axis=1)
    ok = valid & np.all(np.isfinite(wheels), axis=1) & np.all(np.isfinite(target), axis=1)
    settled = ok & _settled(t, seq, changing, s.settle_s)
    wl, wr = wheels[:, 0], wheels[:, 1]
    mean_rate = (wl + wr) / 2.0
    diff = wr - wl
    moving = np.abs(mean_rate) >= s.min_wheel_rate
    straight = settled & moving & (np.abs(diff) <= s.straight_ratio * np.abs(mean_rate))
    turning = settled & (np.abs(diff) >= s.min_turn_rate)
    low_turn = ok & moving & (np.abs(diff) <= LOW_TURN_RATIO * np.abs(mean_rate))
    mean_accel = table[["cmd_dwl", "cmd_dwr"]].to_numpy(float).mean(axis=1)
    source = "encoders" if has_enc else "commands"
    blocks = _blocks(t, seq, s.block_s)
    return _Rows(source, valid, mean_rate, diff, target, blocks, straight, turning, low_turn, mean_accel)


def _wheel_radius(rows: _Rows, spec: Robot, s: CalibrationSettings) -> dict[str, Any]:
    """The effective wheel radius: vx = r (wl + wr) / 2 on the settled straight rows; with too few, on
    the low-turn rows with the commanded acceleration as a nuisance regressor (:func:`_low_turn_radius`);
    the spec sheet's when neither has ``min_rows``."""
    straight = rows.straight
    if straight.sum() < s.min_rows:
        return _low_turn_radius(rows, spec, s)
    fit = _slope_with_ci(rows.mean_rate[straight], rows.target[straight, 0], rows.blocks[straight], s)
    r_eff = fit["slope"]
    out = {
        "value": r_eff,
        "identified": True,
        **{k: v for k, v in fit.items() if k != "slope"},
        "ratio_to_spec": r_eff / spec.wheel_radius,
        "method": f"straight settled rows: vx = r (wl + wr) / 2 through the origin; wheels: {rows.source}",
    }
    if rows.source == "commands":
        out["note"] = _COMMANDS_NOTE
    return out


_COMMANDS_NOTE = (
    "from commanded wheel rates (no encoders): includes the velocity controller's steady-state "
    "tracking error and the longitudinal slip of straight driving"
)


def _low_turn_radius(rows: _Rows, spec: Robot, s: CalibrationSettings) -> dict[str, Any]:
    """The radius from the low-turn rows, settled or not: vx = r (wl + wr) / 2 + b d/dt (wl + wr) / 2 (the
    commanded mean wheel acceleration takes what a lag or an acceleration slip moves while the wheels
    change speed), least squares through the origin, r with a block-bootstrap interval."""
    low, n_straight = rows.low_turn, int(rows.straight.sum())
    if low.sum() < s.min_rows:
        return {
            "value": spec.wheel_radius,
            "identified": False,
            "n_rows": n_straight,
            "reason": f"{n_straight} settled straight rows and {int(low.sum())} low-turn rows "
            f"(< min_rows {s.min_rows}); spec kept",
        }
    X = np.column_stack([rows.mean_rate[low], rows.mean_accel[low]])
    fit = _regression_with_ci(X, rows.target[low, 0], rows.blocks[low], s)
    r_eff = fit["coef"][0]
    out = {
        "value": r_eff,
        "identified": True,
        **{k: v for k, v in fit.items() if k != "coef"},
        "accel_coef_s": fit["coef"][1] / max(r_eff, 1e-12),
        "ratio_to_spec": r_eff / spec.wheel_radius,
        "method": f"{n_straight} settled straight rows (< min_rows {s.min_rows}); low-turn rows "
        f"(|wr - wl| <= {LOW_TURN_RATIO:g} |wl + wr| / 2): vx = r (wl + wr) / 2 + b d/dt (wl + wr) / 2 "
        f"through the origin; wheels: {rows.source}",
    }
    if rows.source == "commands":
        out["note"] = _COMMANDS_NOTE
    return out


def _regression_with_ci(
    X: np.ndarray, y: np.ndarray, blocks: np.ndarray, s: CalibrationSettings
) -> dict[str, Any]:
    """Least squares y = X b through the origin, with a block-bootstrap percentile interval and s.e. of
    the first coefficient (the blocks' normal equations summed per draw)."""
    coef = np.linalg.lstsq(X, y, rcond=None)[0]
    ub, inv = np.unique(blocks, return_inverse=True)
    p = X.shape[1]
    xtx = np.zeros((len(ub), p, p))
    xty = np.zeros((len(ub), p))
    np.add.at(xtx, inv, X[:, :, None] * X[:, None, :])
    np.add.at(xty, inv, X * y[:, None])
    if len(ub) >= 2:
        draws = np.random.default_rng(SEED).integers(0, len(ub), size=(s.bootstrap, len(ub)))
        A = xtx[draws].sum(axis=1) + 1e-12 * np.eye(p)
        bs = np.linalg.solve(A, xty[draws].sum(axis=1)[:, :, None])[:, 0, 0]
        a = (1.0 - s.ci) / 2.0
        lo, hi = np.quantile(bs, [a, 1.0 - a])
        se = float(np.std(bs, ddof=1))
    else:
        lo = hi = se = float("nan")
    resid = y - X @ coef
    return {
        "coef": [float(c) for c in coef],
        "ci": [float(lo), float(hi)],
        "se": se,
        "n_rows": len(y),
        "n_blocks": len(ub),
        "residual_rms": float(np.sqrt(np.mean(resid**2))),
    }


def _track_width(rows: _Rows, r_eff: float, spec: Robot, s: CalibrationSettings) -> dict[str, Any]:
    """The effective track width: wz = r_eff (wr - wl) / B on the settled turning rows, from encoders only
    (the spec sheet's otherwise, with too few rows, or with a slope that is not positive)."""
    turning = rows.turning
    if rows.source != "encoders":
        return {
            "value": spec.track_width,
            "identified": False,
            "reason": (
                "no wheel encoders: in a turn the motors carry the skid torque, and a wheel that falls short "
                "of its command cannot be told from a wider effective track; spec sheet value kept (the ICR "
                "coefficient of edd/roc absorbs the difference)"
            ),
        }
    if turning.sum() < s.min_rows:
        return {
            "value": spec.track_width,
            "identified": False,
            "n_rows": int(turning.sum()),
            "reason": f"{int(turning.sum())} settled turning rows (< min_rows {s.min_rows}); spec value kept",
        }
    fit = _slope_with_ci(r_eff * rows.diff[turning], rows.target[turning, 1], rows.blocks[turning], s)
    k = fit["slope"]
    if not k > 0:
        return {
            "value": spec.track_width,
            "identified": False,
            "reason": f"yaw rate against wheel-rate difference has slope {k:.3g} <= 0; spec value kept",
        }
    lo, hi = fit["ci"]
    return {
        "value": 1.0 / k,
        "identified": True,
        "ci": [1.0 / hi if hi > 0 else float("nan"), 1.0 / lo if lo > 0 else float("inf")],
        "se": fit["se"] / k**2,
        "n_rows": fit["n_rows"],
        "n_blocks": fit["n_blocks"],
        "residual_rms": fit["residual_rms"],
        "ratio_to_spec": (1.0 / k) / spec.track_width,
        "method": "turning settled rows: wz = r_eff (wr - wl) / B through the origin (encoders)",
    }


def calibrate_table(table: pd.DataFrame, spec: Robot, s: CalibrationSettings) -> dict[str, Any]:
    """The calibration document of one terrain from its concatenated Train table (``sequence`` column as
    :func:`skidbench.pipeline.core.schema.concat_sequences` adds). See the module docstring."""
    rows = _rows(table, s)
    doc: dict[str, Any] = {
        "schema": CALIBRATION_SCHEMA,
        "source": rows.source,
        "spec": {"wheel_radius": spec.wheel_radius, "track_width": spec.track_width},
        "settings": identification(s),
        "n_rows": int(rows.valid.sum()),
    }
    doc["wheel_radius"] = _wheel_radius(rows, spec, s)
    doc["track_width"] = _track_width(rows, doc["wheel_radius"]["value"], spec, s)
    doc["not_identified"] = [c for c in CONSTANTS if not doc[c]["identified"]]
    doc["wheel_response"] = wheel_response_doc(table if rows.source == "encoders" else None)
    return doc


def wheel_response_doc(table: pd.DataFrame | None) -> dict[str, Any]:
    """The ``wheel_response`` entry of a calibration: the response the Train encoders identify
    (:func:`~skidbench.pipeline.calibrate.wheel_response.identify_response`: structure chosen on held-out
    Train
    blocks, parameters, their block-jackknife standard errors, per-structure RMSEs), or why not (no
    encoders, too few readings)."""
    if table is None:
        return {"identified": False, "reason": "no wheel encoders in the Train split: the response cannot be "
                "identified (inputs=response is not available for this terrain)"}  # fmt: skip
    fit: ResponseFit | None = identify_response(table)
    if fit is None:
        return {"identified": False, "reason": "fewer encoder readings than the identification needs"}
    return {
        "identified": True,
        **fit.to_dict(),
        "method": "pipeline/calibrate/wheel_response.py identify_response on the Train encoders",
    }


def wheel_response_of(doc: Mapping[str, Any] | None) -> WheelResponse | None:
    """The identified wheel response of a calibration document (None: not identified or absent)."""
    entry = (doc or {}).get("wheel_response") or {}
    return WheelResponse.from_dict(entry) if entry.get("identified") else None


# -- the stage's files ----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Calibrations:
    """What reading a terrain's calibration needs of the config: the dataset's folders, the robot spec
    the calibration must have been made for, and whether fits use the calibrated constants
    (``calibrate.use``; the wheel response is read either way). The apps make it (:meth:`from_cfg`)."""

    layout: Layout
    spec: Robot
    use: bool = True

    @classmethod
    def from_cfg(cls, cfg: Any) -> Calibrations:
        return cls(layout_from_cfg(cfg), robot_from_hydra(cfg.robot), cfg.calibrate.use)


def train_files(layout: Layout, terrain: str | None = None) -> list[Path]:
    """The Train split files of the current manifest's sequences (one terrain, or all); [] without a
    manifest; CalibrationError when one is not written (:meth:`Layout.require_split_files`)."""
    from skidbench.pipeline.core.manifest import Manifest

    if not layout.manifest.is_file():
        return []
    return layout.require_split_files(Manifest.read(layout.manifest), terrain, "train", CalibrationError)


def calibration_stamp(layout: Layout, terrain: str) -> Stamp:
    """The stamp of ``terrain``'s calibration (``<ds>/.stamps/calibrate/<terrain>.json``): made from the
    Train split files, the robot spec, the settings and ``CALIBRATION_SCHEMA``."""
    return Stamp(stamp_file(layout.root, "calibrate", f"{terrain}.json"), "calibrate")


def calibrate_terrain(
    layout: Layout,
    terrain: str,
    spec: Robot,
    s: CalibrationSettings,
    dataset: str = "",
    model_usage: Mapping[str, str] | None = None,
) -> tuple[dict[str, Any], bool]:
    """The calibration of ``terrain`` (``<ds>/calibration/<terrain>.json``), recomputed only when its
    stamp (Train split files, robot spec, settings) is stale. Returns (document, recomputed).
    ``model_usage``: how the installed models take the constants (model name -> text, their
    ``calibration_usage``), recorded in the document as it is given."""
    files = train_files(layout, terrain)
    if not files:
        raise CalibrationError(
            f"{layout.splits / terrain / 'train'}: no Train split files to calibrate; run `skidbench split`"
        )
    path = layout.calibration_file(terrain)
    stamp = calibration_stamp(layout, terrain)
    key = stamp.key(
        files, {"robot": spec.to_dict(), "settings": identification(s), "schema": CALIBRATION_SCHEMA}
    )
    if stamp.is_fresh(key):
        return json.loads(path.read_text()), False
    tables = [read_split(p) for p in files]
    table = concat_sequences(tables)
    doc = calibrate_table(table, spec, s)
    doc.update(
        {
            "terrain": terrain,
            "dataset": dataset,
            "robot": spec.name,
            "split": "train",
            "sequences": [p.stem for p in files],
            "model_usage": dict(model_usage or {}),
        }
    )
    write_json_atomic(path, doc)
    stamp.record(key, [path])
    return doc, True


def load_calibration(cal: Calibrations, terrain: str) -> dict[str, Any] | None:
    """The terrain's calibration for a fit: the one ``calibrate`` saved from the current Train files and
    robot spec (whatever its settings); None when ``calibrate.use`` is false. MissingCalibrationError
    when there is none or it is stale (only ``calibrate`` computes it)."""
    if not cal.use:
        return None
    return calibration_doc(cal, terrain)


class MissingCalibrationError(StaleInputError):
    """A stage needs the calibration of a terrain and ``calibrate`` has not made it (or made it from other
    Train files or another robot spec)."""


def calibration_doc(cal: Calibrations, terrain: str) -> dict[str, Any] | None:
    """The terrain's calibration document whatever ``calibrate.use`` says, as ``calibrate`` saved it;
    None when the terrain has no Train files. MissingCalibrationError (one line) when there is none or it
    is not current: its stamp (:func:`calibration_stamp`) says it was made from other Train files or
    another robot spec (whatever its settings), or the document is missing or changed since. Only the
    ``calibrate`` stage computes it."""
    layout, spec = cal.layout, cal.spec
    path = layout.calibration_file(terrain)
    files = train_files(layout, terrain)
    if not files:
        return None
    if not path.is_file():
        why = "there is none"
    else:
        stale = calibration_stamp(layout, terrain).stale_reason(
            files, {"robot": spec.to_dict(), "schema": CALIBRATION_SCHEMA}
        )
        if stale is None:
            try:
                return json.loads(path.read_text())
            except (OSError, ValueError) as exc:
                stale = f"it cannot be read ({exc})"
        why = f"stale: {stale}"
    raise MissingCalibrationError(
        f"{path}: no current calibration of terrain {terrain} ({why}); "
        "run `skidbench calibrate` first (or set calibrate.use=false for the spec's constants)"
    )


def calibrated_robot(spec: Robot, doc: Mapping[str, Any] | None, constants: Sequence[str]) -> Robot:
    """``spec`` with the identified constants of ``doc`` among ``constants`` replaced."""
    if not doc:
        return spec
    changes = {
        c: float(doc[c]["value"]) for c in constants if c in CONSTANTS and doc.get(c, {}).get("identified")
    }
    return dataclasses.replace(spec, **changes) if changes else spec


def robot_for_model(
    cal: Calibrations, constants: Sequence[str], terrain: str
) -> tuple[Robot, dict[str, Any]]:
    """The robot a model that takes the calibrated ``constants`` (its class's ``calibrated_constants``,
    e.g. ``("wheel_radius",)``) is built with on ``terrain``, and a record of where each constant came
    from (for the fit JSON and MLflow)."""
    spec = cal.spec
    constants = tuple(constants)
    doc = load_calibration(cal, terrain)
    robot = calibrated_robot(spec, doc, constants)
    record: dict[str, Any] = {}
    for c in CONSTANTS:
        if doc is None:
            src = "spec (calibrate.use=false)" if not cal.use else "spec (no calibration)"
        elif c not in constants:
            src = "spec (absorbed by the model's own parameters)"
        elif not doc[c]["identified"]:
            src = "spec (not identified)"
        else:
            src = "calibrated"
        record[c] = {"value": float(getattr(robot, c)), "spec": float(getattr(spec, c)), "source": src}
    return robot, record


def response_for(cal: Calibrations, terrain: str) -> WheelResponse | None:
    """The wheel response ``calibrate`` identified for ``terrain`` (the ``response`` input protocol's; also
    with ``calibrate.use=false``, which concerns the robot constants only); None when not identified."""
    return wheel_response_of(calibration_doc(cal, terrain))
