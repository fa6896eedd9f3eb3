"""Configs written for the original system load the ASAC way (algorithm/config_port.py): moved keys
land on their new paths with one warning each, keys that cannot be carried over stop the load naming
key, file and what to write instead, and a file read as the original's gets its defaults where it is
silent and a warning for each key counting something else here. The original's gym and bullet task files
of each era (as /work/original_facts.md lists them) are written out and loaded section by section."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pytest
import yaml

from algorithm.config import ConfigError, load_config
from algorithm.config_port import CONVERTED, DROPPED, MOVED, REFUSED, REFUSED_VALUES, RESTATED, UNSET
from algorithm.config_schema import Config

ROOT = Path(__file__).resolve().parents[2]

# The original's algorithm/default_config.yaml (standalone), as its README printed it.
ORIGINAL_STANDALONE = """
base_config:
  env_type: UNITY
  scene: scene
  no_graphics: true
  build_path:
    win32: path_win32
    linux: path_linux
  port: 5005
  name: "{time}"
  nn: nn
  n_agents: 1
  max_iter: -1
  max_step: -1
  max_step_each_iter: -1
  reset_on_iteration: true
reset_config: null
replay_config:
  batch_size: 256
  capacity: 524288
  alpha: 0.9
  beta: 0.4
  beta_increment_per_sampling: 0.001
  td_error_min: 0.01
  td_error_max: 1.
sac_config:
  seed: null
  write_summary_per_step: 1000
  save_model_per_step: 100000
  save_model_per_minute: 5
  ensemble_q_num: 2
  ensemble_q_sample: 2
  burn_in_step: 0
  n_step: 1
  use_rnn: false
  tau: 0.005
  update_target_per_step: 1
  init_log_alpha: -2.3
  use_auto_alpha: true
  learning_rate: 0.0003
  gamma: 0.99
  v_lambda: 1.0
  v_rho: 1.0
  v_c: 1.0
  clip_epsilon: 0.2
  discrete_dqn_like: false
  use_priority: true
  use_n_step_is: true
  use_prediction: false
  transition_kl: 0.8
  use_extra_data: true
  use_curiosity: false
  curiosity_strength: 1
  use_rnd: false
  rnd_n_sample: 10
  use_normalization: false
"""

# The original's ds/default_config.yaml (distributed), as its README printed it; its commented-out
# random_params sat at the end of sac_config.
ORIGINAL_DS = """
base_config:
  env_type: UNITY
  scene: scene
  no_graphics: true
  build_path:
    win32: path_win32
    linux: path_linux
  port: 5005
  name: "{time}"
  nn: nn
  update_policy_mode: true
  update_policy_variables_per_step: -1
  update_sac_bak_per_step: 200
  noise_increasing_rate: 0
  noise_max: 0.1
  n_agents: 1
  max_step_each_iter: -1
  reset_on_iteration: true
  max_actors_each_learner: 10
  evolver_cem_length: 50
  evolver_cem_best: 0.3
  evolver_cem_min_length: 2
  evolver_cem_time: 3
  evolver_remove_worst: 4
net_config:
  evolver_host: 127.0.0.1
  evolver_port: 61000
  learner_host: 127.0.0.1
  learner_port: 61001
  replay_host: 127.0.0.1
  replay_port: 61002
reset_config: null
replay_config:
  batch_size: 256
  capacity: 524288
  alpha: 0.9
  beta: 0.4
  beta_increment_per_sampling: 0.001
  td_error_min: 0.01
  td_error_max: 1.
sac_config:
  seed: null
  write_summary_per_step: 1000
  save_model_per_step: 100000
  save_model_per_minute: 5
  ensemble_q_num: 2
  ensemble_q_sample: 2
  burn_in_step: 0
  n_step: 1
  use_rnn: false
  tau: 0.005
  update_target_per_step: 1
  init_log_alpha: -2.3
  use_auto_alpha: true
  learning_rate: 0.0003
  gamma: 0.99
  v_lambda: 1.0
  v_rho: 1.0
  v_c: 1.0
  clip_epsilon: 0.2
  discrete_dqn_like: false
  use_prediction: false
  use_extra_data: true
  use_curiosity: false
  curiosity_strength: 1
  use_rnd: false
  rnd_n_sample: 10
  use_normalization: false
  random_params:
    n_step:
      in: [1, 2, 3]
"""

# A distributed HalfCheetah config of the original's kind: keys that moved, a variant with
# random_params under sac_config, and max_step.
HALF_CHEETAH = """
default:
  base_config:
    env_type: GYM
    scene: HalfCheetah
    build_path: HalfCheetah-v5
    update_sac_bak_per_step: 100
    noise_increasing_rate: 0.02
    noise_max: 0.2
    n_agents: 10
    evolver_cem_time: 8
    max_step: 500000
  net_config:
    evolver_host: cheetah-ds-evolver
  sac_config:
    write_summary_per_step: 100
    save_model_per_step: 10000
    n_step: 5
    v_lambda: 0.9
hard:
  base_config:
    scene: HalfCheetahHard
    noise_max: 0.3
  sac_config:
    use_rnn: true
    random_params:
      n_step:
        in: [3, 4, 5]
      burn_in_step:
        in: [10, 20, 30]
      v_rho:
        truncated: [1.0, 2.0]
"""


def write_task(tmp_path: Path, text: str) -> Path:
    task = tmp_path / "task"
    task.mkdir()
    (task / "config.yaml").write_text(text)
    return task


def as_task(layout: str, **base: Any) -> str:
    """An original default file as the `default` section of a task file, ``base`` keys replaced
    (None removes one)."""
    body = yaml.safe_load(layout)
    for key, value in base.items():
        if value is None:
            del body["base_config"][key]
        else:
            body["base_config"][key] = value
    return yaml.safe_dump({"default": body}, sort_keys=False)


def port_notes(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "asac.config" and r.levelno == logging.WARNING]


def schema_keys(section: str) -> set[str]:
    """The keys of an ASAC section (none for a top-level value such as reset_config)."""
    return set(getattr(Config.model_fields[section].annotation, "model_fields", {}))


def leaves(data: dict[str, Any]) -> list[str]:
    """section.key paths of a layout (reset_config, a top-level value, as itself)."""
    return [f"{s}.{k}" if isinstance(body, dict) else s for s, body in data.items() for k in (body or {"": 0})]


@pytest.mark.parametrize("layout", [ORIGINAL_STANDALONE, ORIGINAL_DS], ids=["standalone", "distributed"])
def test_every_key_of_the_original_layouts_is_ASACs_or_in_the_port_table(layout: str) -> None:
    table = {*MOVED, *DROPPED, *REFUSED}
    for path in leaves(yaml.safe_load(layout)):
        section, _, key = path.partition(".")
        same = section in Config.model_fields and (not key or key in schema_keys(section))
        assert same != (path in table), f"{path}: ASAC's own key and in the table, or neither"
    for new, _ in MOVED.values():  # every new home exists
        section, key = new.split(".")
        assert section == "random_params" or key in schema_keys(section)
    for path in (*RESTATED, *REFUSED_VALUES, *UNSET):  # same key, other meaning or values: ASAC has the key
        section, key = path.split(".")
        assert key in schema_keys(section)
    for path in CONVERTED:  # a key of the original only (nn_config's rep and policy: of its E5 layout)
        section, key = path.split(".")
        assert key not in schema_keys(section)


def test_the_original_distributed_defaults_fail_naming_key_file_and_what_to_do(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    task = write_task(tmp_path, as_task(ORIGINAL_DS))
    with caplog.at_level(logging.WARNING), pytest.raises(ConfigError) as err:
        load_config(task)
    message = str(err.value)
    where = f"({task / 'config.yaml'} [default])"
    assert f"base_config.env_type {where}: Unity environments are out of scope" in message
    assert f"base_config.build_path {where}: a mapping of Unity executables" in message
    assert "update_policy_variables_per_step" not in message  # dropped with a note, not refused
    assert "unknown key" not in message  # every key of the original is known
    assert "\n" not in message


def test_the_original_distributed_defaults_made_gym_load_with_one_note_per_moved_key(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    task = write_task(tmp_path, as_task(ORIGINAL_DS, env_type="GYM", build_path="Pendulum-v1"))
    with caplog.at_level(logging.WARNING):
        resolved = load_config(task)
    c, source = resolved.config, f"{task / 'config.yaml'} [default]"
    assert c.actor_config.update_policy_mode is True
    assert (c.actor_config.noise_increasing_rate, c.actor_config.noise_max) == (0.0, 0.1)
    assert c.sac_config.update_policy_variables_per_step == 200
    assert c.random_params == {"sac_config": {"n_step": {"in": [1, 2, 3]}}}
    assert c.sac_config.clip_epsilon == 0.2 and c.net_config.evolver_host == "127.0.0.1"
    assert c.sac_config.use_n_step_is is True  # the original's default, which the layout does not set
    assert resolved.sources["actor_config.noise_max"] == source
    assert resolved.sources["random_params.sac_config.n_step"] == source
    notes = port_notes(caplog)
    assert (
        f"{source}: base_config.noise_increasing_rate is actor_config.noise_increasing_rate now; read as that" in notes
    )
    assert f"{source}: base_config.noise_max is actor_config.noise_max now; read as that" in notes
    assert f"{source}: base_config.update_policy_mode is actor_config.update_policy_mode now; read as that" in notes
    assert f"{source}: sac_config.random_params is random_params.sac_config now; read as that" in notes
    assert any(
        n.startswith(
            f"{source}: base_config.update_sac_bak_per_step is sac_config.update_policy_variables_per_step now"
        )
        for n in notes
    )
    assert any(n.startswith(f"{source}: base_config.no_graphics has no counterpart") for n in notes)
    assert any(n.startswith(f"{source}: base_config.port has no counterpart") for n in notes)
    assert any(
        n.startswith(f"{source}: base_config.update_policy_variables_per_step has no counterpart") for n in notes
    )
    assert any("save_model_per_step counts env steps in ASAC" in n for n in notes)  # an original file: said
    assert any(n.startswith(f"{source}: base_config.reset_on_iteration (true) cuts and resets") for n in notes)
    assert (
        f"{task / 'config.yaml'} is read as the original's (it sets base_config.env_type): its defaults "
        "apply where it is silent: use_n_step_is true" in notes
    )
    # 5 moved, 3 dropped, 3 restated (this layout has no max_step), the file read as the original's
    assert len(notes) == len(set(notes)) == 12


def test_a_half_cheetah_config_of_the_original_loads_with_its_values_on_the_new_keys(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    task = write_task(tmp_path, HALF_CHEETAH)
    with caplog.at_level(logging.WARNING):
        c = load_config(task, "hard").config
    assert (c.actor_config.noise_increasing_rate, c.actor_config.noise_max) == (0.02, 0.3)  # hard wins
    assert c.sac_config.update_policy_variables_per_step == 100
    assert c.random_params == {
        "sac_config": {
            "n_step": {"in": [3, 4, 5]},
            "burn_in_step": {"in": [10, 20, 30]},
            "v_rho": {"truncated": [1.0, 2.0]},
        }
    }
    assert (c.base_config.max_step, c.base_config.scene, c.net_config.evolver_host) == (
        500000,
        "HalfCheetahHard",
        "cheetah-ds-evolver",
    )
    notes = port_notes(caplog)
    # noise_max is in both sections: one note, naming where it was met first
    assert [n for n in notes if "base_config.noise_max is" in n] == [
        f"{task / 'config.yaml'} [default]: base_config.noise_max is actor_config.noise_max now; read as that"
    ]
    (max_step,) = [n for n in notes if "base_config.max_step" in n]
    assert "counts env steps" in max_step and "the original counted learner updates" in max_step
    assert max_step.startswith(f"{task / 'config.yaml'} [default]: ")


def test_update_policy_variables_per_step_of_the_original_is_dropped_saying_what_asac_does(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    text = HALF_CHEETAH.replace("    update_sac_bak_per_step: 100\n", "    update_policy_variables_per_step: 50\n")
    task = write_task(tmp_path, text)
    with caplog.at_level(logging.WARNING):
        c = load_config(task).config
    assert c.sac_config.update_policy_variables_per_step == 1  # ASAC's default: the key is not read
    (note,) = [n for n in port_notes(caplog) if "update_policy_variables_per_step" in n]
    assert note.startswith(f"{task / 'config.yaml'} [default]: base_config.update_policy_variables_per_step has no")
    assert "ASAC actors act with every publication as it arrives" in note
    assert "sac_config.update_policy_variables_per_step sets the learner updates" in note


def test_a_key_set_at_its_old_and_new_path_in_one_section_is_refused(tmp_path: Path) -> None:
    task = write_task(tmp_path, "default:\n  base_config: {noise_max: 0.2}\n  actor_config: {noise_max: 0.3}\n")
    with pytest.raises(ConfigError, match=r"base_config.noise_max \(.*\[default\]\): is actor_config.noise_max now"):
        load_config(task)


def test_a_moved_random_params_spec_is_checked_at_its_new_path(tmp_path: Path) -> None:
    task = write_task(tmp_path, "default:\n  sac_config:\n    random_params:\n      n_stpe: {in: [1, 2]}\n")
    with pytest.raises(ConfigError, match=r"random_params.sac_config.n_stpe \(.*config.yaml \[default\]\): unknown"):
        load_config(task)


def test_overrides_in_the_original_spelling_land_on_the_new_keys(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        c = load_config(None, None, ["base.noise_max=0.4", "base_config.no_graphics=true"]).config
    assert c.actor_config.noise_max == 0.4
    notes = port_notes(caplog)
    assert "override 'base.noise_max=0.4': base_config.noise_max is actor_config.noise_max now; read as that" in notes
    assert any(n.startswith("override 'base_config.no_graphics=true': base_config.no_graphics has no") for n in notes)
    with pytest.raises(ConfigError, match=r"base_config.sac \(override 'base.sac=sac_hard'\): an E1 model file"):
        load_config(None, None, ["base.sac=sac_hard"])
    c = load_config(None, None, ["sac.seq_encoder=RNN", "sac.curiosity=INVERSE", "sac.batch_size=64"]).config
    assert (c.sac_config.use_rnn, c.sac_config.use_curiosity, c.sac_config.curiosity_inverse) == (True, True, True)
    assert c.replay_config.batch_size == 64


def test_the_same_config_in_asacs_spelling_is_equal_and_asac_configs_say_nothing(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    native = """
default:
  base_config: {scene: HalfCheetah, build_path: HalfCheetah-v5, n_agents: 10, max_step: 500000}
  actor_config: {noise_increasing_rate: 0.02, noise_max: 0.2}
  sac_config: {update_policy_variables_per_step: 100, save_model_per_step: 10000, n_step: 5, use_rnn: true,
               use_n_step_is: true, clip_epsilon: 0.2}
  replay_config: {samples_per_insert: 25.6}
  random_params:
    sac_config: {n_step: {in: [3, 4, 5]}}
"""
    original = """
default:
  base_config: {scene: HalfCheetah, build_path: HalfCheetah-v5, n_agents: 10, max_step: 500000,
                update_sac_bak_per_step: 100, noise_increasing_rate: 0.02, noise_max: 0.2}
  sac_config:
    save_model_per_step: 10000
    n_step: 5
    use_rnn: true
    random_params: {n_step: {in: [3, 4, 5]}}
"""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    with caplog.at_level(logging.WARNING):
        ported = load_config(write_task(tmp_path / "a", original)).config
        # 4 moved keys, max_step, save_model_per_step, the original's defaults and reset_on_iteration's
        assert len(port_notes(caplog)) == 8
        caplog.clear()
        assert load_config(write_task(tmp_path / "b", native)).config == ported
        assert port_notes(caplog) == []  # max_step and save_model_per_step in an ASAC file: nothing said
        for path in sorted((ROOT / "envs").rglob("config.yaml")):  # nor in any variant of this repository's
            for name in yaml.safe_load(path.read_text()):
                load_config(path.parent, None if name == "default" else name)
    assert port_notes(caplog) == []
