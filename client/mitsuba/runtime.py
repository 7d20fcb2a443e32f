"""Import Mitsuba 3 safely: a libLLVM >= 16 found (`client.llvm`) *before* drjit loads one.

drjit's llvm backend aborts the whole process (no Python exception) when it loads LLVM 15 or older.
`import_mitsuba` checks LLVM first (`neumip.engines.llvm.ensure_llvm`) and raises `MitsubaUnavailable`
with an actionable message where Mitsuba cannot run.
"""

from __future__ import annotations

from neumip.engines.llvm import LLVMUnavailable, ensure_llvm

DEFAULT_VARIANT = "llvm_ad_rgb"


class MitsubaUnavailable(LLVMUnavailable):
    """Mitsuba or a usable LLVM is missing; the message says how to fix it."""


def import_mitsuba(variant: str = DEFAULT_VARIANT):
    """Check LLVM (for llvm variants) or a CUDA device (cuda variants), import mitsuba, set `variant`,
    return the module."""
    if variant.startswith("llvm"):
        try:
            ensure_llvm()
        except LLVMUnavailable as exc:
            raise MitsubaUnavailable(str(exc)) from None
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise MitsubaUnavailable("mitsuba is not installed: pip install 'neumip[render]'") from exc
    if variant.startswith("cuda"):
        import drjit as dr

        if not dr.has_backend(dr.JitBackend.CUDA):
            raise MitsubaUnavailable(f"Mitsuba variant {variant} needs an NVIDIA GPU and its driver (libcuda): "
                                     "drjit found no CUDA device here")
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi
