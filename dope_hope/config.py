"""YAML configs and settings: find configs by name, load them; the settings classes of their
sections (:class:`SectionSettings`), the value rules they use, and the one loader of a
command's settings (:func:`load_settings`: defaults, a --config file, --set items).

A config file is a plain nested dict. ``load_config("lite")`` reads ``dope_hope/configs/lite.yaml``,
which ships inside the package (the repository's top-level ``configs`` links to it); any other
argument is a path to a YAML file (one with a folder in it, ``./my_settings``, always).

This module owns reading them (:func:`load_yaml`): UTF-8, or UTF-16 / UTF-8 with a byte order
mark as Windows editors save them (PyYAML's own detection); any other bytes, a value nested
deeper than :data:`MAX_NESTING` (a file's or a ``--set`` value's) and malformed YAML are one
line naming the file; a key set twice in one mapping (YAML allows it, the last value wins)
is a warning naming both lines.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import re
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import yaml

from dope_hope.errors import ConfigError, InputFileError

#: The packaged configs (``dope_hope/configs/*.yaml``), found the same way in a wheel install.
CONFIG_DIR = Path(__file__).resolve().parent / "configs"


#: Deepest nesting of lists and mappings a config file or ``--set`` value may hold (a config
#: is sections of keys; a value a list of lists at most).
MAX_NESTING = 32


def config_path(name_or_path: str | Path) -> Path:
    """Resolve a config name ("lite") or a path to an existing YAML file (a value with a
    folder in it, or a .yaml / .yml suffix, or an existing file, is a path)."""
    p = Path(name_or_path)
    text = str(name_or_path)
    # A bare name ("synth") is a config name even when a folder of that name exists in the
    # working directory (e.g. the output folder of `dope-hope synth --out synth/...`).
    if p.suffix in (".yaml", ".yml") or p.is_file() or "/" in text or "\\" in text:
        if p.is_dir():
            raise InputFileError(text, "config file is a folder, not a YAML file")
        if not p.is_file():
            raise InputFileError(text, "config file not found")
        return p
    candidate = CONFIG_DIR / f"{name_or_path}.yaml"
    if candidate.is_file():
        return candidate
    known = sorted(q.stem for q in CONFIG_DIR.glob("*.yaml")) if CONFIG_DIR.is_dir() else []
    raise ConfigError(f"unknown config {text!r}; known: {', '.join(known) or 'none'} (or a path to a YAML file)")


class _CheckedLoader(yaml.SafeLoader):
    """PyYAML's safe loader that notes each key a mapping sets twice: (key, first line, line)."""

    def __init__(self, stream: Any):
        super().__init__(stream)
        self.repeated: list[tuple[Any, int, int]] = []

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                if key in seen:
                    self.repeated.append((key, seen[key], key_node.start_mark.line + 1))
                seen.setdefault(key, key_node.start_mark.line + 1)
            except TypeError:  # an unhashable key: the base class says why
                pass
        return super().construct_mapping(node, deep=deep)


def _nesting(value: Any) -> int:
    """How deep lists and mappings nest in ``value`` (a scalar: 0), without recursion."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        item, depth = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else None
        if children is None:
            continue
        deepest = max(deepest, depth + 1)
        if deepest > MAX_NESTING:
            break
        stack.extend((c, depth + 1) for c in children)
    return deepest


def parse_yaml_text(data: str | bytes, where: str, error: Callable[[str], Exception]) -> Any:
    """The YAML value of ``data`` (bytes: UTF-8, or UTF-16 / UTF-8 with a byte order mark);
    ``error(problem)`` is raised for bytes of another encoding, malformed YAML and a value
    nested deeper than :data:`MAX_NESTING`; a key set twice is a warning naming ``where``."""
    loader = None
    try:
        loader = _CheckedLoader(data)  # decodes bytes already
        value = loader.get_single_data()
    except yaml.reader.ReaderError as exc:
        raise error(f"not UTF-8 or UTF-16 text ({exc.reason} at byte {exc.position}); save it as UTF-8") from None
    except yaml.YAMLError as exc:
        raise error(f"malformed YAML ({str(exc).splitlines()[0]})") from None
    except RecursionError:
        raise error(f"nested deeper than {MAX_NESTING} levels") from None
    finally:
        if loader is not None:
            loader.dispose()
    if _nesting(value) > MAX_NESTING:
        raise error(f"nested deeper than {MAX_NESTING} levels")
    for key, first, line in loader.repeated:
        warnings.warn(f"{where}: line {line} sets {key!r} again (first on line {first}); the last value is "
                      "taken", stacklevel=2)
    return value


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping (module docstring: encodings, nesting, repeated keys); an unreadable
    or malformed file raises InputFileError naming the file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None
    except IsADirectoryError:
        raise InputFileError(path, "is a folder, not a YAML file") from None
    data = parse_yaml_text(raw, str(path), lambda problem: InputFileError(path, problem))
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


def boolean(value: Any, name: str) -> bool:
    """True or false (1, 0 and "yes" are refused)."""
    if not isinstance(value, bool):
        raise ConfigError(f"{name} must be true or false, got {value!r}")
    return value


def pair(rule: Rule, ordered: bool = True) -> Rule:
    """The rule of a [min, max] pair, each end checked by ``rule`` (``ordered``: min <= max); a tuple."""
    def checked(value: Any, name: str) -> tuple:
        if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__len__") or len(value) != 2:
            raise ConfigError(f"{name} must be a [min, max] pair, got {value!r}")
        lo, hi = (rule(v, name) for v in value)
        if ordered and lo > hi:
            raise ConfigError(f"{name} has min > max, got {value!r}")
        return lo, hi
    return checked


_Settings = TypeVar("_Settings", bound="SectionSettings")


def _section_type(f: dataclasses.Field) -> type[SectionSettings] | None:
    """The settings class of a field that holds a nested section (``section(Cls)``), else None."""
    factory = f.default_factory
    if isinstance(factory, type) and issubclass(factory, SectionSettings):
        return factory
    return None


def section(cls: type[SectionSettings]) -> Any:
    """A dataclass field holding the nested section ``cls`` (its defaults by default)."""
    return dataclasses.field(default_factory=cls)


class SectionSettings:
    """Base of the frozen dataclasses that hold one config section's settings (a stage's
    section of ``configs/infer.yaml``, as ``icp_refine``; the ``train`` section of a training
    recipe; a whole config, whose fields are its sections): each field a key of the
    section, its default the section's default. A field made by :func:`section` holds a
    nested section (its own settings class).

    Subclasses set ``SECTION`` (the section's dotted name, in messages; "" for a whole
    config) and ``RULES`` (field -> a :data:`Rule`); construction checks every field named
    there and keeps the checked value, so a bad value is a ConfigError naming
    ``SECTION.field``. :func:`load_settings` is the one loader of a command's settings.
    """

    SECTION: ClassVar[str] = "settings"
    RULES: ClassVar[Mapping[str, Rule]] = {}

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # a nested section given as a mapping
            nested = _section_type(f)
            if nested is not None and not isinstance(getattr(self, f.name), nested):
                object.__setattr__(self, f.name, nested.from_mapping(getattr(self, f.name)))
        for name, rule in self.RULES.items():
            object.__setattr__(self, name, rule(getattr(self, name), self.key(name)))

    @classmethod
    def key(cls, name: str) -> str:
        """The dotted name of this section's key ``name`` ("train.lr"), as messages write it."""
        return f"{cls.SECTION}.{name}" if cls.SECTION else name

    @classmethod
    def from_mapping(cls: type[_Settings], values: Mapping[str, Any] | None) -> _Settings:
        """Settings from a section's mapping (None: the defaults); nested sections from their
        mappings; an unknown key is a ConfigError naming it (``section.key``) and the known ones."""
        if values is None:
            values = {}
        if not isinstance(values, Mapping):
            raise ConfigError(f"{cls.SECTION or 'the config'} must be a mapping of settings, got {values!r}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted((k for k in values if k not in fields), key=str)
        if unknown:
            where = f" in {cls.SECTION}" if cls.SECTION else ""
            raise ConfigError(f"unknown setting {cls.key(str(unknown[0]))} (known{where}: "
                              f"{', '.join(sorted(fields))})")
        given = {}
        for name, value in values.items():
            nested = _section_type(fields[name])
            given[name] = nested.from_mapping(value) if nested is not None else value
        return cls(**given)

    def to_dict(self) -> dict[str, Any]:
        """The settings as plain data (nested sections as dicts, tuples as lists): what a
        YAML file or a checkpoint holds, and :meth:`from_mapping` reads back."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}


def _plain(value: Any) -> Any:
    if isinstance(value, SectionSettings):
        return value.to_dict()
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def changed_settings(settings: SectionSettings) -> dict[str, Any]:
    """The keys of ``settings`` that differ from its class's defaults, nested as a config
    file writes them (what a recipe holds)."""
    return _differences(settings.to_dict(), type(settings)().to_dict())


def _differences(values: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for key, value in values.items():
        default = defaults.get(key)
        if isinstance(value, dict) and isinstance(default, dict):
            inner = _differences(value, default)
            if inner:
                out[key] = inner
        elif value != default:
            out[key] = value
    return out


_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d+")


def parse_assignment(item: str) -> dict[str, Any]:
    """``section.key=value`` (the value parsed as YAML) as a nested mapping ``{section: {key: value}}``."""
    if "=" not in item:
        raise ConfigError(f"--set {item}: expected section.key=value")
    dotted, raw = item.split("=", 1)
    keys = dotted.strip().split(".")
    if not all(keys):
        raise ConfigError(f"--set {item}: empty key")
    shown = item if len(item) <= 80 else item[:60] + "..." + item[-12:]
    value: Any = parse_yaml_text(raw, f"--set {shown}", lambda problem: ConfigError(
        f"--set {shown}: {problem.replace('malformed YAML', 'malformed value')}"))
    if len(keys) > MAX_NESTING:
        raise ConfigError(f"--set {shown}: key nested deeper than {MAX_NESTING} levels")
    if isinstance(value, str) and _NUMBER.fullmatch(raw.strip()):
        value = float(raw)  # 1e-3: a number (YAML 1.1 reads it as text)
    for key in reversed(keys):
        value = {key: value}
    return value


def settings_layers(config: str | Path | Mapping[str, Any] | None = None,
                    assignments: list[str] | tuple[str, ...] = (), base: Mapping[str, Any] | None = None,
                    ) -> list[tuple[str, Mapping[str, Any]]]:
    """Each source of a command's settings read once, in the order they apply: (where it came
    from, as messages name it; its nested mapping): ``base`` ("recorded config"), ``config`` (a
    packaged config's name, a YAML file or a mapping), then each ``section.key=value`` of
    ``assignments`` ("--set ITEM").

    Raises:
        ConfigError: a malformed ``--set`` item. InputFileError: an unreadable or malformed file.
    """
    layers: list[tuple[str, Mapping[str, Any]]] = []
    if base is not None:
        layers.append(("recorded config", base))
    if isinstance(config, Mapping):
        layers.append(("config", config))
    elif config is not None:
        path = config_path(config)
        layers.append((str(config) if path.parent == CONFIG_DIR and not str(config).endswith(".yaml")
                       else str(path), load_yaml(path)))
    for item in assignments:
        layers.append((f"--set {item}", parse_assignment(item)))
    return layers


def settings_from_layers(cls: type[_Settings], layers: Sequence[tuple[str, Mapping[str, Any]]]) -> _Settings:
    """``cls``'s defaults with each layer of :func:`settings_layers` deep-merged over the ones
    before (a file or ``--set`` only holds what it changes), each checked as it comes: a bad
    key or value is a ConfigError naming the layer and ``section.key``."""
    settings = cls()
    values = settings.to_dict()
    for where, layer in layers:
        values = merge(values, dict(layer))
        try:
            settings = cls.from_mapping(values)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    return settings


def load_settings(cls: type[_Settings], config: str | Path | Mapping[str, Any] | None = None,
                  assignments: list[str] | tuple[str, ...] = (), base: Mapping[str, Any] | None = None,
                  ) -> _Settings:
    """The one loader of a command's settings: ``cls``'s defaults, then ``base`` (e.g. the
    config a checkpoint recorded), then ``config`` (a packaged config's name, a YAML file or a
    mapping) and last each ``section.key=value`` of ``assignments``
    (:func:`settings_from_layers` over :func:`settings_layers`).

    Raises:
        ConfigError: one line naming where the bad key or value came from (the file, or the
            ``--set`` item) and ``section.key`` (unknown key, or the value's rule).
        InputFileError: an unreadable or malformed file.
    """
    return settings_from_layers(cls, settings_layers(config, assignments, base))


def settings_yaml(settings: SectionSettings) -> str:
    """The settings as YAML text, in field order (what ``dope-hope settings CMD`` prints)."""
    return yaml.safe_dump(settings.to_dict(), sort_keys=False)
