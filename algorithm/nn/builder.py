"""Default models from config: what a task gets when its folder has no ``nn.py``."""

from __future__ import annotations

from algorithm.config_schema import NNConfig, SacConfig
from algorithm.nn.models import QEnsemble, SacModels, TanhGaussianPolicy, VectorRepresentation
from algorithm.spaces import EnvSpec


def build_models(spec: EnvSpec, sac: SacConfig, nn: NNConfig) -> SacModels:
    """Representation (concatenated vector sensors), ``sac.ensemble_q_num`` Q heads and a
    tanh-Gaussian policy, all with ``nn.hidden_units`` and ``nn.activation``.

    Raises NotImplementedError naming what is not built yet (images, discrete actions)."""
    if spec.action.discrete_branches:
        raise NotImplementedError(
            f"discrete action branches {spec.action.discrete_branches}: only continuous actions are built yet"
        )
    if spec.action.continuous_dim < 1:
        raise ValueError("the action spec has no continuous dimensions")
    rep = VectorRepresentation(spec.sensors)
    q = QEnsemble(rep.state_dim, spec.action.size, nn.hidden_units, sac.ensemble_q_num, nn.activation)
    policy = TanhGaussianPolicy(
        rep.state_dim,
        spec.action.continuous_dim,
        nn.hidden_units,
        nn.activation,
        nn.log_std_min,
        nn.log_std_max,
    )
    return SacModels(rep, q, policy)
