#!/usr/bin/env bash
# Every measurement of experiments/server_overhead, appended to results.txt. Run from the repository root on a
# clean working tree (each A/B applies a patch to the working tree, runs bench_server_ab.py against HEAD, and
# takes the patch back out). About 8 minutes on 2 cores.
set -euo pipefail
here=experiments/server_overhead
out=$here/results.txt
py=.venv/bin/python
git diff --quiet || { echo "run.sh needs a clean working tree" >&2; exit 1; }
stamp() { echo; echo "# $* (at $(git rev-parse --short HEAD), $(date -u +%F), load avg $(cut -d' ' -f1 /proc/loadavg))"; }
ab() {  # PATCH ARGS...: the patched working tree against HEAD
  local patch=$1; shift
  git apply "$here/$patch"
  trap 'git apply -R "$here/$patch"' EXIT
  stamp "git apply $here/$patch; $py benchmarks/bench_server_ab.py --base HEAD $*"
  $py benchmarks/bench_server_ab.py --base HEAD "$@" 2>&1 | grep -v '^$'
  git apply -R "$here/$patch"
  trap - EXIT
}
{
  ab chunked_checks.patch --engine kernel --protocol shm --model models/rock.onnx --rows 131072,1048576 \
     --big-rounds 9 --calls 4 --slow-runs 0
  ab full_rows.patch --engine kernel --protocol shm --model models/rock.onnx --rows 65536,131072 \
     --big-rounds 7 --clients 2 --slow-runs 0
  stamp "$py $here/kernel_chunks.py"
  $py $here/kernel_chunks.py
  stamp "$py $here/huge_tables.py"
  $py $here/huge_tables.py
  ab pool_shrink.patch --engine kernel --protocol shm --model models/rock.onnx --rows 131072,1048576 \
     --big-rounds 7 --calls 5 --slow-runs 0
  stamp "$py $here/idle_pool.py rock yarn"
  $py $here/idle_pool.py rock yarn
} | tee -a "$out"
