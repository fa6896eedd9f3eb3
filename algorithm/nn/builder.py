"""Default models from config: what a task gets when its folder has no ``nn.py``."""

from __future__ import annotations

import math

from algorithm.config.schema import NNConfig, SacConfig
from algorithm.nn.encoders import MultiSensorRepresentation
from algorithm.nn.exploration import Curiosity, RandomNetworkDistillation
from algorithm.nn.models import (
    DiscretePolicy,
    QEnsemble,
    Representation,
    SacModels,
    TanhGaussianPolicy,
    VectorRepresentation,
)
from algorithm.nn.normalization import ObservationNormalizer
from algorithm.nn.prediction import PredictionModels, observation_targets
from algorithm.nn.recurrent import RecurrentRepresentation
from algorithm.spaces import EnvSpec


def build_models(
    spec: EnvSpec, sac: SacConfig, nn: NNConfig, representation: Representation | None = None
) -> SacModels:
    """Representation (concatenated vector sensors; a conv encoder per image sensor and critic-only
    sensors last when there are any), ``sac.ensemble_q_num`` Q heads, a tanh-Gaussian
    policy for the continuous part and a categorical one per discrete branch (none with
    ``discrete_dqn_like``), all with ``nn.hidden_units`` and ``nn.activation``. ``representation``
    replaces the default encoder (a task's model file)."""
    act = spec.action
    rep: Representation
    if representation is not None:  # a task's model file (nn/user.py)
        rep = representation
    elif any(s.is_image for s in spec.sensors) or nn.critic_only:
        rep = MultiSensorRepresentation(spec.sensors, nn.conv_features, nn.critic_only, nn.activation)
    else:
        rep = VectorRepresentation(spec.sensors)
    if sac.use_rnn:
        rep = RecurrentRepresentation(rep, act.size, nn.rnn_units, nn.rnn_type)
    q_sigma = nn.noisy_sigma0 if nn.noisy_q else None
    policy_sigma = nn.noisy_sigma0 if nn.noisy_policy else None
    q = QEnsemble(
        rep.state_dim,
        act.continuous_dim,
        nn.hidden_units,
        sac.ensemble_q_num,
        nn.activation,
        act.discrete_size,
        q_sigma,
    )
    policy = None
    if act.continuous_dim:
        policy = TanhGaussianPolicy(
            rep.policy_state_dim,
            act.continuous_dim,
            nn.hidden_units,
            nn.activation,
            nn.log_std_min,
            nn.log_std_max,
            policy_sigma,
        )
    discrete_policy = None
    if act.discrete_branches and not sac.discrete_dqn_like:
        discrete_policy = DiscretePolicy(
            rep.policy_state_dim, act.discrete_branches, nn.hidden_units, nn.activation, policy_sigma
        )
    normalizer = ObservationNormalizer(spec.sensors) if sac.use_normalization else None
    curiosity = None
    if sac.use_curiosity:
        curiosity = Curiosity(rep.state_dim, act.size, nn.hidden_units, sac.curiosity_inverse)
    rnd = (
        RandomNetworkDistillation(rep.state_dim, act.size, nn.hidden_units, normalize=sac.rnd_normalize)
        if sac.use_rnd
        else None
    )
    prediction = None
    if sac.use_prediction:
        targets = observation_targets(spec.sensors, nn.critic_only, sac.use_extra_data)
        observation_dim = sum(math.prod(spec.sensors[i].shape) for i in targets)
        prediction = PredictionModels(rep.state_dim, act.size, observation_dim, nn.hidden_units)
    return SacModels(rep, q, policy, discrete_policy, normalizer, curiosity, rnd, prediction)
