#!/bin/bash
# Seeds 3-4 of HalfCheetah-v5 and Ant-v5, ASAC and SB3 side by side (PLAN.md here), from a `git archive`
# snapshot of COMMIT (default HEAD) so that edits to the working tree never reach a run. Skips the runs
# already in bench/results/mujoco_float32/summary.csv, so the same command resumes the set.
#   nohup bash bench/results/mujoco_seeds_3_4/run.sh [COMMIT] > /tmp/mujoco34.log 2>&1 &
set -euo pipefail
repo=$(cd "$(dirname "$0")/../../.." && pwd)
commit=$(git -C "$repo" rev-parse --short "${1:-HEAD}")
source "$repo/bench/snapshot.sh"
snap=$(snapshot "$repo" "$commit")
cd "$snap"
for task in half_cheetah ant; do
    for which in ours sb3; do
        ASAC_BENCH_CODE=$commit "$repo/.venv/bin/python" -m bench.vs_sb3 mujoco "$task" --seeds 3 4 --which "$which" \
            --override sac.compute_dtype=float32 --out "$repo/bench/results/mujoco_float32" \
            --runs /work/asac_long_runs >"/tmp/mujoco34_${task}_$which.log" 2>&1 &
    done
    wait
done
