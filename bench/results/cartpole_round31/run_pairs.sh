#!/bin/bash
# round 31: round 30's driver on seeds 33..40, rows here; the file $STOP (default /tmp/round31_stop) stops it before the next pair
OUT=bench/results/cartpole_round31 STOP=${STOP:-/tmp/round31_stop} SEEDS="33 34 35 36 37 38 39 40" \
  exec bash "$(dirname "$0")/../cartpole_round30/run_pairs.sh"
