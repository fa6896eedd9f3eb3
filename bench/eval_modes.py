"""Each checkpoint of a run scored twice on the same start states: by the policy's mode and by sampling.

    python -m bench.eval_modes RUN_DIR [--episodes 20] [--seed 12345] [--steps 30000 ...] [--critic-greedy]
    python -m bench.eval_modes RUN_DIR --critic STEP [--episodes 20] [--seed 12345]

Reported evaluations act with the mode (``argmax`` for a discrete policy, ``tanh(mean)`` for a
continuous one). When a discrete policy's actions are near-equal in value for long stretches (a
balanced CartPole pole), the argmax picks the same action whenever the tie leans one way, and a
small systematic lean could walk the cart to the edge of its track over 500 steps, where sampling
would jitter around it (on CartPole it does not: sampling scores below the mode; bench/results/cartpole/README.md).
This prints, per checkpoint, both returns, and how the mode's episodes ended: by the time limit,
or (for CartPole, from the last observation) by the cart leaving the track (``|x| > 2.4``) or the
pole falling (``|theta| > 12 degrees``) -- the diagnostic behind bench/results/cartpole/README.md's question
of why CartPole's late evaluations dip.

``--critic STEP`` (a discrete policy) asks whether the critic of checkpoint STEP saw such an ending
coming: along each mode episode that ended before the time limit it prints the chosen action's
``min_i Q_i(s, a)`` (the value the targets use) k steps before the end against what a perfect
critic of that policy would say, the discounted count of steps left ``(1 - gamma^k) / (1 - gamma)``
(rewards of 1; the entropy bonus adds a little); and over all episodes, how often the mode is the
action of the highest min-Q (how closely the policy follows its critic) and the mean Q along the
episodes that reached the time limit.

``--critic-greedy`` (a policy with one discrete branch) adds a column: the checkpoint acting by its
critic instead of its policy, the action of the highest ``min_i Q_i(s, a)`` at every step, on the
same start states. Where the policy lags behind a critic that knows a better action, this column
is the higher one; where both fail alike, the critic does not know the better action either.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from algorithm.config.load import Config, ConfigError, config_from_file
from algorithm.run.checkpoint import checkpoint_path, list_checkpoints, load_checkpoint
from algorithm.run.evaluation import evaluate
from algorithm.run.folder import RunDir
from algorithm.sac.policy import Policy
from cli import _load_policy, env_factory, run_model_builder
from envs.make import VectorEnv

CART_EDGE = 2.4  # CartPole-v1's termination thresholds (gymnasium's cartpole.py)
POLE_EDGE = 12 * 2 * np.pi / 360


def mode_endings(env: VectorEnv, policy: Policy, episodes: int, seed: int) -> dict[str, int]:
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


def critic_min_q(policy: Policy, obs: list[np.ndarray]) -> np.ndarray:
    """``min_i Q_i(s, a)`` of a discrete policy's critic, the value its targets use: ``[N, actions]``."""
    import torch

    with torch.no_grad():
        state = policy.models.representation(policy.obs_tensors(obs))
        return policy.models.q(state, None).min(dim=0).values.numpy()


class CriticGreedy:
    """Acts, for ``evaluate``, with the action of the highest ``min_i Q_i(s, a)`` of ``policy``'s critic."""

    def __init__(self, policy: Policy) -> None:
        action = policy.spec.action
        if policy.models.discrete_policy is None or len(action.discrete_branches) != 1 or action.continuous_dim:
            raise SystemExit("--critic-greedy: the run's policy does not have exactly one discrete branch")
        if policy.rnn_state_size:
            raise SystemExit("--critic-greedy: the run's policy is recurrent")
        self.policy = policy
        self.actions = action.discrete_branches[0]

    def act(self, obs: list[np.ndarray], deterministic: bool = True) -> tuple[np.ndarray, np.ndarray]:
        greedy = np.eye(self.actions, dtype=np.float32)[np.argmax(critic_min_q(self.policy, obs), axis=-1)]
        return greedy, np.zeros(len(greedy), dtype=np.float32)


def critic_along_failures(env: VectorEnv, policy: Policy, config: Config, episodes: int, seed: int) -> list[str]:
    """The ``--critic`` report's lines for ``episodes`` mode-acting episodes on the single env ``env``."""
    if policy.models.discrete_policy is None:
        raise SystemExit("--critic: the run's policy is not discrete")
    gamma = float(config.sac_config.gamma)
    lines = ["episode,ending,length,steps_before_end,q_chosen,discounted_steps_left,x"]
    chosen_q: list[tuple[float, float]] = []  # (Q of the chosen action, cart position) per step
    q_at_time_limit: list[float] = []
    reached_time_limit = 0
    follows: list[bool] = []
    obs = env.reset(seed=seed)
    done = 0
    while done < episodes:
        q_min = critic_min_q(policy, obs)[0]  # [actions]
        actions, _ = policy.act(obs, deterministic=True)
        chosen = int(np.argmax(np.asarray(actions).reshape(-1)))  # one-hot over the branch's actions
        follows.append(chosen == int(np.argmax(q_min)))
        chosen_q.append((float(q_min[chosen]), float(obs[0][0][0])))
        result = env.step(actions)
        if result.terminated[0] or result.truncated[0]:
            if result.truncated[0]:
                q_at_time_limit += [q for q, _ in chosen_q]
                reached_time_limit += 1
            else:
                ending = "cart edge" if abs(result.final_obs[0][0][0]) > CART_EDGE else "pole"
                length = len(chosen_q)
                for k in (300, 200, 100, 50, 20, 10, 5, 1):
                    if k <= length:
                        q, x = chosen_q[length - k]
                        left = (1 - gamma**k) / (1 - gamma)
                        lines.append(f"{done},{ending},{length},{k},{q:.1f},{left:.1f},{x:+.2f}")
            chosen_q = []
            done += 1
        obs = result.obs
    lines.append(f"# the mode is the action of the highest min-Q on {np.mean(follows):.3f} of {len(follows)} steps")
    if q_at_time_limit:
        lines.append(f"# mean Q along the {reached_time_limit} episodes that reached the time limit: "
                     f"{np.mean(q_at_time_limit):.1f} (1 / (1 - gamma) = {1 / (1 - gamma):.1f})")  # fmt: skip
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--critic", type=int, metavar="STEP", help="the critic along checkpoint STEP's failures")
    parser.add_argument("--steps", type=int, nargs="+", metavar="STEP", help="score only these checkpoints")
    parser.add_argument("--critic-greedy", action="store_true", help="add a column: acting by the critic's min-Q")
    args = parser.parse_args(argv)
    paths = RunDir(args.run)
    try:
        config = config_from_file(paths.config)
    except ConfigError as e:
        raise SystemExit(f"{args.run}: not a run folder ({e})") from None
    steps = list_checkpoints(paths.model)
    if not steps:
        raise SystemExit(f"{args.run}: no checkpoints under {paths.model}")
    missing = sorted(set(args.steps or []) - set(steps))
    if missing:
        raise SystemExit(f"--steps {missing}: no such checkpoint; the run has {steps}")
    steps = args.steps or steps
    is_cartpole = "CartPole" in str(config.base_config.build_path)
    if args.critic is not None:
        if args.critic not in steps:
            raise SystemExit(f"--critic {args.critic}: no such checkpoint; the run has {steps}")
        env, policy = checkpoint_policy(paths, config, args.critic, args.seed)
        print("\n".join(critic_along_failures(env, policy, config, args.episodes, args.seed)))
        return 0
    header = "step,mode_return,sampled_return" + (",time_limit,cart_edge,pole,other" if is_cartpole else "")
    print(header + (",critic_greedy_return" if args.critic_greedy else ""))
    for step in steps:
        env, policy = checkpoint_policy(paths, config, step, args.seed)
        mode = evaluate(env, policy, args.episodes, args.seed).mean
        sampled = evaluate(env, policy, args.episodes, args.seed, deterministic=False).mean
        row = f"{step},{mode:.1f},{sampled:.1f}"
        if is_cartpole:
            ends = mode_endings(env, policy, args.episodes, args.seed)
            row += f",{ends['time limit']},{ends['cart edge']},{ends['pole']},{ends['other']}"
        if args.critic_greedy:
            row += f",{evaluate(env, CriticGreedy(policy), args.episodes, args.seed).mean:.1f}"  # type: ignore[arg-type]
        print(row, flush=True)
    return 0


def checkpoint_policy(paths: RunDir, config: Config, step: int, seed: int) -> tuple[VectorEnv, Policy]:
    """One env of the run's task and the policy of its checkpoint at ``step``."""
    path = checkpoint_path(paths.model, step)
    state = load_checkpoint(path)
    env = env_factory(config)(1, seed)
    policy = Policy(env.spec, config.sac_config, config.nn_config, device="cpu", build=run_model_builder(paths))
    _load_policy(policy, state, path)
    return env, policy


if __name__ == "__main__":
    raise SystemExit(main())
