"""What MLflow shows of an evaluate's runs beside their numbers: the description and reproduce command of a
parent or child run, the splits as MLflow dataset inputs, the UI's saved views of an evaluate."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from skidbench.benchmark.evaluate.testsets import TRAIN, split_fingerprint
from skidbench.benchmark.scoring import metrics as mt
from skidbench.benchmark.tracking import mlflow_ui as mu
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking import tags as run_tags
from skidbench.pipeline.core.layout import Layout
from skidbench.pipeline.core.schema import concat_sequences, read_split


def describe_run(layout: Layout, inputs: str, models, terrains, splits, horizons) -> tuple[str, str]:
    """The description of an evaluate run (parent: every model and terrain; child: one of each) and the
    command(s) that reproduce it."""
    one = len(models) == 1 and len(terrains) == 1
    cmd = run_tags.reproduce_command(
        "evaluate", [f"models=[{','.join(models)}]", f"terrains=[{','.join(terrains)}]"] if one else [],
        drop=("force",),
    )  # fmt: skip
    if one:
        cmd = run_tags.reproduce_command("fit", [f"model={models[0]}", f"terrain={terrains[0]}"],
                                    drop=("models", "terrains", "force")) + "\n" + cmd  # fmt: skip
    title = (f"**{models[0]}** on **{terrains[0]}**, fitted on Train, scored on {'/'.join(splits).upper()}"
             if one else f"Benchmark of {len(models)} models on {len(terrains)} terrains")  # fmt: skip
    facts = {
        "dataset": f"`{layout.dataset}` ({layout.root})",
        "input protocol": f"`{inputs}` (what a model is given at predict time)",
        "horizon": ", ".join(f"{h:g} s" for h in horizons),
        "models": None if one else ", ".join(models),
        "terrains": None if one else ", ".join(terrains),
        "metrics": mt.describe() + "; lower is better",
    }
    return run_tags.describe(title, facts, cmd), cmd


def split_inputs(layout: Layout, terrain, files, tests) -> list[trk.SplitData]:
    """The Train split and the test splits of one terrain as MLflow dataset inputs."""
    out = []
    for split in [TRAIN, *tests]:
        fs = [p for p in files if p.parent.name == split]
        tables = (
            [(s.table, {"sequence": s.name}) for s in tests[split]]
            if split in tests
            else [read_split(p) for p in fs]
        )
        name = f"{layout.dataset}/{terrain}/{split}"
        out.append(trk.SplitData(name, split, layout.splits / terrain / split,
                                 split_fingerprint(fs, layout.splits), concat_sequences(tables)))  # fmt: skip
    return out


def save_views(
    tracker, parent_id: str, splits, horizons, protocol: str, children: Sequence[Any] = ()
) -> list[str]:
    """The UI's saved views of an evaluate (:func:`mlflow_ui.save_evaluate_views`): its child runs and the
    runs of its ``children`` (ChildResults) it took from earlier evaluates, with the columns of
    :func:`mlflow_ui.board_columns`, best LD translational first. Returns their keys."""
    cols, _ = mu.board_columns(splits, horizons[0])
    name = tracker.client.get_run(parent_id).info.run_name
    return mu.save_evaluate_views(tracker.client, tracker.experiment_id, parent_id, name, cols, protocol,
                                  horizons[0], [c.run_id for c in children if c.reused])  # fmt: skip
