"""The libLLVM check that runs before drjit loads one (`engines/llvm.py`): an LLVM older than
16 would abort the process, so it is refused with a message; a machine with none at all may still use
drjit's CUDA backend (`ensure_llvm(required=False)`, the kernel module's check)."""

from __future__ import annotations

import pytest

from neumip.engines import llvm


@pytest.fixture
def found(monkeypatch):
    """Set which libLLVM files the search finds; the check sees (and sets) a copy of the environment
    without DRJIT_LIBLLVM_PATH, so this process's stays as it was."""
    environ = {k: v for k, v in llvm.os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    monkeypatch.setattr(llvm.os, "environ", environ)

    def use(libraries: list[tuple[int, str]]) -> None:
        monkeypatch.setattr(llvm, "find_libllvm", lambda: libraries)

    return use


def test_a_new_enough_llvm_is_chosen_for_drjit(found):
    found([(19, "/x/libLLVM-19.so"), (15, "/x/libLLVM-15.so")])
    assert llvm.ensure_llvm() == "/x/libLLVM-19.so"
    assert llvm.os.environ["DRJIT_LIBLLVM_PATH"] == "/x/libLLVM-19.so"


def test_only_an_older_llvm_is_refused_whether_or_not_one_is_required(found):
    found([(15, "/x/libLLVM-15.so")])
    for required in (True, False):
        with pytest.raises(llvm.LLVMUnavailable, match=r"found: LLVM 15.*libllvm19"):
            llvm.ensure_llvm(required=required)


def test_no_llvm_at_all_is_refused_only_where_one_is_required(found):
    found([])
    with pytest.raises(llvm.LLVMUnavailable, match="found: none"):
        llvm.ensure_llvm()
    assert llvm.ensure_llvm(required=False) is None


def test_a_bad_drjit_libllvm_path_is_refused_either_way(found):
    found([])
    llvm.os.environ["DRJIT_LIBLLVM_PATH"] = "/nowhere/libLLVM-19.so"
    for required in (True, False):
        with pytest.raises(llvm.LLVMUnavailable, match="does not exist"):
            llvm.ensure_llvm(required=required)
