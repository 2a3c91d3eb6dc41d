"""Model names to model classes: an installed model (:mod:`skidbench.models.registry.plugins`) or the
augmented
model of a spec ``base+effect+...`` (:mod:`skidbench.models.augmented.model`). Sits above both, so the
registry
never imports the augmented model that builds on it."""

from __future__ import annotations

from skidbench.models.augmented.model import SEP, augmented_class
from skidbench.models.base import KinematicModel
from skidbench.models.registry.plugins import plugin_class


def get_model_class(name: str) -> type[KinematicModel]:
    """The model class registered as ``name``, or the augmented model of a spec ``base+effect+...``
    (``skidbench.models.augmented.model``); ModelError (one line) if absent or broken."""
    if SEP in str(name):
        return augmented_class(str(name))
    return plugin_class(name)
