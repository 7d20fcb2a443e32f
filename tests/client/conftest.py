"""Fixtures of the client's tests."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

CHECKERBOARD = Path(__file__).resolve().parents[2] / "scenes" / "checkerboard.py"


@pytest.fixture(scope="session")
def checkerboard():
    """``checkerboard(checks, light, dark)``: the foreign material of scenes/checkerboard.py, an
    ``onnx.ModelProto`` written with onnx.helper alone (no neumip metadata, no query groups)."""
    spec = importlib.util.spec_from_file_location("checkerboard", CHECKERBOARD)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.checkerboard
