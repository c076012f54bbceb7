"""The package's layering keeps itself: imports only look down, no cycles, short functions.

Layers, bottom-up (docs/architecture.md draws them):

    0 core        errors, atomic files, units and frames conventions
    1 sign        signpose.frontend.sign: the sign definition
    2 frontend    signpose.frontend.*      |  maps  signpose.maps.*
    3 estimator   signpose.estimator.*
    4 io          signpose.io.*: one module per file format
    5 sim         signpose.sim.*: simulated flights
    6 training    signpose.training.*: offline cascade training
    7 app         signpose.pipeline, signpose.batch, signpose.plots, signpose.report_html,
                  signpose.fingerprint
    8 cli         signpose.cli.*

A module may import its own subpackage or any lower layer, never a higher one
nor a sibling of its own layer (frontend and maps do not import each other).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import signpose

MAX_FUNCTION_LINES = 80
APP_LAYER = 7  # pipeline, batch and plots are one floor: they may import each other

LAYERS: tuple[tuple[str, int], ...] = (
    ("signpose.frontend.sign", 1),
    ("signpose.core", 0),
    ("signpose.frontend", 2),
    ("signpose.maps", 2),
    ("signpose.estimator", 3),
    ("signpose.io", 4),
    ("signpose.sim", 5),
    ("signpose.training", 6),
    ("signpose.pipeline", 7),
    ("signpose.batch", 7),
    ("signpose.plots", 7),
    ("signpose.fingerprint", 7),
    ("signpose.report_html", 7),
    ("signpose.cli", 8),
)


def _package_files() -> dict[str, Path]:
    """Installed module name -> source file, for every module of the package."""
    roots = {"signpose": Path(signpose.__file__).parent}
    for sub in ("frontend", "maps", "estimator"):
        module = __import__(f"signpose.{sub}", fromlist=["_"])
        roots[f"signpose.{sub}"] = Path(module.__file__).parent
    files: dict[str, Path] = {}
    for prefix, root in roots.items():
        for path in root.rglob("*.py"):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            name = ".".join([prefix, *parts])
            files.setdefault(name, path)
    return files


FILES = _package_files()


def layer_of(module: str) -> tuple[str, int]:
    """(subpackage, layer) of a module of the package."""
    if module == "signpose":
        return "signpose", 0
    for prefix, layer in LAYERS:
        if module == prefix or module.startswith(prefix + "."):
            return ("app" if layer == APP_LAYER else prefix), layer
    raise AssertionError(f"{module} belongs to no layer: add it to LAYERS and the docs")


def _resolve(module: str, node: ast.ImportFrom | ast.Import) -> list[str]:
    """Project modules named by one import statement."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:
            base = ".".join(module.split(".")[: -node.level] + ([base] if base else []))
        names = [base] + [f"{base}.{alias.name}" for alias in node.names]
    out = []
    for name in names:
        while name and name not in FILES:
            name = name.rpartition(".")[0]
        if name:
            out.append(name)
    return out


def _imports(module: str) -> tuple[set[str], list[str]]:
    """(project modules imported anywhere, project imports found inside functions)."""
    tree = ast.parse(FILES[module].read_text(encoding="utf-8"))
    found: set[str] = set()
    inner: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            for sub in ast.walk(node):
                if isinstance(sub, ast.Import | ast.ImportFrom) and _resolve(module, sub):
                    inner.append(f"{module}:{sub.lineno}")
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.update(name for name in _resolve(module, node) if name != module)
    return found, inner


GRAPH = {module: _imports(module)[0] for module in FILES}


def test_the_package_has_every_layer():
    layers = {layer_of(module)[1] for module in FILES}
    assert layers == set(range(9))


def forbidden_imports(module: str, imported: set[str]) -> list[str]:
    """The imports of ``module`` that run upward or sideways."""
    own, layer = layer_of(module)
    bad = []
    for name in sorted(imported - {"signpose"}):
        their, their_layer = layer_of(name)
        if their_layer > layer or (their_layer == layer and their != own):
            bad.append(f"{name} (layer {their_layer})")
    return bad


@pytest.mark.parametrize("module", sorted(FILES))
def test_imports_only_look_down(module):
    bad = forbidden_imports(module, GRAPH[module])
    assert not bad, f"{module} (layer {layer_of(module)[1]}) imports upward or sideways: {bad}"


def test_the_package_root_imports_nothing_of_the_project():
    assert GRAPH["signpose"] <= set()


def test_no_import_cycles():
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for nxt in sorted(GRAPH[module]):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt) :] + [nxt] if nxt in path else [module, nxt])
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[module] = 2

    for module in sorted(GRAPH):
        if module not in state:
            visit(module, [module])
    assert not cycles, f"import cycles: {cycles}"


def test_project_imports_are_at_module_level():
    inner = [where for module in FILES for where in _imports(module)[1]]
    assert not inner, f"imports of the project inside functions: {inner}"


def test_no_function_longer_than_the_limit():
    long = []
    for module, path in FILES.items():
        if module.startswith("signpose.cli"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"{module}.{node.name} ({lines})")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {sorted(long)}"


def test_the_checker_sees_an_upward_and_a_sideways_import():
    # The rule itself can fail: frontend importing the estimator runs upward,
    # frontend importing maps runs sideways; its own subpackage and lower floors pass.
    assert forbidden_imports("signpose.frontend.decoder", {"signpose.estimator.camera"})
    assert forbidden_imports("signpose.frontend.decoder", {"signpose.maps.loader"})
    assert not forbidden_imports(
        "signpose.frontend.decoder", {"signpose.frontend.homography", "signpose.core.errors"}
    )
