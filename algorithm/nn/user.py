"""Task model files: ``envs/<task>/nn.py`` (or ``--nn NAME`` for ``envs/<task>/NAME.py``).

A model file is user Python that builds models from our base classes. It defines either

- ``build_representation(spec: EnvSpec, nn_config: NNConfig) -> Representation``: a custom
  encoder (a :class:`~algorithm.nn.models.Representation` subclass); Q heads, policies,
  recurrence, normalization and exploration models are then built around it from the config; or
- ``build_models(spec, sac_config, nn_config) -> SacModels``: everything, for full control
  (:func:`algorithm.nn.builder.build_models` is the default to start from).

The trainer copies the file into the run directory (``models/<task>/<name>/nn.py``) when a run
starts and always loads that copy, so resuming and ``--run`` keep working after the task's file
changes.
"""

from __future__ import annotations

import hashlib
import importlib.util
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

from algorithm.config.schema import NNConfig, SacConfig
from algorithm.nn.builder import build_models
from algorithm.nn.models import Representation, SacModels
from algorithm.nn.recurrent import RecurrentRepresentation
from algorithm.nn.shapes import default_recurrent_state_size
from algorithm.spaces import EnvSpec

ModelBuilder = Callable[[EnvSpec, SacConfig, NNConfig], SacModels]


class _AroundRepresentation:
    """The default models built around a model file's ``build_representation``: their recurrence,
    like everything but the encoder, comes from the config."""

    def __init__(self, make_representation: Callable[[EnvSpec, NNConfig], Representation]) -> None:
        self.make_representation = make_representation

    def __call__(self, spec: EnvSpec, sac: SacConfig, nn: NNConfig) -> SacModels:
        return build_models(spec, sac, nn, representation=self.make_representation(spec, nn))


def load_model_file(path: Path) -> ModuleType:
    """Import ``path`` as a fresh module (named after its content hash, so two runs' copies never
    collide); errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file {path} does not exist")
    name = "asac_user_nn_" + hashlib.sha1(path.read_bytes()).hexdigest()[:12]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"model file {path} cannot be imported")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as e:
        raise ImportError(f"model file {path} failed to import: {type(e).__name__}: {e}") from e
    return module


def model_builder(path: Path | None) -> ModelBuilder:
    """The model builder a task's model file asks for (:func:`build_models` when ``path`` is None)."""
    if path is None:
        return build_models
    module = load_model_file(path)
    if hasattr(module, "build_models"):
        return module.build_models
    if hasattr(module, "build_representation"):
        return _AroundRepresentation(module.build_representation)
    raise AttributeError(f"model file {path} defines neither build_models nor build_representation")


def recurrent_state_size(spec: EnvSpec, sac: SacConfig, nn: NNConfig, build: ModelBuilder = build_models) -> int:
    """The width of the recurrent state ``build``'s models carry (0: not recurrent), without building
    a SAC (a replay needs only this): from the config where the recurrence is built from it (the
    default models, or a model file's ``build_representation``); a model file's own ``build_models``
    decides it itself, so its models are built once (no target copies, no optimizers)."""
    if build is build_models or isinstance(build, _AroundRepresentation):
        return default_recurrent_state_size(sac, nn)
    rep = build(spec, sac, nn).representation
    return rep.rnn_state_size if isinstance(rep, RecurrentRepresentation) else 0
