#!/usr/bin/env bash
# experiments/maps/maps.py's variants trained on an NVIDIA GPU, each judged on a low-noise reference set: e.g. the
# spread from seed to seed of the shipped recipe (experiments/seeds/seeds.txt):
#
#   bash experiments/gpu/gpu_train.sh DATA MATERIAL REFERENCE OUT SECONDS VARIANT...
#
# OUT gets each run's record (VARIANT.json) and the models with the lowest and the highest reference error
# (best.onnx, worst.onnx, named in OUT/choice.txt; the device returns 8 files at most, so 6 variants fit), to be
# scored in images on the CPU (`maps.py score`). Runs as
# experiments/gpu/gpu_check.sh does (experiments/gpu/gpu_site.sh); a variant that would end past SECONDS is not started.
set -u
data=$1 material=$2 reference=$3 out=$4 budget=$5
shift 5
start=$SECONDS
source experiments/gpu/gpu_site.sh
mkdir -p "$out"
nvidia-smi -L
last=60
for variant in "$@"; do
    left=$((budget - (SECONDS - start)))
    [ "$left" -gt $((last + 20)) ] || { echo "$variant: not started, $left s left"; continue; }
    began=$SECONDS
    timeout $((left - 10)) python3 experiments/maps/maps.py train "$variant" --data "$data" --material "$material" \
        --runs "$runs" --device cuda --reference "$reference" 2>&1 | grep -v "^\s*$" | tail -1
    last=$((SECONDS - began))
    cp "$runs/$variant/"*.json "$out/$variant.json" 2>/dev/null
done
python3 - "$runs" "$out" <<'PY'
import json, shutil, sys
from pathlib import Path
runs, out = Path(sys.argv[1]), Path(sys.argv[2])
scored = sorted((json.loads(r.read_text())["reference_log_mse"], r.parent.name, r.with_suffix(".onnx"))
                for r in runs.glob("*/*.json"))
for error, variant, _ in scored:
    print(f"{variant:<20} reference log MSE {error * 1e3:.3f}e-3")
(out / "choice.txt").write_text(f"best {scored[0][1]} {scored[0][0]}\nworst {scored[-1][1]} {scored[-1][0]}\n")
shutil.copy(scored[0][2], out / "best.onnx")
shutil.copy(scored[-1][2], out / "worst.onnx")
PY
echo "done in $((SECONDS - start)) s"
