#!/usr/bin/env bash
# The checks that need an NVIDIA GPU, in one short run (experiments/gpu/gpu.txt has the figures of each run):
#   1. CUDA parity: the in-kernel engine on drjit's CUDA backend against ONNX Runtime
#      (tests/engines/test_kernel.py), the material on the GPU against its graph (tests/training/export/test_graph.py)
#      and a run trained on the GPU that resumes on the CPU and exports what it computed (tests/training/loop/test_train.py);
#   2. the in-kernel engine on the GPU against its bounds and an MLP-only torch graph (benchmarks/bench_cuda.py);
#   3. `neumip train` of the shipped `maps` recipe with `--device auto` (the GPU there), each PRESET in turn, timed.
#
#   bash experiments/gpu/gpu_check.sh DATA OUT [SECONDS] [PRESET...]
#
# DATA: a `neumip generate` data set of rock (made on a machine with Mitsuba) with its progress views in DATA/views
# (a short `neumip train DATA -o x.onnx` there traces them into x.run/views; each run here starts from a copy);
# OUT: where the logs go; SECONDS (default 420): the wall-clock budget, so that a step that
# would outrun it is cut. PRESETs (default ship). It runs where the repository is not installed: with the python that
# has torch (and numpy, onnx, onnxruntime, msgpack, pytest), the repository's areas linked into a `neumip` namespace
# (gpu_site.sh), and drjit from wheels in .whl/.
set -u
data=$1 out=$2 budget=${3:-420}
shift $(($# < 3 ? $# : 3))
presets=${*:-ship}
start=$SECONDS
source experiments/gpu/gpu_site.sh
mkdir -p "$out"
left() { echo $((budget - (SECONDS - start))); }

{ nvidia-smi -L; python3 -c "import torch, drjit as dr; print('torch', torch.__version__, torch.cuda.get_device_name(),
'| drjit', dr.__version__, 'CUDA backend', dr.has_backend(dr.JitBackend.CUDA))"; } 2>&1 | tee "$out/device.txt"

echo "== 1. CUDA parity"
timeout $(( $(left) / 4 )) python3 -m pytest -q -rs -p no:cacheprovider tests/engines/test_kernel.py \
    tests/training/export/test_graph.py tests/training/loop/test_train.py -k "cuda or gpu" 2>&1 | tee "$out/parity.txt"

echo "== 2. the kernel on the GPU"
timeout $(( $(left) / 3 )) python3 benchmarks/bench_cuda.py models/rock.onnx 2>&1 | tee "$out/kernel.txt"

echo "== 3. training on the GPU"
for preset in $presets; do
    [ "$(left)" -gt 60 ] || { echo "$preset: not started, $(left) s left"; continue; }
    work="$runs/$preset"
    mkdir -p "$work/rock.run" && cp -r "$data/views" "$work/rock.run/views"
    began=$SECONDS
    timeout $(( $(left) - 20 )) python3 -c "import sys; from neumip.client.cli import main; sys.exit(main())" \
        train "$data" --recipe maps --preset "$preset" --device auto -o "$work/rock.onnx" 2>&1 \
        | tr '\r' '\n' | grep -v "^\s*$" | grep -v "step/s\]$" | tail -12
    echo "$preset: $((SECONDS - began)) s on the GPU"
done 2>&1 | tee "$out/train.txt"
echo "done in $((SECONDS - start)) s"
