#!/bin/bash
# The new default (the ramp) on seeds 0-4, DECISION.md here: from a `git archive` snapshot of COMMIT (default HEAD),
# two workers taking seeds from a queue in order; each row is copied into reported_seeds.csv here as it lands.
#   nohup bash bench/results/cartpole_default_ramp/run.sh [COMMIT] > /tmp/cartpole_default.log 2>&1 &
set -uo pipefail
repo=$(cd "$(dirname "$0")/../../.." && pwd)
commit=$(git -C "$repo" rev-parse --short "${1:-HEAD}")
source "$repo/bench/snapshot.sh"
snap=$(snapshot "$repo" "$commit")
out=$repo/bench/results/cartpole_default_ramp
queue=$out/queue; printf '%s\n' 0 1 2 3 4 > "$queue"
next_seed() { flock "$queue.lock" bash -c "head -n 1 $queue; sed -i 1d $queue"; }
worker() {
    while seed=$(next_seed); [ -n "$seed" ]; do
        (cd "$snap" && "$repo/.venv/bin/python" -m bench.tasks gym/cartpole --threshold 475 --steps 30000 --every 1000 \
            --seeds "$seed" --final-episodes 100) > "$out/log_seed$seed.txt" 2>&1
        row=$(grep "^gym/cartpole,default,,$seed,30000,475.0,.*,100," "$snap/bench/results/tasks.csv" | tail -1)
        [ -z "$row" ] && { echo "no row for seed $seed" >> "$out/errors.txt"; continue; }
        flock "$out/rows.lock" bash -c "echo '$row' >> $out/reported_seeds.csv"
    done
}
worker & worker & wait
rm -f "$queue" "$queue.lock"
