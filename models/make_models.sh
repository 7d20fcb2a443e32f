#!/usr/bin/env bash
# Reproduce the shipped materials: path-traced data (64^2 level of detail, 256 queries per texel,
# 16 spp), then `neumip train` with the preset $PRESET (default `ship`), replacing models/NAME.onnx
# (--force). Each step resumes if interrupted (a checkpoint in runs/NAME/ from another preset is
# refused: move it away first).
# Run from the repository root: [PRESET=quick] [THREADS=2] bash models/make_models.sh [NAME ...]
# RAY=auto (or HOST:PORT, or local) runs data chunks and then one training per material as Ray tasks
# (`neumip generate --ray`, `neumip train-many --ray`; pip install 'neumip[cluster]'); THREADS is
# then the CPUs of each training task, and models already finished are skipped.
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
RES=64
PRESET=${PRESET:-ship}
THREADS=${THREADS:-1}  # the shipped models were trained with one torch thread
RAY=${RAY:-}
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(flat rock rock_nooffset yarn yarn_nooffset turtle foam)
generate_data() {  # MATERIAL [--ray=ADDRESS]
  [ -f "data/$1/meta.json" ] && grep -q '"complete": true' "data/$1/meta.json" ||
    "$NEUMIP" generate "$1" -o "data/$1" --queries-per-texel 256 --resolution $RES --spp 16 --seed 0 "${@:2}"
}
if [ -n "$RAY" ]; then
  jobs=() flags=()
  for name in "${names[@]}"; do
    material=${name%_nooffset}
    generate_data "$material" --ray="$RAY"
    jobs+=("$name=data/$material")
    [ "$name" != "$material" ] && flags+=(--no-offset "$name")
  done
  exec "$NEUMIP" train-many "${jobs[@]}" "${flags[@]}" -o models --preset "$PRESET" --threads "$THREADS" \
    --resolution $RES --ray="$RAY"
fi
for name in "${names[@]}"; do
  material=${name%_nooffset}
  flags=()
  [ "$name" != "$material" ] && flags=(--no-offset)
  generate_data "$material"
  "$NEUMIP" train "data/$material" -o "models/$name.onnx" --force --preset "$PRESET" --threads "$THREADS" --resolution $RES "${flags[@]}" \
    --description "$material, ${RES}^2, $([ ${#flags[@]} -gt 0 ] && echo 'no neural offset' || echo 'neural offset'), $PRESET preset"
done
