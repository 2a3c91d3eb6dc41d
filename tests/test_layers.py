"""The layers of the package run one way (CONTRIBUTING.md, "Layers"): every import, including one inside a
function, goes to the same layer or one below, and no two modules import each other in a circle.

    core        pipeline/{errors,geometry,io,cache,layout,manifest,schema,robot,protocol,constants}
    stages      the rest of pipeline/ (simulate, extract, groundtruth, splits, sources, calibration, ...)
    models      models/
    benchmark   benchmark/ (evaluation, tracking, comparison, discovery)
    apps        every stage's Hydra entry point (``app.py``, ``*_app.py``), ``pipeline/cli.py`` and the stage
                plumbing beside it (``pipeline/stage.py``, ``pipeline/overrides.py``)

The check reads the source (``ast``), so it also sees imports that a test run would never execute.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "models", "benchmark")
CORE = {"errors", "geometry", "io", "cache", "layout", "manifest", "schema", "robot", "protocol", "constants"}
#: modules of the app layer by their dotted name below ``skidbench.`` (beside every ``*_app``)
APP_MODULES = {"pipeline.cli", "pipeline.api", "pipeline.overrides", "pipeline.stage", "models.app"}
RANK = {"core": 0, "stages": 1, "models": 2, "benchmark": 3, "apps": 4}


def module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer(mod: str) -> str | None:
    """The layer of a module named below ``skidbench.`` (``pipeline.io``), None if not ours."""
    parts = mod.split(".")
    if parts[0] not in PACKAGES:
        return None
    if mod in APP_MODULES or parts[-1] == "app" or parts[-1].endswith("_app"):
        return "apps"
    if parts[0] == "pipeline":
        return "core" if len(parts) == 2 and parts[1] in CORE else "stages"
    return parts[0]


def our_modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for p in sorted((REPO / pkg).rglob("*.py")):
            mods[module_name(p)] = p
    return mods


def imports_of(mod: str, path: Path, known: set[str]) -> list[tuple[int, str]]:
    """(line, imported module below ``skidbench.``) for every import of our package in ``path``."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    found = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = base[: len(base) - (node.level - 1)]
                target = ".".join(anchor + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = [target] + [f"{target}.{a.name}" for a in node.names]
        for n in names:
            n = n.removeprefix("skidbench.")
            if n.split(".")[0] not in PACKAGES:
                continue
            # the longest of our modules that the name starts with (``from .x import func`` -> ``x``)
            while n and n not in known:
                n = n.rpartition(".")[0]
            if n and n != mod:
                found.append((node.lineno, n))
    return sorted(set(found))


@pytest.fixture(scope="module")
def graph() -> dict[str, list[tuple[int, str]]]:
    mods = our_modules()
    known = set(mods)
    return {m: imports_of(m, p, known) for m, p in mods.items()}


def test_every_import_goes_down_or_stays_in_its_layer(graph):
    upward = []
    for mod, deps in graph.items():
        for line, dep in deps:
            a, b = layer(mod), layer(dep)
            if a and b and RANK[b] > RANK[a]:
                upward.append(f"{mod.replace('.', '/')}.py:{line} ({a}) imports {dep} ({b})")
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_no_import_cycles(graph):
    # a package __init__ that only re-exports is not an edge back into its package
    edges = {m: {d for _, d in deps} for m, deps in graph.items()}
    cycles, state = [], {}

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(edges.get(m, ())):
            if d.startswith(m + ".") or m.startswith(d + "."):  # a package and its own modules
                continue
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d) :] + [d]) if d in stack else f"{m} -> {d}")
            elif not state.get(d):
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(edges):
        if not state.get(m):
            visit(m, [m])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_the_check_sees_imports_inside_functions(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("def f():\n    from skidbench.benchmark import evaluate\n")
    assert imports_of("models.x", src, {"benchmark.evaluate"}) == [(2, "benchmark.evaluate")]
    assert layer("models.x") == "models" and layer("benchmark.evaluate") == "benchmark"
    assert layer("pipeline.io") == "core" and layer("pipeline.calibrate_app") == "apps"


def test_the_installed_package_never_imports_the_perf_harness():
    """``perf/`` (``make bench``) sits outside the installed package: an import of it from the package
    would work in a checkout and fail in an installed copy."""
    found = []
    for mod, path in our_modules().items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or ""]
            else:
                continue
            found += [f"{mod}:{node.lineno} imports {n}" for n in names if n.split(".")[0] == "perf"]
    assert not found, "\n".join(found)


#: the benchmark's pure modules: scoring and its metrics (no MLflow, no files, no figures); of the benchmark
#: layer they import only each other, so that a server, a notebook or a test can score without a store
PURE = {"benchmark.horizon", "benchmark.metrics", "benchmark.scoring", "benchmark.intervals"}
IMPURE_LIBS = {"mlflow", "matplotlib", "pyarrow", "ray", "hydra", "omegaconf"}


def test_scoring_and_metrics_are_pure(graph):
    found = []
    for mod in sorted(PURE):
        path = REPO / (mod.replace(".", "/") + ".py")
        found += [f"{mod}:{line} imports {dep} ({layer(dep)})" for line, dep in graph[mod]
                  if layer(dep) == "benchmark" and dep not in PURE]  # fmt: skip
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import | ast.ImportFrom) and not getattr(node, "level", 0):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                found += [f"{mod}:{node.lineno} imports {n}" for n in names if n.split(".")[0] in IMPURE_LIBS]
            if isinstance(node, ast.Name) and node.id == "open":
                found.append(f"{mod}:{node.lineno} opens a file")
    assert not found, "\n".join(found)
