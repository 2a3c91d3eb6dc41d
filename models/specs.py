"""Model names to model classes: an installed model (:mod:`skidbench.models.registry`) or the augmented
model of a spec ``base+effect+...`` (:mod:`skidbench.models.augmented`). Sits above both, so the registry
never imports the augmented model that builds on it."""

from __future__ import annotations

from .augmented import SEP, augmented_class
from .base import KinematicModel
from .registry import plugin_class


def get_model_class(name: str) -> type[KinematicModel]:
    """The model class registered as ``name``, or the augmented model of a spec ``base+effect+...``
    (``skidbench.models.augmented``); ModelError (one line) if absent or broken."""
    if SEP in str(name):
        return augmented_class(str(name))
    return plugin_class(name)
