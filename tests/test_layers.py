"""The layers point one way: `neumip.core` imports nothing from client, server or training, and the
engines (`neumip.client.local`, `neumip.client.kernel`, `neumip.server.*`, and every neumip module they
reach) import nothing from `neumip.training`.

Read statically from the source files (every ``import`` statement, those inside functions included,
relative ones resolved), so an import that only runs on some path still counts; and checked in a fresh
interpreter that importing the client and the engines pulls in no torch.
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


def imported_names(module: str) -> set[str]:
    """Absolute names of everything `module` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    path = module_files()[module]
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            source = ".".join(base + ([node.module] if node.module else []))
            names |= {source} | {f"{source}.{alias.name}" for alias in node.names}
    return names


def neumip_imports(module: str) -> set[str]:
    """The neumip modules `module` imports."""
    return {name for name in imported_names(module) if name in module_files()}


def within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def engine_modules() -> list[str]:
    """The engines and every neumip module outside training they import, directly or through others."""
    todo = [m for m in module_files() if m in ("neumip.client.local", "neumip.client.kernel")
            or within(m, "neumip.server")]
    seen = set()
    while todo:
        module = todo.pop()
        if module not in seen and not within(module, "neumip.training"):
            seen.add(module)
            todo += neumip_imports(module)
    return sorted(seen)


def test_the_reader_sees_relative_and_function_level_imports():
    """The check below would pass vacuously if the reader missed imports: these are known ones."""
    assert "neumip.core.errors.NeumipError" in imported_names("neumip.core.contract")  # from .errors import ...
    assert "neumip.client.kernel" in neumip_imports("neumip.server.engine")  # inside Engine.kernel
    assert {"neumip.client.local", "neumip.server.app", "neumip.core.contract"} <= set(engine_modules())


@pytest.mark.parametrize("module", sorted(m for m in module_files() if within(m, "neumip.core")))
def test_core_imports_nothing_from_the_areas_above_it(module):
    above = {name for name in imported_names(module)
             if any(within(name, f"neumip.{area}") for area in ("client", "server", "training"))}
    assert not above, f"{module} imports {sorted(above)}"


@pytest.mark.parametrize("module", engine_modules())
def test_engines_import_nothing_from_training(module):
    training = {name for name in imported_names(module) if within(name, "neumip.training")}
    assert not training, f"{module} imports {sorted(training)}"


def test_importing_the_client_and_the_server_pulls_in_no_torch():
    code = (
        "import sys, neumip.client, neumip.core.contract, neumip.core.weights, neumip.client.local, "
        "neumip.client.http, neumip.client.cli, neumip.server.app;"
        "assert 'torch' not in sys.modules, 'torch imported';"
        "assert 'mitsuba' not in sys.modules, 'mitsuba imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
