"""YAML configs: find them by name, load them, apply command-line overrides.

A config is a plain nested dict. ``load_config("lite")`` reads ``dope_hope/configs/lite.yaml``,
which ships inside the package (the repository's top-level ``configs`` links to it); any other
argument is a path to a YAML file.
"""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

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


def apply_overrides(config: dict[str, Any], assignments: list[str]) -> dict[str, Any]:
    """Apply ``section.key=value`` strings (values parsed as YAML) to a copy of ``config``."""
    out = copy.deepcopy(config)
    for item in assignments:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.key=value")
        dotted, raw = item.split("=", 1)
        node = out
        keys = dotted.split(".")
        for key in keys[:-1]:
            node = node.setdefault(key, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r}: {key!r} is not a section")
        node[keys[-1]] = yaml.safe_load(raw)
    return out
