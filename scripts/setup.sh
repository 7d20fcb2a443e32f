#!/usr/bin/env bash
# Set up a development environment in .venv: system LLVM for Mitsuba, CPU torch, neumip with all extras.
# Idempotent: re-running on a set-up machine takes seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# Mitsuba's llvm variants need a shared libLLVM >= 16; with only an older one the process aborts.
if ! ls /usr/lib/*/libLLVM*.so* 2>/dev/null | grep -qE 'libLLVM(-|\.so\.)(1[6-9]|[2-9][0-9])'; then
  echo "setup: installing libllvm19 (Mitsuba needs libLLVM >= 16)"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get install -y -q libllvm19 >/dev/null 2>&1 || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q libllvm19 >/dev/null; }
fi

if [ ! -x .venv/bin/python ] && ! "$PY" -m venv .venv; then
  echo "setup: installing python3-venv"
  rm -rf .venv
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get install -y -q python3-venv >/dev/null
  "$PY" -m venv .venv
fi
# A fresh install puts about 2.1 GB in .venv, and pip unpacks each download in $TMPDIR first (torch's is the largest).
# Say so plainly rather than fail half-way with pip's "No space left on device". Downloads are not cached: on a fresh
# machine (CI) a cache only doubles the bytes written, and a set-up one installs nothing more.
export PIP_NO_CACHE_DIR=${PIP_NO_CACHE_DIR:-1}
need_mb() {  # DIR MB: stop with a plain message when the disk DIR lies on has less free (a disk df cannot read passes)
  local free
  free=$(df -Pm "$1" 2>/dev/null | awk 'NR == 2 {print $4}') || true
  if [ -n "$free" ] && [ "$free" -lt "$2" ]; then
    echo "setup: only $free MB free where $1 lies; a fresh install needs about $2 MB there" >&2
    exit 1
  fi
}
if ! .venv/bin/python -c "import torch, neumip" 2>/dev/null; then
  tmp=${TMPDIR:-/tmp}
  if [ "$(stat -c %d .venv)" = "$(stat -c %d "$tmp" 2>/dev/null)" ]; then need_mb .venv 3000  # one disk holds both
  else need_mb .venv 2500; need_mb "$tmp" 1000; fi
fi
.venv/bin/python -m pip install -q --upgrade pip
# The pinned torch first, its CPU build: from PyPI it pulls several GB of CUDA packages. Where pip
# finds a local CPU wheel (this project's CI machines) the pin alone does; elsewhere set
# TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu.
.venv/bin/python -c "import torch" 2>/dev/null || .venv/bin/pip install -q torch==2.13.0 ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"}
# setuptools tells every editable install of a package-dir mapping to mind same-named folders: ours are the package.
PYTHONWARNINGS="${PYTHONWARNINGS:+$PYTHONWARNINGS,}ignore:Editable installation" .venv/bin/pip install -q -e '.[all,test]'
echo "setup: ready (.venv)"
