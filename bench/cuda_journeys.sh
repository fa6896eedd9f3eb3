#!/bin/bash
# The --device cuda journeys on a machine with a GPU: main.py trains and plays (--run), main_ds.py local
# trains with its learner on the GPU; prints each exit code and the last evaluations. Short runs
# (600 env steps): a check that the paths work, not a measurement. Usage: bash bench/cuda_journeys.sh [DEVICE]
D=${1:-cuda}; R=/tmp/cc_models; rm -rf $R
O="--override base_config.max_step=600 --override replay.min_size_to_sample=200 --override eval.eval_per_step=300"
timeout 100 ${PYTHON:-python3} main.py gym/pendulum -n g --model_root $R --device $D --no_progress $O > /tmp/m1.log 2>&1; echo "main.py train rc=$?"; grep -E "eval at|stopped|finished" /tmp/m1.log | tail -3
timeout 60 ${PYTHON:-python3} main.py gym/pendulum -n g --model_root $R --device $D --run --episodes 2 > /tmp/m3.log 2>&1; echo "--run rc=$?"; tail -1 /tmp/m3.log
timeout 100 ${PYTHON:-python3} main_ds.py gym/pendulum local --actors 2 -n l --model_root $R --device $D $O > /tmp/m2.log 2>&1; echo "local rc=$?"; grep -E "eval at|final evaluation|Traceback|Error" /tmp/m2.log | tail -4
