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


def test_render_variant_is_checked_before_it_is_set(tmp_path, capsys):
    """`neumip render --variant`: a CUDA variant without a CUDA device is one clear line (a fresh
    process, nothing set); another variant than the one this process already renders with is refused."""
    import drjit as dr

    from neumip.client import cli
    from neumip.client.mitsuba.bsdf import mi

    from .scenes import write_xml

    if not dr.has_backend(dr.JitBackend.CUDA):
        out = subprocess.run(
            [sys.executable, "-m", "neumip.client.cli", "render", write_xml(tmp_path), "-o", str(tmp_path / "a.png"),
             "--variant", "cuda_ad_rgb"], capture_output=True, text=True, timeout=120)
        assert out.returncode == 2, out.stderr[-2000:]
        assert "cuda_ad_rgb needs an NVIDIA GPU and its driver" in out.stderr
        assert not (tmp_path / "a.png").exists()
    other = "cuda_ad_rgb" if mi.variant() != "cuda_ad_rgb" else "llvm_ad_rgb"
    assert cli.main(["render", write_xml(tmp_path), "-o", str(tmp_path / "b.png"), "--variant", other]) == 2
    assert f"already renders with Mitsuba variant {mi.variant()}" in capsys.readouterr().err
