#!/usr/bin/env bash
# Fill docker/wheels/ with every wheel `pip install '.[serve,kernel]'` needs (plus the build backend), so that
# `docker build` installs with no network. Run on a host with the same Python minor version and
# architecture as the base image (bookworm: Python 3.11, x86-64).
#
#   docker/wheelhouse.sh [PYTHON]        (default: .venv/bin/python, else python3)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
PY="${1:-}"
if [ -z "$PY" ]; then
    if [ -x "$ROOT/.venv/bin/python" ]; then PY="$ROOT/.venv/bin/python"; else PY=python3; fi
fi
OUT="$ROOT/docker/wheels"
mkdir -p "$OUT"
# Dependencies of the server and kernel extras (neumip itself is built inside the image from the source tree).
"$PY" -m pip download --quiet --only-binary=:all: --dest "$OUT" \
    "setuptools>=77" wheel pip
"$PY" -m pip wheel --quiet --wheel-dir "$OUT" "$ROOT[serve,kernel]"
rm -f "$OUT"/neumip-*.whl
echo "wheelhouse: $(ls "$OUT"/*.whl | wc -l) wheels in $OUT"
