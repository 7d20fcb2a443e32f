#!/usr/bin/env bash
# The checks that need an NVIDIA GPU, in one short run (experiments/gpu/gpu.txt has the last one's figures):
#   1. CUDA parity: the in-kernel engine on drjit's CUDA backend against ONNX Runtime
#      (tests/engines/test_kernel.py), the material on the GPU against its graph (tests/training/export/test_graph.py)
#      and a run trained on the GPU that resumes on the CPU and exports what it computed (tests/training/loop/test_train.py);
#   2. training on the GPU: experiments/maps/maps.py's relief + base recipe at 64^2 (the shipped one), at the maps'
#      256^2, and both with the `quality` schedule (4.2x the steps), each judged on a low-noise reference set;
#   3. the kernel's throughput on the GPU beside the CPU's (benchmarks/bench_models.py).
#
#   bash experiments/gpu/gpu_check.sh DATA MATERIAL REFERENCE OUT [SECONDS]
#
# DATA: a `neumip generate` data set of MATERIAL; REFERENCE: its low-noise reference set (make_models.sh's
# runs/NAME/reference); OUT: where the logs and each run's record go (the models stay in /tmp);
# SECONDS (default 420): the wall-clock budget, so
# that the last steps are cut rather than the whole run. It runs where the repository is not installed:
# with the python that has torch (and numpy, onnx, onnxruntime, msgpack, pytest), the repository's areas
# linked into a `neumip` namespace under /tmp/neumip_site, and drjit from wheels in .whl/ if there are any.
set -u
data=$1 material=$2 reference=$3 out=$4 budget=${5:-420}
start=$SECONDS
source experiments/gpu/gpu_site.sh
mkdir -p "$out"
left() { echo $((budget - (SECONDS - start))); }

{ nvidia-smi -L; python3 -c "import torch, drjit as dr; print('torch', torch.__version__, torch.cuda.get_device_name(),
'| drjit', dr.__version__, 'CUDA backend', dr.has_backend(dr.JitBackend.CUDA))"; } 2>&1 | tee "$out/device.txt"

echo "== 1. CUDA parity"
timeout $(( $(left) / 3 )) python3 -m pytest -q -rs -p no:cacheprovider tests/engines/test_kernel.py \
    tests/training/export/test_graph.py tests/training/loop/test_train.py -k "cuda or gpu" 2>&1 | tee "$out/parity.txt"

train() {  # experiments/maps/maps.py train VARIANT on the GPU, cut 45 s before the budget ends
    [ "$(left)" -gt 60 ] || { echo "$1: skipped, $(left) s left"; return; }
    timeout $(( $(left) - 45 )) python3 experiments/maps/maps.py train "$1" --data "$data" --material "$material" \
        --runs "$runs" --device cuda --reference "$reference" 2>&1 | grep -v "^\s*$" | tail -3
}

echo "== 2. training on the GPU: the shipped recipe"
train Nbr 2>&1 | tee "$out/train.txt"

echo "== 3. the kernel on the GPU and on the CPU (where drjit finds libLLVM)"
mkdir -p "$runs/models"
cp "$runs"/Nbr/*.onnx "$runs/models/"
backends=$(python3 -c "import drjit as dr; print('llvm,cuda' if dr.has_backend(dr.JitBackend.LLVM) else 'cuda')")
timeout 90 python3 benchmarks/bench_models.py "$runs/models" --queries 20 --rounds 3 --backends "$backends" 2>&1 \
    | tee "$out/kernel.txt"

echo "== 4. training on the GPU: 256^2 and the longer schedule"
for variant in Nbr256 Nbr_quality Nbr256_quality; do train $variant; done 2>&1 | tee -a "$out/train.txt"
for record in "$runs"/*/*.json; do cp "$record" "$out/$(basename "$(dirname "$record")").json"; done
echo "done in $((SECONDS - start)) s"
