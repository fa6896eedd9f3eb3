"""``random_params``: hyper-parameters drawn per learner (by the evolver) or per run (by
``main.py``), written once for any pydantic config model.

A config's ``random_params`` maps ``{section: {key: spec}}`` with spec ``{in: [...]}``
(categorical), ``{truncated: [lo, hi]}`` (uniform), ``{std: s}`` (normal around the configured
value) or ``{std: s, truncated: [lo, hi]}`` (truncated normal). Sections are the config's
sub-models, plus ``reset_config`` (the env's reset options, a free mapping).

Usage::

    specs = parse_random_params(config.random_params, config)   # ParamSpecError names a bad entry
    values = sample_params(specs, config, counts={}, rng=rng)     # {"sac_config.n_step": 3, ...}
    run_config = apply_params(config, values)                     # concrete values, random_params emptied
    run_config, values = draw_for_run(config, seed)               # main.py: one draw from the seed

Only pydantic's ``BaseModel`` is assumed of the config (``algorithm/config/schema.py`` validates its
``random_params`` with :func:`parse_random_params`, and the evolver's CEM in
``algorithm/evolution.py`` weights the ``in`` choices by elite counts), so neither imports the other.
"""

from __future__ import annotations

import difflib
import math
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError, create_model

ConfigT = TypeVar("ConfigT", bound=BaseModel)

MAX_TRIES = 100  # draws per key before sample_params falls back (see _fallback)
_SPEC_FORMS = ({"in"}, {"truncated"}, {"std"}, {"std", "truncated"})


class ParamSpecError(ValueError):
    """A ``random_params`` entry is invalid; ``path`` is its key, e.g. ``random_params.sac_config.n_step``."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


@dataclass(frozen=True)
class ParamSpec:
    """One validated ``random_params`` entry for the config key ``section.key``.

    ``values`` holds the ``in`` choices as the section stores them (after pydantic's coercion);
    ``bounds`` the ``truncated`` interval (rounded inwards to integers for integer keys);
    ``std`` the spread of a normal around the key's configured value.
    """

    section: str
    key: str
    values: tuple[Any, ...] = ()
    bounds: tuple[float, float] | None = None
    std: float | None = None
    integer: bool = False

    @property
    def path(self) -> str:
        return f"{self.section}.{self.key}"

    @property
    def kind(self) -> str:
        """``in`` (categorical), ``uniform`` (``truncated`` alone) or ``normal`` (``std``)."""
        if self.values:
            return "in"
        return "uniform" if self.std is None else "normal"


def parse_random_params(raw: Mapping[str, Any], config: ConfigT) -> dict[str, ParamSpec]:
    """Validate ``config.random_params``-shaped ``raw`` against ``config``; specs by dotted key.

    Raises :class:`ParamSpecError` for an unknown section or key, a spec of another form, an empty
    or duplicated ``in``, ``lo >= hi``, ``std <= 0``, ``truncated``/``std`` on a key that is not a
    number, ``std`` around a key configured as null, or any value the section's schema rejects
    (each ``in`` value and both bounds are checked with the rest of ``config`` as configured).
    """
    sections = [name for name in type(config).model_fields if isinstance(getattr(config, name), BaseModel)]
    sections.append("reset_config")
    specs: dict[str, ParamSpec] = {}
    for section, keys in raw.items():
        where = f"random_params.{section}"
        if section not in sections:
            raise ParamSpecError(where, "unknown section" + _did_you_mean(section, sections))
        if not isinstance(keys, Mapping):
            raise ParamSpecError(where, "must map keys of the section to specs")
        for key, entry in keys.items():
            spec = _parse_spec(config, section, key, entry)
            specs[spec.path] = spec
    return specs


def _parse_spec(config: ConfigT, section: str, key: str, entry: Any) -> ParamSpec:
    path = f"random_params.{section}.{key}"
    model = _section(config, section)
    fields = type(model).model_fields
    if key not in fields and section == "reset_config":
        raise ParamSpecError(path, f"reset_config has no option {key!r}: give it its configured value there first")
    if key not in fields:
        raise ParamSpecError(path, "unknown key" + _did_you_mean(key, list(fields)))
    if not isinstance(entry, Mapping) or set(entry) not in _SPEC_FORMS:
        got = f"keys {sorted(map(str, entry))}" if isinstance(entry, Mapping) else repr(entry)
        forms = "{in: [...]}, {truncated: [lo, hi]}, {std: s} or {std: s, truncated: [lo, hi]}"
        raise ParamSpecError(path, f"expected {forms}; got {got}")
    if "in" in entry:
        return ParamSpec(section, key, values=_parse_choices(model, key, entry["in"], path))
    number = _number_type(fields[key].annotation)
    if number is None:
        raise ParamSpecError(path, f"'truncated' and 'std' need a numeric key; {section}.{key} is not a number")
    integer = number is int
    bounds = _parse_bounds(model, key, entry["truncated"], integer, path) if "truncated" in entry else None
    std = None
    if "std" in entry:
        std = entry["std"]
        if not _is_real(std) or not math.isfinite(std) or std <= 0:
            raise ParamSpecError(path, f"'std' must be a number > 0; got {std!r}")
        if getattr(model, key) is None:
            raise ParamSpecError(path, f"'std' draws around the configured value, and {section}.{key} is null")
        std = float(std)
    return ParamSpec(section, key, bounds=bounds, std=std, integer=integer)


def _parse_choices(model: BaseModel, key: str, values: Any, path: str) -> tuple[Any, ...]:
    if not isinstance(values, list) or not values:
        raise ParamSpecError(path, "'in' must be a non-empty list")
    choices: list[Any] = []
    for value in values:
        try:
            stored = _validated(type(model), model.model_dump(), key, value)
        except ValueError as e:
            raise ParamSpecError(path, f"'in' value {value!r} is not valid for the key: {e}") from None
        if stored in choices:
            raise ParamSpecError(path, f"'in' lists {value!r} twice")
        choices.append(stored)
    return tuple(choices)


def _parse_bounds(model: BaseModel, key: str, bounds: Any, integer: bool, path: str) -> tuple[float, float]:
    if not (isinstance(bounds, list) and len(bounds) == 2 and all(map(_is_real, bounds))):
        raise ParamSpecError(path, f"'truncated' must be [lo, hi] with two numbers; got {bounds!r}")
    lo, hi = float(bounds[0]), float(bounds[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ParamSpecError(path, f"'truncated' needs finite lo < hi; got {bounds!r}")
    if integer:
        lo, hi = math.ceil(lo), math.floor(hi)
        if lo > hi:
            raise ParamSpecError(path, f"'truncated' {bounds!r} holds no integer, and {key} is an integer key")
    for bound in (lo, hi):
        try:
            _validated(type(model), model.model_dump(), key, bound)
        except ValueError as e:
            raise ParamSpecError(path, f"'truncated' bound {bound!r} is not valid for the key: {e}") from None
    return lo, hi


def sample_params(
    specs: Mapping[str, ParamSpec], defaults: BaseModel, counts: Mapping[str, Sequence[int]], rng: np.random.Generator
) -> dict[str, Any]:
    """Draw one value per spec, keyed by dotted path (``"sac_config.n_step"``), as plain Python values.

    - ``in``: probabilities ``p ~ Dirichlet(1 + counts[path])``, then a value ``~ Categorical(p)``.
      Dirichlet(1 + c) is the posterior of the value probabilities under a uniform prior after
      ``c`` elite observations (Dirichlet-categorical conjugacy; Murphy 2012, "Machine Learning: A
      Probabilistic Perspective", 3.4), so value ``i`` comes up with probability
      ``(1 + c_i) / (K + sum(c))`` and values that were often elite are tried more often.
    - ``truncated`` alone: uniform on ``[lo, hi]`` (on the integers in it, for integer keys).
    - ``std``: normal around the key's value in ``defaults``, rounded for integer keys, and with
      ``truncated`` kept to ``[lo, hi]`` by rejection (a draw outside is drawn again).

    Each draw must also pass the section's schema with the values drawn before it (e.g.
    ``gamma <= 1`` for ``{std: ...}`` around 0.99); rejected draws are repeated, so the result
    follows the spec's distribution restricted to valid values. After ``MAX_TRIES`` rejections the
    key takes a fallback: the first valid ``in`` value, the midpoint of ``[lo, hi]`` for uniform,
    the configured value moved into ``[lo, hi]`` for normal (where a truncated normal's mass
    concentrates when its centre lies far outside). ``ValueError`` if even that is invalid.
    """
    sections: dict[str, dict[str, Any]] = {}
    values: dict[str, Any] = {}
    for path, spec in specs.items():
        model = _section(defaults, spec.section)
        data = sections.setdefault(spec.section, model.model_dump())
        centre = getattr(model, spec.key)
        count = counts.get(path)
        value = _sample_one(spec, type(model), data, centre, count, rng)
        data[spec.key] = value
        values[path] = value
    return values


_OUT_OF_BOUNDS = object()


def _sample_one(
    spec: ParamSpec,
    model_cls: type[BaseModel],
    data: dict[str, Any],
    centre: Any,
    count: Sequence[int] | None,
    rng: np.random.Generator,
) -> Any:
    for _ in range(MAX_TRIES):
        draw = _draw(spec, centre, count, rng)
        if draw is _OUT_OF_BOUNDS:
            continue
        try:
            return _validated(model_cls, data, spec.key, draw)
        except ValueError:
            continue
    candidates = list(spec.values) if spec.kind == "in" else [_fallback(spec, centre)]
    error = ""
    for candidate in candidates:
        try:
            return _validated(model_cls, data, spec.key, candidate)
        except ValueError as e:
            error = str(e)
    raise ValueError(f"random_params.{spec.path}: no valid value in {MAX_TRIES} draws nor the fallback: {error}")


def _draw(spec: ParamSpec, centre: Any, count: Sequence[int] | None, rng: np.random.Generator) -> Any:
    if spec.kind == "in":
        counts = np.zeros(len(spec.values)) if count is None else np.asarray(count, dtype=np.float64)
        if counts.shape != (len(spec.values),):
            raise ValueError(f"counts for {spec.path} have {counts.size} entries for {len(spec.values)} values")
        p = rng.dirichlet(1.0 + counts)
        return spec.values[int(rng.choice(len(spec.values), p=p))]
    if spec.kind == "uniform":
        assert spec.bounds is not None
        lo, hi = spec.bounds
        return int(rng.integers(int(lo), int(hi) + 1)) if spec.integer else float(rng.uniform(lo, hi))
    assert spec.std is not None
    x = float(rng.normal(float(centre), spec.std))
    value: float = round(x) if spec.integer else x
    if spec.bounds is not None and not spec.bounds[0] <= value <= spec.bounds[1]:
        return _OUT_OF_BOUNDS
    return value


def _fallback(spec: ParamSpec, centre: Any) -> float:
    if spec.bounds is None:
        return float(centre)
    lo, hi = spec.bounds
    value = (lo + hi) / 2 if spec.kind == "uniform" else min(max(float(centre), lo), hi)
    return round(value) if spec.integer else value


def apply_params(config: ConfigT, values: Mapping[str, Any]) -> ConfigT:
    """A validated copy of ``config`` with ``values`` (by dotted key) set and ``random_params`` emptied.

    The copy is the config one learner runs with: concrete values only, so its saved config.yaml
    says what it ran. Keys the config derives from others (its ``derived_keys()``, where it has one)
    are set back to null first, so they follow the drawn values. ``ValueError`` names the keys when
    the values are rejected.
    """
    data = config.model_dump()
    derived = getattr(config, "derived_keys", None)  # keys the config fills in from others: derive them anew
    for path in derived() if callable(derived) else ():
        section, _, key = path.partition(".")
        data[section][key] = None
    for path, value in values.items():
        section, _, key = path.partition(".")
        if not isinstance(data.get(section), dict) or key not in data[section]:
            raise ValueError(f"apply_params: {path!r} is not a config key")
        data[section][key] = value
    data["random_params"] = {}
    try:
        return type(config).model_validate(data)
    except ValidationError as e:
        problems = "; ".join(f"{'.'.join(map(str, err['loc'])) or 'config'}: {err['msg']}" for err in e.errors())
        raise ValueError(f"apply_params: {problems}") from None


def draw_for_run(config: ConfigT, seed: int) -> tuple[ConfigT, dict[str, Any]]:
    """A single run's config (``main.py``): each ``random_params`` entry drawn once, as the evolver
    draws a first-round learner's (no elite counts), from a generator seeded by ``seed`` (the run's
    ``sac_config.seed``: the same seed draws the same values), applied by :func:`apply_params`.
    Returns the config to run and the values drawn, by dotted key (empty without random_params)."""
    raw = getattr(config, "random_params", None)
    if not raw:
        return config, {}
    specs = parse_random_params(raw, config)
    values = sample_params(specs, config, {}, np.random.default_rng([seed, _RUN_DRAW_STREAM]))
    return apply_params(config, values), values


_RUN_DRAW_STREAM = 0x72616E64  # keeps these draws apart from every other use of the seed


def _section(config: ConfigT, name: str) -> BaseModel:
    """The config section ``name`` as a model. ``reset_config`` (the env's reset options, a free
    mapping) becomes a model with one field per configured option, typed as its value (an int
    option stays an int), so its options are drawn and checked like any other section's keys."""
    if name != "reset_config":
        section: BaseModel = getattr(config, name)
        return section
    options = getattr(config, "reset_config", None) or {}
    fields: dict[str, Any] = {key: (type(value) if value is not None else Any, value) for key, value in options.items()}
    return create_model("reset_config", **fields)()


def _validated(model_cls: type[BaseModel], data: dict[str, Any], key: str, value: Any) -> Any:
    """``value`` as the section stores it with ``data`` around it; ``ValueError`` with pydantic's reason."""
    try:
        return getattr(model_cls.model_validate({**data, key: value}), key)
    except ValidationError as e:
        raise ValueError("; ".join(err["msg"].removeprefix("Value error, ") for err in e.errors())) from None


def _number_type(annotation: Any) -> type | None:
    """``int`` or ``float`` for numeric fields (``int | None`` included), ``None`` for the rest (bool too)."""
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    kinds = {a for a in (typing.get_args(annotation) if union else (annotation,)) if a is not type(None)}
    if kinds == {int}:
        return int
    if kinds and kinds <= {int, float}:
        return float
    return None


def _is_real(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _did_you_mean(name: str, known: list[str]) -> str:
    close = difflib.get_close_matches(name, known, n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""
