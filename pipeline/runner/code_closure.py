"""The skidbench code a module runs: its source file and those of the skidbench modules it imports,
transitively (the import graph, read from the source with ``ast``; nothing is imported to read it).

A model's code digest (pipeline/runner/environment.py ``code_identity``) covers exactly these files, so an
edit of one model's module refits and rescores that model and the models that import it, not every model:
``ideal`` (models/kinematic/ideal.py) runs none of models/friction/, the friction model does; both run
models/base.py, so an edit there refits both.

What counts as an import of a module (each one followed, whether it runs or not):

- ``import skidbench.a.b`` and ``from skidbench.a import b`` (``skidbench.a``, and ``skidbench.a.b`` when
  it is a module), relative ones resolved against the module's package, at the top of the file, inside a
  function or under ``if TYPE_CHECKING``;
- ``importlib.import_module("skidbench....")`` and ``__import__`` with a literal name;
- the packages above a module (importing ``skidbench.models.friction.model`` runs
  ``skidbench/models/__init__.py`` and ``skidbench/models/friction/__init__.py``);
- the classes a module loads by name from an entry-point group: a module that declares
  ``LOADS_ENTRY_POINTS = "<group>"`` (models/registry/plugins.py: the model classes of ``skidbench.models``)
  runs the module of each of the group's entry points that skidbench itself provides. A dynamics model on a
  kinematic base loads its base through the registry, so its digest covers every built-in model. Plugins'
  entry points are not followed: a plugin's edit refits that plugin alone (a built-in model configured to
  run on a plugin's model, ``+model.base=<plugin>``, is not refitted by it: ``force=true``).

Only modules under ``skidbench.`` are followed; libraries are recorded by version (``environment``).
Reading a file's imports is memoised by its content hash and a module's file by its name: asking again
costs a ``stat`` per file."""

from __future__ import annotations

import ast
import functools
import importlib.metadata as md
import importlib.util
from collections.abc import Callable, Iterable
from pathlib import Path

PREFIX = "skidbench."
#: the module-level name by which a module says it loads the classes of an entry-point group by name
LOADS = "LOADS_ENTRY_POINTS"

#: path -> (content hash, the absolute module names it imports, the entry-point groups it loads)
_parsed: dict[str, tuple[str, frozenset[str], frozenset[str]]] = {}


@functools.cache
def module_file(name: str) -> Path | None:
    """The source file of module ``name``, or None when ``name`` is not a module (a class imported from
    one, a module that is not installed); found once per process (a module's file does not move while it
    runs; its content is hashed on every digest)."""
    try:
        spec = importlib.util.find_spec(name)
    except Exception:  # noqa: BLE001 - not a module (its parent is a module, not a package) or not importable
        return None
    if spec is None or not spec.has_location or not spec.origin:
        return None
    return Path(spec.origin)


def _resolve(node: ast.ImportFrom, package: str) -> str:
    if not node.level:
        return node.module or ""
    base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _literal(tree: ast.Module, name: str) -> str | None:
    """The string a module-level ``name = "..."`` (or ``name = OTHER`` with ``OTHER = "..."``) binds."""
    values: dict[str, ast.expr] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign | ast.AnnAssign) and node.value is not None:
            for t in node.targets if isinstance(node, ast.Assign) else [node.target]:
                if isinstance(t, ast.Name):
                    values[t.id] = node.value
    value = values.get(name)
    if isinstance(value, ast.Name):
        value = values.get(value.id)
    return value.value if isinstance(value, ast.Constant) and isinstance(value.value, str) else None


def source_imports(source: str, package: str) -> tuple[set[str], set[str]]:
    """(the absolute names ``source`` imports: modules and ``module.name`` of each name imported from one,
    the entry-point groups it declares it loads by name); ``package``: the package relative imports start
    from. A file that does not parse imports nothing (its own content is still digested)."""
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError):
        return set(), set()
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            mod = _resolve(node, package)
            names.add(mod)
            names.update(f"{mod}.{a.name}" for a in node.names if a.name != "*")
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if func in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                names.add(node.args[0].value)
    group = _literal(tree, LOADS)
    return {n for n in names if n}, {group} if group else set()


def _imports_of(path: Path, package: str, file_hash: Callable[[Path], str]) -> tuple[frozenset, frozenset]:
    digest = file_hash(path)
    hit = _parsed.get(str(path))
    if hit is None or hit[0] != digest:
        if path.suffix == ".py":
            names, groups = source_imports(path.read_text(encoding="utf-8", errors="replace"), package)
        else:
            names, groups = set(), set()
        hit = _parsed[str(path)] = (digest, frozenset(names), frozenset(groups))
    return hit[1], hit[2]


@functools.cache
def group_modules(group: str) -> list[str]:
    """The modules of the entry points of ``group`` that skidbench provides (its built-in models; read once
    per process: skidbench's own entry points change only with a new install)."""
    return sorted({ep.module for ep in md.entry_points(group=group) if ep.module.startswith(PREFIX)})


def _parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(2, len(parts))]


def closure(names: Iterable[str], file_hash: Callable[[Path], str]) -> dict[str, Path]:
    """``{module: source file}`` of the skidbench modules among ``names`` and every skidbench module they
    import, transitively (module docstring); ``file_hash``: the content hash of a file (memoised by the
    caller)."""
    files: dict[str, Path] = {}
    done: set[str] = set()
    todo = [n for n in names if n.startswith(PREFIX)]
    while todo:
        name = todo.pop()
        if name in done:
            continue
        done.add(name)
        path = module_file(name)
        if path is None:
            continue
        files[name] = path
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        imported, groups = _imports_of(path, package, file_hash)
        todo += _parents(name) + [n for n in imported if n.startswith(PREFIX)]
        for group in groups:
            todo += group_modules(group)
    return files
