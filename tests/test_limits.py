"""The rooms stay small and the config stays at the door (issue 31, CONTRIBUTING.md "Layers"):

- no module of ``pipeline/``, ``models/``, ``benchmark/`` over :data:`MAX_MODULE_LINES` lines;
- no function over :data:`MAX_FUNCTION_LINES` lines, except numba kernels (``@njit``: one compiled loop
  reads best whole, and a call between kernels costs);
- no function outside the app layer (tests/test_layers.py) with a parameter named ``cfg``: an app turns
  the Hydra config into the small settings a library function takes (``HorizonConfig`` shows the shape).
  A converter named ``from_cfg`` / ``*_from_cfg`` is that door and may take it.

Each allow-list names what is over today and why; it only shrinks (a test fails when an entry is no longer
needed, so a fixed one is removed with its fix).
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

from test_layers import PACKAGES, REPO, layer, module_name

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80

#: module -> why it is still over MAX_MODULE_LINES
LONG_MODULES: dict[str, str] = {}

#: module:function -> why it is still over MAX_FUNCTION_LINES
LONG_FUNCTIONS: dict[str, str] = {}

#: module:function taking ``cfg`` outside the app layer (to become settings objects; issue 31 item 4)
CFG_TAKERS: set[str] = set()


def _files() -> list[Path]:
    return [p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))]


@functools.cache
def _tree(p: Path) -> ast.Module:
    return ast.parse(p.read_text(), str(p))


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield node


def _is_numba_kernel(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    for d in fn.decorator_list:
        name = ast.unparse(d.func if isinstance(d, ast.Call) else d)
        if name.split(".")[-1] in {"njit", "jit", "vectorize", "guvectorize"}:
            return True
    return False


def test_no_module_over_the_line_limit():
    over = {}
    for p in _files():
        n = len(p.read_text().splitlines())
        if n > MAX_MODULE_LINES:
            over[str(p.relative_to(REPO))] = n
    assert set(over) - set(LONG_MODULES) == set(), f"modules over {MAX_MODULE_LINES} lines: {over}"
    fixed = set(LONG_MODULES) - set(over)
    assert not fixed, f"no longer over the limit, remove from LONG_MODULES: {sorted(fixed)}"


def test_no_function_over_the_line_limit():
    over = {}
    for p in _files():
        for fn in _functions(_tree(p)):
            n = fn.end_lineno - fn.lineno + 1
            if n > MAX_FUNCTION_LINES and not _is_numba_kernel(fn):
                over[f"{p.relative_to(REPO)}:{fn.name}"] = n
    assert set(over) - set(LONG_FUNCTIONS) == set(), f"functions over {MAX_FUNCTION_LINES} lines: {over}"
    fixed = set(LONG_FUNCTIONS) - set(over)
    assert not fixed, f"no longer over the limit, remove from LONG_FUNCTIONS: {sorted(fixed)}"


def test_library_functions_do_not_take_the_config():
    takers = set()
    for p in _files():
        mod = module_name(p)
        if layer(mod) == "apps":
            continue
        for fn in _functions(_tree(p)):
            a = fn.args
            params = {x.arg for x in a.posonlyargs + a.args + a.kwonlyargs}
            if "cfg" in params and not (fn.name == "from_cfg" or fn.name.endswith("_from_cfg")):
                takers.add(f"{mod}:{fn.name}")
    new = takers - CFG_TAKERS
    assert not new, (
        f"library functions taking the whole config (take a settings object instead): {sorted(new)}"
    )
    fixed = CFG_TAKERS - takers
    assert not fixed, f"no longer take cfg, remove from CFG_TAKERS: {sorted(fixed)}"
