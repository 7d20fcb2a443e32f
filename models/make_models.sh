#!/usr/bin/env bash
# Train the materials: path-traced data ($RES^2 level of detail, $QPT queries per texel, $SPP spp),
# then `neumip train` with the preset $PRESET, replacing models/NAME.onnx (--force). Each step
# resumes if interrupted (a checkpoint in runs/NAME/ from another preset is refused: move it away).
# Defaults: the `quality` recipe (models/README.md, "Quality levers"): 10 000 steps of 16 384 at
# RES=64. The models shipped now were made with the earlier recipe, reproduced by
#   PRESET=ship bash models/make_models.sh
# Run from the repository root: [PRESET=quality] [RES=64] [THREADS=1] bash models/make_models.sh [NAME ...]
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
RES=${RES:-64}
QPT=${QPT:-256}  # queries per finest texel: measured better than fewer queries with more spp each
SPP=${SPP:-16}
PRESET=${PRESET:-quality}
THREADS=${THREADS:-1}  # one torch thread: fastest on the shared 2-core machines (training/TRAINING.md)
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(flat rock rock_nooffset yarn yarn_nooffset turtle foam)
data_dir() {  # the 64^2 / 256 / 16 data keep their old folder (data/NAME)
  if [ "$RES" = 64 ] && [ "$QPT" = 256 ] && [ "$SPP" = 16 ]; then echo "data/$1"; else echo "data/$1_r${RES}_q${QPT}_s${SPP}"; fi
}
for name in "${names[@]}"; do
  material=${name%_nooffset}
  data=$(data_dir "$material")
  flags=()
  [ "$name" != "$material" ] && flags=(--no-offset)
  [ -f "$data/meta.json" ] && grep -q '"complete": true' "$data/meta.json" ||
    "$NEUMIP" generate "$material" -o "$data" --queries-per-texel "$QPT" --resolution "$RES" --spp "$SPP" --seed 0
  "$NEUMIP" train "$data" -o "models/$name.onnx" --force --preset "$PRESET" --threads "$THREADS" --resolution "$RES" "${flags[@]}" \
    --description "$material, ${RES}^2, $([ ${#flags[@]} -gt 0 ] && echo 'no neural offset' || echo 'neural offset'), $PRESET preset"
done
