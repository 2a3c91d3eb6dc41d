"""Scaling: fit and evaluation time of every built-in model at 1x, 4x and 16x the data; the cost must grow
linearly (log-log slope, the exponent, about 1).

Data: synthetic split tables (``models/fitting/synthetic.py``: smooth random commands, ground truth from an
extended differential drive with side slip and noise), written as Train and CV split files of
``SEQ_ROWS``-row sequences (50 s at 30 Hz) under a temporary out root; 1x = 2 sequences (3,000 rows),
4x = 8, 16x = 32 (48,000 rows). Fit is ``model.fit`` on the concatenated Train table, built
as :func:`skidbench.models.fitting.fit.fit_model` builds it (configured initial params and options; reading,
config composition and fingerprinting are a constant ~0.3 s per fit and are not timed);
evaluation is :func:`benchmark.scoring.predict_split` + :func:`score_split` at the 6 s horizon on a CV
split of the same size, always of the model fitted at 1x: the same parameters at every size (a model
fitted on other data is another problem; the friction model's count of unbalanced steps, which cost
extra solves, depends on its parameters: evaluating each size's own fit gave 0.04 / 0.55 / 1.57 s).

Times are CPU seconds of this process (``time.process_time``: on a shared machine the wall clock
carries other jobs' load); each point is the best of ``REPEATS`` runs. The exponent is the least-squares
slope of log(time) on log(rows) over the three sizes; wall-clock exponents are reported too.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import register

SEQ_ROWS = 1500
BASE_SEQS = 2
FACTORS = (1, 4, 16)
REPEATS = 2
HORIZON_S = 6.0
BUILTIN_PACKAGE = "skidbench"


def builtin_models() -> list[str]:
    from skidbench.models.registry.plugins import discover

    return [n for n, i in discover().items() if i.ok and i.package == BUILTIN_PACKAGE]


def write_splits(
    root: Path, robot, dataset: str, n_seq: int, seq_rows: int, seed: int = 0, terrain: str = "tile"
) -> None:
    """Train and CV split files (``n_seq`` sequences each) of one terrain, and the manifest that lists
    them with any other terrain already written there (stages read their sequences from it)."""
    from skidbench.models.fitting.synthetic import command_table, label_with
    from skidbench.models.kinematic.linear import ExtendedDifferentialDrive
    from skidbench.pipeline.core.manifest import Manifest, Sequence
    from skidbench.pipeline.core.schema import write_split

    seqs = []
    truth = ExtendedDifferentialDrive(robot, {"chi": 1.5})
    rng = np.random.default_rng(seed)
    for split in ("train", "cv"):
        for i in range(n_seq):
            tab = command_table(robot, seq_rows, seed=seed + 1000 * (split == "cv") + i)
            vel = truth.predict(tab)
            vel[:, 1] = 0.03 * vel[:, 2] + rng.normal(0, 0.01, len(tab))
            vel[:, 0] += rng.normal(0, 0.02, len(tab))
            vel[:, 2] += rng.normal(0, 0.02, len(tab))
            tab = label_with(tab, vel)
            seq = f"{terrain}_{split}_{i:02d}"
            meta = {
                "sequence": seq,
                "terrain": terrain,
                "split": split,
                "robot": robot.name,
                "sources": {},
                "rate_hz": 30.0,
            }
            write_split(tab, root / dataset / "splits" / terrain / split / f"{seq}.parquet", meta)
            seqs.append(Sequence(seq, terrain, split, f"{seq}.bag"))
    manifest_path = root / dataset / "raw" / "manifest.json"
    if manifest_path.is_file():  # other terrains written before into the same dataset stay listed
        seqs = [s for s in Manifest.read(manifest_path).sequences if s.terrain != terrain] + seqs
    Manifest(seqs, robot=robot.name, base=root / dataset / "raw").write(manifest_path)


def _compose(out_root: Path, dataset: str):
    from hydra import compose

    return compose(config_name="evaluate", overrides=[f"out_root={out_root}", f"dataset={dataset}"])


def time_model(cfg, name: str, repeats: int, eval_params: tuple | None = None) -> dict[str, Any]:
    """Best-of CPU and wall seconds of fit (``model.fit`` on the Train table, as ``fit_model`` calls it)
    and evaluation (predict + score the CV split) of the model ``eval_params`` (``(to_json(), arrays)``;
    default the model just fitted); ``"fitted"``: the fitted model's ``(to_json(), arrays)``."""
    from skidbench.benchmark.evaluate.testsets import load_test_split, split_files
    from skidbench.benchmark.scoring.horizon import HorizonConfig
    from skidbench.benchmark.scoring.predictions import predict_split, score_split
    from skidbench.models.fitting.fit import ModelConfigs, build_model
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.robot import robot_from_hydra
    from skidbench.pipeline.core.schema import concat_sequences, read_split

    layout = layout_from_cfg(cfg)
    train = concat_sequences([read_split(p) for p in split_files(layout, "tile", "train")])
    seqs = load_test_split(layout, "tile", "cv")
    best: dict[str, Any] = {"fit_cpu": np.inf, "fit_wall": np.inf, "eval_cpu": np.inf, "eval_wall": np.inf}
    for _ in range(repeats):
        # configured initial params and options (not timed)
        model = build_model(ModelConfigs.from_cfg(cfg), name, robot_from_hydra(cfg.robot))
        c, w = time.process_time(), time.perf_counter()
        model.fit(train)
        best["fit_cpu"] = min(best["fit_cpu"], time.process_time() - c)
        best["fit_wall"] = min(best["fit_wall"], time.perf_counter() - w)
        # a learned model's fitted arrays travel with its JSON (as a saved fit's .npz does)
        best["fitted"] = (model.to_json(), dict(getattr(model, "arrays", None) or {}))
        if eval_params is not None:
            saved, arrays = eval_params
            model = type(model).from_json(model.robot, saved)
            if arrays:
                model.set_arrays(arrays)
        c, w = time.process_time(), time.perf_counter()
        vel, _ = predict_split(model, seqs)
        windows = score_split(seqs, vel, [HORIZON_S], HorizonConfig(HORIZON_S))
        best["eval_cpu"] = min(best["eval_cpu"], time.process_time() - c)
        best["eval_wall"] = min(best["eval_wall"], time.perf_counter() - w)
        if len(windows) == 0:
            raise RuntimeError(f"model {name}: no evaluation windows")
    return best


def exponent(rows: list[float], seconds: list[float]) -> float:
    """Least-squares slope of log(seconds) on log(rows)."""
    x, y = np.log(np.asarray(rows, float)), np.log(np.maximum(np.asarray(seconds, float), 1e-9))
    return float(np.polyfit(x, y, 1)[0])


def scaling(
    factors=FACTORS, seq_rows: int = SEQ_ROWS, base_seqs: int = BASE_SEQS, repeats: int = REPEATS, models=None
) -> dict[str, Any]:
    from hydra import initialize_config_module
    from threadpoolctl import threadpool_limits

    from skidbench.pipeline.core.robot import robot_from_hydra

    models = list(models or builtin_models())
    out: dict[str, Any] = {}
    table: dict[str, dict[str, list[float]]] = {m: {} for m in models}
    eval_params: dict[str, tuple] = {}
    rows: list[float] = []
    # one BLAS thread: CPU time then measures work, not idle spinning of a second thread
    with (
        tempfile.TemporaryDirectory(prefix="skidbench-scaling-") as tmp,
        initialize_config_module("skidbench.conf", version_base="1.3"),
        threadpool_limits(1),
    ):
        for f in factors:
            dataset = f"scaling-{f}x"
            cfg = _compose(Path(tmp), dataset)
            write_splits(Path(tmp), robot_from_hydra(cfg.robot), dataset, base_seqs * f, seq_rows)
            rows.append(float(base_seqs * f * seq_rows))
            for m in models:
                t = time_model(cfg, m, repeats, eval_params.get(m))
                eval_params.setdefault(m, t["fitted"])  # every size evaluates the model fitted at 1x
                for k in ("fit_cpu", "fit_wall", "eval_cpu", "eval_wall"):
                    table[m].setdefault(k, []).append(t[k])
    out["rows"] = " / ".join(str(int(r)) for r in rows)
    worst = 0.0
    for m in models:
        for kind in ("fit", "eval"):
            cpu, wall = table[m][f"{kind}_cpu"], table[m][f"{kind}_wall"]
            e = exponent(rows, cpu)
            worst = max(worst, e)
            out[f"{m}_{kind}_exponent"] = e
            out[f"{m}_{kind}_exponent_wall"] = exponent(rows, wall)
            out[f"{m}_{kind}_cpu_s"] = " / ".join(f"{v:.3g}" for v in cpu)
    out["max_exponent"] = worst
    return out


@register(
    "scaling",
    "fit and evaluation CPU time of every built-in model at 1x, 4x, 16x the data (3,000 rows = 1x): "
    "log-log exponent",
    targets={"max_exponent": ("<=", 1.2)},
)
def scaling_bench(quick: bool) -> dict[str, Any]:
    if quick:
        return scaling(seq_rows=500, repeats=1)
    return scaling()
