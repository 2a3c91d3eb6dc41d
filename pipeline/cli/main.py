"""``skidbench <stage> [hydra overrides]``: one console script, one Hydra app per stage.

Each stage module exposes ``main()`` decorated with ``@hydra.main(version_base="1.3",
config_path="pkg://skidbench.conf", config_name="<stage>")`` and wrapped in :func:`stage`, which turns a
:class:`SkidbenchError` into one line on stderr and exit status 2.
"""

from __future__ import annotations

import errno
import functools
import importlib
import json
import logging
import os
import re
import sys
import tempfile
from collections.abc import Callable
from importlib.resources import files
from pathlib import Path

from skidbench.pipeline.cli.config_schema import check_value, spec_for
from skidbench.pipeline.cli.overrides import validate
from skidbench.pipeline.core.errors import (
    EXIT_INTERRUPTED,
    EXIT_PARTIAL,
    ConfigError,
    PartialFailure,
    SkidbenchError,
    one_line,
)
from skidbench.pipeline.core.layout import default_out_root, register_resolvers, remove_atomic

# Not imported here: what a stage's run needs and `skidbench --help` does not (.cache, .imported: PyArrow
# through .io), so that the command starts with only what the chosen stage imports itself.

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
    "calibrate": ("skidbench.pipeline.calibrate.app:main", "effective wheel radius, track width from Train"),
    "fit": ("skidbench.models.fitting.app:main", "fit a model on a terrain's Train split"),
    "models": ("skidbench.models.registry.plugins:list_main", "list the installed models (plugins)"),
    "evaluate": ("skidbench.benchmark.evaluate.app:main", "6 s horizon benchmark, logged to MLflow"),
    "compare": ("skidbench.benchmark.board.app:main", "leaderboard and the paper's figures"),
    "discover": ("skidbench.benchmark.discovery.app:main", "find the missing physical effect"),
    "datasets": ("skidbench.pipeline.datasets.app:main", "list the datasets the output root holds"),
    "runs": (
        "skidbench.benchmark.tracking.runs_app:main",
        "MLflow runs left open; --reap ends those whose process is gone",
    ),
    "export": (
        "skidbench.benchmark.release.release_app:export_main",
        "<dataset> <dir>: dataset, board as a bundle",
    ),
    "import": (
        "skidbench.benchmark.release.release_app:import_main",
        "<dir>: verify a bundle, make a dataset of it",
    ),
    "score": (
        "skidbench.benchmark.release.release_app:score_main",
        "<dataset> --predictions <file>: score a model's output",
    ),
    "publish": (
        "skidbench.benchmark.release.release_app:publish_main",
        "<dataset> <dir>: the boards as a static web page",
    ),
}
#: a stage's command-line flags and the override each stands for (``skidbench runs --reap``)
FLAGS: dict[str, dict[str, str]] = {"runs": {"--reap": "reap=true"}}

log = logging.getLogger("skidbench")


def exit_with_error(message: str, name: str | None = None) -> None:
    """Print ``skidbench <stage>: error: <message>`` as one line on stderr and exit with status 2. Without
    ``name``, the stage :func:`main` dispatched to (it sets ``sys.argv[0]`` to ``skidbench <stage>``)."""
    prog = f"skidbench {name}" if name else sys.argv[0]
    if not prog.startswith("skidbench"):
        prog = "skidbench"
    print(f"{prog}: error: {one_line(message)}", file=sys.stderr, flush=True)
    sys.exit(2)


def stage(name: str, home: bool = True, runs: bool = False, interrupted: str = "") -> Callable:
    """Decorator for a stage's task function: SkidbenchError -> one line on stderr, exit 2. The config is
    checked against the declared schema first. With ``home`` (a config with a ``source``), the dataset's
    identity is printed and its folder checked (:func:`skidbench.pipeline.datasets.identity.open_home`), and
    the
    stage refuses to run when a stage it reads from failed on its last run
    (:func:`skidbench.pipeline.core.cache.check_producers`). When the stage fails, a dataset folder it leaves
    holding no data is removed (so ``skidbench datasets`` never lists it); a stage of ``LOCAL_PRODUCERS``
    that changed nothing in the folder (refused before its first write) while what it made before is
    still current leaves the dataset as it was;
    otherwise the failure is recorded, and the stages downstream refuse to run until this one succeeds.

    Exit statuses (pipeline/core/errors.py): a :class:`PartialFailure` (the stage ran to its end, some of its
    runs failed) prints its summary and exits 3 without marking the stage failed. Ctrl-C prints one line
    (``interrupted``: what the stage did about it) and exits 130, no traceback; the stage is marked failed
    unless ``runs`` (its outputs are runs that record their own status, e.g. evaluate's MLflow runs marked
    KILLED: what finished before the interrupt stays valid)."""

    # as Hydra's docs register resolvers: in the app, before @hydra.main composes (`python -m <app>` too)
    register_resolvers()

    def deco(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            from skidbench.pipeline.core.cache import (
                LOCAL_PRODUCERS,
                StaleInputError,
                check_producers,
                clear_failed,
                data_state,
            )
            from skidbench.pipeline.datasets.imported import check_stage

            root = before = None
            register_resolvers()  # a sweep's job may run in a process that did not start at main()
            try:
                cfg = args[0] if args else None
                if hasattr(cfg, "get"):  # a sweep's job or an in-process call: not checked by _preflight
                    validate(cfg)
                if home and hasattr(cfg, "get") and cfg.get("source") is not None and "dataset" in cfg:
                    from skidbench.pipeline.datasets.identity import home_from_cfg, open_home

                    root = open_home(home_from_cfg(cfg), name)[0].root
                    check_producers(root, name)
                    check_stage(cfg.get("robot"), name, root)  # imported: frozen splits, the bundle's robot
                    before = data_state(root) if name in LOCAL_PRODUCERS else None
                result = fn(*args, **kwargs)
            except StaleInputError as exc:  # this stage did not run: nothing of it to record
                exit_with_error(str(exc), name)
            except PartialFailure as exc:  # what succeeded is valid: downstream stages may use it
                if root is not None:
                    clear_failed(root, name)
                print(f"skidbench {name}: {exc}", file=sys.stderr, flush=True)
                sys.exit(EXIT_PARTIAL)
            except KeyboardInterrupt:
                if not runs:
                    _after_failure(root, name, "interrupted (Ctrl-C)", before)
                note = (
                    f"; {interrupted}" if interrupted else "; re-run it to complete what it had not written"
                )
                print(f"\nskidbench {name}: interrupted (Ctrl-C){note}", file=sys.stderr, flush=True)
                sys.exit(EXIT_INTERRUPTED)
            except SkidbenchError as exc:
                _after_failure(root, name, str(exc), before)
                exit_with_error(str(exc), name)
            except SystemExit as exc:  # a stage that exits by itself: a failure unless its status is 0
                if exc.code not in (0, None):
                    _after_failure(root, name, f"exit status {exc.code}", before)
                raise
            except BaseException as exc:  # a bug or an interrupt: what was written may be partial too
                _after_failure(root, name, f"{type(exc).__name__}: {exc}", before)
                raise
            if root is not None:
                clear_failed(root, name)
            return result

        return wrapper

    return deco


def _after_failure(root: Path | None, name: str, message: str, before: dict | None = None) -> None:
    """A failed stage: remove its dataset folder when it holds no data (only ``dataset.json``); leave it
    as it was when the stage changed none of its files (``before``: :func:`data_state` when it started)
    and what it made before is still current (:func:`inputs_changed`); else record the failure for the
    stages downstream."""
    if root is None or not root.is_dir():
        return
    from skidbench.pipeline.core.cache import data_state, inputs_changed, mark_failed
    from skidbench.pipeline.datasets.identity import holds_data

    if not holds_data(root):
        remove_atomic(root)
        return
    if before is not None and data_state(root) == before and inputs_changed(root, name) is None:
        log.info("%s failed before writing anything: %s is as it was", name, root)
        return
    mark_failed(root, name, one_line(message))


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
    register_resolvers()  # before the override check and Hydra compose (and resolve) the stage's config
    args = [FLAGS.get(name, {}).get(a, a) for a in argv[1:]]  # `--reap` -> reap=true
    multirun = any(a in ("-m", "--multirun") for a in args)
    args = _preflight(name, [as_string(a, multirun) for a in positional_overrides(name, fn, args)])
    sys.argv = [f"skidbench {name}", *args]
    register_launchers()
    fn()


def _preflight(name: str, args: list[str]) -> list[str]:
    """Before Hydra runs (and writes anything): overrides checked (an unknown or misspelt key, or a bad
    group option -> one line naming it and the nearest valid keys), another stage's settings dropped
    with a note (so one ``ARGS`` serves every stage), every value checked against the declared schema
    (:mod:`skidbench.pipeline.cli.config_schema`) and the output root checked writable. Returns the
    arguments to hand to Hydra; a problem is one line on stderr, exit 2."""
    from skidbench.pipeline.cli.overrides import check_overrides, parse_value

    try:
        dropped, cfg = check_overrides(name, args)
        for line in dropped:
            key, value = parse_value(line)
            check_value(key, value)  # another stage's setting is still checked
            note = f"skidbench {name}: note: {key} is another stage's setting; {name} ignores it"
            print(note, file=sys.stderr)
        if cfg is not None:
            validate(cfg)
            check_out_root(cfg)
    except SkidbenchError as exc:
        print(f"skidbench {name}: error: {one_line(str(exc))}", file=sys.stderr, flush=True)
        sys.exit(2)
    kept = list(args)
    for line in dropped:
        kept.remove(line)
    return kept


def positional_overrides(name: str, fn: Callable, args: list[str]) -> list[str]:
    """The arguments of a stage that takes positional ones (``skidbench export <dataset> <dir>``) as Hydra
    overrides. The stage's main declares them: ``fn.positional`` = (the keys the positional arguments set,
    in order; ``{"--flag": key}`` for flags that take a value). A positional ``dataset`` also sets
    ``robot=<the dataset's robot>`` (from its manifest) unless ``robot=`` is given. Other arguments pass
    through. A missing or extra argument is one line with the usage, exit 2."""
    spec = getattr(fn, "positional", None)
    if not spec or any(a in ("-h", "--help", "--cfg", "-c", "--info") for a in args):
        return args
    keys, flags = spec
    out, given = [], []
    it = iter(args)
    for a in it:
        flag, eq, value = a.partition("=")
        if flag in flags:
            value = value if eq else next(it, None)
            if value is None:
                exit_with_error(f"{flag} needs a value; usage: {_positional_usage(name, keys, flags)}", name)
            out.append(f"{flags[flag]}={_quoted(value)}")
        elif "=" in a or a.startswith("-"):
            out.append(a)
        else:
            given.append(a)
    set_keys = {o.split("=", 1)[0].lstrip("+~") for o in out}
    wanted = [k for k in keys if k not in set_keys]
    if len(given) != len(wanted):
        what = "missing" if len(given) < len(wanted) else f"unexpected {given[len(wanted)]!r}"
        exit_with_error(f"{what} argument; usage: {_positional_usage(name, keys, flags)}", name)
    out += [f"{k}={_quoted(v)}" for k, v in zip(wanted, given, strict=True)]
    if "dataset" in wanted and "robot" not in set_keys:
        robot = _dataset_robot(out, given[wanted.index("dataset")])
        if robot:
            out.append(f"robot={robot}")
    return out


def _positional_usage(name: str, keys, flags) -> str:
    words = [f"<{k.split('.')[-1]}>" for k in keys] + [f"{f} <{k.split('.')[-1]}>" for f, k in flags.items()]
    return f"skidbench {name} {' '.join(words)} [key=value ...]"


def _quoted(value: str) -> str:
    """A value as a Hydra override reads it back unchanged (quoted when it holds grammar characters)."""
    if re.fullmatch(r"[A-Za-z0-9_./:+@~-]+", value):
        return value
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def as_string(arg: str, multirun: bool = False) -> str:
    """An override of a key the schema declares a string (:mod:`.config_schema`) whose value Hydra would
    read as a number or a boolean (``score.name=nan``, ``score.date=2026``, ``bundle.name=1e3``), or outside
    a multirun as a sweep (``score.description=fast, small``), quoted: the text as given. Any other override
    passes through as it is."""
    key, eq, value = arg.partition("=")
    spec = spec_for(key.lstrip("+")) if eq and not key.startswith(("~", "-")) else None
    if spec is None or spec.kind != "str" or value[:1] in ("'", '"'):
        return arg
    if not (_NOT_TEXT.fullmatch(value.strip()) or ("," in value and not multirun)):
        return arg
    return f"{key}='" + value.replace("'", "\\'") + "'"


#: what Hydra's override grammar reads as a number or a boolean, not as text
_NOT_TEXT = re.compile(r"[+-]?(\d[\d_]*\.?[\d_]*|\.\d[\d_]*)([eE][+-]?\d+)?|[+-]?inf|nan|true|false", re.I)


def _dataset_robot(overrides: list[str], dataset: str) -> str | None:
    """The robot of ``<out_root>/<dataset>/raw/manifest.json`` when it has a packaged config, else None."""

    root = next((o.split("=", 1)[1].strip("'") for o in overrides if o.startswith("out_root=")), None)
    manifest = Path(root or default_out_root()).expanduser() / dataset / "raw" / "manifest.json"
    try:
        robot = str(json.loads(manifest.read_text()).get("robot") or "")
    except (OSError, ValueError, AttributeError):
        return None
    return robot if robot and (files("skidbench.conf") / "robot" / f"{robot}.yaml").is_file() else None


def check_out_root(cfg) -> None:
    """ConfigError when ``out_root`` cannot be created or written (a read-only file system, no
    permission): Hydra would otherwise fail with a traceback creating its run folder there."""
    try:
        root = Path(str(cfg.out_root)).expanduser().absolute()
    except Exception:  # noqa: BLE001 - an unresolvable out_root is reported by the stage
        return
    probe = root
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    reason = None
    if not probe.is_dir():
        reason = f"{probe} is not a folder"
    elif not os.access(probe, os.W_OK | os.X_OK):
        reason = os.strerror(errno.EACCES)
    else:
        try:  # os.access does not see a read-only mount
            fd, tmp = tempfile.mkstemp(prefix=".skidbench-probe-", dir=probe)
            os.close(fd)
            os.unlink(tmp)
        except OSError as exc:
            reason = exc.strerror or str(exc)
    if reason:
        raise ConfigError(
            f"out_root={root}: cannot write there ({reason}); "
            "set out_root=<a writable folder> (or SKIDBENCH_OUT)"
        )


if __name__ == "__main__":
    main()
