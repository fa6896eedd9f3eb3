#!/usr/bin/env bash
# `make image-test`: builds the CPU image (Dockerfile's runtime target) and runs it as docs/deploy.md
# documents, with podman or docker, whichever is installed (ENGINE picks one); skips, saying so,
# where neither is. Checks: the default command (--help), also on a read-only root file system; a short
# `gym/pendulum local --actors 1` writing its run folder to a volume at /data; every role starting
# without extra environment; a role given a model root it cannot write ends with one line, exit 2; a task
# folder of one's own, mounted read-only, trains through `local`.
#
# TORCH_WHEELS: a folder holding the torch 2.13.0+cpu wheel, for machines that cannot reach the
# PyTorch index (podman only: mounted into the build, named by the build argument PIP_FIND_LINKS). Default: the host pip's PIP_FIND_LINKS
# folder when it holds that wheel.
set -euo pipefail
cd "$(dirname "$0")/.."

ENGINE="${ENGINE:-$(command -v podman || command -v docker || true)}"
if [ -z "$ENGINE" ]; then
    echo "image-test: SKIPPED: neither podman nor docker is installed (install one, or set ENGINE)"
    exit 0
fi
IMAGE="${IMAGE:-localhost/asac:image-test}"
MAX_STEP="${MAX_STEP:-1500}"
tag="asac-image-test-$$"
work="$(mktemp -d)"
fail() { echo "image-test: FAILED: $*" >&2; exit 1; }
cleanup() {
    "$ENGINE" rm -f "$tag-replay" "$tag-learner" "$tag-actor" "$tag-evolver" >/dev/null 2>&1 || true
    "$ENGINE" volume rm -f "$tag" >/dev/null 2>&1 || true
    rm -rf "$work"
}
trap cleanup EXIT

build=("$ENGINE" build -t "$IMAGE")
wheels="${TORCH_WHEELS:-${PIP_FIND_LINKS:-}}"
if [ -n "$wheels" ] && compgen -G "$wheels/torch-2.13.0+cpu-*.whl" >/dev/null && [ "$(basename "$ENGINE")" = podman ]; then
    build+=(-v "$wheels:/tmp/wheels:ro" --build-arg PIP_FIND_LINKS=/tmp/wheels)
    echo "image-test: torch's CPU wheel from $wheels"
fi
echo "image-test: $ENGINE, image $IMAGE"
start=$(date +%s)
"${build[@]}" . > "$work/build.log" 2>&1 || { tail -30 "$work/build.log"; fail "the build failed ($work/build.log)"; }
echo "image-test: built in $(( $(date +%s) - start )) s"

# 1. The default command, as built and on a read-only root file system (as k8s/ runs it).
"$ENGINE" run --rm "$IMAGE" > "$work/help.txt" 2>&1 || { cat "$work/help.txt"; fail "docker run IMAGE (--help)"; }
grep -q "usage: main_ds.py" "$work/help.txt" || fail "--help printed no usage: $(head -5 "$work/help.txt")"
"$ENGINE" run --rm --read-only --tmpfs /tmp "$IMAGE" --help > "$work/help_ro.txt" 2>&1 \
    || { cat "$work/help_ro.txt"; fail "--help on a read-only root file system"; }
echo "image-test: ok: --help (and with --read-only --tmpfs /tmp)"

# 2. A short local run; its run folder lands on the volume mounted at /data.
"$ENGINE" volume create "$tag" >/dev/null
"$ENGINE" run --rm -v "$tag:/data" "$IMAGE" gym/pendulum local --actors 1 -n smoke --no_progress \
    --override "base_config.max_step=$MAX_STEP" > "$work/local.txt" 2>&1 \
    || { tail -30 "$work/local.txt"; fail "gym/pendulum local --actors 1"; }
! grep -q Traceback "$work/local.txt" || { cat "$work/local.txt"; fail "a traceback in the local run"; }
"$ENGINE" run --rm -v "$tag:/data" --entrypoint sh "$IMAGE" -c \
    'cd /data/models/gym/pendulum/smoke && ls config.yaml evaluations.csv model/*.pt' > "$work/files.txt" 2>&1 \
    || { cat "$work/files.txt"; fail "no run folder /data/models/gym/pendulum/smoke with config, evaluations, checkpoint"; }
echo "image-test: ok: local run, run folder on the volume: $(tr '\n' ' ' < "$work/files.txt")"

# 3. Every role starts without extra environment (each waits for its peers; none may crash).
for role in replay learner actor evolver; do
    "$ENGINE" run -d --name "$tag-$role" -v "$tag:/data" "$IMAGE" gym/pendulum "$role" -n roles --no_progress >/dev/null
done
sleep "${ROLE_WAIT_S:-20}"
for role in replay learner actor evolver; do
    state="$("$ENGINE" inspect -f '{{.State.Status}}' "$tag-$role")"
    "$ENGINE" logs "$tag-$role" > "$work/$role.txt" 2>&1
    if [ "$state" != running ] || grep -q Traceback "$work/$role.txt"; then
        cat "$work/$role.txt"; fail "$role: $state"
    fi
done
echo "image-test: ok: replay, learner, actor, evolver running"

# 4. A model root the user cannot write (the root-owned /opt/asac): one line, exit 2.
set +e
"$ENGINE" run --rm "$IMAGE" gym/pendulum replay --model_root /opt/asac/models > "$work/bad.txt" 2>&1
code=$?
set -e
[ "$code" = 2 ] && [ "$(wc -l < "$work/bad.txt")" = 1 ] && grep -q "^error: .*/opt/asac" "$work/bad.txt" \
    || { cat "$work/bad.txt"; fail "a non-writable model root: exit $code, not one line with exit 2"; }
echo "image-test: ok: non-writable model root: exit 2: $(cat "$work/bad.txt")"
# 5. A task folder of one's own (README, "Your own environment"), mounted read-only, its env module
#    beside its config.yaml: trains through `local`, its run folder under /data/models/reach/.
mkdir -p "$work/reach"
cat > "$work/reach/reach_env.py" <<'PY'
import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import register


class Reach(gym.Env):
    observation_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, render_mode=None):
        self.render_mode = render_mode

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = float(self.np_random.uniform(-1.0, 1.0))
        return np.array([self.x], np.float32), {}

    def step(self, action):
        self.x = float(np.clip(self.x + 0.2 * float(action[0]), -2.0, 2.0))
        return np.array([self.x], np.float32), -abs(self.x), False, False, {}


register("MyReach-v0", entry_point="reach_env:Reach", max_episode_steps=20)
PY
cat > "$work/reach/config.yaml" <<'YAML'
default:
  base_config: {scene: reach, build_path: "reach_env:MyReach-v0", max_step: 600}
  replay_config: {min_size_to_sample: 200, capacity: 10000}
  nn_config: {hidden_units: [32, 32]}
  eval_config: {eval_per_step: 600, eval_episodes: 1, eval_envs: 1}
YAML
chmod -R a+rX "$work"
"$ENGINE" run --rm -v "$tag:/data" -v "$work/reach:/tasks/reach:ro" "$IMAGE" /tasks/reach local --actors 1 -n own \
    --no_progress > "$work/own.txt" 2>&1 || { tail -30 "$work/own.txt"; fail "/tasks/reach local --actors 1"; }
"$ENGINE" run --rm -v "$tag:/data" --entrypoint sh "$IMAGE" -c 'ls /data/models/reach/own/evaluations.csv' \
    > "$work/own_files.txt" 2>&1 || { cat "$work/own_files.txt"; fail "no /data/models/reach/own/evaluations.csv"; }
echo "image-test: ok: a task folder of one's own, mounted: $(cat "$work/own_files.txt")"
echo "image-test: PASSED ($(( $(date +%s) - start )) s)"
