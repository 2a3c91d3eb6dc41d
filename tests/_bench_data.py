"""Split-like data and a tiny model for the evaluate/compare/MLflow tests (no other stage needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.models.base import KinematicModel
from skidbench.pipeline.core.geometry import integrate_body_velocity
from skidbench.pipeline.core.robot import Robot
from skidbench.pipeline.core.schema import write_split

JACKAL = Robot("jackal", 16.0, 0.098, 0.37559, 0.262, 0.508, 0.430)
TRUE_CHI = 0.7  # the "terrain": yaw rate is 70 % of the ideal one


def sequence_table(seed: int, duration_s: float = 30.0, rate_hz: float = 30.0, chi: float = TRUE_CHI):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    knots = np.arange(0.0, duration_s + 2.0, 2.0)
    v = np.interp(t, knots, rng.uniform(0.2, 1.2, len(knots)))
    w = np.interp(t, knots, rng.uniform(-1.5, 1.5, len(knots)))
    wl, wr = JACKAL.wheel_rates_from_twist(v, w)
    true = np.column_stack([v, 0.02 * w, chi * w])
    pose = integrate_body_velocity(np.zeros(3), true[:-1], np.diff(t))
    df = pd.DataFrame(
        {
            "t": t,
            "stamp_ns": (t * 1e9).astype(np.int64) + 10**18,
            "cmd_v": v,
            "cmd_w": w,
            "cmd_wl": wl,
            "cmd_wr": wr,
            "cmd_dwl": np.gradient(wl, t),
            "cmd_dwr": np.gradient(wr, t),
            "enc_wl": wl,
            "enc_wr": wr,
            "x": pose[:, 0],
            "y": pose[:, 1],
            "yaw": pose[:, 2],
            "vx": true[:, 0],
            "vy": true[:, 1],
            "wz": true[:, 2],
            "valid": np.ones(len(t), bool),
        }
    )
    return df


def write_splits(
    ds_root: Path,
    terrains=("tile", "grass"),
    counts=None,
    duration_s: float = 30.0,
) -> None:
    """<ds_root>/splits/<terrain>/<split>/<seq>.parquet with a few synthetic sequences, the simulator's
    truth of each (``<ds_root>/extracted/<seq>/true_pose.parquet``: the floor's velocities) and the
    manifest that lists them (<ds_root>/raw/manifest.json: stages take their sequences from it)."""
    from skidbench.pipeline.core.manifest import Manifest, Sequence

    counts = counts or {"train": 2, "cv": 1, "ld": 1}
    seed = 0
    seqs = []
    for terrain in terrains:
        for split, n in counts.items():
            for k in range(n):
                name = f"{terrain}_{split}_{k:02d}"
                df = sequence_table(seed, duration_s)
                seed += 1
                meta = {
                    "sequence": name,
                    "terrain": terrain,
                    "split": split,
                    "robot": {"name": "jackal"},
                    "sources": {},
                    "rate_hz": 30.0,
                }
                write_split(df, ds_root / "splits" / terrain / split / f"{name}.parquet", meta)
                truth = ds_root / "extracted" / name  # the simulator's truth, as extract writes it
                truth.mkdir(parents=True, exist_ok=True)
                df[["stamp_ns", "vx", "vy", "wz"]].rename(columns={"stamp_ns": "bag_time_ns"}).to_parquet(
                    truth / "true_pose.parquet"
                )
                seqs.append(Sequence(name, terrain, split, f"bags/{name}.bag"))
    Manifest(seqs, base=ds_root / "raw").write(ds_root / "raw" / "manifest.json")


class ChiModel(KinematicModel):
    """Extended differential drive with one parameter (the yaw-rate factor chi); the tests' model."""

    name = "chi"
    version = "0.1"

    def fit(self, table):
        v, w = self.robot.twist_from_wheel_rates(table["cmd_wl"].to_numpy(), table["cmd_wr"].to_numpy())
        ok = table["valid"].to_numpy(bool)
        self.params = {"chi": float(np.dot(w[ok], table["wz"].to_numpy()[ok]) / np.dot(w[ok], w[ok]))}
        self.fit_loss_ = float(np.mean((self.params["chi"] * w[ok] - table["wz"].to_numpy()[ok]) ** 2))
        return self

    def predict(self, table):
        v, w = self.robot.twist_from_wheel_rates(table["cmd_wl"].to_numpy(), table["cmd_wr"].to_numpy())
        return np.column_stack([v, np.zeros_like(v), self.params.get("chi", 1.0) * w])


class IdealModel(ChiModel):
    name = "ideal_t"

    def fit(self, table):
        self.params = {"chi": 1.0}
        self.fit_loss_ = 0.0
        return self


class BrokenModel(ChiModel):
    name = "broken"

    def fit(self, table):
        raise RuntimeError("singular normal equations on purpose")


class NaNModel(ChiModel):
    name = "nan_model"

    def predict(self, table):
        out = super().predict(table)
        out[5, 2] = np.nan
        return out


class RaisingModel(ChiModel):
    """Fits, then raises in ``predict`` (a plugin that reads a column it is never given)."""

    name = "raiser"

    def predict(self, table):
        return table["vx"].to_numpy()  # KeyError: a model sees the input columns only


MODELS = {m.name: m for m in (ChiModel, IdealModel, BrokenModel, NaNModel, RaisingModel)}


class Fit:
    def __init__(self, model, fit_time_s, n_train):
        self.model, self.fit_time_s, self.n_train = model, fit_time_s, n_train
        self.fit_loss = model.fit_loss_
        self.path = None


def fit_fn(settings, model_name, terrain):
    """A stand-in for skidbench.models.fitting.fit.fit_model (``settings`` a FitSettings) on the synthetic
    splits."""
    import time

    from skidbench.pipeline.core.schema import concat_sequences, load_split_tables

    tables = load_split_tables(settings.layout.splits, terrain, "train")
    table = concat_sequences(tables)
    t0 = time.perf_counter()
    model = MODELS[model_name](JACKAL).fit(table)
    return Fit(model, time.perf_counter() - t0, len(table))


def compose(config_name: str, out_root: Path, overrides=()):
    from hydra import compose as hcompose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        return hcompose(config_name, overrides=[f"out_root={out_root}", *overrides])


def calibrate_splits(cfg) -> list[str]:
    """Run the ``calibrate`` stage's per-terrain step (pipeline/calibrate/calibration.py) for ``cfg``'s
    dataset and
    robot on every terrain with Train files: ``fit`` and ``evaluate`` read its output and only
    ``calibrate`` computes it. 20 bootstrap draws (the intervals are not what these tests check).
    Returns the terrains calibrated."""
    import dataclasses

    from omegaconf import OmegaConf

    from skidbench.pipeline.calibrate.calibration import calibrate_terrain
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.robot import robot_from_hydra

    layout = layout_from_cfg(cfg)
    spec = robot_from_hydra(cfg.robot)
    settings = dataclasses.replace(OmegaConf.to_object(cfg.calibrate), bootstrap=20)
    terrains = sorted(p.name for p in layout.splits.iterdir() if (p / "train").is_dir())
    for terrain in terrains:
        calibrate_terrain(layout, terrain, spec, settings, str(cfg.dataset))
    return terrains
