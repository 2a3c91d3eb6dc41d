"""A data stage's independent items (a bag, a sequence, a terrain) as tasks: forked worker processes on
this machine (:func:`~.forked.map_forked`), or one Ray task each on a Ray cluster when the run was started
with ``hydra/launcher=ray`` (:func:`~.cluster.map_items`; ``hydra.launcher.address`` says which cluster,
as for the sweeps: docs/scaling.md).

Either way each item writes its own outputs (atomically, under ``out_root``, which every node of a
cluster must see) and returns only a small summary of them (counts, scores, a path), so the process
that runs the stage holds no sequence data whatever the number or length of the sequences; the stage's
one progress bar counts the items as they finish, wherever they ran. On a cluster a failed item is run
once more, then the stage fails naming it; locally an item's error is the stage's error, as in a loop.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from skidbench.pipeline.runner.forked import map_forked

RAY_LAUNCHER = "RayLauncher"  # the class name of hydra_plugins/skidbench_ray_launcher's launcher


def ray_settings():
    """The run's Ray settings (:class:`~.cluster.RaySettings`, from ``hydra.launcher``) when the run was
    started with ``hydra/launcher=ray``, else None (not a Hydra run, or another launcher)."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    if not HydraConfig.initialized():
        return None
    launcher = HydraConfig.get().launcher
    if not str(launcher.get("_target_", "")).endswith(f".{RAY_LAUNCHER}"):
        return None
    from skidbench.pipeline.runner.cluster import RaySettings

    keys = {k: v for k, v in OmegaConf.to_container(launcher, resolve=True).items() if k != "_target_"}
    return RaySettings(**keys)


def map_items(
    fn: Callable[..., Any],
    calls: Sequence[tuple],
    names: Sequence[str],
    *,
    what: str,
    unit: str,
    done: Callable[[int, Any], None] | None = None,
    jobs: int | None = None,
    progress: bool | None = None,
) -> list[Any]:
    """``[fn(*args) for args in calls]``: Ray tasks when the run names a Ray cluster (:func:`ray_settings`),
    else forked workers (at most ``jobs``); ``names[i]`` names call ``i`` in errors; ``done(i, result)``
    runs in this process as each call finishes. One tqdm bar (``what``, counting ``unit``) over two or
    more calls: always when ``progress`` is True, on a terminal when None."""
    from tqdm import tqdm

    settings = ray_settings()
    disable = True if progress is False or len(calls) < 2 else (None if progress is None else False)
    bar = tqdm(total=len(calls), desc=what, unit=unit, disable=disable)

    def finished(i: int, result: Any) -> None:
        if done is not None:
            done(i, result)
        bar.update()

    with bar:
        if settings is None:
            return map_forked(fn, calls, finished, jobs)
        from skidbench.pipeline.runner.cluster import map_items as map_ray

        return map_ray(settings, fn, calls, names, finished, what)
