"""``skidbench calibrate``: the robot's effective wheel radius and track width per terrain, from the Train
split (between ``split`` and ``evaluate``; :mod:`skidbench.pipeline.calibrate.calibration` documents the
method).

Writes ``<ds>/calibration/<terrain>.json`` (skipped when its stamp is up to date), prints the calibrated
values next to the spec sheet's, and logs one MLflow run (``skidbench.role`` = calibration) when anything
was recomputed.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import shutil
from typing import Any

import hydra
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from skidbench.models.registry.plugins import calibration_usage
from skidbench.pipeline.calibrate.calibration import (
    CONSTANTS,
    CalibrationError,
    calibrate_terrain,
    train_files,
)
from skidbench.pipeline.calibrate.settings import CalibrateOptions
from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.core.cache import Fingerprints, stamp_file
from skidbench.pipeline.core.io import fingerprint_obj
from skidbench.pipeline.core.layout import layout_from_cfg, root_from_cfg
from skidbench.pipeline.core.robot import robot_from_hydra
from skidbench.pipeline.core.schema import read_split
from skidbench.pipeline.runner.tasks import map_items

log = logging.getLogger("skidbench.calibrate")


def _fmt(x: float, digits: int = 4) -> str:
    return "-" if x is None or not math.isfinite(float(x)) else f"{float(x):.{digits}f}"


def format_table(docs: dict[str, dict[str, Any]]) -> str:
    """Calibrated values next to the spec sheet's, one line per (terrain, constant)."""
    rows = [("terrain", "constant", "spec", "calibrated", "95% CI", "ratio", "rows", "from / why not")]
    for terrain, doc in docs.items():
        for c in CONSTANTS:
            d = doc[c]
            spec = doc["spec"][c]
            if d["identified"]:
                lo, hi = d.get("ci", [math.nan, math.nan])
                level = doc["settings"].get("ci", 0.95)
                ci = f"[{_fmt(lo)}, {_fmt(hi)}]" + ("" if level == 0.95 else f" ({level:g})")
                rows.append(
                    (terrain, c, _fmt(spec), _fmt(d["value"]), ci, _fmt(d["ratio_to_spec"], 3),
                     str(d["n_rows"]), doc["source"])
                )  # fmt: skip
            else:
                rows.append((terrain, c, _fmt(spec), "not identified", "-", "-", str(d.get("n_rows", "-")),
                             d["reason"]))  # fmt: skip
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join(
        "  ".join(v.ljust(w) for v, w in zip(r[:-1], widths, strict=True)) + "  " + r[-1] for r in rows
    )


def format_response(docs: dict[str, dict[str, Any]]) -> str:
    """The wheel response per terrain (the ``response`` input protocol's), one line each."""
    lines = [
        "wheel response (pipeline/calibrate/wheel_response.py; inputs=response drives every model with it):"
    ]
    for terrain, doc in docs.items():
        wr = doc.get("wheel_response") or {}
        if not wr.get("identified"):
            lines.append(f"  {terrain}: not identified ({wr.get('reason', 'no wheel_response entry')})")
            continue
        se = wr.get("param_se") or {}

        def pm(k, wr=wr, se=se):
            return f"{k}={wr[k]:.3f}" + (f"+-{se[k]:.3f}" if k in se else "")

        names = wr["candidates"][wr["structure"]]["params"]
        lines.append(
            f"  {terrain}: {wr['structure']}: {', '.join(pm(k) for k in names)}; "
            f"encoder RMSE {wr['rmse_command']:.3f} rad/s against the commands -> {wr['rmse_response']:.3f} "
            f"(held out {wr['heldout_rmse']:.3f})"
        )
    return "\n".join(lines)


def run(cfg: DictConfig) -> dict[str, dict[str, Any]]:
    layout = layout_from_cfg(cfg)
    spec = robot_from_hydra(cfg.robot)
    s = OmegaConf.to_object(cfg.calibrate)
    opts = root_from_cfg(cfg, CalibrateOptions)
    terrains = sorted({p.parents[1].name for p in train_files(layout)})
    if not terrains:
        raise CalibrationError(
            f"{layout.splits}: no Train split files to calibrate from; run `skidbench split`"
        )
    if opts.force:
        shutil.rmtree(stamp_file(layout.root, "calibrate"), ignore_errors=True)
    usage = calibration_usage()  # the models say how they take the constants; the calibration knows none
    docs, recomputed = {}, []
    results = _calibrate_all(layout, terrains, spec, s, str(cfg.dataset), usage)
    for terrain, (doc, fresh) in zip(terrains, results, strict=True):
        docs[terrain] = doc
        if fresh:
            recomputed.append(terrain)
    print(
        f"calibrate: robot {spec.name} (spec sheet conf/robot/{spec.name}.yaml), Train split of {cfg.dataset}"
    )
    print(format_table(docs))
    print(format_response(docs))
    if not s.use:
        print("calibrate.use=false: every model is fitted with the spec sheet's constants")
    else:
        print("models take: " + "; ".join(f"{m}: {u}" for m, u in usage.items()))
    print(f"written: {layout.calibration}/<terrain>.json" + ("" if recomputed else " (up to date, skipped)"))
    if recomputed and opts.track:
        log_run(cfg, layout, docs, spec.name)
    return docs


def _calibrate_all(layout, terrains: list[str], spec, s, dataset: str, usage) -> list[tuple[dict, bool]]:
    """:func:`calibrate_terrain` of every terrain, in order. The terrains are independent (each its own
    Train files, document and stamp): tasks (:mod:`.tasks`: forked worker processes, one per core, or Ray
    tasks on a cluster), the same documents as one after the other in about two thirds of the time on two
    cores."""
    calls = [(layout, t, spec, s, dataset, usage) for t in terrains]
    return map_items(calibrate_terrain, calls, terrains, what="calibrate", unit="terrain")


def log_run(cfg: DictConfig, layout, docs: dict[str, dict[str, Any]], robot: str) -> str:
    """One MLflow run for the calibration (benchmark/tracking/store.py): per terrain and constant the value,
    the
    interval and the ratio to the spec sheet as metrics, the JSON documents as artifacts."""
    from skidbench.benchmark.tracking import store as trk
    from skidbench.benchmark.tracking import tags as run_tags
    from skidbench.pipeline.runner import environment

    tracker = trk.tracker_from_cfg(cfg, layout)
    tags = {
        run_tags.TAG_ROLE: "calibration",
        run_tags.TAG_DATASET: str(cfg.dataset),
        **environment.run_tags(),  # skidbench's version and commit, libraries, lock, platform, code paths
        run_tags.TAG_GIT: environment.git_commit(),
        "skidbench.robot": robot,
    }
    tags[run_tags.TAG_NOTE] = run_tags.describe(
        f"Calibration of the {robot}'s effective wheel radius and track width per terrain (Train split)",
        {"dataset": f"`{cfg.dataset}` ({layout.root})", "terrains": ", ".join(docs),
         "metrics": "`<constant>_<terrain>` (m), interval `_ci_lo`/`_ci_hi`, `_ratio` to the spec sheet"},
        run_tags.reproduce_command("calibrate", ["force=true"]),
    )  # fmt: skip
    name = tracker.unique_run_name(f"calibrate {cfg.dataset} {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M:%S}")
    with tracker.run(name, tags) as run_id:
        tracker.log_datasets(run_id, _train_inputs(cfg, layout, list(docs)))
        params = {
            "robot": robot,
            **run_tags.flatten({"calibrate": OmegaConf.to_container(cfg.calibrate, resolve=True)}),
        }
        metrics: dict[str, float] = {}
        for terrain, doc in docs.items():
            params[f"{terrain}.source"] = doc["source"]
            for c in CONSTANTS:
                d = doc[c]
                params[f"{terrain}.{c}.identified"] = str(d["identified"])
                metrics[f"{c}_spec"] = float(doc["spec"][c])
                if d["identified"]:
                    metrics[f"{c}_{terrain}"] = float(d["value"])
                    metrics[f"{c}_{terrain}_ci_lo"] = float(d["ci"][0])
                    metrics[f"{c}_{terrain}_ci_hi"] = float(d["ci"][1])
                    metrics[f"{c}_{terrain}_ratio"] = float(d["ratio_to_spec"])
                else:
                    params[f"{terrain}.{c}.reason"] = d["reason"]
            wr = doc.get("wheel_response") or {}
            params[f"{terrain}.wheel_response.identified"] = str(bool(wr.get("identified")))
            if wr.get("identified"):
                params[f"{terrain}.wheel_response.structure"] = wr["structure"]
                for k, v in wr["candidates"][wr["structure"]]["params"].items():
                    metrics[f"wheel_response_{terrain}_{k}"] = float(v)
                for k, v in (wr.get("param_se") or {}).items():
                    metrics[f"wheel_response_{terrain}_{k}_se"] = float(v)
                for name, cand in wr["candidates"].items():
                    if cand.get("heldout_rmse") is not None:
                        key = name.replace("+", "_")  # MLflow names take no "+"
                        metrics[f"wheel_response_{terrain}_heldout_rmse.{key}"] = float(cand["heldout_rmse"])
                metrics[f"wheel_response_{terrain}_rmse_command"] = float(wr["rmse_command"])
                metrics[f"wheel_response_{terrain}_rmse_response"] = float(wr["rmse_response"])
            else:
                params[f"{terrain}.wheel_response.reason"] = wr.get("reason", "")
        tracker.log(run_id, params=params, metrics={k: v for k, v in metrics.items() if math.isfinite(v)})
        tracker.artifact(run_id, layout.calibration, "calibration")
    return run_id


def _train_inputs(cfg: DictConfig, layout, terrains: list[str]) -> list:
    """The Train split of each terrain as an MLflow dataset input (name, folder, fingerprint, table)."""
    from skidbench.benchmark.tracking import store as trk

    fingerprints = Fingerprints()
    files = train_files(layout)
    out = []
    for terrain in terrains:
        fs = [p for p in files if p.parents[1].name == terrain]
        if not fs:
            continue
        table = pd.concat([read_split(p)[0].assign(sequence=p.stem) for p in fs], ignore_index=True)
        fp = fingerprint_obj({str(p.relative_to(layout.splits)): fingerprints(p) for p in fs})
        name = f"{cfg.dataset}/{terrain}/train"
        out.append(trk.SplitData(name, "train", layout.splits / terrain / "train", fp, table))
    return out


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="calibrate")
@stage("calibrate")
def main(cfg: DictConfig) -> None:
    logging.getLogger("skidbench").setLevel(logging.INFO)
    run(cfg)


if __name__ == "__main__":
    main()
