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
    "groundtruth": ("skidbench.pipeline.groundtruth.app:main", "stereo VO / ORB-SLAM / pose topic -> TUM"),
    "split": ("skidbench.pipeline.splits.app:main", "Train/CV/LD Parquet splits per terrain"),
    "card": ("skidbench.pipeline.splits.app:card_main", "print the dataset card (the paper's Table I)"),
    "calibrate": ("skidbench.pipeline.calibrate_app:main", "effective wheel radius, track width from Train"),
    "fit": ("skidbench.models.app:main", "fit a model on a terrain's Train split"),
    "models": ("skidbench.models.registry:list_main", "list the installed models (plugins)"),
    "evaluate": ("skidbench.benchmark.evaluate_app:main", "6 s horizon benchmark, logged to MLflow"),
    "compare": ("skidbench.benchmark.compare_app:main", "leaderboard and the paper's figures"),
    "discover": ("skidbench.benchmark.discover_app:main", "find the missing physical effect"),
}

log = logging.getLogger("skidbench")


def stage(name: str) -> Callable:
    """Decorator for a stage's task function: SkidbenchError -> one line on stderr, exit 2."""

    def deco(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except SkidbenchError as exc:
                print(f"skidbench {name}: error: {one_line(str(exc))}", file=sys.stderr, flush=True)
                sys.exit(2)

        return wrapper

    return deco


def _usage() -> str:
    width = max(map(len, STAGES))
    rows = "\n".join(f"  {k.ljust(width)}  {help_}" for k, (_, help_) in STAGES.items())
    return (
        "usage: skidbench <stage> [key=value ...] [-m] [--cfg job] [--help]\n\n"
        f"stages:\n{rows}\n\nEach stage is a Hydra app: `skidbench <stage> --help` shows its config."
    )


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
    sys.argv = [f"skidbench {name}", *argv[1:]]
    fn()


if __name__ == "__main__":
    main()
