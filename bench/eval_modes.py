"""Each checkpoint of a run scored twice on the same start states: by the policy's mode and by sampling.

    python -m bench.eval_modes RUN_DIR [--episodes 20] [--seed 12345]

Reported evaluations act with the mode (``argmax`` for a discrete policy, ``tanh(mean)`` for a
continuous one). When a discrete policy's actions are near-equal in value for long stretches (a
balanced CartPole pole), the argmax picks the same action whenever the tie leans one way, and a
small systematic lean can walk the cart to the edge of its track over 500 steps, where sampling
would jitter around it. This prints, per checkpoint, both returns, and how the mode's episodes
ended: by the time limit, or (for CartPole, from the last observation) by the cart leaving the
track (``|x| > 2.4``) or the pole falling (``|theta| > 12 degrees``) -- the diagnostic behind
BENCHMARKS.md section 8's question of why CartPole's late evaluations dip.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from algorithm.checkpoint import checkpoint_path, list_checkpoints, load_checkpoint
from algorithm.config import config_from_file
from algorithm.evaluation import evaluate
from algorithm.policy import Policy
from algorithm.run_dir import RunDir
from cli import _load_policy, env_factory, run_model_builder

CART_EDGE = 2.4  # CartPole-v1's termination thresholds (gymnasium's cartpole.py)
POLE_EDGE = 12 * 2 * np.pi / 360


def mode_endings(env, policy: Policy, episodes: int, seed: int) -> dict[str, int]:
    """How ``episodes`` mode-acting episodes on the single CartPole env ``env`` ended, from ``seed``'s
    start states."""
    counts = {"time limit": 0, "cart edge": 0, "pole": 0, "other": 0}
    obs = env.reset(seed=seed)
    while sum(counts.values()) < episodes:
        actions, _ = policy.act(obs, deterministic=True)
        result = env.step(actions)
        if result.truncated[0]:
            counts["time limit"] += 1
        elif result.terminated[0]:
            last = result.final_obs[0][0]
            if abs(last[0]) > CART_EDGE:
                counts["cart edge"] += 1
            elif abs(last[2]) > POLE_EDGE:
                counts["pole"] += 1
            else:
                counts["other"] += 1
        obs = result.obs
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=12345)
    args = parser.parse_args(argv)
    paths = RunDir(args.run)
    config = config_from_file(paths.config)
    steps = list_checkpoints(paths.model)
    if not steps:
        raise SystemExit(f"{args.run}: no checkpoints under {paths.model}")
    is_cartpole = "CartPole" in str(config.base_config.build_path)
    print("step,mode_return,sampled_return" + (",time_limit,cart_edge,pole,other" if is_cartpole else ""))
    for step in steps:
        path = checkpoint_path(paths.model, step)
        state = load_checkpoint(path)
        env = env_factory(config)(1, args.seed)
        policy = Policy(env.spec, config.sac_config, config.nn_config, device="cpu", build=run_model_builder(paths))
        _load_policy(policy, state, path)
        mode = evaluate(env, policy, args.episodes, args.seed).mean
        sampled = evaluate(env, policy, args.episodes, args.seed, deterministic=False).mean
        row = f"{step},{mode:.1f},{sampled:.1f}"
        if is_cartpole:
            ends = mode_endings(env, policy, args.episodes, args.seed)
            row += f",{ends['time limit']},{ends['cart edge']},{ends['pole']},{ends['other']}"
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
