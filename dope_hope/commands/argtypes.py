"""argparse ``type=`` functions: a bad value stops the command before any work, in one line
naming the option (``dope-hope infer: error: argument --threads: must be >= 1, got -1``).

Each wraps the one rule of :mod:`dope_hope.config` (numbers), :mod:`dope_hope.preprocess`
(working size) or :mod:`dope_hope.devices` (torch devices), so that the command line and
the config files and Python API refuse the same values.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from dope_hope import config
from dope_hope.errors import ConfigError

# preprocess and devices are imported inside the argument types: cli.py builds every
# command's --help from them, which must not pay for numpy or torch.


def _wrap(name: str, rule: Callable[[Any, str], Any], parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """An argparse type: ``parse(text)``, then ``rule(value, name)`` (a ConfigError becomes
    argparse's one-line "argument --flag: ..." error). ``name`` is what argparse reports."""
    def convert(text: str) -> Any:
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        try:
            return rule(value, "value")
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc).replace("value ", "", 1)) from None
    convert.__name__ = name
    return convert


def _int(text: str) -> int:
    return int(text, 10)


#: A finite number (e.g. --cx, --min-score).
finite_float = _wrap("finite_float", config.finite_float, float)
#: A finite number > 0 (--depth-scale, --fx, --time-budget ...).
positive_float = _wrap("positive_float", config.positive_float, float)
#: A finite number >= 0 (--lr: 0 freezes the weights).
nonnegative_float = _wrap("nonnegative_float", config.nonnegative_float, float)
#: A whole number >= 1 (--threads, --steps, --epochs, --batch-size ...).
positive_int = _wrap("positive_int", lambda v, name: config.whole_number(v, name, 1), _int)
#: A whole number >= 0 (--workers of train, --count).
nonnegative_int = _wrap("nonnegative_int", lambda v, name: config.whole_number(v, name, 0), _int)


def _working_side(value: int, name: str) -> int:
    from dope_hope.preprocess import check_working_side

    return check_working_side(value, name)


#: A network input height or width (pixels) within the predictor's bounds (--height, --width).
working_side = _wrap("working_side", _working_side, _int)


def _device(text: str, allow_auto: bool) -> str:
    from dope_hope.devices import check_device

    try:
        return check_device(text, allow_auto=allow_auto)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def device(text: str) -> str:
    """A torch device this machine has, or "auto" (train: CUDA when available)."""
    return _device(text, True)


def fixed_device(text: str) -> str:
    """A torch device this machine has ("cpu", "cuda", "cuda:1", ...)."""
    return _device(text, False)


def parse_named_values(values: list[str], flag: str, accepted: tuple[str, ...]) -> str | dict[str, str] | None:
    """``flag [NAME=]VALUE`` values: :func:`dope_hope.io.models_dir.named_object_values`."""
    from dope_hope.io.models_dir import named_object_values  # the catalog costs scipy: not for --help

    return named_object_values(values, flag, accepted)


def parse_mesh_units(values: list[str]) -> str | dict[str, str] | None:
    """``--mesh-units [NAME=]UNIT`` values (evaluate, infer): :func:`parse_named_values` of m, cm, mm."""
    return parse_named_values(values, "--mesh-units", ("m", "cm", "mm"))


#: --up-axis values: the keys of ``dope_hope.inference.mesh_start.UP_AXES``, named here without its imports.
UP_AXIS_NAMES = ("x", "y", "z", "-x", "-y", "-z")


def parse_up_axes(values: list[str]) -> str | dict[str, str] | None:
    """``--up-axis [NAME=]AXIS`` values (a new object's vertical mesh axis, infer):
    :func:`parse_named_values` of :data:`UP_AXIS_NAMES`."""
    return parse_named_values(values, "--up-axis", UP_AXIS_NAMES)
