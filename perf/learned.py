"""Learned models beside the friction model: fit and predict times on the DRIVE Husky Train split
(``make bench BENCH=learned``).

Data: ``../shared/data/real/drive/husky_windows.parquet`` through extract, groundtruth and split into a
temporary output root (the splits ``make reproduce SOURCE=drive_df`` builds); skipped with a note when the
file is absent. Each model is built with its configured options and fitted on the concatenated Train
sequences as ``fit_model`` fits it, then predicts the same table (``predict`` plus ``predict_cov`` for
models that have it). CPU seconds of this process with one BLAS thread, and wall seconds.
``quick``: the first quarter of the Train rows.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from . import REPO, register

MODELS = ("friction", "drive_blr", "gp_residual")
DRIVE = REPO.parent / "shared" / "data" / "real" / "drive"
ARGS = ["source=drive_df", f"source.root={DRIVE}", "robot=husky", "source.file=husky_windows.parquet"]


def husky_train(tmp: Path):
    """(cfg, Train table) of the DRIVE Husky through the pipeline's stages into ``tmp``."""
    from hydra import compose, initialize_config_module

    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.manifest import Manifest
    from skidbench.pipeline.core.schema import concat_sequences, read_split

    env = {**os.environ, "SKIDBENCH_OUT": str(tmp)}
    for stage in ("extract", "groundtruth", "split"):
        subprocess.run(
            [sys.executable, "-m", "skidbench.pipeline.cli.main", stage, *ARGS],
            env=env, check=True, capture_output=True, text=True,
        )  # fmt: skip
    with initialize_config_module("skidbench.conf", version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"out_root={tmp}", *ARGS])
    layout = layout_from_cfg(cfg)
    files = layout.split_files(Manifest.read(layout.manifest), None, "train")
    return cfg, concat_sequences([read_split(p) for p in files])


def compare(quick: bool) -> dict[str, Any]:
    from threadpoolctl import threadpool_limits

    from skidbench.models.fitting.fit import ModelConfigs, build_model
    from skidbench.pipeline.core.robot import robot_from_hydra

    if not (DRIVE / "husky_windows.parquet").is_file():
        return {"note": f"{DRIVE}/husky_windows.parquet absent; nothing measured"}
    with tempfile.TemporaryDirectory(prefix="skidbench-learned-") as tmp:
        cfg, train = husky_train(Path(tmp))
    if quick:
        train = train.iloc[: len(train) // 4].reset_index(drop=True)
    robot = robot_from_hydra(cfg.robot)  # the spec sheet: the same robot for all three (no calibration)
    out: dict[str, Any] = {"rows": len(train), "valid_rows": int(train["valid"].sum())}
    with threadpool_limits(1):
        for name in MODELS:
            model = build_model(ModelConfigs.from_cfg(cfg), name, robot)
            c, w = time.process_time(), time.perf_counter()
            model.fit(train)
            out[f"{name}_fit_cpu_s"] = time.process_time() - c
            out[f"{name}_fit_wall_s"] = time.perf_counter() - w
            c, w = time.process_time(), time.perf_counter()
            model.predict(train)
            if callable(getattr(model, "predict_cov", None)):
                model.predict_cov(train)
            out[f"{name}_predict_cpu_s"] = time.process_time() - c
            out[f"{name}_predict_wall_s"] = time.perf_counter() - w
            out[f"{name}_fit_plus_predict_cpu_s"] = out[f"{name}_fit_cpu_s"] + out[f"{name}_predict_cpu_s"]
    return out


@register(
    "learned",
    "learned models (drive_blr, gp_residual) beside friction: fit and predict (+ predictive covariance) "
    "on the DRIVE Husky Train split; CPU s with one BLAS thread, wall s",
    targets={
        "drive_blr_fit_plus_predict_cpu_s": ("<=", 30.0),
        "gp_residual_fit_plus_predict_cpu_s": ("<=", 30.0),
    },
)
def learned(quick: bool) -> dict[str, Any]:
    return compare(quick)
