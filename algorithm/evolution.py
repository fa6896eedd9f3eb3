"""The evolver's math: per-learner hyper-parameter sampling and the cross-entropy method (CEM).

An evolver (docs/architecture.md section 10) keeps a population of SAC learners. Each learner runs with the
hyper-parameters ``random_params`` draws for it; learners post evaluation returns; when a round is
due, learners are ranked by mean recent return and every non-elite learner gets a fresh draw of
weights from a diagonal Gaussian fitted to the elites' weights. Everything here is pure: numpy
arithmetic with a ``numpy.random.Generator`` passed in, and state that is plain JSON-able data.

Usage::

    population = CemPopulation(config)                    # base_config.evolver_*, config.random_params
    learner_id, params = population.add_learner(rng)   # params: {"sac_config.n_step": 3, ...}
    learner_config = apply_params(config, params)      # the config that learner runs with
    population.post_return(learner_id, 123.4)          # after each of its evaluations
    if population.round_due(minutes_since_last_round):
        elites = population.elites()                   # fetch these learners' weights
        result = population.run_round({i: weights_of(i) for i in elites}, rng)
        for i, weights in result.samples_for.items(): send(i, weights)
        for i in result.retired: stop(i)
    write_atomically(json.dumps(population.to_state()))  # CemPopulation.from_state(config, state)

CEM fits a distribution to the elite fraction of a population and samples the next generation from
it (Rubinstein 1999, "The cross-entropy method for combinatorial and continuous optimization";
de Boer et al. 2005, "A tutorial on the cross-entropy method"). CEM-RL (Pourchot & Sigaud 2019,
arXiv:1810.01222) applies it to the weights of off-policy agents that keep training between
rounds, as the learners here do. The per-key choice of ``{in: [...]}`` values is a
Dirichlet-categorical model: a uniform Dirichlet prior updated by how often each value was elite
(the drawing itself, for any config model, is algorithm/config/random_params.py's).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from algorithm.config.random_params import apply_params, parse_random_params, sample_params

if TYPE_CHECKING:
    from algorithm.config.schema import Config

STATE_VERSION = 1


def elite_count(n: int, best_fraction: float) -> int:
    """``ceil(best_fraction * n)``, at least 1 and at most ``n``.

    Rounding up keeps the elites at least ``best_fraction`` of the population, so a small
    population still averages over more than one learner (4 learners at 0.3: 2 elites, where
    rounding would leave 1 and collapse the Gaussian onto its weights). The tolerance keeps float
    products such as ``0.3 * 10 = 3.0000000000000004`` from rounding up to 4.
    """
    if n < 1 or not 0.0 < best_fraction <= 1.0:
        raise ValueError(f"elite_count needs n >= 1 and best_fraction in (0, 1]; got {n}, {best_fraction}")
    return min(n, max(1, math.ceil(best_fraction * n - 1e-9)))


def elite_indices(mean_returns: Sequence[float] | np.ndarray, best_fraction: float) -> list[int]:
    """Indices of the ``elite_count`` highest mean returns, best first.

    Ties go to the lower index (a stable sort), so for :class:`CemPopulation`, whose learners are in
    id order, to the older learner; NaN ranks below every number.
    """
    r = np.asarray(mean_returns, dtype=np.float64)
    if r.ndim != 1 or r.size == 0:
        raise ValueError(f"elite_indices needs a non-empty 1-d sequence; got shape {r.shape}")
    order = np.argsort(-np.where(np.isnan(r), -np.inf, r), kind="stable")
    return [int(i) for i in order[: elite_count(r.size, best_fraction)]]


def cem_distribution(
    elite_weights: Sequence[Mapping[str, np.ndarray]], std_max: float
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Element-wise mean and std of the elites' weights (best elite first), std capped at ``std_max``.

    This is CEM's Gaussian fit with a diagonal covariance, computed in float64 and returned in
    each tensor's dtype. The std is the population std (ddof=0): it is the maximum-likelihood fit
    CEM prescribes (Rubinstein 1999), and it stays defined for a single elite (std 0: everyone
    gets the best weights) where the sample std (ddof=1) would not. The cap keeps elites that
    drifted far apart from scattering the next generation across weight space. Unlike CEM-RL, no
    noise floor is added to the std: a collapsed fit copies the elites' mean, and the learners'
    own training (with their different hyper-parameters) moves them apart again.

    Tensors that are not floating point (step counters, masks) are not sampled: their mean is the
    best elite's tensor and their std is zero.
    """
    if not elite_weights:
        raise ValueError("cem_distribution needs at least one elite")
    best = elite_weights[0]
    for rank, weights in enumerate(elite_weights[1:], start=1):
        if set(weights) != set(best):
            raise ValueError(f"elite {rank} has tensors {sorted(set(weights) ^ set(best))} the best elite lacks or has")
        for name, array in best.items():
            if weights[name].shape != array.shape or weights[name].dtype != array.dtype:
                raise ValueError(
                    f"tensor {name!r}: elite {rank} is {weights[name].dtype}{weights[name].shape}, "
                    f"the best elite {array.dtype}{array.shape}"
                )
    mean: dict[str, np.ndarray] = {}
    std: dict[str, np.ndarray] = {}
    for name, array in best.items():
        if np.issubdtype(array.dtype, np.floating):
            stack = np.stack([np.asarray(weights[name], dtype=np.float64) for weights in elite_weights])
            mean[name] = stack.mean(axis=0).astype(array.dtype)
            std[name] = np.minimum(stack.std(axis=0), std_max).astype(array.dtype)
        else:
            mean[name] = np.array(array, copy=True)
            std[name] = np.zeros(array.shape, dtype=np.float32)
    return mean, std


def sample_weights(
    mean: Mapping[str, np.ndarray], std: Mapping[str, np.ndarray], rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """One draw of ``N(mean, std**2)`` per element, in ``mean``'s dtypes and shapes.

    Floating tensors are drawn in float64 and cast back; other tensors are copied from ``mean``.
    Tensors are drawn in ``mean``'s key order, so a seeded ``rng`` gives the same weights.
    """
    sample: dict[str, np.ndarray] = {}
    for name, m in mean.items():
        if not np.issubdtype(m.dtype, np.floating):
            sample[name] = np.array(m, copy=True)
            continue
        s = np.asarray(std[name], dtype=np.float64)
        if s.shape != m.shape:
            raise ValueError(f"tensor {name!r}: mean is {m.shape}, std is {s.shape}")
        sample[name] = (m.astype(np.float64) + s * rng.standard_normal(m.shape)).astype(m.dtype)
    return sample


def cem_due(
    lengths: Sequence[int], cem_length: int, min_length: int, minutes_since_last: float, cem_time: float
) -> bool:
    """Whether a CEM round should run, given how many returns each learner holds.

    A round runs when every learner has ``cem_length`` returns, or when ``cem_time`` minutes have
    passed since the last round (the caller measures them) and every learner has ``min_length``.
    Never with fewer than two learners: one learner has no one to exchange weights with.
    """
    if len(lengths) < 2:
        return False
    if all(n >= cem_length for n in lengths):
        return True
    return minutes_since_last >= cem_time and all(n >= min_length for n in lengths)


@dataclass
class LearnerRecord:
    """What the population knows of one learner."""

    learner_id: int
    params: dict[str, Any]  # its random_params draws, by dotted key
    returns: list[float] = field(default_factory=list)  # the last evolver_cem_length returns, oldest first
    rounds: int = 0  # CEM rounds it took part in
    times_elite: int = 0


@dataclass
class RoundResult:
    """The outcome of one CEM round; ``mean``/``std`` are what the samples were drawn from."""

    round: int  # 1 for the first round
    elites: list[int]  # learner ids, best first; they keep their weights
    mean_returns: dict[int, float]  # of every learner that took part
    samples_for: dict[int, dict[str, np.ndarray]]  # new weights for each non-elite, non-retired learner
    retired: list[int]
    mean: dict[str, np.ndarray]
    std: dict[str, np.ndarray]


class CemPopulation:
    """The evolver's bookkeeping: learners, their returns and params, elite counts per ``in`` value.

    The settings come from ``config.base_config.evolver_*`` and the specs from
    ``config.random_params``; the state (:meth:`to_state`) is plain JSON-able data. CEM's mean and
    std are not state: each round fits them afresh to the elites' current weights, and a caller
    that wants them (for logging) takes them from the :class:`RoundResult`. Nor is time: the caller
    measures the minutes since the last round and persists that round's wall time itself.
    """

    def __init__(self, config: Config) -> None:
        base = config.base_config
        self.config = config
        self.specs = parse_random_params(config.random_params, config)
        self.cem_length = base.evolver_cem_length
        self.cem_best = base.evolver_cem_best
        self.cem_min_length = base.evolver_cem_min_length
        self.cem_time = base.evolver_cem_time
        self.remove_worst = base.evolver_remove_worst
        self.std_max = base.evolver_cem_std_max
        self.learners: dict[int, LearnerRecord] = {}
        self.counts = {path: [0] * len(spec.values) for path, spec in self.specs.items() if spec.kind == "in"}
        self.retired: list[int] = []
        self.next_id = 0
        self.rounds = 0

    def add_learner(self, rng: np.random.Generator) -> tuple[int, dict[str, Any]]:
        """Register a learner: a new id (never reused) and its ``random_params`` draws."""
        params = sample_params(self.specs, self.config, self.counts, rng)
        learner_id = self.next_id
        self.next_id += 1
        self.learners[learner_id] = LearnerRecord(learner_id, params)
        return learner_id, copy.deepcopy(params)

    def learner_config(self, learner_id: int) -> Config:
        return apply_params(self.config, self.learners[self._known(learner_id)].params)

    def post_return(self, learner_id: int, value: float) -> None:
        """Add one evaluation return; only the last ``evolver_cem_length`` are kept."""
        if not math.isfinite(value):
            raise ValueError(f"learner {learner_id} posted a non-finite return {value!r}")
        returns = self.learners[self._known(learner_id)].returns
        returns.append(float(value))
        del returns[: -self.cem_length]

    def mean_returns(self) -> dict[int, float]:
        """Mean recent return of every learner that has posted one (the ranking key)."""
        return {
            i: float(np.mean(np.asarray(r.returns, dtype=np.float64))) for i, r in self.learners.items() if r.returns
        }

    def round_due(self, minutes_since_last: float) -> bool:
        lengths = [len(r.returns) for r in self.learners.values()]
        return cem_due(lengths, self.cem_length, self.cem_min_length, minutes_since_last, self.cem_time)

    def elites(self) -> list[int]:
        """Who would be elite in a round now, best first: fetch their weights for :meth:`run_round`."""
        means = self.mean_returns()
        ids = sorted(means)
        return [ids[k] for k in elite_indices([means[i] for i in ids], self.cem_best)] if ids else []

    def run_round(
        self, weights_by_learner: Mapping[int, Mapping[str, np.ndarray]], rng: np.random.Generator
    ) -> RoundResult:
        """Run one CEM round over the learners that have posted returns.

        ``weights_by_learner`` must hold every elite's weights (others are ignored). Every learner
        that took part counts the round and starts a fresh return window (its old returns describe
        weights it may no longer have); each elite counts one more elite round and adds 1 to the
        count of its value of every ``in`` key. A learner is retired after ``evolver_remove_worst``
        rounds without ever being elite, worst mean return first, but never so many that fewer than
        ``elite_count + 1`` learners remain (the population keeps its elites and one learner to
        explore). Every other non-elite gets an independent sample of weights, in id order.
        """
        means = self.mean_returns()
        ids = sorted(means)
        if not ids:
            raise ValueError("run_round: no learner has posted a return")
        elite_ids = [ids[k] for k in elite_indices([means[i] for i in ids], self.cem_best)]
        missing = [i for i in elite_ids if i not in weights_by_learner]
        if missing:
            raise ValueError(f"run_round needs the weights of every elite; missing learners {missing}")
        mean, std = cem_distribution([weights_by_learner[i] for i in elite_ids], self.std_max)

        for i in ids:
            self.learners[i].rounds += 1
            self.learners[i].returns.clear()
        for i in elite_ids:
            record = self.learners[i]
            record.times_elite += 1
            for path, counts in self.counts.items():
                value = record.params.get(path)
                if value in self.specs[path].values:
                    counts[self.specs[path].values.index(value)] += 1
        retired = self._retire(ids, elite_ids, means)
        samples_for = {i: sample_weights(mean, std, rng) for i in ids if i not in elite_ids and i not in retired}
        self.rounds += 1
        return RoundResult(self.rounds, elite_ids, {i: means[i] for i in ids}, samples_for, retired, mean, std)

    def _retire(self, ids: list[int], elite_ids: list[int], means: dict[int, float]) -> list[int]:
        if self.remove_worst == -1:
            return []
        candidates = [
            i
            for i in ids
            if i not in elite_ids and self.learners[i].times_elite == 0 and self.learners[i].rounds >= self.remove_worst
        ]
        candidates.sort(key=lambda i: means[i])  # worst first; a stable sort keeps ties in id order
        room = max(0, len(self.learners) - (len(elite_ids) + 1))
        retired = candidates[:room]
        for i in retired:
            del self.learners[i]
        self.retired.extend(retired)
        return retired

    def _known(self, learner_id: int) -> int:
        if learner_id not in self.learners:
            why = "was retired" if learner_id in self.retired else "is not registered"
            raise KeyError(f"learner {learner_id} {why}")
        return learner_id

    def to_state(self) -> dict[str, Any]:
        """Everything :meth:`from_state` needs, as JSON-able data (ints, floats, strings, lists, dicts)."""
        return {
            "version": STATE_VERSION,
            "next_id": self.next_id,
            "rounds": self.rounds,
            "retired": list(self.retired),
            "counts": {
                path: {"values": copy.deepcopy(list(self.specs[path].values)), "counts": list(counts)}
                for path, counts in self.counts.items()
            },
            "learners": [
                {
                    "id": r.learner_id,
                    "params": copy.deepcopy(r.params),
                    "returns": list(r.returns),
                    "rounds": r.rounds,
                    "times_elite": r.times_elite,
                }
                for r in self.learners.values()
            ],
        }

    @classmethod
    def from_state(cls, config: Config, state: Mapping[str, Any]) -> CemPopulation:
        """The population :meth:`to_state` saved, under ``config``'s settings and specs.

        Counts follow values, not positions: a value still in the config's ``in`` list keeps its
        count, a new value starts at 0, a key or value no longer configured is dropped. With a
        smaller ``evolver_cem_length``, each learner keeps its most recent returns.
        """
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"population state version {state.get('version')!r}; expected {STATE_VERSION}")
        population = cls(config)
        population.next_id = int(state["next_id"])
        population.rounds = int(state["rounds"])
        population.retired = [int(i) for i in state["retired"]]
        for path, saved in state["counts"].items():
            if path not in population.counts:
                continue
            values = population.specs[path].values
            for value, count in zip(saved["values"], saved["counts"], strict=True):
                if value in values:
                    population.counts[path][values.index(value)] = int(count)
        for entry in state["learners"]:
            record = LearnerRecord(
                learner_id=int(entry["id"]),
                params=copy.deepcopy(dict(entry["params"])),
                returns=[float(x) for x in entry["returns"]][-population.cem_length :],
                rounds=int(entry["rounds"]),
                times_elite=int(entry["times_elite"]),
            )
            population.learners[record.learner_id] = record
        return population
