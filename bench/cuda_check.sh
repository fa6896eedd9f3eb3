#!/bin/bash
# The checks this project runs on a machine with a GPU, in one go (BENCHMARKS.md section 12): the CUDA
# graph's tests against eager updates on the GPU and the pinned batches' test, its speed against eager
# updates (bench.cuda_graph), the --device cuda journeys (bench/cuda_journeys.sh), the learner role
# against main.py (bench.learner_rate), and HalfCheetah toward 3,000 with -c throughput and 1, 2, 4 and
# 8 actors side by side for L seconds (bench/scaling_parallel.sh). Packages the machine lacks can travel
# as wheels in .whl/
# (installed into /tmp/site first; on 2026-11-29 the H200 image lacked gymnasium, farama-notifications, mujoco,
# glfw, pyopengl, pyzmq, pydantic, pydantic_core, annotated-types, typing-inspection and grpcio-health-checking,
# and needed grpcio 1.85.3 and protobuf 7.36.2 for protos/: fetch them with `pip download --no-deps
# --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64
# -d .whl NAME==VERSION`, the versions of requirements/, with .whl/ in .git/info/exclude).
# Results go to $OUT (default /tmp/cuda_check).
# Usage: bash bench/cuda_check.sh [L] [DEVICE]
L=${1:-220}; D=${2:-cuda}; O=${OUT:-/tmp/cuda_check}; mkdir -p "$O"
PY=${PYTHON:-python3}
if ls .whl/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1
nvidia-smi -L 2>/dev/null; echo "cores $(nproc)"; $PY -c "import torch; print('torch', torch.__version__)"; date
echo "== tests/algorithm/sac/test_update_graph.py, tests/ds/replay/test_packed.py (pinned batches), test_shared.py (/dev/shm)"
timeout 150 $PY -m pytest -q -p no:cacheprovider tests/algorithm/sac/test_update_graph.py tests/ds/replay/test_packed.py tests/ds/replay/test_shared.py 2>&1 | tail -12
echo "== bench.cuda_graph"
timeout 120 $PY -m bench.cuda_graph --rounds 5 --updates 300 --out "$O/cuda_graph.csv" 2>&1 | tail -6
echo "== bench/cuda_journeys.sh"
PYTHON=$PY timeout 200 bash bench/cuda_journeys.sh "$D" 2>&1
grep -h "CUDA graph" /tmp/m1.log /tmp/m2.log 2>/dev/null | head -4
echo "== bench.learner_rate: the learner role against main.py's CUDA-graph loop, same config"
timeout 300 $PY -m bench.learner_rate mujoco/half_cheetah --steps 16000 --device "$D" --out "$O/learner_rate.csv" 2>&1 | tail -3
echo "== HalfCheetah -c throughput, 1, 2, 4 and 8 actors side by side, $L s"; date
ACTORS="1 2 4 8" SECTION=throughput OUT=$O timeout $((L + 90)) bash bench/scaling_parallel.sh "$L" "$D" "$PY" 2>&1 | tail -30
date
