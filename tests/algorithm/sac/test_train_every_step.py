"""``sac_config.train_every_step``: every stored step of a sampled window is trained as the sampled one
is, each with its own n-step target cut at the window's end (R2D2's use of sequences), while the
window's priority stays its sampled step's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from algorithm.config.load import load_config
from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.run.trainer import EmbeddedTrainer
from algorithm.sac.learner import SAC
from algorithm.sac.window import PassInputs
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from envs.make import vector_env_factory

ROOT = Path(__file__).resolve().parents[3]
OBS, ACT, B = 3, 2, 5


def make_sac(**sac: object) -> SAC:
    spec = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))
    cfg = SacConfig(**{"seed": 4, "gamma": 0.9, **sac})  # type: ignore[arg-type]
    return SAC(spec, cfg, NNConfig(hidden_units=[16], rnn_units=8), ReplayConfig())


def window_tensors(length: int, seed: int, end: int = 1, look_back: int = 0) -> dict[str, torch.Tensor]:
    """``B`` windows of ``length`` steps: window 1's chunk ends after its step ``end`` (masked after it),
    window 2's episode terminates at step ``end``, window 3 starts ``look_back`` rows before its chunk."""
    rng = np.random.default_rng(seed)
    mask = np.ones((B, length), bool)
    mask[1, end + 1 :] = False
    mask[2, end + 1 :] = False
    mask[3, :look_back] = False
    terminated = np.zeros((B, length), bool)
    terminated[2, end] = True
    actions = rng.uniform(-1, 1, (B, length, ACT)).astype(np.float32)
    return {
        "obs": torch.from_numpy(rng.standard_normal((B, length + 1, OBS), dtype=np.float32)),
        "actions": torch.from_numpy(actions),
        "prev_actions": torch.from_numpy(np.roll(actions, 1, axis=1)),
        "rewards": torch.from_numpy(rng.standard_normal((B, length), dtype=np.float32)),
        "terminated": torch.from_numpy(terminated),
        "truncated": torch.zeros((B, length), dtype=torch.bool),
        "mask": torch.from_numpy(mask),
        "behaviour_logp": torch.zeros((B, length)),
    }


def losses(sac: SAC, w: dict[str, torch.Tensor], noise: torch.Tensor, weights: torch.Tensor | None):  # type: ignore[no-untyped-def]
    inputs = PassInputs([w["obs"]], w["actions"], w["prev_actions"], w["rewards"], w["terminated"], w["truncated"],
                        w["mask"], w["behaviour_logp"], None, weights, noise, None, None)  # fmt: skip
    return sac.losses(inputs)


def shifted(w: dict[str, torch.Tensor], t: int, rows: torch.Tensor) -> dict[str, torch.Tensor]:
    """The windows ``rows`` starting at their step ``t``, padded past their end with masked steps."""
    out = {}
    for name, x in w.items():
        x = x[rows, t:]
        pad = w["mask"].shape[1] + (name == "obs") - x.shape[1]
        out[name] = torch.cat([x, x.new_zeros((x.shape[0], pad, *x.shape[2:]))], dim=1)
    return out


def test_every_stored_step_is_trained_as_a_window_starting_there_would_be() -> None:
    n = 3
    every, sampled_only = make_sac(n_step=n, train_every_step=True), make_sac(n_step=n)
    sampled_only.models.load_state_dict(every.models.state_dict())
    w = window_tensors(n, seed=0)
    noise = torch.randn(B, n, 2, ACT, generator=torch.Generator().manual_seed(1))
    weights = torch.tensor([0.5, 1.0, 2.0, 0.25, 1.5])
    got = losses(every, w, noise, weights)

    targets, q_sum, pi_sum, trained = [], torch.zeros(()), torch.zeros(()), 0
    for t in range(n):
        rows = w["mask"][:, t].nonzero().flatten()  # a step is trained where it is stored
        part = losses(sampled_only, shifted(w, t, rows), noise[rows, t], weights[rows])
        full = torch.full((B,), torch.nan)
        full[rows] = part.metrics["learner/target_mean"]
        targets.append(full)
        q_sum, pi_sum, trained = q_sum + part.q * len(rows), pi_sum + part.policy * len(rows), trained + len(rows)
        if t == 0:  # every window's sampled step: its |TD| is the window's priority
            torch.testing.assert_close(got.td_abs, part.td_abs)
    expected = torch.stack(targets, dim=1)[w["mask"]]  # row-major over (window, step)
    torch.testing.assert_close(got.metrics["learner/target_mean"], expected)
    assert trained == int(w["mask"].sum()) == 13
    torch.testing.assert_close(got.q, q_sum / trained)
    torch.testing.assert_close(got.policy, pi_sum / trained)
    # the step after window 2's termination is never trained, and its target is the reward alone
    assert torch.isclose(expected[6], w["rewards"][2, 1])


@pytest.mark.parametrize("burn_in_gradient", [True, False])
def test_a_recurrent_window_trains_its_burn_in_steps_when_their_states_carry_gradients(burn_in_gradient: bool) -> None:
    burn_in, n = 3, 2
    cfg = {"use_rnn": True, "burn_in_step": burn_in, "n_step": n, "burn_in_gradient": burn_in_gradient}
    every, sampled_only = make_sac(**cfg, train_every_step=True), make_sac(**cfg)
    w = window_tensors(burn_in + n, seed=1, end=burn_in, look_back=1)  # the sampled step 3 is stored
    state = torch.zeros(B, 8)

    def q_loss(sac: SAC, rewards: torch.Tensor, trained: int) -> torch.Tensor:
        noise = torch.zeros(B, *((trained,) if sac.sac.train_every_step else ()), 2, ACT)
        return sac.losses(PassInputs([w["obs"]], w["actions"], w["prev_actions"], rewards, w["terminated"],
                                     w["truncated"], w["mask"], w["behaviour_logp"], state, None, noise, None,
                                     None)).q  # fmt: skip

    trained = burn_in + n if burn_in_gradient else n
    moved = w["rewards"].clone()
    moved[:, 0] += 10.0  # a burn-in step's reward: in the targets of burn-in steps only
    assert torch.equal(q_loss(sampled_only, w["rewards"], 0), q_loss(sampled_only, moved, 0))
    assert (q_loss(every, w["rewards"], trained) != q_loss(every, moved, trained)) == burn_in_gradient


def test_a_recurrent_trainer_trains_every_step_of_its_windows(tmp_path: Path) -> None:
    overrides = ["sac.seed=3", "nn.hidden_units=[16, 16]", "nn.rnn_units=8", "replay.batch_size=16",
                 "replay.min_size_to_sample=64", "replay.samples_per_insert=null", "actor.chunk_length=16",
                 "eval.eval_per_step=0", "base.max_step=200", "sac.train_every_step=true"]  # fmt: skip
    config = load_config(ROOT / "envs/gym/pendulum_novel", None, overrides).config
    factory = vector_env_factory(config.base_config.build_path, max_episode_steps=40)
    trainer = EmbeddedTrainer(config, tmp_path, factory, evaluate=False, progress=False)
    trainer.run(until_step=200)
    assert trainer.sac.updates > 0 and trainer.sac.nonfinite_skipped == 0
