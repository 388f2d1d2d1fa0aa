"""Settings with their rules: each sub-config of :class:`~open3d_pnerf.ReconstructionConfig` is a
dataclass of :class:`Settings` whose fields are declared once, with the rule a value must obey
(``levels: int = setting(8, count(1))``), and which validates itself."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from .errors import ConfigError


@dataclasses.dataclass(frozen=True)
class Rule:
    """What a setting's value must be: `expected` says it in words, `ok` checks it."""

    expected: str
    ok: Callable[[Any], bool]

    def holds(self, value) -> bool:
        try:
            return bool(self.ok(value))
        except TypeError:
            return False


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def count(low: int = 1, high: int | None = None) -> Rule:
    """An int in [low, high]."""
    within = f"in [{low}, {high}]" if high is not None else f">= {low}"
    return Rule(f"an int {within}", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= low
                and (high is None or v <= high))


def number(low: float, high: float | None = None, *, low_open: bool = False, high_open: bool = False,
           unit: str = "") -> Rule:
    """A number in the interval from low to high (open at an end where asked; no upper end for None)."""
    if high is None:
        words = f"a number {'>' if low_open else '>='} {low:g}"
    else:
        words = f"a number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"

    def ok(v) -> bool:
        return _number(v) and (v > low if low_open else v >= low) and (
            high is None or (v < high if high_open else v <= high))

    return Rule(words + (f" ({unit})" if unit else ""), ok)


def one_of(values) -> Rule:
    values = tuple(values)
    return Rule(f"one of {values}", lambda v: v in values)


def optional(rule: Rule) -> Rule:
    """None or what `rule` accepts."""
    return Rule(f"None or {rule.expected}", lambda v: v is None or rule.holds(v))


FLAG = Rule("True or False", lambda v: isinstance(v, bool))


def setting(default, rule: Rule):
    """A dataclass field with its default and the rule its values obey."""
    return dataclasses.field(default=default, metadata={"rule": rule})


def section(cls: type):
    """A dataclass field holding a sub-config of type `cls` (its defaults), validated by its own rules."""
    return dataclasses.field(default_factory=cls)


class Settings:
    """Base of the sub-configs: from_dict() builds one from plain values (as saved in JSON),
    validate() checks every field against the rule it was declared with; a field that is itself
    Settings does both for its own fields."""

    @classmethod
    def from_dict(cls, values: dict, prefix: str = ""):
        """An instance from a dict of its fields (a sub-config as a dict of its own fields, a tuple
        as a list); unknown names raise ConfigError naming them with `prefix`."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = [name for name in values if name not in fields]
        if unknown:
            where = f" in {prefix[:-1]!r}" if prefix else ""
            raise ConfigError(f"unknown config field(s) {[prefix + name for name in unknown]}{where}; "
                              f"valid fields: {sorted(fields)}")
        kwargs = {}
        for name, value in values.items():
            default = _default(fields[name])
            if isinstance(default, Settings) and isinstance(value, dict):
                value = type(default).from_dict(value, f"{prefix}{name}.")
            elif isinstance(default, tuple) and isinstance(value, list):
                value = tuple(value)
            kwargs[name] = value
        return cls(**kwargs)

    def validate(self, prefix: str = "") -> None:
        """Raise ConfigError naming the first field (as `prefix` + name) with a bad value or type."""
        for field in dataclasses.fields(self):
            value, default = getattr(self, field.name), _default(field)
            if isinstance(default, Settings):
                if not isinstance(value, type(default)):
                    raise ConfigError(f"config field {prefix}{field.name}={value!r} is invalid: expected a "
                                      f"{type(default).__name__} or a dict of its fields")
                value.validate(f"{prefix}{field.name}.")
                continue
            rule = field.metadata.get("rule")
            if rule is not None and not rule.holds(value):
                raise ConfigError(f"config field {prefix}{field.name}={value!r} is invalid: expected {rule.expected}")


def _default(field: dataclasses.Field):
    return field.default_factory() if field.default_factory is not dataclasses.MISSING else field.default
