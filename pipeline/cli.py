"""``skidbench <stage> [hydra overrides]``: one console script, one Hydra app per stage.

Each stage module exposes ``main()`` decorated with ``@hydra.main(version_base="1.3",
config_path="pkg://skidbench.conf", config_name="<stage>")`` and wrapped in :func:`stage`, which turns a
:class:`SkidbenchError` into one line on stderr and exit status 2.
"""

from __future__ import annotations

import functools
import importlib
import logging
import sys
from collections.abc import Callable

from .errors import SkidbenchError, one_line

# stage -> "module:function" (imported lazily so that `skidbench --help` is instant)
STAGES: dict[str, tuple[str, str]] = {
    "simulate": ("skidbench.pipeline.simulate.app:main", "simulate the built-in default dataset (bags)"),
    "extract": ("skidbench.pipeline.extract.app:main", "bags and raw sources -> one Parquet table per topic"),
    "inspect": (
        "skidbench.pipeline.extract.inspect:main",
        "a bag's topics, rates, gaps; its source.topics",
    ),
    "groundtruth": ("skidbench.pipeline.groundtruth.app:main", "stereo VO / ORB-SLAM / pose topic -> TUM"),
    "split": ("skidbench.pipeline.splits.app:main", "Train/CV/LD Parquet splits per terrain"),
    "card": ("skidbench.pipeline.splits.app:card_main", "print the dataset card (the paper's Table I)"),
    "calibrate": ("skidbench.pipeline.calibrate_app:main", "effective wheel radius, track width from Train"),
    "fit": ("skidbench.models.app:main", "fit a model on a terrain's Train split"),
    "models": ("skidbench.models.registry:list_main", "list the installed models (plugins)"),
    "evaluate": ("skidbench.benchmark.evaluate_app:main", "6 s horizon benchmark, logged to MLflow"),
    "compare": ("skidbench.benchmark.compare_app:main", "leaderboard and the paper's figures"),
    "discover": ("skidbench.benchmark.discover_app:main", "find the missing physical effect"),
    "datasets": ("skidbench.pipeline.datasets_app:main", "list the datasets the output root holds"),
}

log = logging.getLogger("skidbench")


def exit_with_error(message: str, name: str | None = None) -> None:
    """Print ``skidbench <stage>: error: <message>`` as one line on stderr and exit with status 2. Without
    ``name``, the stage :func:`main` dispatched to (it sets ``sys.argv[0]`` to ``skidbench <stage>``)."""
    prog = f"skidbench {name}" if name else sys.argv[0]
    if not prog.startswith("skidbench"):
        prog = "skidbench"
    print(f"{prog}: error: {one_line(message)}", file=sys.stderr, flush=True)
    sys.exit(2)


def stage(name: str, home: bool = True) -> Callable:
    """Decorator for a stage's task function: SkidbenchError -> one line on stderr, exit 2. With ``home``
    (a config with a ``source``), the dataset's identity is printed and its folder checked first
    (:func:`skidbench.pipeline.dataset.open_home`)."""

    def deco(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            try:
                cfg = args[0] if args else None
                if home and hasattr(cfg, "get") and cfg.get("source") is not None and "dataset" in cfg:
                    from .dataset import open_home

                    open_home(cfg, name)
                return fn(*args, **kwargs)
            except SkidbenchError as exc:
                exit_with_error(str(exc), name)

        return wrapper

    return deco


def _usage() -> str:
    width = max(map(len, STAGES))
    rows = "\n".join(f"  {k.ljust(width)}  {help_}" for k, (_, help_) in STAGES.items())
    return (
        "usage: skidbench <stage> [key=value ...] [-m] [--cfg job] [--help]\n\n"
        f"stages:\n{rows}\n\nEach stage is a Hydra app: `skidbench <stage> --help` shows its config."
    )


def register_launchers() -> None:
    """Register skidbench's Hydra launcher (``hydra/launcher=ray``) with Hydra. Hydra finds plugins by
    listing the ``hydra_plugins`` namespace package, which an editable install (``make setup``) cannot
    list; a regular install is found either way (registering twice is a no-op)."""
    try:
        from hydra.core.plugins import Plugins

        from hydra_plugins.skidbench_ray_launcher.ray_launcher import RayLauncher
    except ImportError:  # pragma: no cover (installed with the package)
        return
    Plugins.instance().register(RayLauncher)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return
    name = argv[0]
    if name not in STAGES:
        print(f"skidbench: error: unknown stage {name!r}\n\n{_usage()}", file=sys.stderr)
        sys.exit(2)
    target, _ = STAGES[name]
    module, func = target.split(":")
    try:
        fn = getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as exc:  # a stage that is not built yet says so plainly
        print(f"skidbench {name}: error: stage not available ({exc})", file=sys.stderr)
        sys.exit(2)
    _check_overrides(name, argv[1:])
    sys.argv = [f"skidbench {name}", *argv[1:]]
    register_launchers()
    fn()


def _check_overrides(name: str, args: list[str]) -> None:
    """An unknown or misspelt override -> one line naming it and the nearest valid keys, exit 2."""
    from .overrides import check_overrides

    try:
        check_overrides(name, args)
    except SkidbenchError as exc:
        print(f"skidbench {name}: error: {one_line(str(exc))}", file=sys.stderr, flush=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
