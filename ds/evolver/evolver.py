"""The evolver (docs/architecture.md section 10): one per experiment, it keeps the population of learners, runs CEM
rounds over their weights on its own thread, and tells actors and replays where to work.

Usage (``ds/evolver/service.py`` serves it over gRPC; protos/evolver.proto documents the calls)::

    evolver = Evolver(config, run_dir / "evolver", experiment=name, metrics=MetricsWriter(run_dir / "log/evolver"))
    evolver.start()                          # the round thread: checks for a due round every second, saves
    me = evolver.register_learner("l0", "10.0.0.5", 61001, replay_address="10.0.0.6:61002")
    evolver.post_reward(me.learner_id, -170.0, env_steps=20_000)           # queues, never waits for a round
    orders = evolver.learner_heartbeat(me.learner_id, env_steps=21_000)      # CONTINUE | LOAD_WEIGHTS | RETIRE
    round_, frames = evolver.sample(me.learner_id)                           # after LOAD_WEIGHTS
    job = evolver.assign(Role.ACTOR, "a0")                                   # ds/evolver/assign.py
    evolver.stop()                           # joins the thread and saves

The math is :class:`algorithm.evolution.CemPopulation`'s; leases, stale returns and assignments are the
registry's (ds/evolver/registry.py). What this class adds:

- **Rounds on one thread.** Every ``check_every_s`` the thread moves queued returns into the
  population and checks :func:`~algorithm.evolution.cem_due` over the *live* learners: a gone
  learner (lease expired) neither holds a round up nor takes part in one (its returns are set aside
  for the round and put back after). The thread fetches the elites' full weights with the
  learners' ``GetWeights`` rpc, outside every lock; an elite that does not answer (or sends weights
  that do not decode) sits the round out, logged, and the elites are ranked again without it. With
  fewer than two learners left the round waits ``retry_round_s``. Then ``CemPopulation.run_round``
  fits the Gaussian and draws a sample for every other learner, under the population lock only.
- **Late learners.** The last round's Gaussian is kept (and saved): a learner that registers as new
  after a round gets a draw of it as its pending sample (``sample_weights``, as in a round), saved
  before the registration returns, so it loads it (GetSample) before its first update instead of
  starting from its own random weights. Before the first round, and for a learner back with
  ``previous_id``, nothing is drawn.
- **Persistence** (ds/evolver/state.py). Registrations, rounds and new assignments are saved before
  the call returns (a round before any learner hears of it); returns, acknowledgements and expiries
  are saved by the thread within ``save_every_s``, so a ``kill -9`` loses at most that much. A new
  Evolver on the same directory carries on: same learners, round counter, pending samples, rng and
  assignments, each with a fresh lease. The time of the last round is wall-clock time, so
  ``evolver_cem_time`` counts across restarts.
- **Metrics** under the run's ``log/evolver``, written by the thread: ``evolver/learner_<id>/return``
  and ``/mean_return`` at the learner's env steps, ``evolver/learner_<id>/params`` (text), and per
  round ``evolver/cem_std`` (mean std over every sampled weight), ``evolver/best_mean_return``,
  ``evolver/participants``, ``evolver/retired``, ``evolver/learner_<id>/elite`` and the text
  ``evolver/round`` (elites, mean returns, retired).

Lock order: save lock -> population lock -> registry lock. Registration, :meth:`info` and saves
wait for a round's arithmetic; nothing waits for its network calls.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import numpy as np
import yaml

from algorithm.config.schema import Config
from algorithm.evolution import CemPopulation, RoundResult, cem_due, sample_weights
from algorithm.files import WriteFailures
from algorithm.run.logging import MetricsWriter, Throttle
from ds.evolver.registry import LearnerRegistry, Return, check_address, check_host, check_port
from ds.evolver.state import (
    FORMAT,
    SAMPLES_DIR,
    STATE_FILE,
    Assignment,
    CemDistribution,
    EvolverInfo,
    EvolverStateError,
    LearnerOrders,
    LearnerRegistration,
    Role,
    load_state,
    read_distribution,
    read_sample,
    remove_unreferenced,
    save_state,
    write_distribution,
    write_sample,
)
from ds.learner.client import LearnerClient
from ds.net.params import ParamsError, Token, decode_params
from ds.net.rpc import RetryPolicy
from ds.net.security import NO_CREDENTIALS, Credentials

log = logging.getLogger("asac.evolver")
EVOLVER_MESSAGE_BYTES = 256 * 1024 * 1024  # whole SAC models travel (GetWeights, GetSample)
_Event = Callable[[MetricsWriter], None]


class Evolver:
    """The population, its rounds and its saved state, around a :class:`LearnerRegistry`.

    ``config`` is the experiment's (``base_config.evolver_*``, ``max_actors_each_learner``,
    ``random_params``); ``state_dir`` is where its state lives (the run directory's ``evolver/``);
    ``token`` verifies the elites' weights and signs samples; ``credentials`` (ds/net/security.py: TLS, the
    token's bearer) open the channels to the learners for GetWeights; ``metrics`` gets the ``evolver/*``
    metrics; ``seed`` seeds the draws of params and weights (default ``sac_config.seed``). A saved
    state in ``state_dir`` is loaded (:class:`EvolverStateError` names a file that cannot be).
    Thread-safe.
    """

    def __init__(
        self,
        config: Config,
        state_dir: Path,
        experiment: str,
        *,
        lease_s: float = 30.0,
        token: Token = None,
        credentials: Credentials = NO_CREDENTIALS,
        metrics: MetricsWriter | None = None,
        seed: int | None = None,
        max_message_bytes: int = EVOLVER_MESSAGE_BYTES,
        weights_timeout_s: float = 60.0,
        check_every_s: float = 1.0,
        save_every_s: float = 0.5,
        retry_round_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self.state_dir = Path(state_dir)
        self.experiment = experiment
        self.token = token
        self.credentials = credentials
        self.metrics = metrics
        self.max_message_bytes = int(max_message_bytes)
        self.weights_timeout_s = float(weights_timeout_s)
        self.check_every_s = float(check_every_s)
        self.save_every_s = float(save_every_s)
        self.retry_round_s = float(retry_round_s)
        self._log_round_waits = Throttle(60.0)
        self._clock, self._wall = clock, wall_clock
        self._save_lock, self._pop_lock = threading.Lock(), threading.Lock()
        self._events: queue.SimpleQueue[_Event] = queue.SimpleQueue()
        self._round_retry_at = -math.inf
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.registry = LearnerRegistry(config, experiment, lease_s, clock, token)
        self.population = CemPopulation(config)
        self._rng = np.random.default_rng(config.sac_config.seed if seed is None else seed)
        self._started_wall = self._last_round_wall = wall_clock()
        self._cem: CemDistribution | None = None  # the last round's Gaussian, for learners that join later
        self.retry_save_s = 10.0  # after a failed save (a full disk), the round thread tries again this much later
        self._save_failed_at = -math.inf
        self.state_writes = WriteFailures("evolver state", log, retry=f"trying again in {self.retry_save_s:g} s")
        self._load()

    @property
    def lease_s(self) -> float:
        return self.registry.lease_s

    # ------------------------------------------------------------------ the rpcs' side

    def register_learner(
        self,
        name: str,
        host: str,
        learner_port: int,
        params_port: int = 0,
        replay_address: str = "",
        previous_id: int | None = None,
    ) -> LearnerRegistration:
        """A new learner (a new id and its random_params draws), or ``previous_id`` back with its id
        and config at the address given now. :class:`~ds.evolver.state.UnknownLearner` for an id this
        evolver never gave out, :class:`~ds.evolver.state.LearnerRetired` for a retired one. A new
        learner after a round gets a sample of the last round's Gaussian, waiting for it (GetSample)."""
        if not host:
            raise ValueError("host: empty; say where actors reach this learner")
        check_host("host", host)
        check_port("learner_port", learner_port, lowest=1)
        check_port("params_port", params_port, lowest=0)
        if replay_address:
            check_address("replay_address", replay_address)
        ports = (learner_port, params_port, replay_address)
        with self._pop_lock:
            if previous_id is not None:
                entry = self.registry.reattach(previous_id, name, host, *ports)
                log.info("learner %d is back at %s (%s)", previous_id, entry.address, name)
            else:
                learner_id, params = self.population.add_learner(self._rng)
                entry = self.registry.add(learner_id, params, name, host, *ports)
                self._event(_params_text(learner_id, params))
                log.info("learner %d registered at %s (%s) with %s", learner_id, entry.address, name, params)
                if (cem := self._cem) is not None:
                    self.registry.add_sample(learner_id, cem.round, sample_weights(cem.mean, cem.std, self._rng))
                    log.info("learner %d joined after round %d: starting from a sample of the CEM distribution",
                             learner_id, cem.round)  # fmt: skip
        registration = self.registry.registration(entry)
        self.save()
        return registration

    def learner_heartbeat(self, learner_id: int, env_steps: int, loaded_round: int | None = None) -> LearnerOrders:
        """Renew the lease, acknowledge ``loaded_round``, and say what to do next."""
        return self.registry.heartbeat(learner_id, env_steps, loaded_round)

    def post_reward(self, learner_id: int, mean_return: float, env_steps: int, weights_round: int = 0) -> bool:
        """Queue one evaluation return; False when it was dropped as stale (a later sample waits)."""
        return self.registry.post(learner_id, mean_return, env_steps, weights_round)

    def sample(self, learner_id: int) -> tuple[int, list[bytes]] | None:
        """``(round, frames)`` of the weights waiting for this learner (ds/net/params.py frames, the round
        as version, signed with the token), or None when none waits."""
        return self.registry.sample(learner_id)

    def assign(self, role: Role, name: str, address: str = "", previous: str = "") -> Assignment:
        """Work for an actor or a replay (ds/evolver/assign.py); :class:`~ds.evolver.state.NoWorkYet`
        when nobody can take it now."""
        assignment, changed = self.registry.assign(role, name, address, previous)
        if changed:
            log.info("%s %r works for learner %d (%s)", role, name, assignment.learner_id, assignment.assignment_id)
            self.save()
        return assignment

    def renew_assignment(self, assignment_id: str) -> Assignment:
        """Renew an assignment's lease; it comes back with its learner's current address and replay."""
        return self.registry.renew(assignment_id)

    def info(self) -> EvolverInfo:
        """Every learner (retired ones too, by id), the rounds run and the live assignments."""
        with self._pop_lock:
            self._drain()
            window = {i: len(r.returns) for i, r in self.population.learners.items()}
            return self.registry.info(self.population.mean_returns(), window)

    # ------------------------------------------------------------------ CEM rounds

    def run_round_if_due(self) -> RoundResult | None:
        """Run a CEM round if one is due; what the thread calls every ``check_every_s``."""
        if self._clock() < self._round_retry_at:
            return None
        with self._pop_lock:
            self._drain()
            if not self._round_due():
                return None
            with self._set_aside(self.registry.gone()):
                wanted = self.population.elites()
        fetched: dict[int, dict[str, np.ndarray]] = {}
        failed: set[int] = set()
        while True:  # every pass fetches or fails at least one new elite, so it ends
            for learner_id in wanted:
                if learner_id not in fetched and learner_id not in failed:
                    weights = self._fetch_weights(learner_id)
                    if weights is None:
                        failed.add(learner_id)
                    else:
                        fetched[learner_id] = weights
            with self._pop_lock:
                self._drain()
                skip = self.registry.gone() | failed
                taking_part = [i for i in self.population.mean_returns() if i not in skip]
                if len(taking_part) < 2:
                    if self._log_round_waits():  # every retry_round_s while it lasts: said once a minute
                        log.warning("CEM round waits: only %d learners can take part (retrying every %.0f s)",
                                    len(taking_part), self.retry_round_s)  # fmt: skip
                    self._round_retry_at = self._clock() + self.retry_round_s
                    return None
                with self._set_aside(skip):
                    wanted = self.population.elites()
                    if all(i in fetched for i in wanted):
                        try:
                            result = self.population.run_round(fetched, self._rng)
                        except ValueError as e:  # the elites' weights do not match (names, shapes): say so
                            log.error("CEM round failed, next try in %.0f s: %s", self.retry_round_s, e)
                            self._round_retry_at = self._clock() + self.retry_round_s
                            return None
                        self.registry.apply_round(result, self.population)
                        self._cem = CemDistribution(result.round, result.mean, result.std)
                        self._last_round_wall = self._wall()
                        self._event(_round_metrics(result))
                        break
        log.info(
            "CEM round %d: mean returns %s, elites %s, samples for %s, retired %s, sat out %s",
            result.round,
            {i: round(r, 1) for i, r in result.mean_returns.items()},
            result.elites,
            sorted(result.samples_for),
            result.retired,
            sorted(skip),
        )
        self.save()
        return result

    def _fetch_weights(self, learner_id: int) -> dict[str, np.ndarray] | None:
        address = self.registry.address(learner_id)
        retry = RetryPolicy(attempts=3)
        client = LearnerClient(
            address,
            max_message_bytes=self.max_message_bytes,
            rpc_timeout_s=self.weights_timeout_s,
            retry=retry,
            credentials=self.credentials,
        )
        try:
            return decode_params(client.get_weights()[1], token=self.token)[1]
        except grpc.RpcError as e:
            log.warning(
                "learner %d at %s sits this round out: GetWeights failed (%s: %s)",
                learner_id,
                address,
                e.code().name,
                e.details(),
            )
        except ParamsError as e:
            log.warning("learner %d at %s sits this round out: its weights do not decode (%s)", learner_id, address, e)
        finally:
            client.close()
        return None

    def _round_due(self) -> bool:
        lengths = [len(self.population.learners[i].returns) for i in self.registry.live()]
        minutes = (self._wall() - self._last_round_wall) / 60.0
        p = self.population
        return cem_due(lengths, p.cem_length, p.cem_min_length, minutes, p.cem_time)

    @contextlib.contextmanager
    def _set_aside(self, learner_ids: set[int]) -> Iterator[None]:
        """Hide these learners' returns from the population (they sit the round out), then put them back."""
        held = {}
        for i in learner_ids:
            if (record := self.population.learners.get(i)) is not None and record.returns:
                held[i], record.returns = record.returns, []
        try:
            yield
        finally:
            for i, returns in held.items():
                self.population.learners[i].returns = returns

    def _drain(self) -> None:
        """Move the registry's queued returns into the population (the caller holds its lock)."""
        for item in self.registry.take_returns():
            self.population.post_return(item.learner_id, item.value)
            returns = self.population.learners[item.learner_id].returns
            self._event(_return_metrics(item, float(np.mean(np.asarray(returns, dtype=np.float64)))))

    # ------------------------------------------------------------------ thread and state

    def start(self) -> None:
        """Start the round thread (rounds, saves, metrics)."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._loop, name="evolver-rounds", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the round thread (after a round in progress) and save."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.save(final=True)
        self._write_metrics()

    def _loop(self) -> None:
        last_check = -math.inf
        while not self._stop.wait(min(self.save_every_s, self.check_every_s)):
            try:
                if self._clock() - last_check >= self.check_every_s:
                    last_check = self._clock()
                    self.run_round_if_due()
                failing_since = self._save_failed_at if self.state_writes.failing else -math.inf
                due = self.registry.dirty and self._clock() - failing_since >= self.retry_save_s
                if due and not self.save():
                    self._save_failed_at = self._clock()
                self._write_metrics()
            except Exception:  # the thread must outlive one bad round or a full disk; the log says why
                log.exception("evolver round thread")

    def save(self, final: bool = False) -> bool:
        """Write new samples, then the state naming them, to ``state_dir``; then drop obsolete files.
        False when a write failed (a full disk: logged once, the previous state and the files it names
        kept, saved again when the round thread next looks, ``final``: at stop, the last try)."""
        with self._save_lock:
            with self._pop_lock:
                self._drain()
                registry, unsaved, obsolete = self.registry.snapshot()
                state = {
                    "format": FORMAT,
                    "experiment": self.experiment,
                    "population": self.population.to_state(),
                    "rng": self._rng.bit_generator.state,
                    "started_wall": self._started_wall,
                    "last_round_wall": self._last_round_wall,
                    "registry": registry,
                    "cem_round": 0 if (cem := self._cem) is None else cem.round,
                }
            new_cem = cem if cem is not None and not cem.saved else None

            def write() -> None:
                for sample in unsaved:
                    write_sample(self.state_dir, sample)
                if new_cem is not None:
                    write_distribution(self.state_dir, new_cem)
                save_state(self.state_dir, state)

            if not self.state_writes.attempt(self.state_dir / STATE_FILE, write, final=final):
                self.registry.save_failed(obsolete)
                return False
            self.registry.mark_saved(unsaved)
            for name in obsolete - {s.file_name for s in unsaved}:
                (self.state_dir / SAMPLES_DIR / name).unlink(missing_ok=True)
            if new_cem is not None:
                new_cem.saved = True
                for path in self.state_dir.glob("cem.round_*.npz"):  # the previous round's
                    if path.name != new_cem.file_name:
                        path.unlink(missing_ok=True)
            return True

    def _load(self) -> None:
        state = load_state(self.state_dir)
        if state is None:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            return
        where = self.state_dir / STATE_FILE
        if state.get("experiment") != self.experiment:
            raise EvolverStateError(
                f"evolver state {where} belongs to experiment {state.get('experiment')!r}, not {self.experiment!r}"
            )
        try:
            self.population = CemPopulation.from_state(self.config, state["population"])
            if state["rng"].get("bit_generator") != "PCG64":
                raise ValueError(f"rng is {state['rng'].get('bit_generator')!r}, expected 'PCG64'")
            self._rng.bit_generator.state = state["rng"]
            self._started_wall, self._last_round_wall = float(state["started_wall"]), float(state["last_round_wall"])
            self.registry.load(state["registry"], lambda i, r: read_sample(self.state_dir, i, r))
            if cem_round := int(state.get("cem_round", 0)):  # absent in states saved before it was kept
                self._cem = read_distribution(self.state_dir, cem_round)
            active = {i for i, e in self.registry.learners.items() if not e.retired}
            if active != set(self.population.learners):
                raise ValueError(f"registry learners {sorted(active)} differ from the population's")
        except (AttributeError, KeyError, TypeError, ValueError) as e:
            raise EvolverStateError(f"evolver state {where} is inconsistent: {type(e).__name__}: {e}") from None
        keep = {p.file_name for p in self.registry.pending.values()} | ({self._cem.file_name} if self._cem else set())
        removed = remove_unreferenced(self.state_dir, keep)
        log.info(
            "evolver state loaded from %s: %d learners, %d rounds, %d samples pending%s",
            where,
            len(self.registry.learners),
            self.registry.rounds,
            len(self.registry.pending),
            f"; removed stale files {removed}" if removed else "",
        )

    def _event(self, write: _Event) -> None:
        if self.metrics is not None:
            self._events.put(write)

    def _write_metrics(self) -> None:
        if self.metrics is None or self._events.empty():
            return
        while not self._events.empty():
            self._events.get()(self.metrics)
        self.metrics.flush()


def _params_text(learner_id: int, params: dict[str, object]) -> _Event:
    text = yaml.safe_dump(params, sort_keys=True) if params else "(no random_params)"
    return lambda w: w.text(f"evolver/learner_{learner_id}/params", text)


def _return_metrics(item: Return, mean: float) -> _Event:
    prefix = f"evolver/learner_{item.learner_id}"
    values = {f"{prefix}/return": item.value, f"{prefix}/mean_return": mean}
    return lambda w: w.write(values, item.env_steps)


def _round_metrics(result: RoundResult) -> _Event:
    floats = [s for name, s in result.std.items() if np.issubdtype(result.mean[name].dtype, np.floating)]
    size = sum(s.size for s in floats)
    values = {
        "evolver/cem_std": sum(float(s.sum(dtype=np.float64)) for s in floats) / size if size else 0.0,
        "evolver/best_mean_return": result.mean_returns[result.elites[0]],
        "evolver/participants": len(result.mean_returns),
        "evolver/retired": len(result.retired),
    }
    values |= {f"evolver/learner_{i}/elite": float(i in result.elites) for i in result.mean_returns}
    text = json.dumps({"elites": result.elites, "mean_returns": result.mean_returns, "retired": result.retired})

    def write(w: MetricsWriter) -> None:
        w.write(values, result.round)
        w.text("evolver/round", text, result.round)

    return write
