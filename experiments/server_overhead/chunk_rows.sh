#!/usr/bin/env bash
# The kernel engine's call size (NEUMIP_KERNEL_CHUNK_ROWS) 2^18 against 2^20, appended to results.txt: four fresh
# servers of each, alternately (one client), then two of each with two client processes at once, each run
# `server_cpu.py` (rock, shared memory and msgpack, 3 rounds); then one call's memory (`call_memory.py`). The
# server processes differ in speed by up to 25 %, so each setting gets several. About 15 minutes on 2 cores.
set -euo pipefail
here=experiments/server_overhead
py=.venv/bin/python
{
  echo; echo "# $here/chunk_rows.sh (at $(git rev-parse --short HEAD), $(date -u +%F), load avg $(cut -d' ' -f1 /proc/loadavg))"
  for clients in 1 1 1 1 2 2; do
    for rows in 262144 1048576; do
      batches=17,20; [ "$clients" = 1 ] || batches=20
      echo "== NEUMIP_KERNEL_CHUNK_ROWS=$rows, $clients client(s): $py benchmarks/server_cpu.py --batches $batches --protocols shm,msgpack --rounds 3 --clients $clients --server-env NEUMIP_KERNEL_CHUNK_ROWS=$rows"
      $py benchmarks/server_cpu.py --batches $batches --protocols shm,msgpack --rounds 3 --clients $clients \
        --server-env NEUMIP_KERNEL_CHUNK_ROWS=$rows | grep -v '^$'
    done
  done
  echo "# $py $here/call_memory.py rock"
  $py $here/call_memory.py rock
} | tee -a $here/results.txt
