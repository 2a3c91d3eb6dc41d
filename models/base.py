"""The model plugin interface (scikit-learn style).

A model predicts body velocities (vx, vy, wz) from the columns of a split table (see
``skidbench.pipeline.core.schema.SPLIT_COLUMNS``). It is fitted per terrain on the Train split, and its
parameters are plain JSON data (``params``) plus, for a learned model, named numpy arrays (``arrays``:
saved beside the JSON as ``.npz``, logged to MLflow, reloaded by ``evaluate``). Built-in models and
third-party plugins register the same way: an entry point in the group ``skidbench.models``
(``name = "package.module:Class"``). The whole contract: docs/plugins.md.

``predict``'s table holds several sequences concatenated (``sequence`` column, ``t`` restarting at 0 in
each) and only the input protocol's columns (``skidbench.pipeline.core.protocol.INPUT_COLUMNS``: ``t sequence
cmd_v cmd_w cmd_wl cmd_wr cmd_dwl cmd_dwr``). A model may also define ``predict_cov(table) -> (T, 3, 3)``,
the predictive covariance of (vx, vy, wz) per row; the horizon evaluation then scores its pose
uncertainty. ``error_autocorrelation_`` (optional, (L, 3), lag 0 = 1, lags of the table's clock) says how
the model's velocity errors are correlated in time (white noise when absent).

Minimal plugin::

    class MyModel(KinematicModel):
        name = "mymodel"
        version = "1.0"
        required_columns = ("cmd_wl", "cmd_wr")

        def fit(self, table):
            ...; self.params = {"k": 1.0}; self.fit_loss_ = 0.01; return self

        def predict(self, table):
            return np.column_stack([vx, vy, wz])   # (T, 3) float64
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.robot import Robot


class ModelError(SkidbenchError):
    """A model cannot be built, fitted or used on the given table (the message names the model)."""


class KinematicModel(ABC):
    name: ClassVar[str]
    version: ClassVar[str] = "1.0"
    #: split columns ``fit`` and ``predict`` read (``valid``, ``vx``, ``vy``, ``wz`` are implied for fit)
    required_columns: ClassVar[tuple[str, ...]] = ("cmd_wl", "cmd_wr")
    #: the robot constants this model takes from the ``calibrate`` stage (effective values identified on
    #: the terrain's Train split, ``skidbench.pipeline.calibrate.calibration``); the others stay the spec
    # sheet's,
    #: because the model's own parameters absorb them. Default: the effective wheel radius only (what r
    #: means in any kinematic model); a model whose geometry is the physical track keeps it.
    calibrated_constants: ClassVar[tuple[str, ...]] = ("wheel_radius",)
    #: how the model takes the calibrated constants, in a line (``skidbench calibrate`` prints it and the
    #: calibration JSON records it as ``model_usage``); empty: not listed
    calibration_usage: ClassVar[str] = ""
    #: the options the model takes and their defaults; when set, an option it does not list is refused
    #: (ModelError naming the known ones) and the others default to these. None: options are not checked
    DEFAULTS: ClassVar[dict[str, Any] | None] = None

    def __init__(self, robot: Robot, params: dict[str, Any] | None = None, **options: Any):
        if self.DEFAULTS is not None:
            unknown = sorted(set(options) - set(self.DEFAULTS))
            if unknown:
                known = sorted(self.DEFAULTS)
                raise ModelError(f"model {self.name}: unknown option(s) {unknown}; known: {known}")
            options = {**self.DEFAULTS, **options}
        self.robot = robot
        self.params: dict[str, Any] = dict(params or {})
        self.options: dict[str, Any] = dict(options)
        self.fit_loss_: float | None = None  # mean squared velocity error on the training table
        #: fitted arrays (name -> numpy array), saved as ``<terrain>.arrays.npz`` beside the fit JSON
        self.arrays: dict[str, np.ndarray] = {}

    # -- the two methods a plugin implements --------------------------------------------------
    @abstractmethod
    def fit(self, table: pd.DataFrame) -> KinematicModel:
        """Fit on a training table (rows with ``valid`` False must be ignored). Returns self."""

    @abstractmethod
    def predict(self, table: pd.DataFrame) -> np.ndarray:
        """Body velocities (T, 3) = (vx, vy, wz) in m/s, m/s, rad/s, one row per table row."""

    # -- shared plumbing ----------------------------------------------------------------------
    def check_columns(self, table: pd.DataFrame, fitting: bool = False) -> None:
        """Raise ModelError naming the model if the table lacks a needed column or holds non-finite
        values in one."""
        need = list(self.required_columns) + (["vx", "vy", "wz", "valid"] if fitting else [])
        missing = [c for c in need if c not in table.columns]
        if missing:
            raise ModelError(f"model {self.name}: table lacks column(s) {missing}")
        if fitting and len(table) and not table["valid"].any():
            raise ModelError(f"model {self.name}: training table has no valid rows")
        rows = table["valid"].to_numpy(bool) if (fitting and "valid" in table) else slice(None)
        for c in need:
            if c == "valid":
                continue
            col = table[c].to_numpy(dtype=float, na_value=np.nan)[rows]
            if not np.all(np.isfinite(col)):
                bad = int(np.sum(~np.isfinite(col)))
                raise ModelError(f"model {self.name}: column {c} holds {bad} non-finite value(s)")

    def get_params(self) -> dict[str, Any]:
        """``params`` as plain JSON data (numpy scalars become numbers). A numpy array is refused with a
        ModelError naming the key: fitted arrays belong in ``self.arrays``."""
        for where, value in _walk(self.params, "params"):
            if isinstance(value, np.ndarray):
                raise ModelError(
                    f"model {self.name}: {where} is a numpy array {value.shape}; put fitted arrays in "
                    "self.arrays (saved as .npz with the fit), params hold JSON data only"
                )
        try:
            return json.loads(json.dumps(self.params, default=_json_scalar))
        except (TypeError, ValueError) as exc:
            raise ModelError(f"model {self.name}: params are not JSON data ({exc})") from None

    def set_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Called with the arrays a saved fit holds (after ``from_json``); override to unpack them."""
        self.arrays = {k: np.asarray(v) for k, v in arrays.items()}

    def to_json(self) -> dict[str, Any]:
        return {
            "model": self.name,
            "version": self.version,
            "params": self.get_params(),
            "options": self.options,
            "fit_loss": self.fit_loss_,
        }

    @classmethod
    def from_json(cls, robot: Robot, data: dict[str, Any]) -> KinematicModel:
        if data.get("model") != cls.name:
            raise ModelError(f"model {cls.name}: parameters are for model {data.get('model')!r}")
        m = cls(robot, data.get("params") or {}, **(data.get("options") or {}))
        m.fit_loss_ = data.get("fit_loss")
        return m

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, version={self.version!r}, params={self.params})"


def _walk(obj: Any, where: str):
    """(path, leaf) pairs of a nested dict/list."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk(v, f"{where}[{k!r}]")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _walk(v, f"{where}[{i}]")
    else:
        yield where, obj


def _json_scalar(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    raise TypeError(f"{type(v).__name__} is not JSON data")


def calibrated_constants(cls: type) -> tuple[str, ...]:
    """The robot constants a model class takes from the calibration (``calibrated_constants``; a duck-typed
    plugin without it takes the radius, as :class:`KinematicModel`)."""
    return tuple(getattr(cls, "calibrated_constants", ("wheel_radius",)))
