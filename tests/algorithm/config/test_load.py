"""Config layering, validation errors that name key and file, YAML round trip."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from algorithm.config.load import (
    DEFAULT_CONFIG_PATH,
    ConfigError,
    apply_overrides,
    config_from_yaml,
    config_to_yaml,
    load_config,
    parse_yaml,
)
from algorithm.config.schema import Config

ROOT = Path(__file__).resolve().parents[3]


def write_task(tmp_path: Path, text: str) -> Path:
    task = tmp_path / "task"
    task.mkdir()
    (task / "config.yaml").write_text(text)
    return task


def test_default_file_matches_schema_defaults() -> None:
    assert load_config().config == Config()


def test_layers_apply_in_order_and_record_sources(tmp_path: Path) -> None:
    task = write_task(
        tmp_path,
        """
default:
  sac_config: {n_step: 3, gamma: 0.95}
  base_config: {build_path: HalfCheetah-v5}
fast:
  sac_config: {n_step: 5}
""",
    )
    r = load_config(task, "fast", ["sac.gamma=0.9"])
    c = r.config
    assert (c.sac_config.n_step, c.sac_config.gamma, c.base_config.build_path) == (5, 0.9, "HalfCheetah-v5")
    assert c.sac_config.tau == 0.005  # untouched keys keep the defaults
    assert r.sources["sac_config.n_step"].endswith("config.yaml [fast]")
    assert r.sources["sac_config.gamma"] == "override 'sac.gamma=0.9'"
    assert r.sources["base_config.build_path"].endswith("config.yaml [default]")


@pytest.mark.parametrize("text", ["3e-4", "3E-4", "1e3", "-2.5e-1", ".5"])
def test_exponent_numbers_parse_as_floats(text: str) -> None:
    assert isinstance(parse_yaml(f"x: {text}", "t")["x"], float)


def test_exponent_learning_rate_in_task_file(tmp_path: Path) -> None:
    task = write_task(tmp_path, "default:\n  sac_config:\n    learning_rate: 1e-3\n")
    assert load_config(task).config.sac_config.learning_rate == pytest.approx(1e-3)


@pytest.mark.parametrize(
    ("section_text", "key", "fragment"),
    [
        ("sac_config: {lerning_rate: 0.1}", "sac_config.lerning_rate", "did you mean 'learning_rate'"),
        ("sac_config: {n_step: two}", "sac_config.n_step", "valid integer"),
        ("sac_config: {n_step: 0}", "sac_config.n_step", "greater than or equal to 1"),
        ("replay_config: {alpha: 1.5}", "replay_config.alpha", "less than or equal to 1"),
        ("replay_config: {td_error_min: 2.0, td_error_max: 1.0}", "replay_config", "td_error_min"),
        ("sac_config: {ensemble_q_num: 2, ensemble_q_sample: 3}", "sac_config", "ensemble_q_sample"),
        ("nn_config: {activation: swish}", "nn_config.activation", "relu"),
        ("bogus_config: {a: 1}", "bogus_config", "unknown key"),
    ],
)
def test_errors_name_key_and_file(tmp_path: Path, section_text: str, key: str, fragment: str) -> None:
    task = write_task(tmp_path, "default:\n  " + section_text + "\n")
    with pytest.raises(ConfigError) as err:
        load_config(task)
    message = str(err.value)
    assert key in message
    assert str(task / "config.yaml") in message
    assert fragment in message


def test_override_errors_name_the_override() -> None:
    with pytest.raises(ConfigError, match=r"sac_config.gamma \(override 'sac.gamma=2'\)"):
        load_config(overrides=["sac.gamma=2"])
    with pytest.raises(ConfigError, match="unknown section 'sax'.*'sac'"):
        load_config(overrides=["sax.gamma=0.5"])
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(overrides=["gamma"])


def test_missing_variant_section_lists_available(tmp_path: Path) -> None:
    task = write_task(tmp_path, "default: {}\nfast: {}\nslow: {}\n")
    with pytest.raises(ConfigError, match=r"no config section 'medium'; available: \['fast', 'slow'\]"):
        load_config(task, "medium")


def test_bad_yaml_and_bad_shapes_are_config_errors(tmp_path: Path) -> None:
    task = write_task(tmp_path, "default:\n  sac_config: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(task)
    task2 = tmp_path / "t2"
    task2.mkdir()
    (task2 / "config.yaml").write_text("default:\n  sac_config: 5\n")
    with pytest.raises(ConfigError, match="sac_config"):
        load_config(task2)


def test_resolved_config_round_trips_through_yaml() -> None:
    for task in sorted(ROOT.glob("envs/*/*/config.yaml")):
        sections = [None] + [k for k in yaml.safe_load(task.read_text()) if k != "default"]
        for section in sections:
            config = load_config(task.parent, section).config
            assert config_from_yaml(config_to_yaml(config)) == config, (task, section)


def test_apply_overrides_on_a_saved_config() -> None:
    base = load_config(ROOT / "envs/gym/pendulum").config
    updated = apply_overrides(base, ["base.max_step=123"])
    assert updated.base_config.max_step == 123
    assert updated.replay_config == base.replay_config
    with pytest.raises(ConfigError, match="base_config.max_step"):
        apply_overrides(base, ["base.max_step=-7"])


def test_default_config_file_documents_every_key() -> None:
    # Every key of every section of the schema is in the default file, with a comment on its line or
    # on the line above: the file is where a user reads what a key does.
    lines = DEFAULT_CONFIG_PATH.read_text().splitlines()
    commented: dict[str, bool] = {}
    section = ""
    for i, line in enumerate(lines):
        if match := re.match(r"^(\w+):", line):
            section = match.group(1)
        elif match := re.match(r"^  (\w+):", line):
            above = lines[i - 1].strip().startswith("#")
            commented[f"{section}.{match.group(1)}"] = "#" in line or above
    config = Config()
    expected = [f"{name}.{key}" for name in type(config).model_fields
                if isinstance(section_model := getattr(config, name), BaseModel)
                for key in type(section_model).model_fields]  # fmt: skip
    assert [key for key in expected if key not in commented] == []
    assert [key for key in expected if not commented[key]] == []


def test_strings_that_read_as_numbers_survive_the_run_folders_round_trip() -> None:
    """CI's hypothesis found ``reset_config.0E0=null``: the key is the string "0E0", written
    unquoted by PyYAML's dumper and read back by ours (which takes 3e-4 as a float) as 0.0."""
    config = Config.model_validate({"reset_config": {"0E0": None, "1e5": "2E-3", "plain": 1e5}})
    assert config_from_yaml(config_to_yaml(config)) == config


def test_a_section_only_the_other_task_file_has_is_named_there(tmp_path: Path) -> None:
    """config_ds.yaml (main_ds.py's) without the -c section that config.yaml (main.py's) has: the error
    says where it is, rather than only that this file has none."""
    (tmp_path / "config.yaml").write_text("default: {}\nhard: {sac_config: {n_step: 3}}\n")
    (tmp_path / "config_ds.yaml").write_text("default: {replay_config: {batch_size: 16}}\n")
    with pytest.raises(ConfigError, match=r"no config section 'hard'; available: none \(config.yaml beside it, "
                                          r"which main.py reads, has it: add it to config_ds.yaml"):  # fmt: skip
        load_config(tmp_path, "hard", distributed=True)
    assert load_config(tmp_path, "hard").config.sac_config.n_step == 3  # main.py's file
