"""Configs written for the original Advanced-Soft-Actor-Critic: where each of its keys lives in ASAC.

The original's two default layouts (its ``algorithm/default_config.yaml`` and the distributed
``ds/default_config.yaml``) mostly match ASAC's key for key; the keys that do not are all in the
tables below, and :class:`Port` applies them to each layer of a task's ``config.yaml`` (and to each
``--override``) before :mod:`algorithm.config` merges and validates it:

- ``MOVED``: same meaning, another place; the value is read there, with one WARNING per key and file
  (``<file> [default]: base_config.noise_max is actor_config.noise_max now; read as that``);
- ``DROPPED``: Unity-only settings with no effect on gymnasium envs; ignored, with a WARNING;
- ``REFUSED`` / ``REFUSED_VALUES``: a key or value whose meaning cannot be carried over; an error
  that names the key, the file and what to write instead (all such errors of a load in one message);
- ``RESTATED``: the same key counting something else in ASAC; a WARNING stating the difference,
  given only for a file that looks written for the original (below), since ASAC's own configs use
  these keys the ASAC way.

A file looks written for the original when any of its sections holds a key of ``MOVED``,
``DROPPED`` or ``REFUSED``, or a value of ``REFUSED_VALUES``: paths that only the original's layouts
have (``env_type``, ``net_config`` and the ``evolver_*`` keys exist in both, so they say nothing). A
file of the original that uses none of those (its Pendulum config) is read as ASAC's without a word.

Keys of the original's layouts not named here (``scene``, ``n_agents``, ``replay_config.*``,
``net_config.*``, most of ``sac_config``, ...) are the same key with the same meaning in ASAC.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from typing import Any

CONFIG_LOGGER = "asac.config"  # what a task file's keys became; main_ds.py quiets it in local's children
log = logging.getLogger(CONFIG_LOGGER)

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
}

# old path -> why it has no counterpart (ignored)
DROPPED: dict[str, str] = {
    "base_config.no_graphics": "a Unity setting; ASAC runs gymnasium envs only",
    "base_config.port": "the Unity env port; ASAC runs gymnasium envs only",
}

# old path -> what to do instead (the key's meaning cannot be carried over)
REFUSED: dict[str, str] = {
    "base_config.update_policy_variables_per_step": (
        "the original's actors fetched weights every N of their own env steps (-1: at each episode start); "
        "ASAC actors act with every weight publication as it arrives, so delete the key, and set "
        "sac_config.update_policy_variables_per_step (learner updates between publications) if actors should lag"
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
}

# same path, other meaning -> the difference (stated for files written for the original)
RESTATED: dict[str, str] = {
    "base_config.max_step": (
        "counts env steps of all envs and actors in ASAC, the original counted learner updates; read as env steps "
        "(N updates take about N * batch_size / samples_per_insert + min_size_to_sample env steps)"
    ),
    "sac_config.save_model_per_step": (
        "counts env steps in ASAC, the original counted learner updates; read as env steps"
    ),
    "sac_config.save_model_per_minute": (
        "makes a checkpoint due after this many minutes in ASAC (or after save_model_per_step env steps, whichever "
        "comes first); the original only held saves back until this many minutes had passed; read the ASAC way"
    ),
}


def _present(layer: Any, path: str) -> tuple[bool, Any]:
    """Whether ``section.key`` is in ``layer`` (a mapping of sections), and its value."""
    section, key = path.split(".")
    body = layer.get(section) if isinstance(layer, dict) else None
    if isinstance(body, dict) and key in body:
        return True, body[key]
    return False, None


def looks_like_original(task_file: Any) -> bool:
    """Whether any section of a task file (``default``, variants) holds a key or value only the
    original's layouts have (the module docstring says why these)."""
    if not isinstance(task_file, dict):
        return False
    for layer in task_file.values():
        for path in (*MOVED, *DROPPED, *REFUSED):
            if _present(layer, path)[0]:
                return True
        for path, (is_original, _) in REFUSED_VALUES.items():
            found, value = _present(layer, path)
            if found and is_original(value):
                return True
    return False


class Port:
    """One config load's port: notes logged once per key and file, errors kept for one message."""

    def __init__(self) -> None:
        self.errors: list[str] = []
        self._noted: set[tuple[str, str]] = set()

    def _note(self, file: str, path: str, message: str) -> None:
        if (file, path) not in self._noted:
            self._noted.add((file, path))
            log.warning(message)

    def layer(self, layer: Any, source: str, file: str, original: bool) -> Any:
        """``layer`` (one section of a task file) with the original's keys read the ASAC way; ``source``
        names the section (``path [default]``), ``file`` the file (notes come once per key in it)."""
        if not isinstance(layer, dict):
            return layer  # algorithm.config reports the shape
        out = copy.deepcopy(layer)
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
        for path, (new, what) in MOVED.items():
            found, value = _present(out, path)
            if found and self._move(out, path, new, value, source):
                _pop(out, path)
                self._note(file, path, f"{source}: {path} is {new} now{what}; read as that")
        if original:
            for path, difference in RESTATED.items():
                if _present(out, path)[0]:
                    self._note(file, path, f"{source}: {path} {difference}")
        return out

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

    def override(self, parts: list[str], source: str) -> list[str] | None:
        """The ``[section, key]`` an override of the original's ``parts`` sets in ASAC; None when it sets
        nothing (a dropped key, noted, or a refused one, kept in ``errors``)."""
        path = ".".join(parts)
        if path in REFUSED:
            self.errors.append(f"{path} ({source}): {REFUSED[path]}")
            return None
        if path in DROPPED:
            self._note(source, path, f"{source}: {path} has no counterpart in ASAC ({DROPPED[path]}); ignored")
            return None
        if path in MOVED:
            new, what = MOVED[path]
            self._note(source, path, f"{source}: {path} is {new} now{what}; read as that")
            return new.split(".")
        return parts


def _pop(layer: dict[str, Any], path: str) -> None:
    section, key = path.split(".")
    del layer[section][key]
    if not layer[section]:
        del layer[section]  # an emptied section (base_config with only noise_max) is not a layer's value
