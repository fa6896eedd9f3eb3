"""Configs written for the original system load the ASAC way (algorithm/config/original.py): moved keys
land on their new paths with one warning each, keys that cannot be carried over stop the load naming
key, file and what to write instead, and a file read as the original's gets its defaults where it is
silent and a warning for each key counting something else here. The original's gym and bullet task files
of each era are written out and loaded section by section."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from algorithm.config.load import ConfigError, load_config
from algorithm.config.original import CONVERTED, DROPPED, MOVED, REFUSED, REFUSED_VALUES, RESTATED, UNSET
from algorithm.config.schema import Config

ROOT = Path(__file__).resolve().parents[3]

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


# ---------------------------------------------------------------------------------------------------------------
# The original's gym and bullet task files, per era (E1: TF sac.py files; E2: TF nn.py files, the main snapshot;
# E3: PyTorch; E4: seq_encoder; E5: env_name/n_envs), as its folders held them; bullet files share one skeleton
# of anchored variants.


def bullet_config(build_path: str, scene: str, hard: str, base: str, sac: str, hard_sac: str, nn: str = "nn") -> str:
    """A bullet ``config.yaml``: ``default`` plus ``hard`` (anchored) and its two variants."""
    return f"""
default:
  base_config: {{env_type: GYM, scene: {scene}, build_path: "{build_path}", {base}n_agents: 10}}
  sac_config: {{{sac}}}
hard:
  base_config: &hard_base
    scene: {hard}
    {nn}_hard
  sac_config: &hard_sac {{{hard_sac}}}
hard_noextra:
  base_config:
    <<: *hard_base
    name: "noextra_{{time}}"
  sac_config:
    <<: *hard_sac
    use_extra_data: false
hard_nopre:
  base_config:
    <<: *hard_base
    name: "nopre_{{time}}"
  sac_config:
    <<: *hard_sac
    use_prediction: false
"""


SAVES = "write_summary_per_step: 100, save_model_per_step: 10000"
ORIGINAL_FILES = {
    "walker_E2": bullet_config(
        "Walker2DBulletEnv-v0",
        "Walker2D",
        "Walker2DHard",
        "max_iter: -1, max_step: 1000000, ",
        f"{SAVES}, save_model_per_minute: 5, n_step: 5, v_lambda: 0.99, use_normalization: true",
        "burn_in_step: 30, use_rnn: true, use_prediction: false",
        "nn: nn",
    ),
    "ant_E2": bullet_config(
        "AntBulletEnv-v0",
        "Ant",
        "AntHard",
        "max_iter: -1, max_step: 1000000, ",
        f"{SAVES}, save_model_per_minute: 20, ensemble_q_num: 5, use_normalization: true",
        "burn_in_step: 30, use_rnn: true, use_prediction: true",
        "nn: nn",
    ),
    "humanoid_E3": bullet_config(
        "HumanoidBulletEnv-v0",
        "Humanoid",
        "HumanoidHard",
        "max_iter: -1, ",
        f"{SAVES}, save_model_per_minute: 20, ensemble_q_num: 5, use_normalization: true",
        "burn_in_step: 20, use_rnn: true, use_prediction: true",
        "nn: nn",
    ),
    "half_cheetah_E4": bullet_config(
        "HalfCheetahBulletEnv-v0",
        "HalfCheetahBullet",
        "HalfCheetahHard",
        "max_iter: -1, max_step: 500000, ",
        f"{SAVES}, init_log_alpha: 0., n_step: 1, v_lambda: 0.99, use_rnd: true, rnd_n_sample: 50",
        "burn_in_step: 30, seq_encoder: RNN, use_prediction: true",
        "nn: nn",
    ),
    "cart_pole_E2": """
default:
  base_config: {env_type: GYM, scene: CartPole, build_path: CartPole-v1, max_step: -1, max_iter: 1000, n_agents: 10}
  replay_config: {batch_size: 128, capacity: 100000, alpha: 0., beta_increment_per_sampling: 0}
  sac_config: {save_model_per_step: 1000, save_model_per_minute: 1, n_step: 3, clip_epsilon: -1, use_n_step_is: true,
               learning_rate: 0.01, discrete_dqn_like: true}
""",
    "mountain_car_E2": """
default:
  base_config: {env_type: GYM, scene: MountainCar, build_path: MountainCarContinuous-v0, max_step: -1, max_iter: 100,
                n_agents: 10}
  sac_config: {seed: 42, n_step: 10, tau: 0.9, v_lambda: 0.99, init_log_alpha: 0, use_rnd: true}
"""
    + "".join(f"rnd{n}: {{sac_config: {{rnd_n_sample: {n}}}}}\n" for n in (1, 10, 20, 30, 40, 50)),
    "mountain_car_E3": """
default:
  base_config: {env_type: GYM, scene: MountainCar, build_path: MountainCarContinuous-v0, max_step: -1, max_iter: 100,
                n_agents: 10}
  sac_config: {seed: 42, n_step: 10, tau: 0.9, v_lambda: 0.99, init_log_alpha: 0}
curiosity:
  base_config: {name: "curiosity_{time}"}
  sac_config: {curiosity: FORWARD, curiosity_strength: 500}
"""
    + "".join(
        f"rnd{n}: {{base_config: {{name: 'rnd{n}_{{time}}'}}, sac_config: {{use_rnd: true, rnd_n_sample: {n}}}}}\n"
        for n in (1, 10, 20, 30, 40, 50)
    ),
    "pendulum_E1": """
default:
  base_config: {env_type: GYM, scene: Pendulum, build_path: Pendulum-v0, max_step: -1, max_iter: 1000,
                save_model_per_iter: 50, n_agents: 10}
  sac_config: {seed: 42, n_step: 10, tau: 0.9, _lambda: 0.99, init_log_alpha: -4.6}
""",
    "pendulum_E3": """
default:
  base_config: {env_type: GYM, env_name: Pendulum-v0, max_step: -1, max_iter: 100, n_agents: 10}
  sac_config: {seed: 42, n_step: 10, tau: 0.9, v_lambda: 0.99, init_log_alpha: 0}
""",
    # E5's gym layout (its humanoid folder), defaults written out where a task file of that time had them
    "humanoid_E5": """
default:
  base_config:
    env_type: GYM
    env_name: Humanoid-v3
    env_args: null
    unity_args: {no_graphics: true, build_path: {win32: path_win32, linux: path_linux}, group_aggregation: false}
    n_envs: 10
    max_iter: -1
    max_step: -1
    max_step_each_iter: -1
    reset_on_iteration: true
  reset_config: null
  nn_config: {rep: null, policy: null}
  sac_config: {nn: nn, seq_encoder: null, save_model_per_step: 5000}
  oc_config: null
  ma_config: null
rnn:
  sac_config: {nn: nn_rnn, seq_encoder: RNN, burn_in_step: 10}
""",
}

ANT_DS_E2 = """
default:
  base_config: {env_type: GYM, scene: Ant, build_path: "AntBulletEnv-v0", update_policy_variables_per_step: 20,
                noise_increasing_rate: 0.01, n_agents: 10, evolver_cem_time: 8}
  net_config: {evolver_host: ant-ds-evolver, learner_host: ant-ds-lr, replay_host: ant-ds-lr}
  sac_config: {write_summary_per_step: 100, save_model_per_step: 10000, save_model_per_minute: 20, ensemble_q_num: 5,
               n_step: 3}
  replay_config: {batch_size: 1024}
hard:
  base_config: &hard_base {scene: AntHard, nn: nn_hard}
  net_config: {evolver_host: ant-hard-ds-evolver, learner_host: ant-hard-ds-lr, replay_host: ant-hard-ds-lr}
  sac_config: &hard_sac
    use_rnn: true
    use_prediction: true
    random_params:
      n_step: {in: [3, 4, 5]}
      burn_in_step: {in: [10, 20, 30]}
      v_rho: {truncated: [1.0, 2.0]}
      v_c: {truncated: [1.0, 2.0]}
"""
ORIGINAL_DS_FILES = {
    "ant_ds_E2": ANT_DS_E2,
    "humanoid_ds_E2": ANT_DS_E2.replace("Ant", "Humanoid").replace("ant-", "human-"),
    "walker_ds_E2": """
default:
  base_config: {env_type: GYM, scene: Walker2D, build_path: "Walker2DBulletEnv-v0",
                update_policy_variables_per_step: 20, noise_increasing_rate: 0.01, n_agents: 10, evolver_cem_time: 8,
                evolver_enabled: false}
  net_config: {evolver_host: walker-ds-evolver}
  sac_config: {write_summary_per_step: 100, save_model_per_step: 10000, save_model_per_minute: 20, n_step: 5,
               v_lambda: 0.9}
  replay_config: {batch_size: 16}
hard:
  base_config: &hard_base {scene: Walker2DHard, nn: nn_hard}
  sac_config: &hard_sac
    burn_in_step: 10
    use_rnn: true
    use_prediction: true
    random_params:
      n_step: {in: [3, 5, 7]}
      burn_in_step: {in: [10, 20, 30]}
      v_rho: {truncated: [1.0, 2.0]}
      v_c: {truncated: [1.0, 2.0]}
hard_nopre:
  base_config: {<<: *hard_base, name: "nopre_{time}"}
  net_config: {evolver_host: walker-hard-nopre-ds-evolver}
  sac_config: {<<: *hard_sac, use_prediction: false}
""",
    "half_cheetah_ds_E2": """
default:
  base_config: {env_type: GYM, scene: HalfCheetah, build_path: "HalfCheetahBulletEnv-v0",
                update_policy_variables_per_step: 20, noise_increasing_rate: 0.02, n_agents: 10, evolver_cem_time: 8}
  net_config: {evolver_host: cheetah-ds-evolver, learner_host: cheetah-ds-learner, replay_host: cheetah-ds-replay}
  sac_config: {write_summary_per_step: 100, save_model_per_step: 10000, save_model_per_minute: 20, n_step: 5,
               v_lambda: 0.9}
  replay_config: {batch_size: 1024}
""",
    "half_cheetah_ds_E4": """
default:
  base_config: {env_type: GYM, scene: HalfCheetah, build_path: "HalfCheetahBulletEnv-v0", noise_increasing_rate: 0.02,
                n_agents: 10, evolver_cem_time: 8}
  net_config: {evolver_host: cheetah-ds-evolver}
  sac_config: {write_summary_per_step: 100, save_model_per_step: 10000, batch_size: 1024, n_step: 5, v_lambda: 0.9}
hard:
  base_config: {scene: HalfCheetahHard, nn: nn_hard}
  net_config: {evolver_host: cheetah-hard-ds-evolver}
  sac_config:
    seq_encoder: RNN
    use_prediction: true
    v_lambda: 0.99
    use_normalization: true
    random_params:
      n_step: {in: [3, 4, 5]}
      burn_in_step: {in: [10, 20, 30]}
      v_rho: {truncated: [1.0, 2.0]}
      v_c: {truncated: [1.0, 2.0]}
""",
}

# What each load says, as "[section] path" (a key's note), "original" (the file read as the original's, with the
# defaults applied) and "unset path" (a key whose default differs, left unset); and values it resolves to.
READ_AS_ORIGINAL = ["original", "unset base_config.reset_on_iteration"]
DS_READ_AS_ORIGINAL = [*READ_AS_ORIGINAL, "unset base_config.evolver_enabled"]
ORIGINAL_DEFAULTS = {"sac_config.use_n_step_is": True, "sac_config.clip_epsilon": 0.2}
BULLET_SAVES = ["[default] sac_config.save_model_per_step", "[default] sac_config.save_model_per_minute"]
WALKER = ["[default] base_config.build_path", "[default] base_config.max_step", *BULLET_SAVES, *READ_AS_ORIGINAL]
HUMANOID = ["[default] base_config.build_path", *BULLET_SAVES, *READ_AS_ORIGINAL]
CHEETAH = ["[default] base_config.build_path", "[default] base_config.max_step",
           "[default] sac_config.save_model_per_step", *READ_AS_ORIGINAL]  # fmt: skip
CART_POLE = ["[default] base_config.max_iter", *BULLET_SAVES, "[default] sac_config.clip_epsilon", *READ_AS_ORIGINAL]
MOUNTAIN_CAR = ["[default] base_config.max_iter", *READ_AS_ORIGINAL]
E5 = ["[default] base_config.env_name", "[default] base_config.n_envs", "[default] base_config.unity_args",
      "[default] sac_config.nn", "[default] oc_config", "[default] ma_config", "[default] base_config.build_path",
      "[default] base_config.reset_on_iteration", "[default] sac_config.save_model_per_step", "original"]  # fmt: skip
ANT_DS = ["[default] base_config.update_policy_variables_per_step", "[default] base_config.noise_increasing_rate",
          "[default] base_config.build_path", *BULLET_SAVES, *DS_READ_AS_ORIGINAL]  # fmt: skip
WALKER_DS = [*ANT_DS[:-1]]  # it sets evolver_enabled: false
CHEETAH_DS_E4 = ["[default] base_config.noise_increasing_rate", "[default] sac_config.batch_size",
                 "[default] base_config.build_path", "[default] sac_config.save_model_per_step",
                 *DS_READ_AS_ORIGINAL]  # fmt: skip
SPI = "replay_config.samples_per_insert"

HARD = {"sac_config.use_rnn": True, "base_config.nn": "nn_hard"}
LOADS: list[tuple[str, str | None, list[str], dict[str, Any]]] = [
    ("walker_E2", None, WALKER, {
        "base_config.build_path": "Walker2d-v5", "base_config.max_step": 1000000, SPI: 25.6, **ORIGINAL_DEFAULTS,
        "sac_config.v_lambda": 0.99, "sac_config.n_step": 5, "sac_config.use_normalization": True,
        "base_config.reset_on_iteration": False, "base_config.scene": "Walker2D", "sac_config.use_rnn": False}),
    ("walker_E2", "hard", WALKER, {**HARD, "sac_config.burn_in_step": 30, "sac_config.use_prediction": False,
                                   "base_config.scene": "Walker2DHard", SPI: 25.6}),
    ("walker_E2", "hard_noextra", WALKER, {**HARD, "base_config.name": "noextra_{time}",
                                           "sac_config.use_extra_data": False, "sac_config.burn_in_step": 30}),
    ("walker_E2", "hard_nopre", WALKER, {**HARD, "base_config.name": "nopre_{time}",
                                         "sac_config.use_extra_data": True}),
    ("ant_E2", None, WALKER, {"base_config.build_path": "Ant-v5", "sac_config.ensemble_q_num": 5, SPI: 25.6,
                              **ORIGINAL_DEFAULTS}),
    ("ant_E2", "hard", WALKER, {**HARD, "sac_config.use_prediction": True, "base_config.scene": "AntHard"}),
    ("ant_E2", "hard_noextra", WALKER, {**HARD, "sac_config.use_extra_data": False}),
    ("ant_E2", "hard_nopre", WALKER, {**HARD, "sac_config.use_prediction": False}),
    ("humanoid_E3", None, HUMANOID, {"base_config.build_path": "Humanoid-v5", "base_config.max_step": -1}),
    ("humanoid_E3", "hard", HUMANOID, {**HARD, "sac_config.burn_in_step": 20}),
    ("humanoid_E3", "hard_noextra", HUMANOID, {**HARD, "sac_config.use_extra_data": False}),
    ("humanoid_E3", "hard_nopre", HUMANOID, {**HARD, "sac_config.use_prediction": False}),
    ("half_cheetah_E4", None, CHEETAH, {"base_config.build_path": "HalfCheetah-v5", "base_config.max_step": 500000,
                                        "sac_config.init_log_alpha": 0.0, "sac_config.rnd_n_sample": 50}),
    ("half_cheetah_E4", "hard", [*CHEETAH, "[hard] sac_config.seq_encoder"], {**HARD, "sac_config.use_rnd": True}),
    ("half_cheetah_E4", "hard_noextra", [*CHEETAH, "[hard_noextra] sac_config.seq_encoder"], HARD),
    ("half_cheetah_E4", "hard_nopre", [*CHEETAH, "[hard_nopre] sac_config.seq_encoder"],
     {**HARD, "sac_config.use_prediction": False}),
    ("cart_pole_E2", None, CART_POLE, {
        "sac_config.clip_epsilon": None, "sac_config.use_n_step_is": True, SPI: 12.8, "base_config.max_iter": 1000,
        "replay_config.alpha": 0.0, "sac_config.discrete_dqn_like": True, "base_config.build_path": "CartPole-v1"}),
    ("mountain_car_E2", None, MOUNTAIN_CAR, {**ORIGINAL_DEFAULTS, SPI: 25.6, "sac_config.seed": 42,
                                             "sac_config.tau": 0.9, "sac_config.use_rnd": True}),
    ("mountain_car_E2", "rnd1", MOUNTAIN_CAR, {"sac_config.rnd_n_sample": 1, "sac_config.use_rnd": True}),
    ("mountain_car_E2", "rnd50", MOUNTAIN_CAR, {"sac_config.rnd_n_sample": 50}),
    ("mountain_car_E3", None, MOUNTAIN_CAR, {"sac_config.use_rnd": False, "sac_config.use_curiosity": False}),
    ("mountain_car_E3", "curiosity", [*MOUNTAIN_CAR, "[curiosity] sac_config.curiosity"], {
        "sac_config.use_curiosity": True, "sac_config.curiosity_inverse": False,
        "sac_config.curiosity_strength": 500.0, "base_config.name": "curiosity_{time}"}),
    ("mountain_car_E3", "rnd30", MOUNTAIN_CAR, {"sac_config.use_rnd": True, "sac_config.rnd_n_sample": 30}),
    ("pendulum_E1", None, ["[default] base_config.build_path", "[default] base_config.max_iter",
                           "[default] base_config.save_model_per_iter", "[default] sac_config._lambda",
                           *READ_AS_ORIGINAL],
     {"base_config.build_path": "Pendulum-v1", "sac_config.v_lambda": 0.99, SPI: 25.6, **ORIGINAL_DEFAULTS}),
    ("pendulum_E3", None, ["[default] base_config.env_name", "[default] base_config.build_path",
                           "[default] base_config.max_iter", *READ_AS_ORIGINAL],
     {"base_config.build_path": "Pendulum-v1", "sac_config.v_lambda": 0.99, "base_config.n_agents": 10}),
    ("humanoid_E5", None, E5, {"base_config.build_path": "Humanoid-v5", "base_config.n_agents": 10, SPI: 25.6,
                               "base_config.reset_on_iteration": True, "base_config.env_kwargs": {}}),
    ("humanoid_E5", "rnn", [*E5, "[rnn] sac_config.seq_encoder"], {
        "base_config.nn": "nn_rnn", "sac_config.use_rnn": True, "sac_config.burn_in_step": 10}),
    ("ant_ds_E2", None, ANT_DS, {
        SPI: 102.4, "replay_config.batch_size": 1024, "actor_config.noise_increasing_rate": 0.01,
        "base_config.evolver_cem_time": 8.0, "base_config.evolver_enabled": False,
        "net_config.replay_host": "ant-ds-lr",
        "sac_config.update_policy_variables_per_step": 1, "sac_config.n_step": 3, **ORIGINAL_DEFAULTS}),
    ("ant_ds_E2", "hard", [*ANT_DS, "[hard] sac_config.random_params"], {
        **HARD, "net_config.evolver_host": "ant-hard-ds-evolver",
        "random_params.sac_config.n_step": {"in": [3, 4, 5]}, "random_params.sac_config.v_c": {"truncated": [1, 2]}}),
    ("humanoid_ds_E2", None, ANT_DS, {"base_config.build_path": "Humanoid-v5",
                                      "net_config.learner_host": "human-ds-lr"}),
    ("humanoid_ds_E2", "hard", [*ANT_DS, "[hard] sac_config.random_params"], {
        **HARD, "base_config.scene": "HumanoidHard", "net_config.replay_host": "human-hard-ds-lr"}),
    ("walker_ds_E2", None, WALKER_DS, {SPI: 1.6, "replay_config.batch_size": 16, "base_config.evolver_enabled": False,
                                       "base_config.build_path": "Walker2d-v5"}),
    ("walker_ds_E2", "hard", [*WALKER_DS, "[hard] sac_config.random_params"], {
        **HARD, "sac_config.burn_in_step": 10, "random_params.sac_config.n_step": {"in": [3, 5, 7]}}),
    ("walker_ds_E2", "hard_nopre", [*WALKER_DS, "[hard_nopre] sac_config.random_params"], {
        **HARD, "sac_config.use_prediction": False, "net_config.evolver_host": "walker-hard-nopre-ds-evolver"}),
    ("half_cheetah_ds_E2", None, ANT_DS, {
        "actor_config.noise_increasing_rate": 0.02, "net_config.replay_host": "cheetah-ds-replay", SPI: 102.4,
        "sac_config.v_lambda": 0.9, "base_config.build_path": "HalfCheetah-v5"}),
    ("half_cheetah_ds_E4", None, CHEETAH_DS_E4, {"replay_config.batch_size": 1024, SPI: 102.4}),
    ("half_cheetah_ds_E4", "hard", [*CHEETAH_DS_E4, "[hard] sac_config.seq_encoder", "[hard] sac_config.random_params"],
     {**HARD, "sac_config.use_prediction": True, "sac_config.v_lambda": 0.99, "sac_config.use_normalization": True}),
]  # fmt: skip


def write_original(tmp_path: Path, name: str) -> tuple[Path, Path, bool]:
    """The task folder, the file a load reads and whether that is the distributed one."""
    task = tmp_path / name
    task.mkdir()
    distributed = name in ORIGINAL_DS_FILES
    file = task / ("config_ds.yaml" if distributed else "config.yaml")
    file.write_text((ORIGINAL_DS_FILES if distributed else ORIGINAL_FILES)[name])
    return task, file, distributed


def subjects(notes: list[str], file: Path) -> list[str]:
    """Each note as what it is about: ``[section] path``, ``original`` or ``unset path``."""
    out = []
    for note in notes:
        rest = note.removeprefix(str(file))
        if rest.startswith(" is read as the original's ("):
            out.append("original")
        elif m := re.match(r" \[(\w+)\]: ([\w.]+)[: ]", rest):
            out.append(f"[{m[1]}] {m[2]}")
        elif m := re.match(r": ([\w.]+) is not set: ", rest):
            out.append(f"unset {m[1]}")
        else:
            out.append(note)
    return sorted(out)


def value_at(config: Config, path: str) -> Any:
    data: Any = config.model_dump()
    for part in path.split("."):
        data = data[part]
    return data


@pytest.mark.parametrize("name, section, notes, values", LOADS, ids=[f"{n}-{s or 'default'}" for n, s, *_ in LOADS])
def test_the_originals_gym_and_bullet_files_load_with_the_originals_meaning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, name: str, section: str | None, notes: list[str],
    values: dict[str, Any],
) -> None:  # fmt: skip
    task, file, distributed = write_original(tmp_path, name)
    with caplog.at_level(logging.WARNING):
        config = load_config(task, section, distributed=distributed).config
    assert subjects(port_notes(caplog), file) == sorted(notes)
    for path, value in values.items():
        assert value_at(config, path) == (pytest.approx(value) if isinstance(value, float) else value), path


def test_every_section_of_every_original_file_is_loaded_above() -> None:
    loaded = {(name, section or "default") for name, section, *_ in LOADS}
    for name, text in {**ORIGINAL_FILES, **ORIGINAL_DS_FILES}.items():
        sections = set(yaml.safe_load(text))
        if name.startswith("mountain_car"):  # rndN differ in rnd_n_sample only: three of them are loaded
            sections = {s for s in sections if not s.startswith("rnd")} | {s for n, s in loaded if n == name}
        assert sections == {s for n, s in loaded if n == name}, name


def test_walker_of_the_original_is_read_as_it_meant_in_exact_words(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    task, file, _ = write_original(tmp_path, "walker_E2")
    with caplog.at_level(logging.WARNING):
        load_config(task)
    notes = port_notes(caplog)
    assert (
        f"{file} is read as the original's (it sets base_config.env_type): its defaults apply where it is silent: "
        "use_n_step_is true, clip_epsilon 0.2, one update per vector step (samples_per_insert 25.6 with batch 256 "
        "and 10 envs)"
    ) in notes
    assert (
        f"{file} [default]: base_config.build_path Walker2DBulletEnv-v0 is PyBullet's, which is not installed with "
        "ASAC; read as its MuJoCo counterpart Walker2d-v5, whose observation and reward differ (ASAC's task for it: "
        "envs/mujoco/walker2d)"
    ) in notes
    assert f"{file} [default]: base_config.max_step counts env steps of all envs and actors in ASAC, the original " \
        "counted learner updates; read as env steps (N updates take about N * batch_size / samples_per_insert + " \
        "min_size_to_sample env steps)" in notes  # fmt: skip
    (reset,) = [n for n in notes if "reset_on_iteration" in n]
    assert reset.startswith(f"{file}: base_config.reset_on_iteration is not set: the original's default true")
    assert "ASAC's default false applies here" in reset


def test_the_originals_distributed_file_names_the_evolver_default(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    task, file, _ = write_original(tmp_path, "ant_ds_E2")
    with caplog.at_level(logging.WARNING):
        load_config(task, distributed=True)
    (evolver,) = [n for n in port_notes(caplog) if "evolver_enabled" in n]
    assert evolver == (
        f"{file}: base_config.evolver_enabled is not set: the original's distributed roles ran an evolver unless "
        "evolver_enabled: false; ASAC's default false applies here (an evolver runs with evolver_enabled: true or "
        "main_ds.py <task> local --learners N)"
    )


def test_overrides_win_over_the_originals_defaults(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    task, file, _ = write_original(tmp_path, "walker_E2")
    with caplog.at_level(logging.WARNING):
        c = load_config(task, None, ["replay.samples_per_insert=64", "sac.use_n_step_is=false"]).config
        assert (c.replay_config.samples_per_insert, c.sac_config.use_n_step_is, c.sac_config.clip_epsilon) == (
            64,
            False,
            0.2,
        )
        assert f"{file} is read as the original's (it sets base_config.env_type): its defaults apply where it is " \
            "silent: clip_epsilon 0.2" in port_notes(caplog)  # fmt: skip
        one_env = load_config(task, None, ["base.n_agents=1", "replay.batch_size=64"]).config
        assert one_env.replay_config.samples_per_insert is None  # one env: one update per env step already
        two_envs = load_config(task, None, ["base.n_agents=2", "replay.batch_size=64"]).config
        assert two_envs.replay_config.samples_per_insert == 32  # the envs the run steps, the batch it samples
        with pytest.raises(ConfigError, match=r"override 'sac.clip_epsilon=-1'\): clip_epsilon: -1: .*write clip"):
            load_config(task, None, ["sac.clip_epsilon=-1"])  # an override is written for ASAC


def test_a_config_yaml_beside_a_config_ds_yaml_is_the_originals(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    task = write_task(tmp_path, "default:\n  base_config: {build_path: Pendulum-v1, n_agents: 4, max_step: 2000}\n")
    with caplog.at_level(logging.WARNING):
        assert load_config(task).config.sac_config.use_n_step_is is False  # alone: ASAC's
        assert port_notes(caplog) == []
        (task / "config_ds.yaml").write_text("default: {}\n")
        c = load_config(task).config
    assert (c.sac_config.use_n_step_is, c.replay_config.samples_per_insert) == (True, 64)
    assert any(n.startswith(f"{task / 'config.yaml'} is read as the original's (its folder holds config_ds.yaml)")
               for n in port_notes(caplog))  # fmt: skip


# ---------------------------------------------------------------------------------------------------------------
# Bad and edge inputs


def test_an_asac_file_with_max_step_keeps_asacs_meaning_and_defaults(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    text = "default:\n  base_config: {build_path: Walker2d-v5, max_step: 1000000, max_iter: 100, n_agents: 10}\n"
    text += "  sac_config: {save_model_per_step: 1000, v_lambda: 0.99}\n"
    task = write_task(tmp_path, text)
    with caplog.at_level(logging.WARNING):
        c = load_config(task).config
    assert port_notes(caplog) == []
    assert (c.sac_config.use_n_step_is, c.sac_config.clip_epsilon, c.replay_config.samples_per_insert) == (
        False,
        None,
        None,
    )
    assert c.base_config.reset_on_iteration is False and c.base_config.max_step == 1000000


def test_clip_epsilon_off_in_an_asac_file_says_to_write_null(tmp_path: Path) -> None:
    task = write_task(tmp_path, "default:\n  sac_config: {clip_epsilon: -1}\n")
    with pytest.raises(ConfigError) as err:
        load_config(task)
    assert str(err.value) == (
        f"invalid config: sac_config.clip_epsilon ({task / 'config.yaml'} [default]): clip_epsilon: -1: ASAC turns "
        "the clip off with null (the original's -1 or 0); write clip_epsilon: null"
    )


def test_a_bullet_id_in_an_asac_file_is_mapped_too(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    task = write_task(tmp_path, "default:\n  base_config: {build_path: ReacherBulletEnv-v0}\n")
    with caplog.at_level(logging.WARNING):
        c = load_config(task).config
    assert c.base_config.build_path == "Reacher-v5" and c.sac_config.use_n_step_is is False
    (note,) = port_notes(caplog)
    assert "PyBullet's, which is not installed with ASAC" in note and "ASAC's task for it" not in note  # none


@pytest.mark.parametrize(
    "text, says",
    [
        ("default:\n  sac_config: {seq_encoder: ATTN}\n",
         "sac_config.seq_encoder ({file} [default]): ASAC has no attention encoder; its recurrent option is "
         "use_rnn: true (GRU or LSTM: nn_config.rnn_type); got 'ATTN'"),
        ("default:\n  oc_config: {num_options: 4}\n",
         "oc_config ({file} [default]): the original's option-critic settings; ASAC has no options; delete the "
         "section"),
        ("default:\n  ma_config: {x: 1}\n", "ma_config ({file} [default]): the original's multi-agent settings"),
        ("default:\n  model_config: {dense_n: 64}\n", "model_config ({file} [default]): arguments of the original's"),
        ("default: {}\nbig:\n  inherited: default\n  sac_config: {n_step: 3}\n",
         "inherited ({file} [big]): ASAC's -c section layers over default only; copy the keys of the inherited "
         "section into this one and delete inherited; got 'default'"),
        ("default:\n  nn_config: {rep: {rnn_units: 32}, policy: null}\n",
         "nn_config.rep ({file} [default]): arguments of the original's model-file classes; ASAC's nn_config keys "
         "are hidden_units"),
        ("default:\n  sac_config: {siamese: ATC}\n", "sac_config.siamese ({file} [default]): ASAC has no siamese"),
        ("default:\n  sac_config: {curiosity: BOTH}\n", "sac_config.curiosity ({file} [default]): ASAC's curiosity"),
        ("default:\n  base_config: {env_args: '--speed 2'}\n",
         "base_config.env_args ({file} [default]): ASAC passes base_config.env_kwargs, a mapping"),
        ("default:\n  base_config: {max_actors_each_learner: -1}\n",
         "base_config.max_actors_each_learner ({file} [default]): -1 (the original's 'no limit') has no counterpart"),
        ("default: {}\nhard:\n  base_config: {sac: sac_hard}\n",
         "base_config.sac ({file} [hard]): an E1 model file (sac.py, sac_hard.py)"),
    ],
    ids=["seq_encoder_attn", "oc_config", "ma_config", "model_config", "inherited", "nn_config_rep", "siamese",
         "curiosity", "env_args", "max_actors", "e1_sac"],
)  # fmt: skip
def test_what_cannot_be_carried_over_is_refused_saying_what_to_write(tmp_path: Path, text: str, says: str) -> None:
    task = write_task(tmp_path, text)
    section = "big" if "big:" in text else "hard" if "hard:" in text else None
    with pytest.raises(ConfigError) as err:
        load_config(task, section)
    message = str(err.value)
    assert says.format(file=task / "config.yaml") in message
    assert "unknown key" not in message and "Input should" not in message


def test_a_unity_file_of_the_later_layout_reaches_the_unity_refusal(tmp_path: Path) -> None:
    text = """
default:
  base_config:
    env_type: UNITY
    env_name: Roller
    unity_args: {no_graphics: true, build_path: {win32: C:/roller.exe, linux: /roller.x86_64}}
    n_envs: 4
  sac_config: {nn: nn, seq_encoder: null}
  nn_config: {rep: null, policy: null}
  oc_config: null
  ma_config: null
"""
    task = write_task(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(task)
    assert str(err.value) == (
        f"invalid config: base_config.env_type ({task / 'config.yaml'} [default]): Unity environments are out of "
        "scope in ASAC; set env_type: GYM and build_path to a gymnasium id; got 'UNITY'"
    )


def test_an_e5_section_with_the_original_null_keys_loads_quietly_apart_from_its_moves(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Null values switching an option of the original off (seq_encoder, curiosity, siamese, env_args, nn_config's
    rep and policy) are ASAC's defaults already: nothing to say about them."""
    text = """
default:
  base_config: {env_type: GYM, env_name: Pendulum-v1, env_args: null}
  nn_config: {rep: null, policy: null}
  sac_config: {seq_encoder: null, curiosity: null, siamese: null, siamese_use_adaptive: false}
"""
    task = write_task(tmp_path, text)
    with caplog.at_level(logging.WARNING):
        c = load_config(task).config
    assert (c.sac_config.use_rnn, c.sac_config.use_curiosity, c.base_config.env_kwargs) == (False, False, {})
    assert subjects(port_notes(caplog), task / "config.yaml") == sorted(
        ["[default] base_config.env_name", *READ_AS_ORIGINAL]
    )


def test_an_original_file_setting_the_original_defaults_otherwise_keeps_its_values(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    text = """
default:
  base_config: {env_type: GYM, build_path: Pendulum-v0, n_agents: 10, reset_on_iteration: false}
  sac_config: {use_n_step_is: false, clip_epsilon: 0.5}
  replay_config: {samples_per_insert: 256}
"""
    task = write_task(tmp_path, text)
    with caplog.at_level(logging.WARNING):
        c = load_config(task).config
    assert (c.sac_config.use_n_step_is, c.sac_config.clip_epsilon, c.replay_config.samples_per_insert) == (
        False,
        0.5,
        256,
    )
    file = task / "config.yaml"
    assert f"{file} is read as the original's (it sets base_config.env_type)" in port_notes(caplog)
    assert subjects(port_notes(caplog), file) == ["[default] base_config.build_path", "original"]
