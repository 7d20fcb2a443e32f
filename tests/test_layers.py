"""The layers point one way, as ARCHITECTURE.md draws them: `LAYERS` is the table of allowed arrows.

Imports are read statically from the source files: every ``import`` statement, those inside functions
included, relative ones resolved, and every string that names a neumip module in a module that calls
`importlib` (the CLI loads its areas' commands by name). An import that only runs on some path still
counts. A fresh interpreter checks that importing the client, the engines and the server pulls in no
torch and no mitsuba.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

LAYERS = {
    "core": set(),
    "engines": {"core"},
    "client": {"core", "engines"},
    "server": {"core", "engines"},
    "groundtruth": {"core", "client"},
    "training": set(),
    "training.model": {"core", "groundtruth"},
    "training.export": {"core", "training.model"},
    "training.loop": {"core", "engines", "client", "groundtruth", "training.model", "training.export"},
    "report": {"core", "engines", "client", "groundtruth", "training.model", "training.export", "training.loop"},
    "cli": {"core", "engines", "client", "server", "groundtruth", "training", "training.model", "training.export",
            "training.loop", "report"},
}
"""Layer -> the layers its modules may import (besides their own). Nothing imports the CLI."""

PACKAGE_LAYERS = {
    "neumip.core": "core",
    "neumip.engines": "engines",
    "neumip.client": "client",
    "neumip.server": "server",
    "neumip.groundtruth": "groundtruth",
    "neumip.training": "training",
    "neumip.training.model": "training.model",
    "neumip.training.export": "training.export",
    "neumip.training.loop": "training.loop",
    "neumip.report": "report",
}
"""Package -> its layer (the longest match wins); `layer` puts command modules in "cli"."""


def layer(module: str) -> str:
    """The layer of a neumip module: "cli" for the entry point and every area's command modules."""
    leaf = module.rsplit(".", 1)[-1]
    if module == "neumip.client.cli" or leaf == "commands" or leaf.endswith("_command"):
        return "cli"
    package = max((p for p in PACKAGE_LAYERS if module == p or module.startswith(p + ".")), key=len)
    return PACKAGE_LAYERS[package]


@cache
def module_files() -> dict[str, Path]:
    """Every neumip module -> its source file, from pyproject's package-dir mapping."""
    mapping = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    files = {}
    for package, folder in mapping.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            files[".".join([package] + [p for p in parts if p != "__init__"])] = path
    return files


@cache
def imported_names(module: str) -> frozenset[str]:
    """Absolute names of everything `module` imports (``from a import b`` gives ``a`` and ``a.b``), and the
    neumip module names it holds as strings where it uses `importlib`."""
    path = module_files()[module]
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    tree = ast.parse(path.read_text(), str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            source = ".".join(base + ([node.module] if node.module else []))
            names |= {source} | {f"{source}.{alias.name}" for alias in node.names}
    if "importlib" in names:
        names |= {node.value for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in module_files()}
    return frozenset(names)


def neumip_imports(module: str) -> set[str]:
    """The neumip modules `module` imports (a package imported for one of its modules counts as that module)."""
    found = {name for name in imported_names(module) if name in module_files() and name != module}
    packages = {name for name in found if module_files()[name].name == "__init__.py"}
    return {name for name in found if name not in packages or not any(m.startswith(name + ".") for m in found)}


def arrows(module: str) -> set[tuple[str, str]]:
    """(imported module, its layer) for each import of `module` into another layer."""
    own = layer(module)
    return {(name, layer(name)) for name in neumip_imports(module) if layer(name) != own}


def cycles() -> list[list[str]]:
    """The import graph's strongly connected components of more than one module (Tarjan)."""
    graph = {m: neumip_imports(m) for m in module_files()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_reader_sees_relative_function_level_and_importlib_imports():
    """The checks below would pass vacuously if the reader missed imports: these are known ones."""
    assert "neumip.core.errors.NeumipError" in imported_names("neumip.core.contract")  # from .errors import ...
    assert "neumip.engines.kernel" in neumip_imports("neumip.server.engine")  # inside Engine.kernel
    assert "neumip.report.commands" in neumip_imports("neumip.client.cli")  # a name given to importlib
    assert layer("neumip.training.commands") == "cli" and layer("neumip.training.loop.train") == "training.loop"


def test_every_package_has_a_layer_and_every_layer_a_row():
    assert {layer(m) for m in module_files()} <= set(LAYERS)
    assert all(allowed <= set(LAYERS) for allowed in LAYERS.values())


@pytest.mark.parametrize("module", sorted(module_files()))
def test_imports_follow_the_table_of_layers(module):
    allowed = LAYERS[layer(module)]
    against = sorted(f"{name} ({to})" for name, to in arrows(module) if to not in allowed)
    assert not against, f"{module} ({layer(module)}) imports {against}"


def test_the_imports_have_no_cycle():
    assert not cycles()


def test_importing_the_client_the_engines_and_the_server_pulls_in_no_torch():
    code = (
        "import sys, neumip.client, neumip.core.contract, neumip.core.weights, neumip.engines.local, "
        "neumip.client.http, neumip.client.cli, neumip.server.app;"
        "assert 'torch' not in sys.modules, 'torch imported';"
        "assert 'mitsuba' not in sys.modules, 'mitsuba imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
