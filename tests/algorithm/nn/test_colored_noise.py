"""Colored acting noise (``sac_config.action_noise_color``, algorithm/nn/colored_noise.py): every step
is a standard normal whatever the color, its spectrum falls as 1/f^beta, consecutive acting steps are
correlated as asked, discrete choices keep the policy's probabilities and never pick a masked action,
and a policy restored from its state dict draws on exactly where it left off."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.colored_noise import ColoredNoise, colored_sequences, inverse_cdf_choice
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec

OBS = SensorSpec("obs", (3,))


def lag1(x: np.ndarray) -> float:
    """Mean lag-1 autocorrelation of the rows of ``x``."""
    return float(np.mean([np.corrcoef(r[:-1], r[1:])[0, 1] for r in x]))


@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0])
@pytest.mark.parametrize("horizon", [1000, 999])
def test_every_step_is_a_standard_normal_and_the_spectrum_falls_as_one_over_f_to_the_beta(
    beta: float, horizon: int
) -> None:
    x = colored_sequences(beta, 3000, horizon, np.random.default_rng(0))
    assert abs(x.mean()) < 0.03 and abs(x.std() - 1.0) < 0.02
    per_step = x.std(axis=0)  # across sequences, at each step: the marginal, not the within-sequence spread
    assert per_step.min() > 0.9 and per_step.max() < 1.1
    power = (np.abs(np.fft.rfft(x, axis=1)) ** 2).mean(axis=0)[1:]
    freqs = np.fft.rfftfreq(horizon)[1:]
    slope = np.polyfit(np.log(freqs), np.log(power), 1)[0]
    assert slope == pytest.approx(-beta, abs=0.1)


def test_white_steps_are_independent_and_colored_ones_persist() -> None:
    rng = np.random.default_rng(1)
    assert abs(lag1(colored_sequences(0.0, 200, 1000, rng))) < 0.02
    assert 0.6 < lag1(colored_sequences(1.0, 200, 1000, rng)) < 0.9  # pink
    assert lag1(colored_sequences(2.0, 200, 1000, rng)) > 0.95  # red


def test_the_stream_hands_out_one_step_per_call_and_starts_anew_past_its_horizon_or_on_a_new_shape() -> None:
    noise = ColoredNoise(2.0, np.random.default_rng(0), horizon=50)
    steps = np.stack([noise.draw(4, 2) for _ in range(50)])  # [50, 4, 2]: one horizon
    assert steps.dtype == np.float32 and steps.shape == (50, 4, 2)
    assert lag1(steps.reshape(50, 8).T) > 0.8  # consecutive calls continue the same sequences
    after = noise.draw(4, 2)  # past the horizon: fresh sequences, still one value per (env, dim)
    assert after.shape == (4, 2) and not np.array_equal(after, steps[0])
    assert noise.draw(3, 2).shape == (3, 2)
    with pytest.raises(ValueError, match="beta"):
        ColoredNoise(-1.0, np.random.default_rng(0))


def test_inverse_cdf_choice_keeps_the_probabilities_and_never_picks_a_masked_action() -> None:
    probs = torch.tensor([[0.2, 0.5, 0.3, 0.0]]).expand(200_000, 4)
    z = torch.randn(200_000, generator=torch.Generator().manual_seed(0))
    counts = torch.bincount(inverse_cdf_choice(probs, z), minlength=4).double() / 200_000
    torch.testing.assert_close(counts, torch.tensor([0.2, 0.5, 0.3, 0.0], dtype=torch.float64), atol=4e-3, rtol=0)
    # z far in the tail: a uniform that rounds to 1, past a total of 0.9999999 in float32
    edge = inverse_cdf_choice(torch.tensor([[0.3, 0.6999999, 0.0]]), torch.tensor([40.0]))
    assert edge.tolist() == [1]


def make(action: ActionSpec, color: float) -> SAC:
    sac = SacConfig(seed=0, action_noise_color=color)
    return SAC(EnvSpec((OBS,), action), sac, NNConfig(hidden_units=[16]), ReplayConfig())


@pytest.mark.parametrize("color, low, high", [(0.0, -0.1, 0.1), (1.0, 0.5, 1.0)])
def test_acting_noise_is_correlated_across_steps_as_asked(color: float, low: float, high: float) -> None:
    obs = [np.full((2, 3), 0.1, np.float32)]  # one observation held fixed: the actions vary by noise alone
    continuous = make(ActionSpec((), 1, (-1.0,), (1.0,)), color)
    pre_tanh = np.arctanh(np.clip([continuous.act(obs)[0][:, 0] for _ in range(600)], -0.999, 0.999))
    assert low < lag1(pre_tanh.T) < high
    discrete = make(ActionSpec((2,), 0, (), ()), color)
    with torch.no_grad():
        state = discrete.models.representation([torch.from_numpy(obs[0])])
        p_first = float(discrete.models.discrete_policy(state, None).exp()[0, 0])  # type: ignore[misc]
    choices = np.array([discrete.act(obs)[0][:, 0] for _ in range(3000)])  # one-hot's first entry
    assert choices.mean() == pytest.approx(p_first, abs=0.06)  # the policy's own probability
    switches = float((choices[1:] != choices[:-1]).mean())
    white_switches = 2 * p_first * (1 - p_first)
    if color == 0.0:
        assert switches == pytest.approx(white_switches, abs=0.04)
    else:
        assert switches < 0.7 * white_switches  # the same action held for longer runs


def test_a_restored_policy_draws_the_same_noise_on() -> None:
    obs = [np.random.default_rng(0).normal(size=(3, 3)).astype(np.float32)]
    action = ActionSpec((2,), 1, (-1.0,), (1.0,))
    first = make(action, 1.0)
    for _ in range(7):
        first.act(obs)
    second = make(action, 1.0)
    second.load_state_dict(first.state_dict())
    for _ in range(5):
        a, logp = first.act(obs)
        b, logq = second.act(obs)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(logp, logq)


@pytest.mark.parametrize("color", [0.0, 1.0])
def test_actors_built_from_one_config_draw_their_own_noise_once_seeded_apart(color: float) -> None:
    """Distributed actors build their policies from one config (one sac.seed); each reseeds its acting
    noise from its own seed (ds/actor/actor.py), or they would all draw the same noise."""
    obs = [np.zeros((4, 3), np.float32)]
    action = ActionSpec((2,), 1, (-1.0,), (1.0,))
    actors = [make(action, color) for _ in range(3)]
    for policy, seed in zip(actors, (1000, 2000, 1000), strict=True):
        policy.seed_acting(seed)
    runs = [np.stack([policy.act(obs)[0] for _ in range(20)]) for policy in actors]
    assert not np.array_equal(runs[0], runs[1])  # two actors: their own noise
    np.testing.assert_array_equal(runs[0], runs[2])  # the same seed: the same draws
