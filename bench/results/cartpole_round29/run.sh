#!/bin/bash
# as run on the machine of 2026-12-05 (its paths); two copies side by side take seeds from the queue file in order
# round 29: the Munchausen ramp on seeds 0-4 then 5-9, two workers, every seed run (none dropped)
cd /work/main
OUT=bench/results/cartpole_round29; STOP=/work/round29_stop
run() {
  seed=$1
  .venv/bin/python -m bench.tasks gym/cartpole --threshold 475 --steps 30000 --every 1000 --seeds $seed --final-episodes 100 --override sac.munchausen_scale=0.9 --override sac.munchausen_scale_start=0 > $OUT/log_ramp_seed$seed.txt 2>&1
  row=$(grep "^gym/cartpole,default,sac.munchausen_scale=0.9 sac.munchausen_scale_start=0,$seed,30000,475.0,.*,100," bench/results/tasks.csv | tail -1)
  [ -z "$row" ] && { echo "no row for $seed" >> $OUT/errors.txt; return; }
  file=$OUT/reported_seeds.csv; [ $seed -ge 5 ] && file=$OUT/unused_seeds.csv
  flock $OUT/rows.lock bash -c "echo '$row' >> $file"
}
QUEUE=/work/round29_queue  # seeds in order, one per line; each worker takes the next
next_seed() { flock $QUEUE.lock bash -c "head -n 1 $QUEUE; sed -i 1d $QUEUE"; }
while [ ! -e $STOP ]; do seed=$(next_seed); [ -z "$seed" ] && break; run $seed; done
