#!/usr/bin/env bash
# The README's first command: set up (idempotent), then render the demo scene in-process with the
# shipped materials (models/). Prints where the image is and how long it took.
# Extra arguments go to `neumip render`, e.g.  bash scripts/demo.sh --spp 16 -D resx=256 -D resy=256
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/neumip render scenes/demo.xml -o out/demo.png --models models "$@"
