"""How far a trained policy pushes its pre-tanh actions, along one deterministic episode of its own.

    python -m bench.saturation RUN_DIR|SB3_ZIP [...] [--seed 12345]

Where ``|u| > ~6.5`` the squashed Gaussian's log-density differs between ASAC, which computes
``log(1 - tanh(u)^2)`` exactly (``2 (log 2 - u - softplus(-2u))``), and SB3 or CleanRL, which add 1e-6
inside the log: there ``1 - tanh(u)^2 ~ 4 exp(-2|u|)`` falls to ~1e-5 and below, so the epsilon caps
the entropy bonus's pull back from the edge. Below ~5 the two agree to under 1% per dimension. This
prints, per run (its latest checkpoint), the episode's return and the distribution of ``|mean u|`` over
steps and action dimensions, and the policy's standard deviation: whether that difference can matter
for the task at all (bench/results/mujoco_float32/README.md). An SB3 model that ``python -m bench.vs_sb3 mujoco``
saved (``<runs>/mujoco_suite/<task>/sb3_s<seed>_<k>k.zip``) is probed the same way, on the same env.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from algorithm.config.load import config_from_file
from algorithm.run.checkpoint import load_for_resume
from algorithm.run.folder import RunDir
from algorithm.sac.policy import Policy
from bench.systems import MUJOCO_TASKS, SB3Policy
from cli import _load_policy, env_factory, run_model_builder
from envs.make import VectorEnv, make_vector_env

EDGE = 6.5  # |u| past which 1e-6 is more than ~10% of 1 - tanh(u)^2
PreTanh = Callable[[list[np.ndarray]], tuple[torch.Tensor, torch.Tensor]]  # obs -> the policy's mean u, log std
Act = Callable[..., tuple[np.ndarray, np.ndarray]]  # Policy.act: (obs, deterministic=) -> (actions, probs)


def probe(run: Path, seed: int) -> str:
    """One deterministic episode of ASAC's run folder ``run`` (its latest checkpoint)."""
    paths = RunDir(run)
    config = config_from_file(paths.config)
    ckpt, state = load_for_resume(paths.model, None)
    env = env_factory(config)(1, seed)
    policy = Policy(env.spec, config.sac_config, config.nn_config, device="cpu", build=run_model_builder(paths))
    _load_policy(policy, state, ckpt)
    models = policy.models
    actor = models.policy
    if actor is None:
        raise SystemExit(f"{run}: no continuous policy")

    def pre_tanh(obs: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        x = [torch.as_tensor(np.asarray(v), dtype=torch.float32) for v in obs]
        if models.normalizer is not None:
            x = models.normalizer(x)
        return actor(models.representation(x))

    return f"{run} ({ckpt.stem}): " + episode(env, pre_tanh, policy.act, seed)


def probe_sb3(model_zip: Path, seed: int) -> str:
    """The same episode for an SB3 SAC model saved by the suite (``<runs>/mujoco_suite/<task>/sb3_*.zip``:
    the task is the folder's name)."""
    task = model_zip.parent.name
    if task not in MUJOCO_TASKS:
        raise SystemExit(
            f"{model_zip}: its folder names no task of {sorted(MUJOCO_TASKS)} (the suite saves to mujoco_suite/<task>/)"
        )
    from stable_baselines3 import SAC as SB3SAC

    model = SB3SAC.load(model_zip, device="cpu")
    env = make_vector_env(MUJOCO_TASKS[task], 1, seed=seed)

    def pre_tanh(obs: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std, _ = model.actor.get_action_dist_params(torch.as_tensor(np.asarray(obs[0]), dtype=torch.float32))
        return mean, log_std

    return f"{model_zip} (SB3): " + episode(env, pre_tanh, SB3Policy(model).act, seed)


def episode(env: VectorEnv, pre_tanh: PreTanh, act: Act, seed: int) -> str:
    """Steps one env through one episode acting deterministically; the return and ``|mean u|``'s spread."""
    means, stds, total = [], [], 0.0
    obs = env.reset(seed=seed)
    while True:
        with torch.no_grad():
            mean, log_std = pre_tanh(obs)
        means.append(mean.numpy().ravel())
        stds.append(log_std.exp().numpy().ravel())
        action, _ = act(obs, deterministic=True)
        step = env.step(action)
        obs = step.obs
        total += float(step.rewards.sum())
        if step.terminated.any() or step.truncated.any():
            break
    env.close()
    u, std = np.abs(np.concatenate(means)), np.concatenate(stds)
    return (
        f"{len(means)} steps, return {total:.0f}; |mean u| median {np.median(u):.2f}, "
        f"p90 {np.percentile(u, 90):.2f}, max {u.max():.2f}; share > 4: {np.mean(u > 4):.3f}, "
        f"> {EDGE}: {np.mean(u > EDGE):.3f}; std median {np.median(std):.3f}"
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="ASAC run folders (models/<task>/<name>) or SB3 models (.zip)")
    p.add_argument("--seed", type=int, default=12345, help="the episode's env seed")
    args = p.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        print((probe_sb3 if run.suffix == ".zip" else probe)(run, args.seed), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
