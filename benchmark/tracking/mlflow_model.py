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

import contextlib
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from mlflow.models import ModelSignature
from mlflow.pyfunc import PythonModel
from mlflow.types import ColSpec, Schema

from skidbench.models.registry.specs import get_model_class
from skidbench.pipeline.core.protocol import INPUT_COLUMNS  # what a model sees at predict time
from skidbench.pipeline.core.robot import Robot

OUTPUT_COLUMNS = ("vx", "vy", "wz")
ARRAYS_ARTIFACT = (
    "fitted_arrays"  # a learned model's .npz (models/registry/saved.py save_arrays), when it has one
)
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


@contextlib.contextmanager
def mlflow_current(uri: str, experiment_id: str) -> Iterator[None]:
    """MLflow's current tracking URI and experiment set for a block, then restored with the environment
    variables ``mlflow.set_tracking_uri``/``set_experiment`` export (the config reads
    MLFLOW_TRACKING_URI: left set, a stage's cache key would change after its run)."""
    import mlflow
    from mlflow.tracking import fluent
    from mlflow.tracking._tracking_service import utils as tracking_utils

    names = ("MLFLOW_TRACKING_URI", "MLFLOW_EXPERIMENT_ID")
    env = {k: os.environ.get(k) for k in names}
    saved = (tracking_utils._tracking_uri, fluent._active_experiment_id)
    mlflow.set_tracking_uri(uri)
    mlflow.set_experiment(experiment_id=experiment_id)
    try:
        yield
    finally:
        tracking_utils._tracking_uri, fluent._active_experiment_id = saved
        for k, v in env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def log_pyfunc(
    uri: str, experiment_id: str, run_id: str, name: str, record: Path, example: Any, arrays: Path | None,
    requirements: Sequence[str],
) -> str:  # fmt: skip
    """Log a fitted model as an MLflow Model of ``run_id`` in the store ``uri`` (pyfunc flavour from the code
    of ``mlflow_model_code.py``, with the protocol's :func:`signature`; ``record`` its JSON, ``arrays`` a
    learned model's arrays, ``example`` a few input rows MLflow stores and checks the model with,
    ``requirements`` given, not inferred: inference loads the model in a subprocess); returns its id.
    Model.log talks to the current tracking URI and creates the model in the current experiment: both set
    for the call only (they are process-wide, and MLFLOW_TRACKING_URI is part of the config)."""
    import mlflow
    from mlflow.models import Model

    with mlflow_current(uri, experiment_id):
        info = Model.log(
            artifact_path=None,
            name=name,
            flavor=mlflow.pyfunc,
            run_id=run_id,
            python_model=str(Path(__file__).with_name("mlflow_model_code.py")),  # models from code
            artifacts={ARTIFACT: str(record), **({ARRAYS_ARTIFACT: str(arrays)} if arrays else {})},
            signature=signature(),
            input_example=example,
            pip_requirements=list(requirements),
        )
    return info.model_id
