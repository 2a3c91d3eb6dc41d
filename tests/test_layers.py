"""The layers of the package run one way (CONTRIBUTING.md, "Layers"): every import, including one inside a
function, goes to the same layer or one below, and no two modules import each other in a circle. The layers
are read from the folders, never from a list of file names:

    core        pipeline/core/
    stages      every other sub-package of pipeline/ (simulate, extract, groundtruth, splits, sources,
                calibrate, datasets, runner)
    models      models/
    benchmark   benchmark/ (scoring, evaluate, tracking, board, report, release, discovery)
    apps        pipeline/cli/ and every stage's Hydra entry point (``app.py``, ``*_app.py``)

Inside the benchmark, ``benchmark/scoring/`` is pure maths: it never opens a file, never imports MLflow,
plotting or a store, and of the benchmark imports only itself and ``benchmark/errors.py``. The check reads
the source (``ast``), so it also sees imports that a test run would never execute.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "models", "benchmark")
RANK = {"core": 0, "stages": 1, "models": 2, "benchmark": 3, "apps": 4}


def module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer(mod: str) -> str | None:
    """The layer of a module named below ``skidbench.`` (``pipeline.core.io``), None if not ours: its
    folder decides, and an ``app`` / ``*_app`` module is an app wherever it sits."""
    parts = mod.split(".")
    if parts[0] not in PACKAGES:
        return None
    if parts[-1] == "app" or parts[-1].endswith("_app") or parts[:2] == ["pipeline", "cli"]:
        return "apps"
    if parts[0] == "pipeline":
        return "core" if parts[:2] == ["pipeline", "core"] else "stages"
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
    assert layer("pipeline.core.io") == "core" and layer("pipeline.calibrate.app") == "apps"
    assert layer("pipeline.cli.overrides") == "apps" and layer("pipeline.splits.build") == "stages"


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


#: libraries the pure scoring maths must not import: a store, figures, files' formats, configuration
IMPURE_LIBS = {"mlflow", "matplotlib", "pyarrow", "ray", "hydra", "omegaconf", "json", "pickle", "shutil"}
#: calls that read or write a file (``open`` itself, and the readers and writers of pandas, NumPy, pathlib)
FILE_CALLS = {
    "open",
    "read_parquet",
    "to_parquet",
    "read_csv",
    "to_csv",
    "read_text",
    "write_text",
    "read_bytes",
    "write_bytes",
    "load",
    "save",
    "savez",
    "loadtxt",
    "savetxt",
    "read_table",
}
SCORING = "benchmark.scoring"
#: what scoring may import of the benchmark: itself and the benchmark's exception
SCORING_MAY_IMPORT = ("benchmark.scoring", "benchmark.errors")


def impurities(mod: str, path: Path, deps: list[tuple[int, str]]) -> list[str]:
    """Why ``mod`` (a module of benchmark/scoring/) is not pure: each import of the benchmark outside
    scoring, of an impure library or of the pipeline's file I/O, and each call that opens a file."""
    found = [f"{mod}:{line} imports {dep}" for line, dep in deps
             if (layer(dep) == "benchmark" and not dep.startswith(SCORING_MAY_IMPORT))
             or dep == "pipeline.core.io"]  # fmt: skip
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import | ast.ImportFrom) and not getattr(node, "level", 0):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            found += [f"{mod}:{node.lineno} imports {n}" for n in names if n.split(".")[0] in IMPURE_LIBS]
        if isinstance(node, ast.Call):
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
            if name in FILE_CALLS:
                found.append(f"{mod}:{node.lineno} calls {name}() (a file)")
    return found


def test_scoring_is_pure_maths(graph):
    mods = our_modules()
    scoring = sorted(m for m in mods if m == SCORING or m.startswith(SCORING + "."))
    assert len(scoring) >= 5, scoring  # the folder is there and holds the maths
    found = [f for m in scoring for f in impurities(m, mods[m], graph[m])]
    assert not found, "\n".join(found)


@pytest.mark.parametrize(
    "body",
    [
        "import mlflow\n",
        "def f(p):\n    return open(p).read()\n",
        "import pandas as pd\nx = pd.read_parquet('w')\n",
        "from skidbench.benchmark.tracking import store\n",
    ],
)
def test_the_purity_check_fails_a_scoring_module_that_opens_a_file_or_imports_mlflow(tmp_path, body):
    src = tmp_path / "bad.py"
    src.write_text(body)
    mod = "benchmark.scoring.bad"
    deps = imports_of(mod, src, {"benchmark.tracking.store", "benchmark.scoring"})
    assert impurities(mod, src, deps), body


def test_every_folder_of_the_package_is_a_concern_of_at_most_eleven_modules():
    """``ls`` of a top folder tells its concerns: each sub-package holds one, small enough to read."""
    tall = {}
    for pkg in PACKAGES:
        for init in (REPO / pkg).rglob("__init__.py"):
            n = len([p for p in init.parent.glob("*.py") if p.name != "__init__.py"])
            if init.parent != REPO / pkg and n > 11:
                tall[str(init.parent.relative_to(REPO))] = n
    assert not tall, tall


def test_every_sub_package_is_installed():
    """A folder that is a package but missing from pyproject.toml's ``packages`` works in a checkout (an
    editable install maps the top folders) and is absent from an installed copy."""
    import tomllib

    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {
        "skidbench." + ".".join(init.parent.relative_to(REPO).parts)
        for pkg in PACKAGES
        for init in (REPO / pkg).rglob("__init__.py")
    }
    assert not on_disk - listed, sorted(on_disk - listed)
