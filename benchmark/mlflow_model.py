"""A fitted skidbench model as an MLflow Model (``pyfunc`` flavour), so that it can be loaded and used
outside skidbench's stages: ``mlflow.pyfunc.load_model("models:/<model id>").predict(table)``.

The MLflow Model holds one JSON artifact (``skidbench_model.json``: the model spec, the fit JSON the
``fit`` stage wrote and the robot constants it was fitted with) and rebuilds the model from it with the
model's own ``from_json``; the skidbench package (and the model's plugin package) must be installed where
it is loaded. This module imports MLflow: import it only where a model is logged or loaded.

Input: a DataFrame with the columns :data:`INPUT_COLUMNS` (time in s, a sequence label, and the commanded
body and wheel velocities and wheel accelerations of the evaluation's input protocol), one row per 30 Hz
step; output: a DataFrame ``vx vy wz`` (m/s, m/s, rad/s; body frame), one row per input row.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from mlflow.models import ModelSignature
from mlflow.pyfunc import PythonModel
from mlflow.types import ColSpec, Schema

from skidbench.models.specs import get_model_class
from skidbench.pipeline.protocol import INPUT_COLUMNS  # what a model sees at predict time
from skidbench.pipeline.robot import Robot

OUTPUT_COLUMNS = ("vx", "vy", "wz")
ARRAYS_ARTIFACT = "fitted_arrays"  # a learned model's .npz (models/saved.py save_arrays), when it has one
ARTIFACT = "skidbench_model"


def signature():
    """The MLflow signature: :data:`INPUT_COLUMNS` in (``sequence`` a string, the rest doubles), body
    velocities ``vx vy wz`` (doubles) out."""
    inputs = Schema([ColSpec("string" if c == "sequence" else "double", c) for c in INPUT_COLUMNS])
    return ModelSignature(inputs=inputs, outputs=Schema([ColSpec("double", c) for c in OUTPUT_COLUMNS]))


def robot_record(robot: Robot) -> dict[str, Any]:
    """The robot as a config mapping :meth:`Robot.from_config` takes back (extra keys flattened)."""
    d = robot.to_dict()
    d.pop("inertia_z", None)  # derived
    extra = d.pop("extra", None) or {}
    return {**extra, **d}


def write_model_record(path: Path, spec: str, fit: dict[str, Any], robot: Robot, inputs: str) -> Path:
    """The JSON the MLflow Model carries: spec, fit JSON, robot constants and input protocol."""
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"spec": spec, "inputs": inputs, "robot": robot_record(robot), "fit": fit}
    path.write_text(json.dumps(doc, indent=1, default=str))
    return path


def load_record(path: str | Path, arrays: str | Path | None = None):
    """The fitted model (a :class:`~skidbench.models.base.KinematicModel`) from a model record, with a
    learned model's fitted arrays (the ``.npz`` of the fit) when given."""
    doc = json.loads(Path(path).read_text())
    cls = get_model_class(doc["spec"])
    model = cls.from_json(Robot.from_config(doc["robot"]), doc["fit"])
    if arrays is not None:
        with np.load(arrays, allow_pickle=False) as z:
            model.set_arrays({k: z[k] for k in z.files})
    return model


class SkidbenchModel(PythonModel):
    """The ``python_model`` of the MLflow Model: rebuilds the fitted model from its record on load."""

    def load_context(self, context) -> None:
        self.model = load_record(context.artifacts[ARTIFACT], context.artifacts.get(ARRAYS_ARTIFACT))

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        """(T, 3) body velocities as a DataFrame ``vx vy wz`` for a table of :data:`INPUT_COLUMNS`."""
        table = pd.DataFrame(model_input).reset_index(drop=True)
        if "sequence" not in table:
            table["sequence"] = "0"
        vel = np.asarray(self.model.predict(table[list(INPUT_COLUMNS)]), dtype=float)
        return pd.DataFrame(vel, columns=list(OUTPUT_COLUMNS))
