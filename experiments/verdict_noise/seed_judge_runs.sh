#!/usr/bin/env bash
# The trainings behind seed_judge_results.txt: the maps recipe at seeds 0 and 1 on one data set per material
# (SEEDS; runs/cal/data_NAME: 16.8 M queries, seed 7, the coarse footprints at 64 spp; planks 4.2 M), two one-thread runs
# side by side (about 8 minutes a pair on 2 cores). Turtle's two runs are session 19's (runs/rs/ctl, runs/cd/ctl1).
#   bash experiments/verdict_noise/seed_judge_runs.sh [MATERIAL...]   (default: rock yarn foam planks)
#   SEEDS=2 bash experiments/verdict_noise/seed_judge_runs.sh turtle rock yarn foam planks   (a third seed)
#   FLAGS="--residual 16 --coarse-decoder 4" OUT=runs/rc bash experiments/verdict_noise/seed_judge_runs.sh ...   (a lever)
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
OUT=${OUT:-runs/sj}
train() { local m=$1 s=$2
          "$NEUMIP" train "runs/cal/data_$m" -o "$OUT/${m}_s$s/$m.onnx" --recipe maps --threads 1 --seed "$s" ${FLAGS:-} \
            > "$OUT/${m}_s$s.log" 2>&1 || { echo "$m seed $s failed: see $OUT/${m}_s$s.log" >&2; return 1; }
          echo "$m seed $s: $(tail -1 "$OUT/${m}_s$s.log")"; }
mkdir -p "$OUT"
[ $# -gt 0 ] || set -- rock yarn foam planks
jobs=()
for m in "$@"; do for s in ${SEEDS:-0 1}; do jobs+=("$m $s"); done; done
for ((i = 0; i < ${#jobs[@]}; i += 2)); do  # two at a time
  read -r m1 s1 <<< "${jobs[i]}"; train "$m1" "$s1" & first=$!
  if [ $((i + 1)) -lt ${#jobs[@]} ]; then read -r m2 s2 <<< "${jobs[i + 1]}"; train "$m2" "$s2"; fi
  wait "$first"  # a failed run stops the script (set -e)
done
