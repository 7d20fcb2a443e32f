#!/usr/bin/env bash
# A larger share of the data for the coarse footprints (QuerySampling.level_fraction): the shipped maps recipe
# trained on data whose log-uniform share of footprints is LEVEL (shipped 0.3) and heavy-tailed share HEAVY
# (shipped 0.6), same size, same spp, same steps; judged by the report's views against the shipped file in the
# same report run (the baseline as "N", the lever as "Nmaps"). One material per call.
#   bash experiments/level_share/run.sh rock [SEED] [LEVEL] [HEAVY] [-- extra train flags]
# SPP=64 traces the data with more samples a query (shipped 16); TAG names the run (default lfLEVEL[_sppSPP]).
# RES: the maps' resolution (default 256). MATERIAL: a shipped name or a .toml; BASELINE: the file judged against (default models/NAME_maps.onnx), e.g.
#   SPP=64 RES=128 BASELINE=docs/materials/planks_models/planks_maps.onnx bash experiments/level_share/run.sh docs/materials/planks.toml 0 0.3 0.6
set -euo pipefail
M=$1 NAME=$(basename "$1" .toml) SEED=${2:-0} LEVEL=${3:-0.6} HEAVY=${4:-0.35}
shift $(( $# < 4 ? $# : 4 )); [ "${1:-}" = "--" ] && shift
SPP=${SPP:-16} EXTRA=("$@")
TAG=${TAG:-lf${LEVEL}$([ "$SPP" = 16 ] || echo "_spp$SPP")}
OUT=${OUT:-runs/level_share} BASELINE=${BASELINE:-models/${NAME}_maps.onnx}
D=data/${NAME}_n1048576_s${SPP}_st1_lf${LEVEL}_hf${HEAVY}
[ -f "$D/meta.json" ] || neumip generate "$M" -o "$D" --queries 1048576 --spp "$SPP" --seed 0 --resolution "${RES:-256}" \
  --sub-texel-levels 1 --level-fraction "$LEVEL" --heavy-fraction "$HEAVY"
neumip train "$D" -o "$OUT/$NAME/${TAG}_s$SEED.onnx" --recipe maps --seed "$SEED" --threads 1 "${EXTRA[@]}"
mkdir -p "$OUT/$NAME/models_${TAG}_s$SEED"
cp "$BASELINE" "$OUT/$NAME/models_${TAG}_s$SEED/$NAME.onnx"                          # the baseline, as N
cp "$OUT/$NAME/${TAG}_s$SEED.onnx" "$OUT/$NAME/models_${TAG}_s$SEED/${NAME}_maps.onnx"  # the lever, as Nmaps
neumip report --materials "$M" --models "$OUT/$NAME/models_${TAG}_s$SEED" -o "$OUT/$NAME/report_${TAG}_s$SEED" \
  --cache "$OUT/cache" --skip stability tradeoff
