#!/usr/bin/env bash
# Free latent textures on the coarse levels of the map-informed model (`--residual SIZE`, MapConfig.residual):
# the shipped recipe with --residual 16, trained on the shipped data, judged by the report's views against the
# shipped file in the same report run (the baseline as "N", the lever as "Nmaps"). One material per call.
#   bash experiments/coarse_levels/run.sh rock [SEED]
set -euo pipefail
M=$1 SEED=${2:-0} OUT=${OUT:-runs/coarse_levels}
D=data/${M}_n1048576_s16_st1
[ -f "$D/meta.json" ] || neumip generate "$M" -o "$D" --queries 1048576 --spp 16 --seed 0 --resolution 256 --sub-texel-levels 1
neumip train "$D" -o "$OUT/$M/res16_s$SEED.onnx" --recipe maps --residual 16 --seed "$SEED" --threads 1
mkdir -p "$OUT/$M/models_s$SEED"
cp "models/${M}_maps.onnx" "$OUT/$M/models_s$SEED/$M.onnx"          # the baseline, as N
cp "$OUT/$M/res16_s$SEED.onnx" "$OUT/$M/models_s$SEED/${M}_maps.onnx"   # the lever, as Nmaps
neumip report --materials "$M" --models "$OUT/$M/models_s$SEED" -o "$OUT/$M/report_s$SEED" --cache "$OUT/cache" \
  --skip stability tradeoff
