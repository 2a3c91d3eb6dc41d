"""``skidbench fit model=<name> terrain=<t>``: fit one model on one terrain's Train split.

Writes ``<out_root>/<dataset>/fits/<model>/<terrain>.json``. Sweeps: ``skidbench fit -m model=a,b
terrain=x,y``. The model comes from the config group ``model`` (``conf/model/<name>.yaml``, or a plugin's
config found on the Hydra search path).
"""

from __future__ import annotations

import json
import logging

import hydra
from omegaconf import DictConfig, OmegaConf

from skidbench.models.base import ModelError
from skidbench.pipeline.cli.main import stage

log = logging.getLogger(__name__)


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="fit")
@stage("fit")
def main(cfg: DictConfig) -> None:
    from skidbench.models.fitting.fit import FitSettings, fit_model
    from skidbench.models.fitting.settings import FitOptions
    from skidbench.pipeline.core.layout import layout_from_cfg, root_from_cfg

    if OmegaConf.is_missing(cfg, "terrain") or cfg.terrain is None:
        raise ModelError("fit: no terrain given; add terrain=<t> (a folder under <dataset>/splits/)")
    opts: FitOptions = root_from_cfg(cfg, FitOptions)
    terrain = opts.terrain
    name = str(cfg.model.name)
    layout = layout_from_cfg(cfg)

    def log_run(res, name, terrain) -> None:
        loss = f"{res.fit_loss:.6g}" if res.fit_loss is not None else "n/a"
        log.info(
            f"fit {name} on {terrain}: {res.n_train} rows, loss {loss}, {res.fit_time_s:.2f} s, "
            f"params {res.model.params} -> {res.path}"
        )
        if opts.track:
            log_fit_run(cfg, layout, name, terrain, res, opts.split)

    # up to date (fitting.fit_stamp, whichever stage made the fit): reused and nothing logged; else
    # fitted, logged, and only then stamped (a job killed before its run was logged refits when retried)
    res = fit_model(
        FitSettings.from_cfg(cfg),
        name,
        terrain,
        reuse=opts.reuse,
        split=opts.split,
        hooks=[log_run],
    )
    if res.reused:
        print(f"fit: {name}/{terrain} up to date, skipped ({res.path})", flush=True)
    elif res.refit_reason:
        print(f"fit: {name}/{terrain}: {res.refit_reason} since its last fit; refitted", flush=True)


def log_fit_run(cfg: DictConfig, layout, name: str, terrain: str, res, split: str) -> str:
    """One MLflow run for this fit (benchmark/tracking/store.py), tagged with model, terrain, the sweep id and
    the job's run key; a job retried after its run finished logs nothing more (returns that run's id)."""
    from skidbench.benchmark.tracking import store as trk
    from skidbench.benchmark.tracking import tags as run_tags
    from skidbench.benchmark.tracking.sweep import TAG_SWEEP, run_key, sweep_id
    from skidbench.models.registry.saved import arrays_file
    from skidbench.pipeline.runner import environment

    tracker = trk.tracker_from_cfg(cfg, layout)
    job_key = run_key()
    done = tracker.claim_key(job_key) if job_key else None
    if done:
        return done
    tags = {
        run_tags.TAG_ROLE: "fit",
        run_tags.TAG_MODEL: name,
        run_tags.TAG_TERRAIN: terrain,
        run_tags.TAG_INPUTS: str(cfg.get("inputs", "commanded")),
        run_tags.TAG_DATASET: str(cfg.dataset),
        run_tags.TAG_MODEL_VERSION: str(getattr(res.model, "version", "unknown")),
        TAG_SWEEP: sweep_id(),
        **environment.run_tags(),  # skidbench's version and commit, libraries, lock, platform, code paths
        **environment.code_tags(res.code),
        run_tags.TAG_GIT: environment.git_commit(),
        **({run_tags.TAG_RUN_KEY: job_key} if job_key else {}),
    }
    tags[run_tags.TAG_NOTE] = run_tags.describe(
        f"**{name}** fitted on the {split} split of **{terrain}**",
        {"dataset": f"`{cfg.dataset}` ({layout.root})", "fit": f"`{res.path}`"},
        run_tags.reproduce_command("fit", [f"model={name}", f"terrain={terrain}", "reuse=false"]),
    )
    with tracker.run(f"fit {name}/{terrain}", tags) as run_id:
        params = {
            "model": name,
            "terrain": terrain,
            "split": split,
            "inputs": str(cfg.get("inputs")),
        }
        params.update(
            run_tags.flatten(dict(res.model.params or {}), "fitted.")
        )  # as evaluate's runs name them
        params.update(run_tags.flatten(dict(getattr(res.model, "options", None) or {}), "model_options."))
        metrics = {"fit_time_s": res.fit_time_s, "n_train": res.n_train}
        if res.fit_loss is not None:
            metrics["fit_loss"] = res.fit_loss
        tracker.log(run_id, params=params)
        tracker.artifact(run_id, res.path, "fit")
        if arrays_file(res.path).is_file():  # a learned model's fitted arrays
            tracker.artifact(run_id, arrays_file(res.path), "fit")
        _log_model(cfg, tracker, run_id, name, terrain, res, layout)
        tracker.log(run_id, metrics=metrics)  # after the model: Model.log re-logs the metrics before it
    return run_id


def _log_model(cfg: DictConfig, tracker, run_id: str, name: str, terrain: str, res, layout) -> None:
    """The fitted model as an MLflow Model of the fit run (as evaluate logs it; tag its id)."""
    from skidbench.benchmark.tracking.mlflow_model import write_model_record
    from skidbench.models.registry.saved import arrays_file

    spec = str((json.loads(res.path.read_text()).get("resolved") or {}).get("spec") or name)
    inputs = str(cfg.get("inputs", "commanded"))
    path = layout.fit_file(name, terrain, inputs).with_suffix(".mlflow_model.json")
    record = write_model_record(path, spec, res.model.to_json(), res.model.robot, inputs)
    arrays = arrays_file(res.path)
    model_id = tracker.log_model(
        run_id, f"{name}-{terrain}", record, None, arrays if arrays.is_file() else None
    )
    tracker.log(run_id, tags={"skidbench.logged_model": model_id})


if __name__ == "__main__":
    main()
