#!/usr/bin/env bash
# Starts, or resumes, the MuJoCo comparison with SB3 (`python -m bench.vs_sb3 suite`) in the
# background, from a snapshot of a commit exported with `git archive` to /tmp/asac_bench_<commit>,
# so that edits in the working tree never reach a run that is going on. Results go to this
# checkout's bench/results/mujoco/ (runs already in its summary.csv are skipped); every row records
# the commit. One run at a time; the log is /tmp/mujoco_suite.log (LOG=...), the driver's pid
# /tmp/mujoco_suite.pid. SIGTERM to the driver (kill $(cat /tmp/mujoco_suite.pid)) saves ASAC's run in
# progress (an SB3 run is dropped) and starts no other; the same command resumes it.
#
#   bash bench/mujoco_suite.sh [COMMIT] [suite arguments, e.g. --tasks hopper --seeds 0 1 2]
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
ref=HEAD
if [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; then ref=$1; shift; fi
commit=$(git -C "$repo" rev-parse --short "$ref")
source "$repo/bench/snapshot.sh"
snap=$(snapshot "$repo" "$commit")
log=${LOG:-/tmp/mujoco_suite.log}
cd "$snap"
ASAC_BENCH_CODE=$commit nohup "$repo/.venv/bin/python" -m bench.vs_sb3 suite --out "$repo/bench/results/mujoco" "$@" \
    >>"$log" 2>&1 &
echo $! >/tmp/mujoco_suite.pid
echo "suite driver pid $! running $snap (commit $commit), log $log"
