"""The evolver's data: the answers it gives (the same types on both ends of the network), the records
it keeps, and how they persist: ``<state_dir>/state.json`` plus one ``.npz`` per pending sample under
``<state_dir>/samples/`` and, once a CEM round ran, the last round's distribution (its mean and std,
from which a learner that joins later is drawn) in ``<state_dir>/cem.round_<R>.npz``.

Every file is written atomically (temp file, fsync, rename; :func:`algorithm.files.atomic_write`),
samples before the state that names them, so a crash at any point leaves a state whose files exist;
files no state names (a crash between the two writes, or an acknowledged sample) are deleted when the
state is next loaded (:func:`remove_unreferenced`). Nothing is unpickled: the state is JSON and
samples load with ``allow_pickle=False``. The state carries a SHA-256 digest of its contents: a
flipped digit is still valid JSON (flipping each bit of a small state in turn, 4% of the flips loaded
a different population without a word). A state or sample that cannot be read, or a state whose
contents do not match its digest, raises :class:`EvolverStateError` naming the file, and nothing
is overwritten.

Usage of the files (by ds/evolver/evolver.py only)::

    saved = load_state(state_dir)                    # None for a fresh directory
    write_sample(state_dir, pending)                 # a CEM round's sample for one learner
    write_distribution(state_dir, cem)               # the round's mean and std (CemDistribution)
    save_state(state_dir, {"format": FORMAT, ...})   # after every change that matters
    remove_unreferenced(state_dir, keep={"learner_3.round_2.npz", "cem.round_2.npz"})

The state names the distribution's round as ``cem_round`` (0: none); a state saved before it was
kept lacks the key and loads without one (late learners start from their own weights until the next
round).
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from algorithm.files import atomic_write

FORMAT = "asac.evolver/2"  # 2: with a "sha256" digest of the rest; states of format 1 still load
_FORMATS = ("asac.evolver/1", FORMAT)
STATE_FILE = "state.json"
SAMPLES_DIR = "samples"
_SAMPLE_NAME = re.compile(r"^learner_(\d+)\.round_(\d+)\.npz$")
_CEM_NAME = re.compile(r"^cem\.round_(\d+)\.npz$")


class EvolverStateError(RuntimeError):
    """The evolver's saved state is unreadable or inconsistent; the message names the file."""


class Role(StrEnum):
    ACTOR = "actor"
    REPLAY = "replay"


class UnknownLearner(LookupError):
    """No such learner, or its lease expired: register again (with ``previous_id``)."""


class LearnerRetired(RuntimeError):
    """The learner was retired (never elite for ``evolver_remove_worst`` rounds): it must exit."""


class UnknownAssignment(LookupError):
    """No such assignment, or it expired, or its learner retired: ``assign`` again."""


class NoWorkYet(RuntimeError):
    """No learner can take this actor or replay now (none registered, or none has room): retry."""


class Instruction(StrEnum):
    CONTINUE = "continue"
    LOAD_WEIGHTS = "load_weights"
    RETIRE = "retire"


@dataclass(frozen=True)
class LearnerRegistration:
    learner_id: int
    experiment: str
    config_yaml: str  # this learner's config: random_params values applied, random_params emptied
    params: dict[str, Any]  # those values by dotted key
    lease_s: float
    replay_address: str  # "" until a replay is assigned
    rounds: int


@dataclass(frozen=True)
class LearnerOrders:
    instruction: Instruction
    sample_round: int  # with LOAD_WEIGHTS: the round to fetch with sample()
    replay_address: str
    lease_s: float
    rounds: int


@dataclass(frozen=True)
class Assignment:
    assignment_id: str
    role: Role
    learner_id: int
    learner_host: str
    learner_port: int
    params_port: int
    replay_address: str
    config_yaml: str
    experiment: str
    lease_s: float
    learner_live: bool


@dataclass(frozen=True)
class LearnerInfo:
    learner_id: int
    name: str
    host: str
    learner_port: int
    params_port: int
    replay_address: str
    mean_return: float | None
    returns: int
    rounds: int
    times_elite: int
    retired: bool
    live: bool
    params: dict[str, Any]
    actors: int
    env_steps: int
    pending_round: int  # 0: no sample waits for it


@dataclass(frozen=True)
class EvolverInfo:
    experiment: str
    rounds: int
    last_elites: list[int]
    learners: list[LearnerInfo]
    assignments: list[Assignment]


@dataclass
class LearnerEntry:
    """What the evolver knows of one learner besides its population record (algorithm/evolution.py).

    ``replay_static``: the learner registered with its replay's address (no replay is assigned to
    it). ``loaded_round``: the last sample round it acknowledged. ``rounds``/``times_elite`` mirror
    its population record, which is deleted when it retires. ``expires`` (monotonic clock) and the
    cached config are not persisted: a loaded learner gets a fresh lease.
    """

    learner_id: int
    name: str
    host: str
    learner_port: int
    params_port: int
    params: dict[str, Any]
    replay_address: str = ""
    replay_static: bool = False
    env_steps: int = 0
    loaded_round: int = 0
    rounds: int = 0
    times_elite: int = 0
    retired_round: int | None = None
    expires: float = 0.0
    config_yaml: str | None = field(default=None, repr=False)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.learner_port}"

    @property
    def retired(self) -> bool:
        return self.retired_round is not None

    def to_json(self) -> dict[str, Any]:
        keys: tuple[str, ...] = (
            "learner_id",
            "name",
            "host",
            "learner_port",
            "params_port",
            "params",
            "replay_address",
        )
        keys += ("replay_static", "env_steps", "loaded_round", "rounds", "times_elite", "retired_round")
        return {k: getattr(self, k) for k in keys}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> LearnerEntry:
        return cls(**data)


@dataclass
class AssignmentEntry:
    """An actor or replay working for ``learner_id``; ``address`` is where a replay serves."""

    assignment_id: str
    role: Role
    name: str
    learner_id: int
    address: str = ""
    expires: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "assignment_id": self.assignment_id,
            "role": self.role.value,
            "name": self.name,
            "learner_id": self.learner_id,
            "address": self.address,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> AssignmentEntry:
        return cls(**{**data, "role": Role(data["role"])})


@dataclass
class PendingSample:
    """Weights a CEM round drew for one learner that has not acknowledged loading them yet.

    ``saved``: its file and the state naming it are on disk; only then is the learner told to load
    it, so a round the evolver lost in a crash was never announced. ``frames`` caches the encoding.
    """

    learner_id: int
    round: int
    weights: dict[str, np.ndarray]
    saved: bool = False
    frames: list[bytes] | None = field(default=None, repr=False)

    @property
    def file_name(self) -> str:
        return f"learner_{self.learner_id}.round_{self.round}.npz"


@dataclass
class CemDistribution:
    """The Gaussian of the last CEM round (``RoundResult.mean``/``std``): a learner that registers
    after the round starts from a draw of it. ``saved``: its file is on disk."""

    round: int
    mean: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    saved: bool = False

    @property
    def file_name(self) -> str:
        return f"cem.round_{self.round}.npz"


def save_state(state_dir: Path, state: dict[str, Any]) -> None:
    """Write ``state`` (JSON-able) and its digest to ``<state_dir>/state.json`` atomically."""
    text = json.dumps({**state, "sha256": _digest(state)}, indent=1, allow_nan=False).encode()
    atomic_write(state_dir / STATE_FILE, lambda f: f.write(text))


def _digest(state: dict[str, Any]) -> str:
    canonical = json.dumps(state, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode()).hexdigest()


def write_sample(state_dir: Path, sample: PendingSample) -> None:
    """Write ``sample``'s weights to ``<state_dir>/samples/<file_name>`` atomically."""
    savez: Any = np.savez  # numpy's stub reads **weights as its own keyword arguments
    atomic_write(state_dir / SAMPLES_DIR / sample.file_name, lambda f: savez(f, **sample.weights))


def write_distribution(state_dir: Path, cem: CemDistribution) -> None:
    """Write ``cem``'s mean and std (as ``mean/<name>``, ``std/<name>``) to ``<state_dir>/<file_name>`` atomically."""
    arrays = {f"mean/{k}": v for k, v in cem.mean.items()} | {f"std/{k}": v for k, v in cem.std.items()}
    savez: Any = np.savez
    atomic_write(state_dir / cem.file_name, lambda f: savez(f, **arrays))


def read_distribution(state_dir: Path, round_: int) -> CemDistribution:
    """The distribution a saved state names; :class:`EvolverStateError` names a missing or corrupt file."""
    cem = CemDistribution(round_, {}, {}, saved=True)
    path = state_dir / cem.file_name
    try:
        with np.load(path, allow_pickle=False) as npz:
            for key in npz.files:
                part, _, name = key.partition("/")
                {"mean": cem.mean, "std": cem.std}[part][name] = npz[key]
        if set(cem.mean) != set(cem.std) or any(cem.mean[k].shape != cem.std[k].shape for k in cem.mean):
            raise ValueError("its means and stds name different tensors or shapes")
    except Exception as e:  # numpy raises several types for a missing, truncated or foreign file
        raise EvolverStateError(
            f"CEM distribution {path} (named by {state_dir / STATE_FILE}) is unreadable: {e}"
        ) from None
    return cem


def load_state(state_dir: Path) -> dict[str, Any] | None:
    """The saved state, or None when ``state_dir`` holds none. :class:`EvolverStateError` names the
    file when it is not valid JSON of this format."""
    path = state_dir / STATE_FILE
    if not path.exists():
        return None
    try:
        state = json.loads(path.read_bytes())
    except (OSError, ValueError) as e:
        raise EvolverStateError(
            f"evolver state {path} is unreadable or truncated ({e}); nothing was overwritten: "
            "repair it or move it away to start a new population"
        ) from None
    if not isinstance(state, dict) or state.get("format") not in _FORMATS:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise EvolverStateError(f"evolver state {path} is not of format {FORMAT!r} (found {found!r})")
    digest = state.pop("sha256", None)
    try:
        actual = _digest(state)
    except ValueError:  # NaN or infinity, which a saved state never holds
        actual = None
    if (digest is not None or state["format"] == FORMAT) and digest != actual:
        raise EvolverStateError(
            f"evolver state {path} is damaged: its contents do not match their digest; nothing was overwritten: "
            "repair it or move it away to start a new population"
        )
    return state


def read_sample(state_dir: Path, learner_id: int, round_: int) -> PendingSample:
    """The pending sample a saved state names; :class:`EvolverStateError` names a missing or corrupt file."""
    sample = PendingSample(learner_id, round_, {}, saved=True)
    path = state_dir / SAMPLES_DIR / sample.file_name
    try:
        with np.load(path, allow_pickle=False) as npz:
            sample.weights = {name: npz[name] for name in npz.files}
    except Exception as e:  # numpy raises several types for a missing, truncated or foreign file
        raise EvolverStateError(
            f"pending sample {path} (named by {state_dir / STATE_FILE}) is unreadable: {e}"
        ) from None
    return sample


def remove_unreferenced(state_dir: Path, keep: set[str]) -> list[str]:
    """Delete sample and distribution files not in ``keep`` and temp files of interrupted writes;
    returns their names."""
    removed = []
    samples = state_dir / SAMPLES_DIR
    for folder in (state_dir, samples):
        if not folder.is_dir():
            continue
        for path in folder.iterdir():
            ours = _SAMPLE_NAME if folder == samples else _CEM_NAME
            stale_sample = ours.match(path.name) and path.name not in keep
            if stale_sample or (path.name.startswith(".") and path.name.endswith(".tmp")):
                path.unlink(missing_ok=True)
                removed.append(path.name)
    return removed
