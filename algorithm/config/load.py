"""Config loading: YAML layering, CLI overrides and validation against the typed schema.

Layers, each overriding the previous (docs/architecture.md section 11):

1. ``algorithm/config/default_config.yaml`` (the schema defaults, written out);
2. the ``default`` section of the task's ``envs/<task>/config.yaml``;
3. the section named by ``-c NAME`` in the same file;
4. ``--override section.key=value`` from the command line (``sac.n_step=5`` works for
   ``sac_config.n_step``).

Every leaf remembers which layer set it, so an unknown key, a wrong type or an out-of-range value
is reported as ``sac_config.learning_rate (envs/gym/pendulum/config.yaml [fast]): ...``.

A task file (and an override) written for the original system is read through
:mod:`algorithm.config.original` first: its moved keys land where ASAC keeps them, with a warning.
"""

from __future__ import annotations

import copy
import difflib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from algorithm.config.original import Port, looks_like_original
from algorithm.config.random_params import ParamSpecError
from algorithm.config.schema import Config

DEFAULT_CONFIG_PATH = Path(__file__).with_name("default_config.yaml")


class ConfigError(ValueError):
    """A config file, section or override is invalid; the message names the key and its source."""


class _Loader(yaml.SafeLoader):
    """SafeLoader that reads ``3e-4`` as a float (YAML 1.1 needs ``3.0e-4``; people write ``3e-4``)."""


_FLOAT_RE = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.X,
)
_Loader.yaml_implicit_resolvers = {
    k: [(tag, rx) for tag, rx in v if tag != "tag:yaml.org,2002:float"]
    for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_RE, list("-+0123456789."))


class _Dumper(yaml.SafeDumper):
    """SafeDumper that quotes a string :class:`_Loader` would read back as a float (``"0E0"``,
    ``"1e5"``: plain YAML 1.1 scalars for SafeDumper), so a config survives its round trip."""


_Dumper.yaml_implicit_resolvers = {k: list(v) for k, v in _Loader.yaml_implicit_resolvers.items()}


def parse_yaml(text: str, source: str) -> Any:
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.MarkedYAMLError as e:  # where and what, on one line (str(e) spans several)
        mark = e.problem_mark or e.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = ": ".join(part for part in (e.context, e.problem) if part)
        raise ConfigError(f"{source}: not valid YAML{where}: {what}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: not valid YAML: {' '.join(str(e).split())}") from None


def read_yaml(path: Path) -> Any:
    return parse_yaml(read_config_text(path), str(path))


def read_config_text(path: Path) -> str:
    """The text of a config file; :class:`ConfigError` when it cannot be read or is not UTF-8."""
    try:
        return path.read_bytes().decode("utf-8")
    except OSError as e:
        raise ConfigError(f"cannot read config file {path}: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (byte {e.object[e.start]:#04x} at offset {e.start})") from None


@dataclass
class ResolvedConfig:
    """The validated config plus where each key came from."""

    config: Config
    sources: dict[str, str]


def config_to_yaml(config: Config) -> str:
    return yaml.dump(config.model_dump(mode="json"), Dumper=_Dumper, sort_keys=False, default_flow_style=False)


def _section_aliases() -> dict[str, str]:
    """``sac`` -> ``sac_config`` etc., for short override keys."""
    aliases = {}
    for name in Config.model_fields:
        aliases[name] = name
        if name.endswith("_config"):
            aliases[name[: -len("_config")]] = name
    return aliases


def _merge(base: dict[str, Any], layer: Any, source: str, sources: dict[str, str], prefix: str = "") -> None:
    """Deep-merge ``layer`` into ``base`` in place, recording the source of every leaf set."""
    if not isinstance(layer, dict):
        where = prefix.rstrip(".") or "top level"
        raise ConfigError(f"{source}: {where} must be a mapping of keys, got {type(layer).__name__}")
    for key, value in layer.items():
        if not isinstance(key, str):
            raise ConfigError(f"{source}: key {key!r} under {prefix.rstrip('.') or 'top level'} is not a string")
        dotted = prefix + key
        if isinstance(value, dict) and _is_section_path(dotted):
            if not isinstance(base.get(key), dict):
                base[key] = {}
            _merge(base[key], value, source, sources, dotted + ".")
        else:
            base[key] = copy.deepcopy(value)
            sources[dotted] = source


def _is_section_path(dotted: str) -> bool:
    """Mappings that are config sections merge key by key, and so do ``random_params``' sections (a
    variant can add one key's spec); dict-valued keys (env_kwargs) and single specs replace."""
    if dotted.startswith("random_params."):
        return dotted.count(".") == 1
    return "." not in dotted and dotted in Config.model_fields


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"sac.n_step=5"`` -> (["sac_config", "n_step"], 5). Values are YAML scalars/lists."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected section.key=value")
    key, raw = text.split("=", 1)
    parts = key.strip().split(".")
    if len(parts) != 2 or not all(parts):
        raise ConfigError(f"override {text!r}: key must be section.key, e.g. sac_config.n_step=5")
    aliases = _section_aliases()
    if parts[0] not in aliases:
        close = difflib.get_close_matches(parts[0], list(aliases), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"override {text!r}: unknown section {parts[0]!r}{hint}")
    parts[0] = aliases[parts[0]]
    return parts, parse_yaml(raw, f"override {text!r}") if raw.strip() else None


def _format_errors(err: ValidationError, sources: dict[str, str]) -> str:
    return _one_line(_error_lines(err, sources))


def _one_line(lines: list[str]) -> str:
    text = "; ".join(lines).replace("\r", "\\r").replace("\n", "\\n")  # a key may hold a line break
    return "invalid config: " + text  # one line, like every command-line error


def _error_lines(err: ValidationError, sources: dict[str, str]) -> list[str]:
    lines = []
    for e in err.errors():
        loc = [str(p) for p in e["loc"]]
        spec_error = e.get("ctx", {}).get("error")
        if isinstance(spec_error, ParamSpecError):  # raised for the whole config; it knows its key
            lines.append(f"{spec_error.path} ({_source_of(spec_error.path.split('.'), sources)}): {spec_error.problem}")
            continue
        dotted = ".".join(loc)
        source = _source_of(loc, sources)
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            model: Any = Config
            for part in loc[:-1]:
                is_model = isinstance(model, type) and issubclass(model, BaseModel)
                field = model.model_fields.get(part) if is_model else None
                model = field.annotation if field is not None else None
            is_model = isinstance(model, type) and issubclass(model, BaseModel)
            known = list(model.model_fields) if is_model else []
            close = difflib.get_close_matches(loc[-1], known, n=1)
            msg = "unknown key" + (f" (did you mean {close[0]!r}?)" if close else "")
        elif e["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")
        lines.append(f"{dotted or 'config'} ({source}): {msg}" + _got(e))
    return lines


def _source_of(loc: list[str], sources: dict[str, str]) -> str:
    """Where the value at ``loc`` came from; for a cross-field error on a whole section, every file
    that set one of its keys (defaults last, since a default alone rarely causes it)."""
    if ".".join(loc) in sources:
        return sources[".".join(loc)]
    prefix = ".".join(loc) + "." if loc else ""
    inside = list(dict.fromkeys(v for k, v in sources.items() if k.startswith(prefix)))
    chosen = [v for v in inside if v != str(DEFAULT_CONFIG_PATH)] or inside
    if chosen:
        return ", ".join(chosen)
    for i in range(len(loc) - 1, 0, -1):
        if ".".join(loc[:i]) in sources:
            return sources[".".join(loc[:i])]
    return "defaults"


def _got(e: Any) -> str:
    if e["type"] in ("extra_forbidden", "missing") or "input" not in e or isinstance(e["input"], dict):
        return ""
    return f"; got {e['input']!r}"


DISTRIBUTED_TASK_FILE = "config_ds.yaml"
"""A task folder's file for the distributed roles, read by ``main_ds.py`` in place of ``config.yaml``
when the folder has one (the original's layout: its distributed roles read only this file)."""


def task_config_path(task_dir: Path, distributed: bool = False) -> Path:
    """The task file a launcher reads: ``config.yaml``, or with ``distributed`` the folder's
    :data:`DISTRIBUTED_TASK_FILE` when there is one."""
    ds_file = task_dir / DISTRIBUTED_TASK_FILE
    return ds_file if distributed and ds_file.is_file() else task_dir / "config.yaml"


def _section_elsewhere(task_dir: Path, read: Path, name: str) -> str:
    """A hint when the folder's other task file (config.yaml beside config_ds.yaml) has section ``name``."""
    other = task_dir / ("config.yaml" if read.name == DISTRIBUTED_TASK_FILE else DISTRIBUTED_TASK_FILE)
    try:
        sections = read_yaml(other) if other.is_file() else None
    except ConfigError:
        return ""
    if isinstance(sections, dict) and name in sections:
        which = "main.py" if other.name == "config.yaml" else "main_ds.py"
        return f" ({other.name} beside it, which {which} reads, has it: add it to {read.name} for this launcher)"
    return ""


def load_config(
    task_dir: str | Path | None = None,
    config_name: str | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    default_path: Path = DEFAULT_CONFIG_PATH,
    distributed: bool = False,
) -> ResolvedConfig:
    """Resolve the four layers into a validated :class:`Config` (raises :class:`ConfigError`);
    ``distributed``: the task file is :func:`task_config_path`'s for the distributed roles."""
    merged: dict[str, Any] = {}
    sources: dict[str, str] = {}
    port = Port()
    _merge(merged, read_yaml(default_path) or {}, str(default_path), sources)

    if task_dir is not None:
        path = task_config_path(Path(task_dir), distributed)
        task_file = read_yaml(path) if path.exists() else {}
        if not isinstance(task_file, dict):
            raise ConfigError(f"{path}: top level must map section names (default, ...) to configs")
        for name in task_file:
            if not isinstance(name, str):  # YAML reads 1, 0E0 or true as numbers and booleans
                raise ConfigError(f"{path}: section name {name!r} is read as {type(name).__name__}, not text; quote it")
        layers = [("default", task_file.get("default"))]
        if config_name is not None:
            if config_name not in task_file or config_name == "default":
                names = sorted(k for k in task_file if k != "default")
                raise ConfigError(f"{path}: no config section {config_name!r}; available: {names or 'none'}"
                                  f"{_section_elsewhere(Path(task_dir), path, config_name)}")  # fmt: skip
            layers.append((config_name, task_file[config_name]))
        # the original's keys anywhere in the file, or the original's distributed file beside it
        original = looks_like_original(task_file, (Path(task_dir) / DISTRIBUTED_TASK_FILE).is_file())
        port.read_as_original(original, str(path), distributed)
        for name, layer in layers:
            source = f"{path} [{name}]"
            _merge(merged, port.layer(layer or {}, source, str(path), original is not None), source, sources)
    elif config_name is not None:
        raise ConfigError(f"-c {config_name}: no task folder to look it up in")

    return _validate(merged, sources, overrides, port)


def apply_overrides(config: Config, overrides: list[str] | tuple[str, ...]) -> Config:
    """``config`` with ``--override`` values applied on top (e.g. to a resumed run's saved config)."""
    if not overrides:
        return config
    return _validate(config.model_dump(mode="json"), {}, overrides).config


def _validate(
    merged: dict[str, Any], sources: dict[str, str], overrides: list[str] | tuple[str, ...], port: Port | None = None
) -> ResolvedConfig:
    port = port or Port()
    for text in overrides:
        for parts, value in port.override(*parse_override(text), f"override {text!r}"):
            if parts[0] == "reset_config" and merged.get("reset_config") is None:
                merged["reset_config"] = {}  # the env's reset options: a free mapping, null until one is set
            section = merged.setdefault(parts[0], {})
            if not isinstance(section, dict):
                raise ConfigError(f"override {text!r}: {parts[0]} is not a section")
            section[parts[1]] = value
            sources[".".join(parts)] = f"override {text!r}"
    port.finish(merged, sources)  # ids, clip_epsilon <= 0 and the original's defaults, on the merged values
    try:
        config = Config.model_validate(merged)
    except ValidationError as e:  # the port's errors first: they say what a key of the original became
        raise ConfigError(_one_line(port.errors + _error_lines(e, sources))) from None
    if port.errors:
        raise ConfigError(_one_line(port.errors))
    return ResolvedConfig(config, sources)


def config_from_file(path: Path) -> Config:
    """:func:`config_from_yaml` of a file (a run directory's ``config.yaml``)."""
    return config_from_yaml(read_config_text(path), str(path))


def config_from_yaml(text: str, source: str = "config.yaml") -> Config:
    """Parse a resolved config written by :func:`config_to_yaml` (e.g. a run directory's)."""
    data = parse_yaml(text, source) or {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: top level must be a mapping of sections, got {type(data).__name__}")
    named = [k for k in data if not isinstance(k, str)]
    if named:  # e.g. a bare "?" or "null:" line: a key YAML reads as None
        raise ConfigError(f"{source}: section names must be strings, got {named[0]!r}")
    try:
        return Config.model_validate(data)
    except ValidationError as e:
        raise ConfigError(_format_errors(e, {k: source for k in data})) from None
