"""SAC learner throughput: our update vs a minimal hand-written PyTorch SAC update, interleaved.

Run: ``.venv/bin/python -m bench.learner [--quick] [--compile]``. HalfCheetah-v5 dimensions (obs 17,
action 6), 256x256 MLPs, batch 256, one-step windows, PER weights on. Reports updates/s (median over
rounds) at 1 and 2 torch threads and the ratio ours / baseline.

The baseline is the update as cleanrl's ``sac_continuous_action.py`` writes it: two separate
``nn.Sequential`` Q nets and their targets, a Gaussian policy, ``log_alpha``, plain ``torch.optim.Adam``
(default implementation), critic step, then actor step, then alpha step, Polyak loop over tensors.
Its actor is updated every step (cleanrl's ``policy_frequency=2`` runs two actor steps every second
update: the same work on average). It gets the same batches, converted with ``torch.from_numpy``.
Ours additionally computes PER weights, gradient norms and the non-finite check.

Each round runs every contender back to back for the same number of updates, so machine noise hits
all alike. ``OMP_WAIT_POLICY=PASSIVE`` is set (unless already set) before torch loads: with another
process holding a core, spinning OpenMP workers made 2-thread torch slower than 1 thread here.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import copy  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch import Tensor, nn  # noqa: E402

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig  # noqa: E402
from algorithm.sac.learner import SAC  # noqa: E402
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec  # noqa: E402
from algorithm.types import Batch  # noqa: E402

OBS, ACT, BATCH, HIDDEN = 17, 6, 256, 256


def make_batch(rng: np.random.Generator, table_size: int = 100_000) -> Batch:
    """A batch of one-step windows with random contents (a few terminal, a few truncated)."""
    b, length = BATCH, 1
    return Batch(
        keys=np.arange(b, dtype=np.uint64),
        probabilities=rng.uniform(0.5, 2.0, b) / table_size,
        table_size=table_size,
        obs=[rng.standard_normal((b, length + 1, OBS), dtype=np.float32)],
        actions=rng.uniform(-1, 1, (b, length, ACT)).astype(np.float32),
        prev_actions=np.zeros((b, length, ACT), dtype=np.float32),
        rewards=rng.standard_normal((b, length), dtype=np.float32),
        terminated=rng.random((b, length)) < 0.01,
        truncated=rng.random((b, length)) < 0.01,
        behaviour_logp=np.zeros((b, length), dtype=np.float32),
        mask=np.ones((b, length), dtype=bool),
    )


class BaselineSAC:
    """The reference update: cleanrl-style SAC in plain PyTorch (written here for comparison)."""

    def __init__(self, gamma: float = 0.99, tau: float = 0.005, lr: float = 3e-4) -> None:
        def q_net() -> nn.Sequential:
            return nn.Sequential(
                nn.Linear(OBS + ACT, HIDDEN),
                nn.ReLU(),
                nn.Linear(HIDDEN, HIDDEN),
                nn.ReLU(),
                nn.Linear(HIDDEN, 1),
            )

        self.gamma, self.tau = gamma, tau
        self.q1, self.q2 = q_net(), q_net()
        self.q1_target, self.q2_target = copy.deepcopy(self.q1), copy.deepcopy(self.q2)
        self.trunk = nn.Sequential(nn.Linear(OBS, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, HIDDEN), nn.ReLU())
        self.mean, self.log_std = nn.Linear(HIDDEN, ACT), nn.Linear(HIDDEN, ACT)
        self.log_alpha = torch.zeros(1, requires_grad=True)
        self.target_entropy = -float(ACT)
        self.q_opt = torch.optim.Adam([*self.q1.parameters(), *self.q2.parameters()], lr=lr)
        self.pi_opt = torch.optim.Adam(
            [*self.trunk.parameters(), *self.mean.parameters(), *self.log_std.parameters()], lr=lr
        )
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=lr)

    def sample(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        h = self.trunk(obs)
        mean, log_std = self.mean(h), self.log_std(h).clamp(-20.0, 2.0)
        std = log_std.exp()
        u = mean + std * torch.randn_like(mean)
        action = torch.tanh(u)
        log_prob = torch.distributions.Normal(mean, std).log_prob(u) - torch.log(1 - action.pow(2) + 1e-6)
        return action, log_prob.sum(-1, keepdim=True)

    def update(self, batch: Batch) -> None:
        obs_all = torch.from_numpy(batch.obs[0])
        obs, next_obs = obs_all[:, 0], obs_all[:, 1]
        actions = torch.from_numpy(batch.actions)[:, 0]
        rewards = torch.from_numpy(batch.rewards)[:, :1]
        dones = torch.from_numpy(batch.terminated)[:, :1].float()
        alpha = self.log_alpha.exp().item()
        with torch.no_grad():
            next_a, next_logp = self.sample(next_obs)
            x = torch.cat([next_obs, next_a], 1)
            next_q = torch.min(self.q1_target(x), self.q2_target(x)) - alpha * next_logp
            y = rewards + self.gamma * (1 - dones) * next_q
        x = torch.cat([obs, actions], 1)
        q_loss = F.mse_loss(self.q1(x), y) + F.mse_loss(self.q2(x), y)
        self.q_opt.zero_grad()
        q_loss.backward()
        self.q_opt.step()

        pi, logp = self.sample(obs)
        x = torch.cat([obs, pi], 1)
        pi_loss = (alpha * logp - torch.min(self.q1(x), self.q2(x))).mean()
        self.pi_opt.zero_grad()
        pi_loss.backward()
        self.pi_opt.step()

        with torch.no_grad():
            _, logp = self.sample(obs)
        alpha_loss = (-self.log_alpha.exp() * (logp + self.target_entropy)).mean()
        self.alpha_opt.zero_grad()
        alpha_loss.backward()
        self.alpha_opt.step()

        with torch.no_grad():
            for net, target in ((self.q1, self.q1_target), (self.q2, self.q2_target)):
                for p, tp in zip(net.parameters(), target.parameters(), strict=True):
                    tp.data.copy_(self.tau * p.data + (1 - self.tau) * tp.data)


def rate(step: Callable[[Batch], object], batches: list[Batch], updates: int) -> float:
    """Updates per second over ``updates`` calls, cycling through ``batches``."""
    start = time.perf_counter()
    for i in range(updates):
        step(batches[i % len(batches)])
    return updates / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rounds and updates (smoke run)")
    parser.add_argument("--compile", action="store_true", help="also measure SAC(compile=True) (~20 s to compile)")
    args = parser.parse_args()
    rounds, updates, warmup = (3, 20, 5) if args.quick else (7, 60, 20)

    spec = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))
    sac_cfg, nn_cfg, replay_cfg = SacConfig(seed=0), NNConfig(hidden_units=[HIDDEN, HIDDEN]), ReplayConfig()
    rng = np.random.default_rng(0)
    batches = [make_batch(rng) for _ in range(8)]
    torch.manual_seed(0)
    contenders: dict[str, Callable[[Batch], object]] = {
        "asac": SAC(spec, sac_cfg, nn_cfg, replay_cfg).update,
        "asac+bf16": SAC(spec, sac_cfg.model_copy(update={"compute_dtype": "bfloat16"}), nn_cfg, replay_cfg).update,
        "baseline": BaselineSAC().update,
    }
    if args.compile:
        compiled = SAC(spec, sac_cfg, nn_cfg, replay_cfg, compile=True)
        start = time.perf_counter()
        compiled.update(batches[0])
        print(f"asac+compile: first update (compilation) took {time.perf_counter() - start:.1f} s")
        contenders["asac+compile"] = compiled.update

    print(
        f"SAC updates/s, obs {OBS}, action {ACT}, {HIDDEN}x{HIDDEN}, batch {BATCH}; "
        f"median of {rounds} rounds x {updates} updates; OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}"
    )
    results: dict[tuple[int, str], float] = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for step in contenders.values():
            rate(step, batches, warmup)
        samples: dict[str, list[float]] = {name: [] for name in contenders}
        for _ in range(rounds):
            for name, step in contenders.items():
                samples[name].append(rate(step, batches, updates))
        for name, values in samples.items():
            results[(threads, name)] = statistics.median(values)

    names = list(contenders)
    print(
        f"{'threads':>7} "
        + " ".join(f"{n:>13}" for n in names)
        + " "
        + " ".join(f"{n + '/base':>19}" for n in names if n != "baseline")
    )
    for threads in (1, 2):
        base = results[(threads, "baseline")]
        cells = " ".join(f"{results[(threads, n)]:13.1f}" for n in names)
        ratios = " ".join(f"{results[(threads, n)] / base:18.2f}x" for n in names if n != "baseline")
        print(f"{threads:>7} {cells} {ratios}")


if __name__ == "__main__":
    main()
