#!/bin/bash
# round 30: default and ramp side by side per seed, seeds 25..32 in order; the file $STOP (default /tmp/round30_stop) stops it before the next pair
# (round 31 runs this with OUT, STOP and SEEDS of its own: ../cartpole_round31/run_pairs.sh)
cd "$(dirname "$0")/../../.."
OUT=${OUT:-bench/results/cartpole_round30}; STOP=${STOP:-/tmp/round30_stop}
RAMP="sac.munchausen_scale=0.9 sac.munchausen_scale_start=0"
run() {  # $1 arm, $2 seed
  arm=$1; seed=$2
  if [ $arm = ramp ]; then ov="--override sac.munchausen_scale=0.9 --override sac.munchausen_scale_start=0"; pat=$RAMP; else ov=""; pat=""; fi
  .venv/bin/python -m bench.tasks gym/cartpole --threshold 475 --steps 30000 --every 1000 --seeds $seed --final-episodes 100 $ov > $OUT/log_${arm}_seed$seed.txt 2>&1
  row=$(grep "^gym/cartpole,default,$pat,$seed,30000,475.0,.*,100," bench/results/tasks.csv | tail -1)
  [ -z "$row" ] && { echo "no row for $arm $seed" >> $OUT/errors.txt; return; }
  flock $OUT/rows.lock bash -c "echo '$row' >> $OUT/$arm.csv"
}
for seed in ${SEEDS:-25 26 27 28 29 30 31 32}; do
  [ -e $STOP ] && break
  grep -q ",$seed,30000," $OUT/ramp.csv 2>/dev/null && grep -q ",$seed,30000," $OUT/default.csv 2>/dev/null && continue
  run default $seed & sleep 2; run ramp $seed & wait
done
