"""Augmented models: any model plus named physical effects of the discovery catalogue, a first-class model.

    skidbench evaluate models=[edd,friction,edd+actuator_lag+angular_acceleration_slip,discovered]

A model spec ``base+effect+effect`` (ids of :mod:`skidbench.models.augmented.effects`) names the base model
(any installed model, ``friction`` too) and the effects added to it; ``discovered`` is, per terrain, the
base model and effects that ``skidbench discover`` wrote to the dataset's ``discovery.json``
(:func:`skidbench.models.fitting.fit.resolve_model_spec`). The augmented model is fitted on the Train split
exactly as discovery fits its final model (:func:`skidbench.models.augmented.fit.fit_effects`: the base
model and the effect parameters by alternation, the lag time constant by a grid and a parabola) and
predicts with :func:`skidbench.models.augmented.effects.augmented_prediction`. It takes the robot constants
its
base model takes (``calibrated_constants``).

The cost of a fit is that of several base-model fits (about 6 alternations, 30 with ``actuator_lag``'s
grid): cheap for the linear models, minutes for ``friction`` on real data.
"""

from __future__ import annotations

import functools
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from skidbench.models.augmented.effects import CATALOGUE, EFFECT_IDS, augmented_prediction
from skidbench.models.augmented.fit import DiscoverError, fit_effects, jsonable_params
from skidbench.models.augmented.terms import is_term_key, parse_term
from skidbench.models.base import KinematicModel, ModelError, calibrated_constants
from skidbench.models.columns import mse, targets
from skidbench.models.registry.plugins import plugin_class
from skidbench.models.registry.saved import from_saved

SEP = "+"
EFFECT_COLUMNS = ("t", "cmd_v", "cmd_w", "cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")


class AugmentedModel(KinematicModel):
    """Base model + effects. Subclasses made by :func:`augmented_class` set ``base_name`` and ``effects``."""

    name: ClassVar[str] = "augmented"
    version: ClassVar[str] = "1.0"
    base_name: ClassVar[str] = ""
    effects: ClassVar[tuple[str, ...]] = ()
    terms: ClassVar[
        tuple[str, ...]
    ] = ()  # open-ended terms discovery found (keys, models/augmented/terms.py)

    def __init__(
        self,
        robot,
        params: dict[str, Any] | None = None,
        base_params: dict[str, Any] | None = None,
        base_options: dict[str, Any] | None = None,
        **options: Any,
    ):
        super().__init__(
            robot,
            params,
            base_params=dict(base_params or {}),
            base_options=dict(base_options or {}),
            **options,
        )
        self.base_model: KinematicModel | None = None
        if self.params.get("base"):
            base_cls = plugin_class(self.base_name)
            self.base_model = from_saved(base_cls, robot, self.params["base"], self.base_name)

    def _new_base(self) -> KinematicModel:
        cls = plugin_class(self.base_name)
        return cls(self.robot, dict(self.options["base_params"]) or None, **self.options["base_options"])

    def _effect_params(self) -> dict[str, np.ndarray]:
        out = {}
        for e in self.effects:
            values = self.params.get("effects", {}).get(e, {})
            out[e] = np.array([float(values[p]) for p in CATALOGUE[e].param_names])
        return out

    def fit(self, table: pd.DataFrame) -> AugmentedModel:
        self.check_columns(table, fitting=True)
        missing = [c for c in ("x", "y", "yaw") if c not in table.columns]
        if missing:
            raise ModelError(f"model {self.name}: training table lacks column(s) {missing}")
        try:
            state = fit_effects(
                table,
                self._new_base,
                self.robot,
                list(self.effects),
                terms=[parse_term(k) for k in self.terms],
            )
        except DiscoverError as exc:
            raise ModelError(f"model {self.name}: {exc}") from None
        self.base_model = state.base
        base_json = state.base.to_json() if hasattr(state.base, "to_json") else {"params": state.base.params}
        self.params = {"base": base_json, "effects": jsonable_params(state.params)}
        if self.terms:
            self.params["terms"] = {k: dict(v) for k, v in state.term_params.items()}
        valid = table["valid"].to_numpy(bool)
        self.fit_loss_ = mse(self.predict(table)[valid], targets(table)[valid])
        return self

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        if self.base_model is None:
            raise ModelError(f"model {self.name}: not fitted")
        return augmented_prediction(
            table,
            self.base_model,
            self._effect_params(),
            self.robot.wheel_radius,
            self.robot.track_width,
            terms=self.params.get("terms") or None,
        )

    def tracking_params(self) -> dict[str, str]:
        """What MLflow records of this model beyond the config: base, effects and their fitted values."""
        out = {"augmented.base": self.base_name, "augmented.effects": ",".join(self.effects)}
        for e, values in self.params.get("effects", {}).items():
            for p, v in values.items():
                out[f"effect.{e}.{p}"] = f"{float(v):.6g}"
        if self.terms:
            out["augmented.terms"] = ",".join(self.terms)
            for i, (k, values) in enumerate(self.params.get("terms", {}).items()):
                out[f"term.{i}.key"] = k
                out[f"term.{i}.theta"] = f"{float(values['theta']):.6g}"
        return out


def parse_spec(spec: str) -> tuple[str, tuple[str, ...], tuple[str, ...]]:
    """``"edd+actuator_lag+sat.wz_pred.wz@0.99"`` -> ("edd", ("actuator_lag",), ("sat.wz_pred.wz@0.99",)):
    base, catalogue effects, open-ended terms (keys of ``skidbench.models.augmented.terms``); ModelError
    naming
    the spec for an unknown or repeated effect."""
    parts = [p.strip() for p in str(spec).split(SEP)]
    terms = tuple(parse_term(p).key for p in parts[1:] if is_term_key(p))  # one spelling of the knots
    base, effects = parts[0], tuple(p for p in parts[1:] if not is_term_key(p))
    if not base or any(not e for e in effects):
        raise ModelError(f"model {spec}: empty part in the spec (write base+effect+effect)")
    unknown = [e for e in effects if e not in CATALOGUE]
    if unknown:
        raise ModelError(f"model {spec}: unknown effect(s) {unknown} (catalogue: {', '.join(EFFECT_IDS)})")
    if len(set(effects)) != len(effects) or len(set(terms)) != len(terms):
        raise ModelError(f"model {spec}: an effect is named twice")
    return base, effects, terms


@functools.lru_cache(maxsize=128)
def augmented_class(spec: str) -> type[AugmentedModel]:
    """The model class of a spec ``base+effect+...`` (the base must be an installed model)."""
    base, effects, terms = parse_spec(spec)
    if SEP in base:
        raise ModelError(f"model {spec}: bad spec")
    base_cls = plugin_class(base)
    required = tuple(dict.fromkeys((*getattr(base_cls, "required_columns", ()), *EFFECT_COLUMNS)))
    return type(
        "Augmented_" + "_".join((base, *effects)),
        (AugmentedModel,),
        {
            "name": spec,
            "version": f"{AugmentedModel.version}+{getattr(base_cls, 'version', '?')}",
            "base_name": base,
            "effects": effects,
            "terms": terms,
            "required_columns": required,
            "calibrated_constants": calibrated_constants(base_cls),
            "__module__": __name__,
        },
    )
