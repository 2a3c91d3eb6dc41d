"""skidbench.models: the kinematic models, their fitting, the plugin interface and the registry."""

from .base import KinematicModel, ModelError

__all__ = ["KinematicModel", "ModelError"]
