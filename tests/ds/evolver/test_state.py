"""The evolver's saved state: a restarted evolver carries on where it stopped, a killed one loses at most the
last save interval, and a damaged, truncated or edited state or sample file is an error naming it, with
nothing overwritten."""

from __future__ import annotations

import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ds.evolver.evolver import Evolver
from ds.evolver.state import SAMPLES_DIR, STATE_FILE, EvolverInfo, EvolverStateError, Instruction, PendingSample, Role
from tests.ds.evolver.evolver_setup import Setup, evolver_config, register, weights_of

pytestmark = pytest.mark.grpc


def test_a_restarted_evolver_carries_on_where_it_stopped(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (0.0, 1.0, 2.0)]
    evolver, client = setup.evolver(evolver_config())
    ids = register(client, fakes)
    for i in ids:
        client.post_reward(i, float(i), 10)
        client.post_reward(i, float(i), 20)
    assert evolver.run_round_if_due() is not None
    job = client.assign_actor("a0")
    before = client.get_sample(ids[0])
    client.post_reward(ids[2], 5.0, 30)  # after the round: the thread has not saved it, stop() does
    info_before = client.info()
    setup.close()

    evolver, client = setup.evolver(evolver_config())
    info = client.info()
    assert (info.rounds, info.last_elites) == (info_before.rounds, info_before.last_elites)
    assert info.learners == info_before.learners and info.assignments == info_before.assignments
    orders = client.heartbeat(ids[0], 40)
    assert (orders.instruction, orders.sample_round) == (Instruction.LOAD_WEIGHTS, 1)
    after = client.get_sample(ids[0])
    assert before is not None and after is not None and after.round == before.round
    for name, array in before.weights.items():
        np.testing.assert_array_equal(after.weights[name], array)
    again = client.register_learner("l1 restarted", "127.0.0.1", fakes[1].port, previous_id=ids[1])
    assert again.learner_id == ids[1] and again.params == info.learners[1].params
    assert client.renew_assignment(job.assignment_id).learner_id == job.learner_id
    assert client.register_learner("new", "127.0.0.1", 61009).learner_id == 3

    client.heartbeat(ids[0], 50, loaded_round=1)
    evolver.save()
    # Left: only the new learner's, drawn from round 1's distribution (tests/ds/evolver/test_evolver_late_join.py).
    assert sorted(p.name for p in (setup.state_dir / SAMPLES_DIR).iterdir()) == ["learner_3.round_1.npz"]


def test_a_killed_evolver_loses_at_most_the_last_save_interval(setup: Setup, tmp_path: Path) -> None:
    evolver, client = setup.evolver(evolver_config(), real_clock=True, save_every_s=0.05)
    evolver.start()
    me = client.register_learner("l0", "127.0.0.1", 61001).learner_id
    client.post_reward(me, 3.0, 10)
    time.sleep(0.5)
    copy = tmp_path / "copy"  # the directory as a kill -9 now would leave it
    shutil.copytree(setup.state_dir, copy)
    revived = Evolver(evolver_config(), copy, "exp")
    assert [x.returns for x in revived.info().learners] == [1]


def test_an_unreadable_state_is_an_error_naming_the_file_and_nothing_is_overwritten(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (0.0, 1.0)]
    evolver, client = setup.evolver(evolver_config())
    for i in register(client, fakes):
        client.post_reward(i, float(i), 10)
        client.post_reward(i, float(i), 20)
    assert evolver.run_round_if_due() is not None
    setup.close()
    state = setup.state_dir / STATE_FILE
    good = state.read_bytes()
    state.write_bytes(good[: len(good) // 2])
    with pytest.raises(EvolverStateError, match=re.escape(f"evolver state {state} is unreadable or truncated")):
        Evolver(evolver_config(), setup.state_dir, "exp")
    assert state.read_bytes() == good[: len(good) // 2]
    state.write_bytes(good)
    with pytest.raises(EvolverStateError, match="belongs to experiment 'exp', not 'other'"):
        Evolver(evolver_config(), setup.state_dir, "other")
    (sample,) = (setup.state_dir / SAMPLES_DIR).iterdir()
    sample.write_bytes(b"not a zip file")
    with pytest.raises(EvolverStateError, match=re.escape(f"pending sample {sample} ") + ".* is unreadable"):
        Evolver(evolver_config(), setup.state_dir, "exp")


@pytest.fixture(scope="module")
def saved_population(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, EvolverInfo]:
    """A saved evolver state with learners, a return, an assignment and a pending sample file."""
    folder = tmp_path_factory.mktemp("population") / "evolver"
    evolver = Evolver(evolver_config(), folder, "exp", lease_s=600.0)
    ids = [evolver.register_learner(f"l{k}", "h", 61001 + k, 0, f"replay-{k}:1").learner_id for k in range(2)]
    evolver.post_reward(ids[0], 1.5, 10)
    evolver.assign(Role.ACTOR, "a0")
    evolver.registry.pending[ids[1]] = PendingSample(ids[1], 1, weights_of(0.5))
    evolver.save()
    return folder, evolver.info()


@settings(max_examples=40, deadline=None)
@given(file=st.sampled_from(["state", "sample"]), how=st.sampled_from(["cut", "flip"]), at=st.integers(0, 10**6),
       xor=st.integers(1, 255))  # fmt: skip
def test_a_damaged_state_or_sample_is_an_error_naming_it_or_loads_unchanged(
    saved_population: tuple[Path, EvolverInfo], tmp_path_factory: pytest.TempPathFactory, file: str, how: str,
    at: int, xor: int
) -> None:  # fmt: skip
    """A flipped digit is still valid JSON: the state's digest catches it (and the zip CRC a sample's)."""
    good, info = saved_population
    folder = tmp_path_factory.mktemp("damaged") / "evolver"
    shutil.copytree(good, folder)
    path = folder / STATE_FILE if file == "state" else next((folder / SAMPLES_DIR).iterdir())
    data = bytearray(path.read_bytes())
    if how == "cut":
        data = data[: at % len(data)]
    else:
        data[at % len(data)] ^= xor
    path.write_bytes(bytes(data))
    try:
        loaded = Evolver(evolver_config(), folder, "exp", lease_s=600.0)
    except EvolverStateError as e:
        assert str(path) in str(e)
    else:
        assert loaded.info() == info
        if file == "sample":
            np.testing.assert_array_equal(loaded.registry.pending[1].weights["q.weight"], weights_of(0.5)["q.weight"])
    assert path.read_bytes() == bytes(data)  # loading wrote nothing over it


def test_a_state_changed_to_other_valid_json_is_refused(
    saved_population: tuple[Path, EvolverInfo], tmp_path: Path
) -> None:
    """One digit of a port flipped: valid JSON and a plausible population, but not the one saved."""
    folder = tmp_path / "evolver"
    shutil.copytree(saved_population[0], folder)
    state = folder / STATE_FILE
    edited = state.read_text().replace('"learner_port": 61001', '"learner_port": 61009', 1)
    assert edited != state.read_text()
    state.write_text(edited)
    with pytest.raises(EvolverStateError, match=re.escape(f"evolver state {state} is damaged")):
        Evolver(evolver_config(), folder, "exp")
    assert state.read_text() == edited
