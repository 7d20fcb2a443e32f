"""Importing the plugins keeps a JIT variant the user already set (a fresh process each)."""

from __future__ import annotations

import subprocess
import sys

import pytest

IMPORT = """
from neumip.client.mitsuba.runtime import import_mitsuba
mi = import_mitsuba({variant!r})
import neumip.client.mitsuba.bsdf, neumip.client.mitsuba.integrator
print(mi.variant())
"""


@pytest.mark.parametrize(
    ("variant", "expected"),
    [("llvm_ad_mono", "llvm_ad_mono"), ("llvm_ad_spectral", "llvm_ad_spectral"), ("scalar_rgb", "llvm_ad_rgb")],
)
def test_plugins_keep_a_set_jit_variant(variant, expected):
    out = subprocess.run(
        [sys.executable, "-c", IMPORT.format(variant=variant)], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-1] == expected
