#!/usr/bin/env bash
# Reproduce the shipped materials: path-traced data (64^2 level of detail, 256 queries per texel,
# 16 spp), then `neumip train` with the preset $PRESET (default `ship`), replacing models/NAME.onnx
# (--force). Each step resumes if interrupted (a checkpoint in runs/NAME/ from another preset is
# refused: move it away first).
# Run from the repository root: [PRESET=quick] [THREADS=2] bash models/make_models.sh [NAME ...]
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
RES=64
PRESET=${PRESET:-ship}
THREADS=${THREADS:-1}  # the shipped models were trained with one torch thread
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(flat rock rock_nooffset yarn yarn_nooffset turtle foam)
for name in "${names[@]}"; do
  material=${name%_nooffset}
  flags=()
  [ "$name" != "$material" ] && flags=(--no-offset)
  [ -f "data/$material/meta.json" ] && grep -q '"complete": true' "data/$material/meta.json" ||
    "$NEUMIP" generate "$material" -o "data/$material" --queries-per-texel 256 --resolution $RES --spp 16 --seed 0
  "$NEUMIP" train "data/$material" -o "models/$name.onnx" --force --preset "$PRESET" --threads "$THREADS" --resolution $RES "${flags[@]}" \
    --description "$material, ${RES}^2, $([ ${#flags[@]} -gt 0 ] && echo 'no neural offset' || echo 'neural offset'), $PRESET preset"
done
