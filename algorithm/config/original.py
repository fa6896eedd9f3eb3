"""Configs written for the original Advanced-Soft-Actor-Critic: where each of its keys lives in ASAC.

The original's default layouts (its ``algorithm/default_config.yaml`` and the distributed
``ds/default_config.yaml``, eras E1-E5: TF ``sac.py`` files, TF ``nn.py`` files, PyTorch, ``seq_encoder``,
the later ``env_name``/``n_envs`` layout) mostly match ASAC's key for key; the keys that do not are all in
the tables below, and :class:`Port` applies them to each layer of a task file (and to each ``--override``)
before :mod:`algorithm.config.load` merges and validates it:

- ``MOVED``: same meaning, another place; the value is read there, with one WARNING per key and file
  (``<file> [default]: base_config.noise_max is actor_config.noise_max now; read as that``);
- ``CONVERTED``: a value that reads as other ASAC keys (``seq_encoder: RNN`` is ``use_rnn: true``);
- ``DROPPED``: settings with no effect in ASAC; ignored, with a WARNING saying what ASAC does;
- ``SECTIONS`` (top level) and ``VARIANT_KEYS`` (``inherited``): dropped when empty, else refused;
- ``REFUSED`` / ``REFUSED_VALUES``: a key or value whose meaning cannot be carried over; an error
  that names the key, the file and what to write instead (all such errors of a load in one message);
- ``RESTATED`` / ``UNSET``: the same key counting something else, or defaulting otherwise, in ASAC; a
  WARNING stating the difference, given only for a file read as the original's (below);
- ``ENV_IDS``: gym ids ASAC cannot make (PyBullet's, renamed ones) read as their gymnasium counterparts,
  in any file, with a WARNING.

A task file is read as the original's when any of its sections (``default`` or a variant) sets
``base_config.env_type`` (ASAC's only kind, GYM, is its default, so its own files never set it; every
original gym or bullet file does), or a key of ``MOVED``, ``CONVERTED``, ``DROPPED``, ``REFUSED``,
``SECTIONS`` or ``VARIANT_KEYS`` (keys only the original's layouts have), or a value of ``REFUSED_VALUES``,
or when the task folder holds a ``config_ds.yaml`` (the original's distributed file). For such a file,
where no layer of it nor an override sets them, the original's defaults apply: ``use_n_step_is: true``,
``clip_epsilon: 0.2`` and one update per vector step (``samples_per_insert: batch_size / n_agents``, of
the values the run gets, overrides included), said in one WARNING; its ``clip_epsilon`` <= 0 (the
original's "off") reads as null. Overrides are ASAC's own: they are ported, never restated.

Keys of the original's layouts not named here (``scene``, ``n_agents``, ``replay_config.*``,
``net_config.*``, most of ``sac_config``, ...) are the same key with the same meaning in ASAC.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

CONFIG_LOGGER = "asac.config"  # what a task file's keys became; main_ds.py quiets it in local's children
log = logging.getLogger(CONFIG_LOGGER)
ENVS_DIR = Path(__file__).resolve().parents[2] / "envs"

# old path -> (new path, what it is there; "" when the name says it)
MOVED: dict[str, tuple[str, str]] = {
    "base_config.update_policy_mode": ("actor_config.update_policy_mode", ""),
    "base_config.noise_increasing_rate": ("actor_config.noise_increasing_rate", ""),
    "base_config.noise_max": ("actor_config.noise_max", ""),
    # The original's learner refreshed the copy actors were served ("sac_bak") every N updates.
    "base_config.update_sac_bak_per_step": (
        "sac_config.update_policy_variables_per_step",
        " (learner updates between refreshes of the weights actors act with)",
    ),
    # The original's random_params sat in sac_config and named sac_config keys; ASAC's is
    # {section: {key: spec}} at the top level.
    "sac_config.random_params": ("random_params.sac_config", ""),
    # The original's learner computed the |TD| of an episode before adding it; ASAC's scores what
    # actors stored, right after it is stored (sampled before that only at the maximum priority).
    "sac_config.use_add_with_td": (
        "sac_config.insert_td_priorities",
        " (new data's priority is its |TD|, scored by the learner just after it is stored)",
    ),
    "sac_config._lambda": ("sac_config.v_lambda", ""),  # E1
    "base_config.max_step_per_iter": ("base_config.max_step_each_iter", ""),  # E2
    "sac_config.batch_size": ("replay_config.batch_size", ""),  # E3, E4
    "base_config.env_name": ("base_config.build_path", ""),  # E5
    "base_config.n_envs": ("base_config.n_agents", ""),  # E5
    "sac_config.nn": ("base_config.nn", ""),  # E5
}


def _off(value: Any) -> bool:
    """Whether a value switches an option of the original off (null, false, empty), as ASAC's defaults do."""
    return value is None or value is False or value == {}


def _curiosity(value: Any) -> dict[str, Any] | str:  # E3: FORWARD | INVERSE | null
    if _off(value):
        return {}
    if value == "FORWARD":
        return {"sac_config.use_curiosity": True}
    if value == "INVERSE":
        return {"sac_config.use_curiosity": True, "sac_config.curiosity_inverse": True}
    return "ASAC's curiosity is sac_config.use_curiosity: true, with curiosity_inverse: true for an inverse model"


def _seq_encoder(value: Any) -> dict[str, Any] | str:  # E4: RNN | ATTN | null
    if _off(value):
        return {}
    if value == "RNN":
        return {"sac_config.use_rnn": True}
    return "ASAC has no attention encoder; its recurrent option is use_rnn: true (GRU or LSTM: nn_config.rnn_type)"


def _env_args(value: Any) -> dict[str, Any] | str:  # E5
    if _off(value):
        return {}
    if isinstance(value, dict):
        return {"base_config.env_kwargs": value}
    return "ASAC passes base_config.env_kwargs, a mapping, to gymnasium.make; write env_kwargs: {name: value}"


def _absent(what: str) -> Callable[[Any], dict[str, Any] | str]:
    """An option ASAC lacks: nothing when the value turns it off, else refused with ``what``."""
    return lambda value: {} if _off(value) else what


_NN_ARGS = (
    "arguments of the original's model-file classes; ASAC's nn_config keys are hidden_units, activation, "
    "rnn_type, rnn_units, ... and its model files (base_config.nn) differ: delete the key and set those"
)

# old path -> how its value reads in ASAC: {new path: value} (empty: nothing to set) or what to write instead
CONVERTED: dict[str, Callable[[Any], dict[str, Any] | str]] = {
    "sac_config.curiosity": _curiosity,
    "sac_config.seq_encoder": _seq_encoder,
    "sac_config.siamese": _absent("ASAC has no siamese representation learning (ATC, BYOL): delete the key"),
    "sac_config.siamese_use_adaptive": _absent("ASAC has no siamese representation learning: delete the key"),
    "base_config.env_args": _env_args,
    "nn_config.rep": _absent(_NN_ARGS),
    "nn_config.policy": _absent(_NN_ARGS),
}

# old path -> why it has no counterpart, or what ASAC does instead (ignored)
DROPPED: dict[str, str] = {
    "base_config.no_graphics": "a Unity setting; ASAC runs gymnasium envs only",
    "base_config.port": "the Unity env port; ASAC runs gymnasium envs only",
    "base_config.unity_args": "Unity settings; ASAC runs gymnasium envs only",  # E5
    "base_config.update_policy_variables_per_step": (  # E2
        "the original's actors fetched weights every N of their own env steps; ASAC actors act with every "
        "publication as it arrives, and sac_config.update_policy_variables_per_step sets the learner updates "
        "between publications"
    ),
    "base_config.attach_replay": "ASAC's replay is a role of its own, which main_ds.py <task> local starts",
    "replay_config.use_mongodb": "ASAC's replay keeps its table in memory (replay_config.save_replay saves it)",
    "base_config.save_model_per_iter": (  # E1
        "ASAC saves every sac_config.save_model_per_step env steps or save_model_per_minute minutes"
    ),
}

# old path -> what to do instead (the key's meaning cannot be carried over)
REFUSED: dict[str, str] = {
    "base_config.sac": (  # E1
        "an E1 model file (sac.py, sac_hard.py); ASAC's model files are named by base_config.nn and written "
        "differently (nn_config sizes its networks): delete the key"
    ),
}

# old path -> (does this value belong to the original only?, what to do instead)
REFUSED_VALUES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "base_config.env_type": (
        lambda value: value == "UNITY",
        "Unity environments are out of scope in ASAC; set env_type: GYM and build_path to a gymnasium id",
    ),
    "base_config.build_path": (
        lambda value: isinstance(value, dict),
        "a mapping of Unity executables (win32/linux) is the original's; ASAC needs a gymnasium id, "
        "e.g. build_path: HalfCheetah-v5",
    ),
    "base_config.max_actors_each_learner": (
        lambda value: value == -1 and not isinstance(value, bool),
        "-1 (the original's 'no limit') has no counterpart: ASAC's learner takes at most this many actors; "
        "write a number, e.g. max_actors_each_learner: 100",
    ),
}

# top-level sections of the original's later layouts -> what ASAC lacks (dropped when null or empty)
SECTIONS: dict[str, str] = {
    "model_config": "arguments of the original's model-file classes; ASAC sizes networks with nn_config",  # E3
    "oc_config": "the original's option-critic settings; ASAC has no options",  # E5
    "ma_config": "the original's multi-agent settings; ASAC trains one agent's policy",  # E5
}

# keys of a whole section (default, a variant) -> what to write instead
VARIANT_KEYS: dict[str, str] = {
    "inherited": (  # E5
        "ASAC's -c section layers over default only; copy the keys of the inherited section into this one "
        "and delete inherited"
    ),
}

# same path, other meaning -> (does the value mean something else?, the difference); for the original's files
RESTATED: dict[str, tuple[Callable[[Any], bool], str]] = {
    "base_config.max_step": (
        lambda value: value != -1,
        "counts env steps of all envs and actors in ASAC, the original counted learner updates; read as env steps "
        "(N updates take about N * batch_size / samples_per_insert + min_size_to_sample env steps)",
    ),
    "base_config.max_iter": (
        lambda value: value != -1,
        "counts episodes of env 0 in ASAC, the original counted iterations (each until every env's episode "
        "ended); read as env 0's episodes",
    ),
    "base_config.reset_on_iteration": (
        lambda value: value is True,
        "(true) cuts and resets every other env when env 0's episode ends in ASAC; the original waited for "
        "every env's episode to end, then reset them all; read the ASAC way",
    ),
    "sac_config.save_model_per_step": (
        lambda value: True,
        "counts env steps in ASAC, the original counted learner updates; read as env steps",
    ),
    "sac_config.save_model_per_minute": (
        lambda value: True,
        "makes a checkpoint due after this many minutes in ASAC (or after save_model_per_step env steps, whichever "
        "comes first); the original only held saves back until this many minutes had passed; read the ASAC way",
    ),
}

# path whose default differs -> (said only when distributed?, what applies); for the original's files silent on it
UNSET: dict[str, tuple[bool, str]] = {
    "base_config.reset_on_iteration": (
        False,
        "the original's default true reset every env at each iteration; ASAC's default false applies here "
        "(each env runs its own episodes; true cuts and resets every env when env 0's episode ends)",
    ),
    "base_config.evolver_enabled": (
        True,
        "the original's distributed roles ran an evolver unless evolver_enabled: false; ASAC's default false "
        "applies here (an evolver runs with evolver_enabled: true or main_ds.py <task> local --learners N)",
    ),
}

# the original's defaults that differ from ASAC's, applied to its files where they are silent (the original's
# clip_epsilon is ASAC's: both take max((Q - y)^2, (Q' + clip(Q - Q', eps) - y)^2), Q' the target critic's)
ORIGINAL_DEFAULTS: dict[str, Any] = {"sac_config.use_n_step_is": True, "sac_config.clip_epsilon": 0.2}

_BULLET = "is PyBullet's, which is not installed with ASAC; read as its MuJoCo counterpart {new}, whose observation "
_BULLET += "and reward differ"
_MUJOCO_PY = "needs mujoco-py, which gymnasium no longer runs; read as {new}, its successor"
# a gym id ASAC cannot make -> (its gymnasium counterpart, why, ASAC's task folder for it under envs/)
ENV_IDS: dict[str, tuple[str, str, str]] = {
    "AntBulletEnv-v0": ("Ant-v5", _BULLET, "mujoco/ant"),
    "HalfCheetahBulletEnv-v0": ("HalfCheetah-v5", _BULLET, "mujoco/half_cheetah"),
    "HumanoidBulletEnv-v0": ("Humanoid-v5", _BULLET, "mujoco/humanoid"),
    "Walker2DBulletEnv-v0": ("Walker2d-v5", _BULLET, "mujoco/walker2d"),
    "HopperBulletEnv-v0": ("Hopper-v5", _BULLET, "mujoco/hopper"),
    "InvertedPendulumBulletEnv-v0": ("InvertedPendulum-v5", _BULLET, "mujoco/inverted_pendulum"),
    "InvertedDoublePendulumBulletEnv-v0": ("InvertedDoublePendulum-v5", _BULLET, "mujoco/inverted_double_pendulum"),
    "ReacherBulletEnv-v0": ("Reacher-v5", _BULLET, "mujoco/reacher"),
    "Pendulum-v0": ("Pendulum-v1", "is not in gymnasium (renamed); read as {new}", "gym/pendulum"),
    "HalfCheetah-v3": ("HalfCheetah-v5", _MUJOCO_PY, "mujoco/half_cheetah"),  # E4 mujoco folder
    "Humanoid-v3": ("Humanoid-v5", _MUJOCO_PY, "mujoco/humanoid"),  # E5 gym folder
    "Ant-v3": ("Ant-v5", _MUJOCO_PY, "mujoco/ant"),
    "Walker2d-v3": ("Walker2d-v5", _MUJOCO_PY, "mujoco/walker2d"),
    "Hopper-v3": ("Hopper-v5", _MUJOCO_PY, "mujoco/hopper"),
}


def _present(layer: Any, path: str) -> tuple[bool, Any]:
    """Whether ``section.key`` (or a top-level ``section``) is in ``layer`` (a mapping of sections), and its value."""
    section, _, key = path.partition(".")
    if not isinstance(layer, dict):
        return False, None
    if not key:
        return section in layer, layer.get(section)
    body = layer.get(section)
    if isinstance(body, dict) and key in body:
        return True, body[key]
    return False, None


def looks_like_original(task_file: Any, has_ds_file: bool = False) -> str | None:
    """Why a task file is read as the original's (``"it sets base_config.env_type"``), or None: a section
    (``default``, a variant) sets a key only the original's layouts have, or ``env_type``, or the task
    folder holds a ``config_ds.yaml`` (``has_ds_file``); the module docstring says why these."""
    layers = [layer for layer in task_file.values() if isinstance(layer, dict)] if isinstance(task_file, dict) else []
    keys = ("base_config.env_type", *MOVED, *CONVERTED, *DROPPED, *REFUSED, *SECTIONS, *VARIANT_KEYS)
    for path in keys:
        if any(_present(layer, path)[0] for layer in layers):
            return f"it sets {path}"
    for path, (is_original, _) in REFUSED_VALUES.items():
        if any(is_original(_present(layer, path)[1]) for layer in layers if _present(layer, path)[0]):
            return f"it sets {path} to the original's value"
    return "its folder holds config_ds.yaml" if has_ds_file else None


class Port:
    """One config load's port: notes logged once per key and file, errors kept for one message.

    :meth:`read_as_original` says the task file is the original's; :meth:`layer` and :meth:`override`
    port what each layer and override sets; :meth:`finish` reads the merged values (env ids, the
    original's ``clip_epsilon`` off, its defaults where the file is silent)."""

    def __init__(self) -> None:
        self.errors: list[str] = []
        self._noted: set[tuple[str, str]] = set()
        self.original: str | None = None  # why the task file is read as the original's
        self._file = ""
        self._distributed = False
        self._given: set[str] = set()  # section.key paths a task layer or an override sets
        self._overridden: set[str] = set()

    def read_as_original(self, why: str | None, file: str, distributed: bool) -> None:
        self.original, self._file, self._distributed = why, file, distributed

    def _note(self, file: str, path: str, message: str) -> None:
        if (file, path) not in self._noted:
            self._noted.add((file, path))
            log.warning(message)

    def layer(self, layer: Any, source: str, file: str, original: bool) -> Any:
        """``layer`` (one section of a task file) with the original's keys read the ASAC way; ``source``
        names the section (``path [default]``), ``file`` the file (notes come once per key in it)."""
        if not isinstance(layer, dict):
            return layer  # algorithm.config.load reports the shape
        out = self._port(layer, source, file)
        if original:
            for path, (differs, difference) in RESTATED.items():
                found, value = _present(out, path)
                if found and differs(value):
                    self._note(file, path, f"{source}: {path} {difference}")
        self._given.update(_leaves(out))
        return out

    def _port(self, layer: dict[str, Any], source: str, file: str) -> dict[str, Any]:
        out = copy.deepcopy(layer)
        for path, instead in VARIANT_KEYS.items():
            found, value = _present(out, path)
            if found and not _off(value):
                self.errors.append(f"{path} ({source}): {instead}; got {value!r}")
            out.pop(path, None)
        for path, lacks in SECTIONS.items():
            found, value = _present(out, path)
            if found and _off(value):
                self._note(file, path, f"{source}: {path} has no counterpart in ASAC ({lacks}); ignored")
            elif found:
                self.errors.append(f"{path} ({source}): {lacks}; delete the section")
            out.pop(path, None)
        for path, (is_original, instead) in REFUSED_VALUES.items():
            found, value = _present(out, path)
            if found and is_original(value):
                self.errors.append(f"{path} ({source}): {instead}; got {value!r}")
                _pop(out, path)
        for path, instead in REFUSED.items():
            if _present(out, path)[0]:
                self.errors.append(f"{path} ({source}): {instead}")
                _pop(out, path)
        for path, why in DROPPED.items():
            if _present(out, path)[0]:
                self._note(file, path, f"{source}: {path} has no counterpart in ASAC ({why}); ignored")
                _pop(out, path)
        for path, convert in CONVERTED.items():
            found, value = _present(out, path)
            if not found:
                continue
            _pop(out, path)
            reads = convert(value)
            if isinstance(reads, str):
                self.errors.append(f"{path} ({source}): {reads}; got {value!r}")
                continue
            for new, new_value in reads.items():
                self._put(out, path, new, new_value, source)
            if reads:
                what = ", ".join(f"{new}: {_yaml(v)}" for new, v in reads.items())
                self._note(file, path, f"{source}: {path}: {_yaml(value)} is {what} now; read as that")
        for path, (new, what) in MOVED.items():
            found, value = _present(out, path)
            if found and self._move(out, path, new, value, source):
                _pop(out, path)
                self._note(file, path, f"{source}: {path} is {new} now{what}; read as that")
        return out

    def _put(self, out: dict[str, Any], old: str, new: str, value: Any, source: str) -> None:
        """Set a converted ``value`` at ``new``; an error when the layer sets it otherwise."""
        section, key = new.split(".")
        if not isinstance(out.get(section), dict):
            out[section] = {}
        if out[section].get(key, value) != value:
            self.errors.append(f"{old} ({source}): is {new}: {_yaml(value)} now, which this section sets otherwise")
        out[section][key] = value

    def _move(self, out: dict[str, Any], old: str, new: str, value: Any, source: str) -> bool:
        """Put ``value`` at ``new`` in ``out``; False (left where it is, for validation to report) when
        the new section is not a mapping; an error when the new key is set in the same layer too."""
        section, key = new.split(".")
        if out.get(section) is None:
            out[section] = {}
        target = out[section]
        if not isinstance(target, dict):
            return False
        if value is None and section == "random_params":
            pass  # a bare `random_params:` under sac_config adds nothing
        elif key not in target or target[key] is None:
            target[key] = value
        elif isinstance(value, dict) and isinstance(target[key], dict) and not set(value) & set(target[key]):
            target[key] = {**target[key], **value}
        else:
            self.errors.append(f"{old} ({source}): is {new} now, which this section sets too; keep only {new}")
        return True

    def override(self, parts: list[str], value: Any, source: str) -> list[tuple[list[str], Any]]:
        """The ``([section, key], value)`` pairs an override of the original's ``parts`` sets in ASAC; none
        when it sets nothing (a dropped key, noted, or a refused one, kept in ``errors``)."""
        out = self._port({parts[0]: {parts[1]: value}}, source, source)
        pairs = [([section, key], v) for section, body in out.items() for key, v in body.items()]
        self._overridden.update(".".join(p) for p, _ in pairs)
        self._given.update(".".join(p) for p, _ in pairs)
        return pairs

    def finish(self, merged: dict[str, Any], sources: dict[str, str]) -> None:
        """Read the merged values (every layer and override in): ids ASAC cannot make, ``clip_epsilon``
        <= 0, and for the original's file its defaults where it is silent; ``merged`` changes in place."""
        found, env_id = _present(merged, "base_config.build_path")
        if found and isinstance(env_id, str) and env_id in ENV_IDS:
            new, why, folder = ENV_IDS[env_id]
            source = sources.get("base_config.build_path", "config")
            task = f" (ASAC's task for it: envs/{folder})" if (ENVS_DIR / folder / "config.yaml").is_file() else ""
            merged["base_config"]["build_path"] = new
            message = f"{source}: base_config.build_path {env_id} {why.format(new=new)}{task}"
            self._note(source, "base_config.build_path", message)
        path = "sac_config.clip_epsilon"
        found, epsilon = _present(merged, path)
        if found and isinstance(epsilon, int | float) and not isinstance(epsilon, bool) and epsilon <= 0:
            source = sources.get(path, "config")
            merged["sac_config"]["clip_epsilon"] = None  # read as off, or refused below (no second message)
            if self.original is not None and path not in self._overridden:
                self._note(source, path, f"{source}: {path} {epsilon} is the original's 'off'; read as null (off)")
            else:
                self.errors.append(
                    f"{path} ({source}): clip_epsilon: {epsilon}: ASAC turns the clip off with null (the original's "
                    "-1 or 0); write clip_epsilon: null"
                )
        if self.original is not None:
            self._original_defaults(merged, sources)

    def _original_defaults(self, merged: dict[str, Any], sources: dict[str, str]) -> None:
        applied = []
        for path, value in ORIGINAL_DEFAULTS.items():
            if path not in self._given:
                section, key = path.split(".")
                if isinstance(merged.get(section), dict):
                    merged[section][key] = value
                    sources[path] = f"{self._file} (the original's default)"
                    applied.append(f"{key} {_yaml(value)}")
        batch = _present(merged, "replay_config.batch_size")[1]
        n_agents = _present(merged, "base_config.n_agents")[1]
        path = "replay_config.samples_per_insert"
        if path not in self._given and _count(batch) and _count(n_agents) and n_agents > 1:
            merged["replay_config"]["samples_per_insert"] = batch / n_agents
            sources[path] = f"{self._file} (the original's one update per vector step)"
            applied.append(
                f"one update per vector step (samples_per_insert {batch / n_agents:g} with batch {batch} and "
                f"{n_agents} envs)"
            )
        said = f": its defaults apply where it is silent: {', '.join(applied)}" if applied else ""
        self._note(self._file, "", f"{self._file} is read as the original's ({self.original}){said}")
        for path, (distributed_only, applies) in UNSET.items():
            if path not in self._given and (self._distributed or not distributed_only):
                self._note(self._file, path, f"{self._file}: {path} is not set: {applies}")


def _count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def _yaml(value: Any) -> str:
    """``value`` as a YAML file writes it (true, null, FORWARD)."""
    if value is None or isinstance(value, bool):
        return "null" if value is None else str(value).lower()
    return str(value)


def _leaves(layer: dict[str, Any]) -> set[str]:
    """The ``section.key`` paths a ported layer sets."""
    return {f"{section}.{key}" for section, body in layer.items() if isinstance(body, dict) for key in body}


def _pop(layer: dict[str, Any], path: str) -> None:
    section, _, key = path.partition(".")
    if not key:
        del layer[section]
        return
    del layer[section][key]
    if not layer[section]:
        del layer[section]  # an emptied section (base_config with only noise_max) is not a layer's value
