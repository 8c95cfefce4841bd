"""YAML configs: find them by name, load them, apply command-line overrides.

A config is a plain nested dict. ``load_config("lite")`` reads ``dope_hope/configs/lite.yaml``,
which ships inside the package (the repository's top-level ``configs`` links to it); any other
argument is a path to a YAML file.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import yaml

from dope_hope.errors import ConfigError, InputFileError

#: The packaged configs (``dope_hope/configs/*.yaml``), found the same way in a wheel install.
CONFIG_DIR = Path(__file__).resolve().parent / "configs"


def config_path(name_or_path: str | Path) -> Path:
    """Resolve a config name ("lite") or a path to an existing YAML file."""
    p = Path(name_or_path)
    # A bare name ("synth") is a config name even when a folder of that name exists in the
    # working directory (e.g. the output folder of `dope-hope synth --out synth/...`).
    if p.suffix in (".yaml", ".yml") or p.is_file():
        if not p.is_file():
            raise InputFileError(p, "config file not found")
        return p
    candidate = CONFIG_DIR / f"{name_or_path}.yaml"
    if candidate.is_file():
        return candidate
    known = sorted(q.stem for q in CONFIG_DIR.glob("*.yaml")) if CONFIG_DIR.is_dir() else []
    raise ConfigError(f"unknown config {str(name_or_path)!r}; known: {', '.join(known) or 'none'}")


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; malformed files raise InputFileError naming the file."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None
    except yaml.YAMLError as exc:
        raise InputFileError(path, f"malformed YAML ({str(exc).splitlines()[0]})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputFileError(path, "expected a YAML mapping at the top level")
    return data


def load_config(name_or_path: str | Path) -> dict[str, Any]:
    """Load a config by name or path (see :func:`config_path`)."""
    return load_yaml(config_path(name_or_path))


def merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """Deep-merge ``override`` into a copy of ``base`` (dicts merge, other values replace)."""
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def unknown_keys(config: dict[str, Any], defaults: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted keys of ``config`` that ``defaults`` does not have (sections compared recursively)."""
    out = []
    for key, value in config.items():
        name = f"{prefix}{key}"
        if key not in defaults:
            out.append(name)
        elif isinstance(value, dict) and isinstance(defaults[key], dict):
            out += unknown_keys(value, defaults[key], name + ".")
    return out


def differing_keys(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """Sorted dotted keys whose values differ between ``a`` and ``b``, sections compared
    recursively (a key present in only one of them differs)."""
    out = []
    for key in sorted(set(a) | set(b), key=str):
        name = f"{prefix}{key}"
        left, right = a.get(key), b.get(key)
        if isinstance(left, dict) and isinstance(right, dict):
            out += differing_keys(left, right, name + ".")
        elif key not in a or key not in b or left != right:
            out.append(name)
    return out


def check_known_keys(config: dict[str, Any], defaults: dict[str, Any], what: str) -> None:
    """ConfigError naming the keys of ``config`` that ``defaults`` lacks (typos: ``target.cuont``)."""
    unknown = unknown_keys(config, defaults)
    if unknown:
        first = unknown[0]
        section = first.rsplit(".", 1)[0] if "." in first else None
        node = defaults
        for part in (section.split(".") if section else []):
            node = node.get(part, {}) if isinstance(node, dict) else {}
        known = ", ".join(sorted(node)) if isinstance(node, dict) else ""
        raise ConfigError(f"{what}: unknown key(s) {', '.join(unknown)}"
                          + (f" (known{' in ' + section if section else ''}: {known})" if known else ""))


def apply_overrides(config: dict[str, Any], assignments: list[str],
                    defaults: dict[str, Any] | None = None) -> dict[str, Any]:
    """Apply ``section.key=value`` strings (values parsed as YAML) to a copy of ``config``.

    With ``defaults`` (the packaged config), a key it does not have is refused (ConfigError).
    """
    out = copy.deepcopy(config)
    for item in assignments:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.key=value")
        dotted, raw = item.split("=", 1)
        keys = dotted.split(".")
        if not all(keys):
            raise ConfigError(f"override {item!r}: empty key")
        if defaults is not None:
            node: Any = defaults
            for depth, key in enumerate(keys):
                if not isinstance(node, dict) or key not in node:
                    where = ".".join(keys[:depth]) or "the config"
                    known = ", ".join(sorted(node)) if isinstance(node, dict) else ""
                    raise ConfigError(f"--set {item}: unknown key {'.'.join(keys[:depth + 1])!r}"
                                      + (f" (known in {where}: {known})" if known else ""))
                node = node[key]
        node = out
        for key in keys[:-1]:
            node = node.setdefault(key, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r}: {key!r} is not a section")
        try:
            node[keys[-1]] = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise ConfigError(f"--set {item}: malformed value ({str(exc).splitlines()[0]})") from None
    return out


# ----------------------------------------------------------------------------- values
# One rule each, shared by the command-line types (dope_hope.commands.argtypes) and the
# config sections that hold the same quantities (train.lr, ...). ``name`` is the option or
# key named in the message.
def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def finite_float(value: Any, name: str) -> float:
    """A finite number."""
    return _number(value, name)


def positive_float(value: Any, name: str) -> float:
    """A finite number > 0."""
    v = _number(value, name)
    if v <= 0:
        raise ConfigError(f"{name} must be > 0, got {value!r}")
    return v


def nonnegative_float(value: Any, name: str) -> float:
    """A finite number >= 0."""
    v = _number(value, name)
    if v < 0:
        raise ConfigError(f"{name} must be >= 0, got {value!r}")
    return v


def whole_number(value: Any, name: str, minimum: int = 0) -> int:
    """An integer >= ``minimum`` (1.0 counts as 1; 1.5, True and "1" do not)."""
    v = _number(value, name)
    if v != int(v):
        raise ConfigError(f"{name} must be a whole number, got {value!r}")
    if v < minimum:
        raise ConfigError(f"{name} must be >= {minimum}, got {value!r}")
    return int(v)


def fraction(value: Any, name: str) -> float:
    """A finite number in [0, 1]."""
    v = _number(value, name)
    if not 0 <= v <= 1:
        raise ConfigError(f"{name} must be in [0, 1], got {value!r}")
    return v


# ----------------------------------------------------------------------------- settings
#: A value rule: ``rule(value, name)`` is the checked value (1.0 -> 1 for a whole number,
#: a list -> a tuple), or a ConfigError naming ``name``.
Rule = Callable[[Any, str], Any]


def at_least(minimum: int) -> Rule:
    """The rule of a whole number >= ``minimum`` (:func:`whole_number`)."""
    return lambda value, name: whole_number(value, name, minimum)


def or_none(rule: Rule) -> Rule:
    """``rule``, or None (the setting is off)."""
    return lambda value, name: None if value is None else rule(value, name)


def or_inf(rule: Rule) -> Rule:
    """``rule``, or +inf (no bound)."""
    def checked(value: Any, name: str) -> Any:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and value == math.inf:
            return math.inf
        return rule(value, name)
    return checked


def one_of(*choices: str) -> Rule:
    """The rule of a value among ``choices``."""
    def checked(value: Any, name: str) -> Any:
        if not isinstance(value, str) or value not in choices:
            raise ConfigError(f"{name} must be one of {', '.join(choices)}, got {value!r}")
        return value
    return checked


def each(rule: Rule) -> Rule:
    """The rule of a non-empty list of values, each checked by ``rule``; a tuple."""
    def checked(value: Any, name: str) -> tuple:
        if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__len__") or not len(value):
            raise ConfigError(f"{name} must be a non-empty list, got {value!r}")
        return tuple(rule(v, name) for v in value)
    return checked


_Settings = TypeVar("_Settings", bound="SectionSettings")


class SectionSettings:
    """Base of the frozen dataclasses that hold one config section's settings (a stage's
    section of ``configs/infer.yaml``, as ``icp_refine``): each field a key of the section,
    its default the section's default.

    Subclasses set ``SECTION`` (the section's name, in messages) and ``RULES`` (field -> a
    :data:`Rule`); construction checks every field named there and keeps the checked value,
    so a bad value is a ConfigError naming ``SECTION.field``.
    """

    SECTION: ClassVar[str] = "settings"
    RULES: ClassVar[Mapping[str, Rule]] = {}

    def __post_init__(self) -> None:
        for name, rule in self.RULES.items():
            object.__setattr__(self, name, rule(getattr(self, name), f"{self.SECTION}.{name}"))

    @classmethod
    def from_mapping(cls: type[_Settings], values: Mapping[str, Any] | None) -> _Settings:
        """Settings from a section's mapping (None: the defaults); unknown keys refused."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values or {}) - names)
        if unknown:
            raise ConfigError(f"unknown {cls.SECTION} option(s) {', '.join(unknown)}; known: "
                              f"{', '.join(sorted(names))}")
        return cls(**dict(values or {}))
