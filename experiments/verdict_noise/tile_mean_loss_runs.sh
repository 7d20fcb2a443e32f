#!/usr/bin/env bash
# The trainings behind tile_mean_loss_results.txt: the maps recipe with the tile-mean term (`--tile-mean PAIRS
# --tile-mean-weight W`) on one data set per material (runs/cal/data_NAME, as seed_judge_runs.sh), two one-thread runs
# side by side. The term is not in the product: `git apply experiments/verdict_noise/tile_mean_loss.patch` first, and
# `git checkout training/` after. PAIRS, POSITIONS: the term's; TAG: text after the weight in the runs' folders'
# names. The first two runs of tile_mean_loss_results.txt had the patch's denominator floor 1e-2 replaced by 1e-4.
# Each argument is MATERIAL:SEED:WEIGHT; the runs go in OUT/MATERIAL_tmWEIGHT[TAG]_sSEED.
#   bash experiments/verdict_noise/tile_mean_loss_runs.sh turtle:0:0.1 turtle:0:0.01
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
OUT=${OUT:-runs/tm}
PAIRS=${PAIRS:-32}
POSITIONS=${POSITIONS:-128}
TAG=${TAG:-}
train() { local m=${1%%:*} rest=${1#*:}; local s=${rest%%:*} w=${rest#*:}; local dir="$OUT/${m}_tm${w}${TAG}_s$s"
          "$NEUMIP" train "runs/cal/data_$m" -o "$dir/$m.onnx" --recipe maps --threads 1 --seed "$s" \
            --tile-mean "$PAIRS" --tile-mean-positions "$POSITIONS" --tile-mean-weight "$w" > "$dir.log" 2>&1 || { echo "$dir failed: see $dir.log" >&2; return 1; }
          echo "$dir: $(tail -1 "$dir.log")"; }
mkdir -p "$OUT"
while [ $# -gt 0 ]; do
  if [ $# -gt 1 ]; then train "$1" & first=$!; train "$2"; wait "$first"; shift 2; else train "$1"; shift; fi
done
