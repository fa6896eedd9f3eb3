#!/usr/bin/env bash
# Adds torchrl's replay buffers to a virtual env so that `python -m bench.replay` measures torchrl's
# PrioritizedReplayBuffer beside ours and cpprb. A bench-only peer: asac never imports it.
#
# Usage: bash bench/torchrl_setup.sh [VENV]   (VENV defaults to .venv; it must already hold torch 2.13.0)
#
# Why it is done this way:
# - torchrl and tensordict publish wheels only (no sdist on PyPI), so there is no source to build.
# - Every package goes in with --no-deps: a plain `pip install torchrl` would replace torch 2.13.0 (CPU)
#   with another version and its CUDA wheels (gigabytes). torch stays as it is.
# - torchrl 0.14.1 declares tensordict>=0.14.3,<0.15; 0.14.3's own C++ extension loads against torch 2.13.
# - torchrl's wheel extension (_torchrl: the segment trees behind PrioritizedSampler) was linked against
#   a newer torch and misses two autograd symbols in 2.13, so a plain import disables the sampler.
#   bench/replay.py imports torchrl with lazy symbol binding, which needs neither symbol, and checks that
#   the sampler samples by priority before timing it. The last step below runs that same check.
set -euo pipefail

venv="$(cd "${1:-.venv}" && pwd)"  # absolute, before changing directory
py="$venv/bin/python"
cd "$(dirname "$0")/.."  # the repository root, for importing bench.replay below

torch_version() { "$py" -c 'import torch; print(torch.__version__.split("+")[0])'; }
[ "$(torch_version)" = 2.13.0 ] || { echo "expected torch 2.13.0 in $venv, found $(torch_version)" >&2; exit 1; }

# Of their declared dependencies only pure-python pyvers is both needed and missing from the project's
# env (numpy, packaging, cloudpickle are there; hoptorch, orjson, importlib_metadata are optional for
# replay buffers). nice: this machine's 2 cores are shared with long benchmarks.
nice -n 19 "$py" -m pip install --quiet --no-deps torchrl==0.14.1 tensordict==0.14.3 pyvers==0.2.3

[ "$(torch_version)" = 2.13.0 ] || { echo "torch changed to $(torch_version)" >&2; exit 1; }
if "$py" -m pip list 2>/dev/null | grep -i nvidia; then echo "nvidia packages appeared in $venv" >&2; exit 1; fi

# The bench's own import and sampler check: prints nothing when torchrl will be measured.
"$py" -c 'from bench.replay import import_torchrl, torchrl_works
classes, note = import_torchrl()
note = note or torchrl_works(classes)
raise SystemExit(note or None)'
echo "torchrl 0.14.1 ready in $venv: python -m bench.replay measures it"
