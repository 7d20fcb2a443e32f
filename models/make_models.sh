#!/usr/bin/env bash
# Reproduce the shipped materials with `neumip fit`: path-traced data ($RES^2 level of detail, $QPT queries
# per texel, $SPP spp) in data/MATERIAL (shared by NAME and NAME_nooffset), then training with the preset
# $PRESET, replacing models/NAME.onnx (--force). Each step resumes if interrupted (a checkpoint in
# runs/NAME/ from another preset is refused: move it away).
# Defaults reproduce the models shipped now (`ship` preset, 64^2, 256 queries per texel, 16 spp).
# PRESET=quality is the longer recipe measured in benchmarks/results/quality_levers_log.md ("Quality levers"): 10 000 steps of 16 384.
# Run from the repository root: [PRESET=ship|quality] [RES=64] [THREADS=1] bash models/make_models.sh [NAME ...]
# RAY=auto (or HOST:PORT, or local) runs data chunks and then one training per material as Ray tasks
# (`neumip generate --ray`, `neumip train-many --ray`; pip install 'neumip[cluster]'); THREADS is
# then the CPUs of each training task, and models already finished are skipped.
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
RES=${RES:-64}
QPT=${QPT:-256}  # queries per finest texel: measured better than fewer queries with more spp each
SPP=${SPP:-16}
PRESET=${PRESET:-ship}
HIDDEN=${HIDDEN:-25}  # MLP width, the paper's; 48 was 0-32 % more accurate in images and 1.34x the render time (models/README.md)
THREADS=${THREADS:-1}  # the shipped models were trained with one torch thread
RAY=${RAY:-}
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(flat rock rock_nooffset yarn yarn_nooffset turtle turtle_nooffset foam foam_nooffset)
data_dir() {  # the 64^2 / 256 / 16 data keep their old folder (data/NAME)
  if [ "$RES" = 64 ] && [ "$QPT" = 256 ] && [ "$SPP" = 16 ]; then echo "data/$1"; else echo "data/$1_r${RES}_q${QPT}_s${SPP}"; fi
}
generate_data() {  # MATERIAL [--ray=ADDRESS]
  local data; data=$(data_dir "$1")
  [ -f "$data/meta.json" ] && grep -q '"complete": true' "$data/meta.json" ||
    "$NEUMIP" generate "$1" -o "$data" --queries-per-texel "$QPT" --resolution "$RES" --spp "$SPP" --seed 0 "${@:2}"
}
describe() {  # NAME
  local material=${1%_nooffset}
  echo "$material, ${RES}^2, $([ "$1" != "$material" ] && echo 'no neural offset' || echo 'neural offset'),$([ "$HIDDEN" != 25 ] && echo " MLP width $HIDDEN,") $PRESET preset"
}
if [ -n "$RAY" ]; then
  jobs=() flags=()
  for name in "${names[@]}"; do
    material=${name%_nooffset}
    generate_data "$material" --ray="$RAY"
    jobs+=("$name=$(data_dir "$material")")
    [ "$name" != "$material" ] && flags+=(--no-offset "$name")
  done
  exec "$NEUMIP" train-many "${jobs[@]}" "${flags[@]}" -o models --preset "$PRESET" --threads "$THREADS" \
    --resolution "$RES" --hidden "$HIDDEN" --ray="$RAY"
fi
for name in "${names[@]}"; do
  material=${name%_nooffset}
  flags=()
  [ "$name" != "$material" ] && flags=(--no-offset)
  "$NEUMIP" fit "$material" -o "models/$name.onnx" --force --work "runs/$name" --data "$(data_dir "$material")" \
    --resolution "$RES" --queries-per-texel "$QPT" --spp "$SPP" --preset "$PRESET" --threads "$THREADS" \
    --hidden "$HIDDEN" "${flags[@]}" --description "$(describe "$name")"
done
