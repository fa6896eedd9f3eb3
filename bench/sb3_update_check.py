"""ASAC's SAC update against SB3's, step for step, from the same weights, batches and noise.

The MuJoCo suite (BENCHMARKS.md section 11) compares the two systems by their returns, which swing by hundreds
between seeds. This checks the update itself. SB3 SAC is built for a task as the suite builds it, its
initial weights are copied into an ASAC learner made from the task's config (float32), and both are
stepped on the same batches of real transitions (uniformly random actions on the task's env, as in the
warm-up) with the same standard-normal draws for the policy's two reparameterised samples. After each
update, per group of parameters, the gap is ``|d_ASAC - d_SB3| / |d_SB3|``, ``d`` the change from the
shared start: 0 where the updates agree.

ASAC runs in five variants (:data:`VARIANTS`), from its default to SB3's own choices in the three places
the two implementations differ: the squashed Gaussian's log-density (exact, or SB3's ``+ 1e-6`` inside
the log: ``sac.tanh_log_det_epsilon``), the order inside an update (``sac.update_order``) and the
arithmetic of the target average (the same average rounded another way). The last lines are the floor:
two ASAC learners, one given each batch's rows in another order (``--floors`` orders), which is what
float32 rounding alone makes of the gap::

    python -m bench.sb3_update_check walker2d

Needs stable-baselines3 (``pip install stable-baselines3==2.9.2``), as the suite does.
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import gymnasium as gym
import numpy as np
import torch

from algorithm.config.load import load_config
from algorithm.nn.layers import EnsembleLinear
from algorithm.sac.learner import SAC
from algorithm.spaces import env_spec
from algorithm.types import Batch
from bench.systems import MUJOCO_TASKS, sb3_model

ROOT = Path(__file__).resolve().parent.parent
GROUPS = ("policy", "q.", "target_q", "log_alpha")
# (log-density, update order, target arithmetic): ASAC's default first, SB3's choices in all three last.
VARIANTS = (
    ("exact", "joint", "lerp"),
    ("exact", "critic_first", "lerp"),
    ("sb3", "joint", "lerp"),
    ("sb3", "critic_first", "lerp"),
    ("sb3", "critic_first", "sb3"),
)
TRANSITIONS = 4000
SB3_LOG_DET_EPSILON = 1e-6  # SB3's SquashedDiagGaussianDistribution adds it inside log(1 - tanh(u)^2)
Report = Callable[[int, dict[str, float]], None]
Params = dict[str, torch.Tensor]


@dataclass
class Transitions:
    """``N`` single steps: observation, action in [-1, 1], reward, next observation, terminated."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray


def random_transitions(env_id: str, steps: int, seed: int) -> Transitions:
    """``steps`` transitions of uniformly random actions on ``env_id``."""
    env = gym.make(env_id)
    space: Any = env.action_space
    rng = np.random.default_rng(seed)
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("obs", "actions", "rewards", "next_obs", "terminated")}
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        action = rng.uniform(-1.0, 1.0, space.shape).astype(np.float32)
        next_obs, reward, terminated, truncated, _ = env.step(
            space.low + (action + 1.0) * 0.5 * (space.high - space.low)
        )
        for key, value in zip(rows, (obs, action, reward, next_obs, terminated), strict=True):
            rows[key].append(np.asarray(value))
        obs = env.reset()[0] if terminated or truncated else next_obs
    return Transitions(*(np.stack(rows[k]).astype(bool if k == "terminated" else np.float32) for k in rows))


def asac_learner(task: str, order: str, log_density: str = "exact") -> tuple[SAC, int]:
    """An ASAC learner from ``envs/mujoco/<task>``'s config in float32 with the update ``order`` and the
    ``log_density`` (exact, or sb3: ``sac.tanh_log_det_epsilon`` 1e-6), and the config's batch size."""
    epsilon = {"exact": 0.0, "sb3": SB3_LOG_DET_EPSILON}[log_density]
    overrides = ["sac.compute_dtype=float32", f"sac.update_order={order}", f"sac.tanh_log_det_epsilon={epsilon}"]
    config = load_config(ROOT / "envs" / "mujoco" / task, overrides=overrides).config
    env = gym.make(MUJOCO_TASKS[task])
    spec = env_spec(env.observation_space, env.action_space)
    return SAC(spec, config.sac_config, config.nn_config, config.replay_config), config.replay_config.batch_size


def asac_parameters(sac: SAC) -> Params:
    """ASAC's compared parameters (the live tensors) by name."""
    assert sac.models.policy is not None
    named: Params = {f"policy.{n}": p for n, p in sac.models.policy.named_parameters()}
    named |= {f"q.{n}": p for n, p in sac.models.q.named_parameters()}
    named |= {f"target_q.{n}": p for n, p in sac.target_q.named_parameters()}
    named["log_alpha"] = sac.log_alpha
    return named


def sb3_parameters(sb3: Any) -> Params:
    """SB3's values of the same parameters in ASAC's layout: ASAC's policy head is SB3's ``mu`` and
    ``log_std`` layers stacked, its Q heads SB3's two critics, one per ensemble index."""
    actor = sb3.policy.actor
    named = {}
    for i in (0, 2):
        named[f"policy.trunk.{i}.weight"] = actor.latent_pi[i].weight
        named[f"policy.trunk.{i}.bias"] = actor.latent_pi[i].bias
    named["policy.head.weight"] = torch.cat([actor.mu.weight, actor.log_std.weight])
    named["policy.head.bias"] = torch.cat([actor.mu.bias, actor.log_std.bias])
    for prefix, critic in (("q", sb3.policy.critic), ("target_q", sb3.policy.critic_target)):
        nets = [critic.qf0, critic.qf1]
        for layer in range(3):
            named[f"{prefix}.layers.{layer}.weight"] = torch.stack([n[2 * layer].weight for n in nets])
            named[f"{prefix}.layers.{layer}.bias"] = torch.stack([n[2 * layer].bias[None] for n in nets])
    named["log_alpha"] = sb3.log_ent_coef.reshape(())
    return named


def copied(params: Params) -> Params:
    return {n: p.detach().clone() for n, p in params.items()}


def relative_gaps(start: Params, ours: Params, theirs: Params) -> dict[str, float]:
    """Per group of parameters, ``|d_ours - d_theirs| / |d_theirs|`` (Euclidean norms over the group),
    ``d`` the change since ``start``. Not the largest absolute difference: Adam's first steps move each
    parameter by about the step size in the sign of its gradient, so a gradient within rounding of 0
    flips one parameter by twice the step size, and that maximum would measure the flip alone."""
    gaps = {}
    for group in GROUPS:
        names = [n for n in start if n.startswith(group)]
        d_ours = torch.cat([(ours[n] - start[n]).flatten().double() for n in names])
        d_theirs = torch.cat([(theirs[n] - start[n]).flatten().double() for n in names])
        gaps[group.rstrip(".")] = float((d_ours - d_theirs).norm() / d_theirs.norm().clamp_min(1e-30))
    return gaps


def asac_batch(data: Transitions, rows: np.ndarray) -> Batch:
    b, n = rows.size, data.obs.shape[0]
    actions = data.actions[rows][:, None]
    return Batch(
        keys=rows.astype(np.uint64), probabilities=np.full(b, 1.0 / n), table_size=n,
        obs=[np.stack([data.obs[rows], data.next_obs[rows]], axis=1)], actions=actions,
        prev_actions=np.zeros_like(actions), rewards=data.rewards[rows][:, None],
        terminated=data.terminated[rows][:, None], truncated=np.zeros((b, 1), dtype=bool),
        behaviour_logp=np.zeros((b, 1), dtype=np.float32), mask=np.ones((b, 1), dtype=bool),
    )  # fmt: skip


def sb3_samples(data: Transitions, rows: np.ndarray) -> Any:
    from stable_baselines3.common.type_aliases import ReplayBufferSamples

    def tensor(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a[rows]))

    return ReplayBufferSamples(
        observations=tensor(data.obs), actions=tensor(data.actions), next_observations=tensor(data.next_obs),
        dones=tensor(data.terminated.astype(np.float32))[:, None], rewards=tensor(data.rewards)[:, None],
        discounts=None,
    )  # fmt: skip


@contextlib.contextmanager
def patched(owner: Any, name: str, value: Any) -> Iterator[None]:
    original = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, original)


def sb3_polyak(targets: list[torch.Tensor], params: list[torch.Tensor], tau: float) -> None:
    """SB3's polyak_update arithmetic, ``t (1 - tau)`` then ``+ tau p``, for ASAC's ``t + tau (p - t)``."""
    for target, param in zip(targets, params, strict=True):
        torch.mul(target, 1 - tau, out=target)
        torch.add(target, param, alpha=tau, out=target)


def as_variant(arithmetic: str) -> contextlib.ExitStack:
    """While open, ASAC computes its target average as the variant says (the density and the order are
    config options: :func:`asac_learner`)."""
    stack = contextlib.ExitStack()
    if arithmetic == "sb3":
        stack.enter_context(patched(torch, "_foreach_lerp_", sb3_polyak))
    return stack


@contextlib.contextmanager
def sb3_noise(draws: list[torch.Tensor]) -> Iterator[None]:
    """SB3's Gaussian samples taken from ``draws`` in order (its SAC.train samples the policy at the
    batch's observations first, then at the next observations) instead of torch's global generator."""
    from stable_baselines3.common.distributions import DiagGaussianDistribution

    queue = list(draws)

    def sample(self: Any) -> torch.Tensor:
        return self.distribution.mean + self.distribution.stddev * queue.pop(0)

    with patched(DiagGaussianDistribution, "sample", sample):
        yield
    if queue:
        raise AssertionError(f"SB3's update took {len(draws) - len(queue)} of the {len(draws)} draws")


def asac_step(sac: SAC, data: Transitions, rows: np.ndarray, noise: torch.Tensor) -> None:
    """One ASAC update on ``rows`` with ``noise [B, 2, A]`` in place of its own draws."""
    with patched(sac, "_noise", lambda batch, generator: noise):
        if sac.update(asac_batch(data, rows)).skipped:
            raise RuntimeError("ASAC skipped the update (non-finite)")


def sb3_step(sb3: Any, data: Transitions, rows: np.ndarray, noise: torch.Tensor) -> None:
    """One SB3 update (its SAC.train) on ``rows`` with the same draws."""
    draws = [noise[:, 0].clone(), noise[:, 1].clone()]
    with patched(sb3.replay_buffer, "sample", lambda batch_size, env=None: sb3_samples(data, rows)), sb3_noise(draws):
        sb3.train(gradient_steps=1, batch_size=rows.size)


def batches(
    data: Transitions, batch: int, actions: int, updates: int, seed: int
) -> Iterator[tuple[np.ndarray, torch.Tensor]]:
    """``updates`` (rows, noise) pairs, the same for every variant of one seed."""
    rng = np.random.default_rng(seed)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(updates):
        yield rng.integers(0, data.obs.shape[0], batch), torch.randn((batch, 2, actions), generator=generator)


def relu_disagreements(sac: SAC, sb3: Any, data: Transitions, rows: np.ndarray) -> list[str]:
    """Where the two critics, each computing as it does (ASAC's batched heads, SB3's separate layers), put
    one of the batch's rows on different sides of a hidden ReLU: ``Q head H layer L unit U row R`` with the
    two pre-activations. The same weights give pre-activations that differ by rounding; a row within
    rounding of 0 is then on for one and off for the other, and that unit's update differs."""
    with torch.no_grad():
        state = sac.models.representation([torch.from_numpy(np.ascontiguousarray(data.obs[rows]))])
        x = torch.cat([state, torch.from_numpy(np.ascontiguousarray(data.actions[rows]))], dim=-1)
        layers = cast(list[EnsembleLinear], list(sac.models.q.layers))
        nets = [sb3.policy.critic.qf0, sb3.policy.critic.qf1]
        ours, theirs = x.expand(len(nets), *x.shape), [x for _ in nets]
        found = []
        for index, layer in enumerate(layers[:-1]):
            z_ours = torch.baddbmm(layer.bias, ours, layer.weight.mT)
            z_theirs = [net[2 * index](h) for net, h in zip(nets, theirs, strict=True)]
            for head, z in enumerate(z_theirs):
                for row, unit in torch.nonzero((z_ours[head] > 0) != (z > 0)).tolist():
                    pair = f"ASAC {float(z_ours[head, row, unit]):.2e}, SB3 {float(z[row, unit]):.2e}"
                    found.append(f"Q head {head} layer {index} unit {unit} row {row}: {pair}")
            ours, theirs = z_ours.relu(), [z.relu() for z in z_theirs]
    return found


def paired_learners(task: str, order: str, seed: int, log_density: str = "exact") -> tuple[SAC, Any, int]:
    """SB3 SAC built for ``task`` as the suite builds it, an ASAC learner (:func:`asac_learner`) holding
    its initial weights, and the batch size."""
    torch.manual_seed(seed)
    sb3 = sb3_model(MUJOCO_TASKS[task], seed, learning_starts=0, buffer_size=1000)
    sac, batch = asac_learner(task, order, log_density)
    with torch.no_grad():
        theirs = sb3_parameters(sb3)
        for name, ours in asac_parameters(sac).items():
            ours.copy_(theirs[name])
    return sac, sb3, batch


def compare(
    task: str,
    updates: int,
    variant: tuple[str, str, str],
    seed: int,
    report: Report,
    boundaries: Callable[[int, list[str]], None] | None = None,
) -> dict[str, float]:
    """Steps SB3 and ASAC (as ``variant``: :data:`VARIANTS`) ``updates`` times from the same weights;
    ``report(update, gaps)`` after each (:func:`relative_gaps`); ``boundaries(update, found)`` before
    each, where :func:`relu_disagreements` finds any. Returns the last gaps."""
    log_density, order, arithmetic = variant
    sac, sb3, batch = paired_learners(task, order, seed, log_density)
    start = copied(asac_parameters(sac))
    data = random_transitions(MUJOCO_TASKS[task], TRANSITIONS, seed)
    gaps: dict[str, float] = {}
    for update, (rows, noise) in enumerate(batches(data, batch, sac.spec.action.continuous_dim, updates, seed), 1):
        if boundaries is not None and (found := relu_disagreements(sac, sb3, data, rows)):
            boundaries(update, found)
        with as_variant(arithmetic):
            asac_step(sac, data, rows, noise)
        sb3_step(sb3, data, rows, noise)
        gaps = relative_gaps(start, copied(asac_parameters(sac)), copied(sb3_parameters(sb3)))
        report(update, gaps)
    return gaps


def rounding_floor(task: str, updates: int, seed: int, report: Report, reorder: int = 0) -> dict[str, float]:
    """The gaps of two ASAC learners in the same state on the same batches, one given each batch's rows
    in another order (drawn from ``reorder``): the same sums taken in another order, what float32 rounding
    alone makes of :func:`compare`'s gaps. Training amplifies rounding once a row's input to a ReLU
    unit lands within rounding of 0 (:func:`relu_disagreements`): some orders take the gap from 1e-6 to
    1e-3 within 200 Walker2d updates (bench/results/mujoco_float32/README.md), so the floor is a spread over orders."""
    torch.manual_seed(seed)
    one, batch = asac_learner(task, "critic_first")
    other, _ = asac_learner(task, "critic_first")
    other.load_state_dict(one.state_dict())
    start = copied(asac_parameters(one))
    data = random_transitions(MUJOCO_TASKS[task], TRANSITIONS, seed)
    shuffle = np.random.default_rng([seed, reorder])
    gaps: dict[str, float] = {}
    for update, (rows, noise) in enumerate(batches(data, batch, one.spec.action.continuous_dim, updates, seed), 1):
        order = shuffle.permutation(batch)
        asac_step(one, data, rows, noise)
        asac_step(other, data, rows[order], noise[order])
        gaps = relative_gaps(start, copied(asac_parameters(one)), copied(asac_parameters(other)))
        report(update, gaps)
    return gaps


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("task", choices=sorted(MUJOCO_TASKS))
    parser.add_argument("--updates", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--at", type=int, nargs="+", default=[1, 10, 100, 150, 200], help="updates to print")
    parser.add_argument("--floors", type=int, default=3, help="row orders the rounding floor is taken with")
    parser.add_argument(
        "--boundaries",
        action="store_true",
        help="SB3's three choices only, and the rows the critics put on either side of a ReLU",
    )
    args = parser.parse_args(argv)
    at = sorted(u for u in set(args.at) if 1 <= u <= args.updates)
    print(f"{args.task}: |d_ASAC - d_SB3| / |d_SB3| per group of parameters (d: the change from the shared start);")
    print(f"{args.updates} updates of the config's batch size, seed {args.seed}")

    def run(label: str, go: Callable[[Report], dict[str, float]]) -> None:
        rows: dict[int, dict[str, float]] = {}
        go(lambda update, gaps: rows.update({update: gaps}) if update in at else None)
        for update in at:
            gaps = ", ".join(f"{g} {v:.1e}" for g, v in rows[update].items())
            print(f"  {label:<62} update {update:4d}: {gaps}", flush=True)

    def against_sb3(variant: tuple[str, str, str]) -> Callable[[Report], dict[str, float]]:
        return lambda report: compare(args.task, args.updates, variant, args.seed, report)

    if args.boundaries:
        said = lambda update, found: print(f"  before update {update:4d}: " + "; ".join(found), flush=True)  # noqa: E731
        every = lambda report: compare(args.task, args.updates, VARIANTS[-1], args.seed, report, said)  # noqa: E731
        run("ASAC with SB3's three choices", every)
        return
    for variant in VARIANTS:
        run("ASAC: log-density {}, order {}, target arithmetic {}".format(*variant), against_sb3(variant))

    def floor(reorder: int) -> Callable[[Report], dict[str, float]]:
        return lambda report: rounding_floor(args.task, args.updates, args.seed, report, reorder)

    for reorder in range(args.floors):
        run(f"floor: ASAC against ASAC, each batch's rows reordered ({reorder})", floor(reorder))


if __name__ == "__main__":
    main()
