"""The learner's checks against the task's spec: SAC options that need a kind of action space, when the
learner is built, and a sampled batch, before any of it reaches the device (a wrong shape, dtype or window
names the field and what was expected)."""

from __future__ import annotations

from algorithm.config.schema import SacConfig
from algorithm.spaces import EnvSpec
from algorithm.types import Batch


def check_batch(batch: Batch, spec: EnvSpec, sac: SacConfig, rnn_state_size: int) -> None:
    """Raise ValueError naming what in ``batch`` does not fit ``spec`` and ``sac`` (``rnn_state_size``: the
    recurrent state's width, 0 without ``use_rnn``)."""
    sensors, n_b, n_l = spec.sensors, batch.batch_size, batch.window
    window = sac.burn_in_step + sac.n_step
    if n_l != window:
        raise ValueError(f"batch window is {n_l} steps, expected burn_in_step + n_step = {window}")
    if len(batch.obs) != len(sensors):
        raise ValueError(f"batch.obs has {len(batch.obs)} sensors, the spec has {len(sensors)}")
    for o, s in zip(batch.obs, sensors, strict=True):
        if o.shape != (n_b, n_l + 1, *s.shape) or o.dtype != s.dtype:
            raise ValueError(
                f"batch.obs for sensor {s.name!r} must be {s.dtype} {(n_b, n_l + 1, *s.shape)}, got {o.dtype} {o.shape}"
            )
    expected = {
        "actions": (n_b, n_l, spec.action.size),
        "rewards": (n_b, n_l),
        "terminated": (n_b, n_l),
        "truncated": (n_b, n_l),
        "mask": (n_b, n_l),
        "probabilities": (n_b,),
    }
    for name, shape in expected.items():
        got = getattr(batch, name).shape
        if got != shape:
            raise ValueError(f"batch.{name} must have shape {shape}, got {got}")
    burn_in = sac.burn_in_step
    if not batch.mask[:, burn_in].all():
        raise ValueError(f"batch.mask[:, {burn_in}] must be True: the sampled step of every window is stored")
    if rnn_state_size and (batch.rnn_state is None or batch.rnn_state.shape != (n_b, rnn_state_size)):
        got = None if batch.rnn_state is None else batch.rnn_state.shape
        raise ValueError(f"batch.rnn_state must have shape {(n_b, rnn_state_size)} with use_rnn, got {got}")
    if sac.use_priority and batch.table_size < 1:
        raise ValueError(f"batch.table_size must be >= 1 with use_priority, got {batch.table_size}")


def check_config_for_task(sac: SacConfig, spec: EnvSpec) -> None:
    """Raise ValueError naming the ``sac_config`` key whose option this task's action space cannot take."""
    act = spec.action
    if sac.discrete_entropy_penalty > 0 and (act.continuous_dim or sac.discrete_dqn_like or not act.discrete_branches):
        raise ValueError(
            "sac_config.discrete_entropy_penalty needs a discrete-only action space and a stochastic discrete "
            f"policy (discrete_dqn_like false); this task has {act.continuous_dim} continuous dims, discrete "
            f"branches {list(act.discrete_branches)}, discrete_dqn_like {sac.discrete_dqn_like}"
        )
    if sac.munchausen_scale > 0 and (
        act.continuous_dim or sac.discrete_dqn_like or not act.discrete_branches or sac.use_n_step_is
    ):
        raise ValueError(
            "sac_config.munchausen_scale needs a discrete-only action space, a stochastic discrete policy "
            "(discrete_dqn_like false) and the n-step target (use_n_step_is false); this task has "
            f"{act.continuous_dim} continuous dims, discrete branches {list(act.discrete_branches)}, "
            f"discrete_dqn_like {sac.discrete_dqn_like}, use_n_step_is {sac.use_n_step_is}"
        )
