"""Widths that the replay's table and the models must agree on, computed without importing torch
(the replay role never imports it)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from algorithm.config.schema import NNConfig, SacConfig

RnnType = Literal["gru", "lstm"]


def recurrent_state_width(hidden_size: int, rnn_type: RnnType) -> int:
    """The flat recurrent state's width: ``h`` for a GRU, ``[h | c]`` for an LSTM."""
    return hidden_size * (2 if rnn_type == "lstm" else 1)


def default_recurrent_state_size(sac: SacConfig, nn: NNConfig) -> int:
    """The recurrent state width of the default models (and of a model file's ``build_representation``,
    whose recurrence is built from the config): 0 unless ``use_rnn``."""
    return recurrent_state_width(nn.rnn_units, nn.rnn_type) if sac.use_rnn else 0
