#!/usr/bin/env bash
# Every run behind tile_mean_results.txt (about 8 minutes on 2 cores): the screen at two seeds on the four shipped
# materials and planks, narrower MLPs and the tracer as the teacher on turtle.
#   bash experiments/verdict_noise/tile_mean_runs.sh > experiments/verdict_noise/tile_mean_results.txt
set -euo pipefail
PY=${PY:-.venv/bin/python}
V="level6_high level8_high level6_side level8_side level6_front level8_front"
run() { local start=$SECONDS; echo "## $PY experiments/verdict_noise/tile_mean_gain.py $*"
        "$PY" experiments/verdict_noise/tile_mean_gain.py "$@" 2>&1 | grep -v Warn; echo "($((SECONDS - start)) s)"; }
echo "# $(date -u +%F), at $(git rev-parse --short HEAD), $(nproc) cores"
for seed in 0 1; do
  for m in turtle yarn foam rock; do run $m $V --seed $seed; done
  run docs/materials/planks.toml $V --models docs/materials/planks_models --seed $seed
done
for h in 16 32; do run turtle $V --hidden $h; done
run turtle $V --tracer
run turtle $V --pairs 8192 --positions 8192
run turtle $V --pairs 8192 --positions 8192 --tracer
