#!/usr/bin/env bash
# Free coarse latents and a coarse decoder together (`--residual 16 --coarse-decoder 4`) on the current `maps`
# recipe, judged by the report's views: per seed, one report run with the control as "N" and the lever as "Nmaps",
# the same references (the committed report's cache, runs/rep/cache) and render seeds.
# The models: runs/sj (controls; turtle's runs/rs/ctl and runs/cd/ctl1) and runs/rc (the lever), from
#   FLAGS="--residual 16 --coarse-decoder 4" OUT=runs/rc bash experiments/verdict_noise/seed_judge_runs.sh turtle foam yarn rock planks
#   bash experiments/coarse_levels/both_report.sh SEED [MATERIAL...]   (default: rock yarn turtle foam planks)
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
SEED=$1; shift
[ $# -gt 0 ] || set -- rock yarn turtle foam planks
control() { case "$1:$SEED" in turtle:0) echo runs/rs/ctl ;; turtle:1) echo runs/cd/ctl1 ;; *) echo "runs/sj/$1_s$SEED" ;; esac; }
for m in "$@"; do
  dir=runs/rc/report_s$SEED/models_$m
  mkdir -p "$dir"
  cp "$(control "$m")/$m.onnx" "$dir/$m.onnx"          # the control, as N
  cp "runs/rc/${m}_s$SEED/$m.onnx" "$dir/${m}_maps.onnx"  # the lever, as Nmaps
  spec=$m; [ "$m" = planks ] && spec=docs/materials/planks.toml
  "$NEUMIP" report --materials "$spec" --models "$dir" -o "runs/rc/report_s$SEED/$m" --cache runs/rep/cache \
    --skip stability tradeoff > "runs/rc/report_s$SEED/$m.log" 2>&1
  echo "$m seed $SEED: $(tail -1 "runs/rc/report_s$SEED/$m.log")"
done
