"""skidbench.models: the kinematic models, their fitting, the plugin interface and the registry."""

import skidbench.pipeline  # noqa: F401 - first: pins the processor code paths before NumPy loads
from skidbench.models.base import KinematicModel, ModelError

__all__ = ["KinematicModel", "ModelError"]
