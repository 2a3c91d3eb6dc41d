"""``hydra/launcher=ray``: every job of a sweep as a Ray task (``conf/hydra/launcher/ray.yaml``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hydra.core.utils import JobReturn
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf


class RayLauncher(Launcher):
    def __init__(self, **settings: Any) -> None:
        from skidbench.pipeline.runner.cluster import RaySettings

        plain = {k: OmegaConf.to_object(v) if OmegaConf.is_config(v) else v for k, v in settings.items()}
        self.settings = RaySettings(**plain)
        self.config: DictConfig | None = None
        self.hydra_context: HydraContext | None = None
        self.task_function: TaskFunction | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config = config
        self.hydra_context = hydra_context
        self.task_function = task_function

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from skidbench.pipeline.cli.main import exit_with_error
        from skidbench.pipeline.core.errors import ClusterError
        from skidbench.pipeline.runner.cluster import launch

        ctx, fn, cfg = self.hydra_context, self.task_function, self.config
        assert ctx is not None and fn is not None and cfg is not None
        try:
            return launch(self.settings, ctx, fn, cfg, job_overrides, initial_job_idx)
        except ClusterError as exc:  # one line, exit status 2, like every stage's errors
            exit_with_error(str(exc))
            raise  # not reached
