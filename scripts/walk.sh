#!/usr/bin/env bash
# The front page walked as a new user would, timed: a fresh clone of this checkout, set up, the demo,
# then a material from texture maps (MATERIAL, default docs/example/bricks.toml, copied out of the
# clone with its maps as "your own") fitted, rendered in the demo and reported. Prints each step's
# start time. WALK=/tmp/neumip-walk-clone is the clone (replaced). REUSE_VENV=PATH/.venv skips the
# ~2 GB install: the clone's .venv then sees that one's packages and installs only neumip itself.
# PRESET (default quick) is the fit's training preset.
#   bash scripts/walk.sh                       REUSE_VENV=$PWD/.venv bash scripts/walk.sh
set -uo pipefail
SRC=$(cd "$(dirname "$0")/.." && pwd)
WALK=${WALK:-/tmp/neumip-walk-clone}
MATERIAL=${MATERIAL:-$SRC/docs/example/bricks.toml}
PRESET=${PRESET:-quick}
T0=$(date +%s)
step() { echo "=== [$(( $(date +%s) - T0 )) s] $*"; }
rm -rf "$WALK" && git clone -q "$SRC" "$WALK" && cd "$WALK" || exit 1
mine=$(mktemp -d)  # "your own" maps, outside the clone
cp "$(dirname "$MATERIAL")"/* "$mine"/
toml="$mine/$(basename "$MATERIAL")"
name=$(python3 -c "import sys, tomllib; d = tomllib.load(open(sys.argv[1], 'rb')); print(d.get('name', sys.argv[1].rsplit('/', 1)[-1][:-5]))" "$toml")
if [ -n "${REUSE_VENV:-}" ]; then
  step "set up: a .venv over $REUSE_VENV's packages"
  base=$("$REUSE_VENV/bin/python" -c "import sys; print(sys.base_prefix)")
  "$base/bin/python3" -m venv .venv
  site=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
  "$REUSE_VENV/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])" > "$site/reuse.pth"
  .venv/bin/python -m pip install -q --no-deps -e .
fi
step "bash scripts/demo.sh --spp 16 -D resx=256 -D resy=256"
bash scripts/demo.sh --spp 16 -D resx=256 -D resy=256 2>&1 | tail -2
step "source .venv/bin/activate"
source .venv/bin/activate
step "neumip fit $toml -o mine/$name.onnx --preset $PRESET"
neumip fit "$toml" -o "mine/$name.onnx" --preset "$PRESET" 2>&1 | tr '\r' '\n' | grep -v "^\s*$" | grep -v "^$name \[" | tail -12
step "neumip render scenes/demo.xml -o out/demo-$name.png --models mine:models -D cube=$name"
neumip render scenes/demo.xml -o "out/demo-$name.png" --models mine:models -D cube="$name" 2>&1 | tail -2
step "neumip report --materials $toml --models mine -o out/report-$name --quick"
neumip report --materials "$toml" --models mine -o "out/report-$name" --quick 2>&1 | tail -2
step "done: $WALK"
