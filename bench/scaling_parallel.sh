#!/bin/bash
# HalfCheetah to 3,000 with several actor counts (ACTORS, default "1 4 12"), the local runs at once (16
# cores, one GPU), each stopped at its first evaluation >= 3,000 or after L seconds (BENCHMARKS.md section
# 12); SECTION picks the config section (e.g. throughput; default: the task's default). Rows and logs
# go to $OUT (default /tmp/ht_out). Usage: bash bench/scaling_parallel.sh [L] [DEVICE] [PYTHON]
L=${1:-520}; D=${2:-cuda}; PY=${3:-python3}; O=${OUT:-/tmp/ht_out}; mkdir -p $O
ACTORS=${ACTORS:-1 4 12}; SEC=${SECTION:+-c $SECTION}
nproc; nvidia-smi -L 2>/dev/null; date
for n in $ACTORS; do
  PYTHONUNBUFFERED=1 $PY -m bench.scaling --actors $n $SEC --device $D --limit-s $L --out $O/ht3000_$n.csv --logs $O > /tmp/drv_$n.txt 2>&1 &
done
wait; date
cat /tmp/drv_*.txt | grep -v "^\s*$" | tail -20
for n in $ACTORS; do echo "== $n actors"; grep -E "evaluation|eval at" $O/actors_$n.log | tail -12; done
