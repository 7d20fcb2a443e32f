#!/usr/bin/env bash
# Reproduce the shipped materials with `neumip fit`: path-traced data ($QPT queries per texel of the $RES^2
# model, footprints sampled for the material's maps' resolution where finer, $SPP spp) in data/MATERIAL_nQUERIES_sSPP
# (shared by NAME and NAME_nooffset; NAME_maps* on data/MATERIAL_nQUERIES_sSPP_stK, footprints K = $LOD_BIAS levels finer), then training with the preset $PRESET, replacing
# models/NAME.onnx (--force). Each step resumes if interrupted (a checkpoint in runs/NAME/ from another
# preset or resolution is refused: move it away). NAME_maps is the map-informed model (`neumip fit --maps`).
# Materials with a height map are fitted with the relief stage (--relief $RELIEF): parallax and occlusion marched
# on the height map, before the neural offset; NAME_nooffset has neither, so its gain is the parallax stages'.
# Materials defined by maps are fitted with --base auto (with and without the classical base, the one with the
# lower reference error kept); NAME_nooffset then takes NAME's choice, so the offset's gain compares like with like.
# The map-informed models (NAME_maps) always stand on the base ($MAPS_BASE).
# A base is fitted with $SHADING: the decoder also reads the directions in the base normal's frame, and the base's only
# shadow is its horizon's (no terminator softening): experiments/terminator/terminator.txt.
# SEEDS=K trains each model from K initial weights (fit --seeds) and keeps the one with the lowest error on a
# low-noise reference set: a first run in runs/NAME[/base], the others in its seedK/ folders.
# Defaults reproduce the models shipped now (`ship` preset, 64^2, 256 queries per texel of it, 16 spp; the
# map-informed models at their maps' resolution with --lod-bias $LOD_BIAS, on data as large, footprints a level finer).
# PRESET=quality is the longer recipe measured in experiments/quality_levers/quality_levers_log.md ("Quality levers"): 10 000 steps of 16 384.
# Run from the repository root: [PRESET=ship|quality] [RES=64] [THREADS=1] bash models/make_models.sh [NAME ...]
# RAY=auto (or HOST:PORT, or local) runs data chunks and then one training per material as Ray tasks
# (`neumip generate --ray`, `neumip train-many --ray`; pip install 'neumip[cluster]'); THREADS is
# then the CPUs of each training task, and models already finished are skipped; train-many trains no base (BASE) and one seed (SEEDS),
# the relief it does.
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
RES=${RES:-64}
QPT=${QPT:-256}  # queries per finest texel: measured better than fewer queries with more spp each
SPP=${SPP:-16}
PRESET=${PRESET:-ship}
HIDDEN=${HIDDEN:-25}  # MLP width, the paper's; 48 was 0-32 % more accurate in images and 1.34x the render time (models/README.md)
THREADS=${THREADS:-1}  # the shipped models were trained with one torch thread
BASE=${BASE:-auto}  # classical base (fit --base): auto keeps it where it lowers the held-out MSE; NAME_nooffset follows NAME's choice; on; off
MAPS_BASE=${MAPS_BASE:-on}  # the same for the map-informed models: at 256^2 auto would drop it on rock (7 % lower reference error), where the report's close-ups are 1.2-1.6x better with it (models/README.md)
SHADING=${SHADING---local-frame --terminator none}  # with the base: the decoder reads the directions in the base normal's frame, and no S(g) (experiments/terminator/terminator.txt)
RELIEF=${RELIEF:-8}  # relief steps (fit --relief) for every material with a height map, 0: none; NAME_nooffset has neither relief nor offset
MAPS_RES=${MAPS_RES:-}  # NAME_maps: finest latent level of the map-informed models; empty: the material's maps' (256^2 shipped: experiments/gpu/gpu.txt)
HORIZONS=${HORIZONS:-8}  # NAME_maps: horizon features towards 8 azimuths (rock: better than none in all 8 close-up views, experiments/maps/maps.txt)
LOD_BIAS=${LOD_BIAS:-1}  # NAME_maps: fit --lod-bias K (the finest level answers footprints of 2^-K texel and less, on data of their own with footprints that fine, data/MATERIAL_nQUERIES_sSPP_stK); 0 is the paper's level of detail, 2 was measured too: experiments/lod_bias/lod_bias.txt
SEEDS=${SEEDS:-1}  # fit --seeds: each model from this many initial weights, the lowest reference error kept; 3 was measured, not shipped (TRAINING.md)
RAY=${RAY:-}
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(flat rock rock_nooffset yarn yarn_nooffset turtle turtle_nooffset foam foam_nooffset
                                  rock_maps rock_maps_nooffset yarn_maps yarn_maps_nooffset turtle_maps
                                  turtle_maps_nooffset foam_maps foam_maps_nooffset)
QUERIES=$(( QPT * RES * RES ))
data_dir() { echo "data/$1_n${QUERIES}_s${SPP}"; }
generate_data() {  # MATERIAL [--ray=ADDRESS]: the data `neumip fit` makes (footprints for max(RES, the maps'))
  local data res; data=$(data_dir "$1")
  res=$("${NEUMIP%neumip}python" -c "import sys; from neumip.groundtruth.description import find_description as f; print(max($RES, f(sys.argv[1]).resolution))" "$1")
  [ -f "$data/meta.json" ] && grep -q '"complete": true' "$data/meta.json" ||
    "$NEUMIP" generate "$1" -o "$data" --queries "$QUERIES" --queries-per-texel "$QPT" --resolution "$res" --spp "$SPP" --seed 0 "${@:2}"
}
has_maps() {  # MATERIAL: whether it is defined by principled maps (a base needs them; flat's [bsdf] is not)
  "${NEUMIP%neumip}python" -c "import sys; from neumip.groundtruth.description import find_description, resolve; sys.exit(resolve(find_description(sys.argv[1])).bsdf is not None)" "$1"
}
base_flags() {  # NAME: the --base flags of its fit, with the base's shading ($SHADING)
  local parent=${1%_nooffset} base=$BASE
  [[ "$1" == *_maps* ]] && base=$MAPS_BASE
  [ "$base" = off ] && return 0
  has_maps "$(material_of "$1")" || return 0
  if [ "$base" = on ]; then echo --base $SHADING; return 0; fi
  if [ "$parent" != "$1" ] && [ -f "models/$parent.json" ]; then  # an ablation keeps its model's choice
    "${NEUMIP%neumip}python" -c "import json, sys; sys.exit(not json.load(open(sys.argv[1]))['material_config'].get('base'))" \
      "models/$parent.json" && echo --base $SHADING
    return 0
  fi
  echo --base auto $SHADING
}
has_height() {  # MATERIAL: whether it has a height map to march (flat's is 1 x 1)
  "${NEUMIP%neumip}python" -c "import sys; from neumip.groundtruth.description import find_description, resolve; sys.exit(resolve(find_description(sys.argv[1])).height.shape[0] <= 1)" "$1"
}
relief_flags() {  # NAME: the --relief flags of its fit (none for an ablation: NAME_nooffset has no parallax stage)
  [[ "$1" == *_nooffset ]] || [ "$RELIEF" = 0 ] && return 0
  has_height "$(material_of "$1")" && echo --relief "$RELIEF"
  return 0
}
material_of() { local m=${1%_nooffset}; echo "${m%_maps}"; }  # rock_maps_nooffset -> rock
resolution_of() {  # NAME: its finest latent level (RES; a map-informed model's MAPS_RES, else its maps' resolution,
  # at least RES: the data set's footprints are sampled for max(RES, the maps'), and every model of a material shares it)
  if [[ "$1" != *_maps* ]]; then echo "$RES"; elif [ -n "$MAPS_RES" ]; then echo "$MAPS_RES"; else
    "${NEUMIP%neumip}python" -c "import sys; from neumip.groundtruth.description import find_description as f; print(max($RES, f(sys.argv[1]).resolution))" "$(material_of "$1")"
  fi
}
describe() {  # NAME
  echo "$(material_of "$1"), $(resolution_of "$1")^2, $([[ "$1" == *_nooffset ]] && echo 'no relief, no neural offset' || echo "$([ -n "$(relief_flags "$1")" ] && echo 'relief, ')neural offset"),$([[ "$1" == *_maps* ]] && echo ' map-informed,')$([ "$HIDDEN" != 25 ] && echo " MLP width $HIDDEN,") $PRESET preset"
}
if [ -n "$RAY" ]; then
  jobs=() flags=()
  for name in "${names[@]}"; do
    material=$(material_of "$name")
    if [[ "$name" == *_maps* ]]; then echo "RAY: train-many trains no map-informed models: $name skipped (run it without RAY)" >&2; continue; fi
    generate_data "$material" --ray="$RAY"
    jobs+=("$name=$(data_dir "$material")")
    [ "$name" != "$material" ] && flags+=(--no-offset "$name")
  done
  [ "$RELIEF" != 0 ] && flags+=(--relief "$RELIEF")
  exec "$NEUMIP" train-many "${jobs[@]}" ${flags[@]+"${flags[@]}"} -o models --preset "$PRESET" --threads "$THREADS" \
    --resolution "$RES" --hidden "$HIDDEN" --ray="$RAY"
fi
for name in "${names[@]}"; do
  material=$(material_of "$name")
  flags=()
  [[ "$name" == *_nooffset ]] && flags+=(--no-offset)
  data=$(data_dir "$material")
  [[ "$name" == *_maps* ]] && flags+=(--maps --horizons "$HORIZONS")
  [[ "$name" == *_maps* ]] && [ "$LOD_BIAS" != 0 ] && flags+=(--lod-bias "$LOD_BIAS") && data+="_st$LOD_BIAS"
  read -r -a base <<< "$(base_flags "$name")"
  flags+=(${base[@]+"${base[@]}"})
  read -r -a relief <<< "$(relief_flags "$name")"
  flags+=(${relief[@]+"${relief[@]}"})
  work="runs/$name"
  [ "${base[0]-}" = --base ] && [ "${base[1]-}" != auto ] && work="runs/$name/base"  # where --base auto trains its base candidate too
  "$NEUMIP" fit "$material" -o "models/$name.onnx" --force --work "$work" --data "$data" \
    --resolution "$(resolution_of "$name")" --queries "$QUERIES" --queries-per-texel "$QPT" --spp "$SPP" --preset "$PRESET" --threads "$THREADS" \
    --hidden "$HIDDEN" --seeds "$SEEDS" ${flags[@]+"${flags[@]}"} --description "$(describe "$name")"
done
