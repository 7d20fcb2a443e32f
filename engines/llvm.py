"""Find a libLLVM >= 16 *before* drjit loads one.

drjit's llvm backend aborts the whole process (no Python exception) when it loads LLVM 15 or older.
`ensure_llvm` looks for a suitable shared libLLVM first, points drjit at it through
``DRJIT_LIBLLVM_PATH``, and raises `LLVMUnavailable` with an actionable message otherwise. The
in-kernel engine (`engines/kernel.py`) and Mitsuba's import (`client/mitsuba/runtime.py`) call it.
"""

from __future__ import annotations

import glob
import logging
import os
import re
from pathlib import Path

from neumip.core.errors import NeumipError

log = logging.getLogger(__name__)

MIN_LLVM = 16
_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
)
_VERSION = re.compile(r"libLLVM(?:-|\.so\.)(\d+)")


class LLVMUnavailable(NeumipError, ImportError):
    """No usable libLLVM for drjit; the message says how to fix it."""


def llvm_version(path: str | Path) -> int | None:
    """Major version of a libLLVM file from its name (libLLVM-19.so, libLLVM.so.19.1), else None."""
    match = _VERSION.search(Path(path).name)
    return int(match.group(1)) if match else None


def find_libllvm() -> list[tuple[int, str]]:
    """(major version, path) of every shared libLLVM found in the usual places, newest first."""
    dirs = list(_SEARCH_DIRS) + os.environ.get("LD_LIBRARY_PATH", "").split(":")
    dirs += glob.glob("/usr/lib/llvm-*/lib")
    found = {}
    for folder in filter(None, dirs):
        for path in glob.glob(os.path.join(folder, "libLLVM*.so*")):
            version = llvm_version(path)
            if version is not None and os.path.exists(path):
                found.setdefault(os.path.realpath(path), (version, path))
    return sorted(found.values(), reverse=True)


def ensure_llvm(required: bool = True) -> str | None:
    """Make sure drjit will load libLLVM >= 16; returns its path. Raises LLVMUnavailable. With
    ``required=False`` (drjit without Mitsuba's llvm variants: a CUDA backend may serve) a machine with
    no libLLVM at all passes (None); only an older one, which would abort the process, or a bad
    ``DRJIT_LIBLLVM_PATH`` raises."""
    chosen = os.environ.get("DRJIT_LIBLLVM_PATH")
    if chosen:
        version = llvm_version(os.path.realpath(chosen)) or llvm_version(chosen)
        if not os.path.exists(chosen):
            raise LLVMUnavailable(f"DRJIT_LIBLLVM_PATH={chosen} does not exist")
        if version is not None and version < MIN_LLVM:
            raise LLVMUnavailable(
                f"DRJIT_LIBLLVM_PATH={chosen} is LLVM {version}; Mitsuba's llvm variants need >= "
                f"{MIN_LLVM} (apt-get install libllvm19)"
            )
        return chosen
    candidates = find_libllvm()
    good = [(v, p) for v, p in candidates if v >= MIN_LLVM]
    if not candidates and not required:
        return None
    if not good:
        have = ", ".join(f"LLVM {v}" for v, _ in candidates) or "none"
        raise LLVMUnavailable(
            f"Mitsuba's llvm variants need a shared libLLVM >= {MIN_LLVM} (found: {have}); with an "
            "older one the process aborts. Install one (Debian: apt-get install libllvm19) or set "
            "DRJIT_LIBLLVM_PATH to its .so"
        )
    version, path = good[0]
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    log.debug("using LLVM %d at %s", version, path)
    return path
