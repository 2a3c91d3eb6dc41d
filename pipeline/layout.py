"""Where every stage reads and writes: one output root (``out_root``, default ``outputs/``, env
``SKIDBENCH_OUT``), one folder per dataset under it, one subfolder per stage.

    <out_root>/mlflow.db, mlartifacts/           MLflow tracking store (shared by all datasets)
    <out_root>/<dataset>/raw/                    simulate output: manifest.json, bags/
    <out_root>/<dataset>/extracted/<seq>/        extract output: <topic_key>.parquet, manifest
    <out_root>/<dataset>/groundtruth/            <seq>.tum, <seq>.json, loop_closure.json
    <out_root>/<dataset>/splits/<terrain>/<split>/<seq>.parquet, card.md
    <out_root>/<dataset>/calibration/<terrain>.json   calibrate output: effective wheel radius, track width
    <out_root>/<dataset>/fits/<model>/<terrain>.json
    <out_root>/<dataset>/eval/, reports/, discovery/
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

DEFAULT_OUT_ROOT = "outputs"


def default_out_root() -> Path:
    return Path(os.environ.get("SKIDBENCH_OUT", DEFAULT_OUT_ROOT)).absolute()


@dataclass(frozen=True)
class Layout:
    out_root: Path
    dataset: str

    def __post_init__(self):
        object.__setattr__(self, "out_root", Path(self.out_root).absolute())

    @property
    def root(self) -> Path:
        return self.out_root / self.dataset

    @property
    def raw(self) -> Path:
        return self.root / "raw"

    @property
    def manifest(self) -> Path:
        return self.raw / "manifest.json"

    @property
    def extracted(self) -> Path:
        return self.root / "extracted"

    @property
    def groundtruth(self) -> Path:
        return self.root / "groundtruth"

    @property
    def splits(self) -> Path:
        return self.root / "splits"

    @property
    def fits(self) -> Path:
        return self.root / "fits"

    @property
    def calibration(self) -> Path:
        return self.root / "calibration"

    @property
    def eval(self) -> Path:
        return self.root / "eval"

    @property
    def reports(self) -> Path:
        return self.root / "reports"

    @property
    def discovery(self) -> Path:
        return self.root / "discovery"

    @property
    def mlflow_uri(self) -> str:
        return "sqlite:///" + str(self.out_root / "mlflow.db")

    @property
    def mlflow_artifacts(self) -> Path:
        return self.out_root / "mlartifacts"

    def split_file(self, terrain: str, split: str, sequence: str) -> Path:
        return self.splits / terrain / split / f"{sequence}.parquet"

    def fit_file(self, model: str, terrain: str) -> Path:
        return self.fits / model / f"{terrain}.json"

    def calibration_file(self, terrain: str) -> Path:
        return self.calibration / f"{terrain}.json"


def layout_from_cfg(cfg) -> Layout:
    return Layout(Path(cfg.out_root), str(cfg.dataset))
