"""The ROS 2 node's parameters: its own (:class:`NodeSettings`: the models, the inputs, the
outputs) and every inference setting of ``infer`` under its ``--set`` name (``min_score``,
``decode.threshold``, ``line_search.search``, ...: :func:`inference_parameter_names`), so a
parameters YAML nests them as ``dope-hope settings infer`` prints them.

A parameter left unset keeps the default (as a key ``--set`` does not name: a model's own
score threshold holds unless ``min_score`` is given). A value ROS cannot type (a nested list,
null) is given as a YAML string (``-p 'height:="null"'``), as ``--set`` takes it. Only
:data:`RUNTIME_PARAMETERS` change while the node runs (:func:`checked_min_score`,
:func:`checked_classes`); the others are read at start.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

from dope_hope.config import (
    SectionSettings,
    boolean,
    finite_float,
    merge,
    one_of,
    parse_assignment,
    positive_float,
    whole_number,
)
from dope_hope.errors import ConfigError
from dope_hope.inference.options import InferenceOptions

#: Parameters that change while the node runs (``ros2 param set``).
RUNTIME_PARAMETERS = ("min_score", "classes")


def string_list(value: Any, name: str) -> tuple[str, ...]:
    """One string or a list of strings (a ROS string array) as a tuple."""
    if isinstance(value, str):
        return (value,) if value else ()
    if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        return tuple(v for v in value if v)
    raise ConfigError(f"{name} must be a string or a list of strings, got {value!r}")


@dataclass(frozen=True)
class NodeSettings(SectionSettings):
    """The node's own parameters (read at start, except ``classes``).

    weights: model files (none: the shipped demo model); mesh, mesh_units, up_axis, start:
    ``infer``'s --mesh, --mesh-units, --up-axis, --start (new objects: meshes without
    weights); classes: the objects reported (none: all), changeable at run time; backend,
    device, threads (0: PyTorch's default): as ``infer``'s. image_transport: raw (Image on the
    image topic) or compressed (CompressedImage on ``<image topic>/compressed``);
    input_reliability: the inputs' QoS reliability, best_effort (sensor-data QoS) or reliable
    (large raw images that best effort loses in fragments, see docs/commands/ros2.md); use_depth:
    subscribe to the aligned depth; depth_tolerance_ms: the largest image-to-depth stamp
    difference; depth_wait_ms: how long an image waits for its depth while depth flows;
    depth_calibration: depth multiplied by it; track: stable track ids and smoothed poses
    (the tracking section); overlay: publish the overlay image.
    """

    SECTION = ""
    RULES = {"weights": string_list, "mesh": string_list, "mesh_units": string_list, "up_axis": string_list,
             "classes": string_list, "backend": one_of("auto", "torch", "onnx"),
             "threads": lambda v, n: whole_number(v, n, 0), "image_transport": one_of("raw", "compressed"),
             "input_reliability": one_of("best_effort", "reliable"),
             "use_depth": boolean, "depth_tolerance_ms": positive_float, "depth_wait_ms": positive_float,
             "depth_calibration": positive_float, "track": boolean, "overlay": boolean}

    weights: tuple[str, ...] = ()
    mesh: tuple[str, ...] = ()
    mesh_units: tuple[str, ...] = ()
    up_axis: tuple[str, ...] = ()
    start: str = ""
    classes: tuple[str, ...] = ()
    backend: str = "auto"
    device: str = "cpu"
    threads: int = 0
    image_transport: str = "raw"
    input_reliability: str = "best_effort"
    use_depth: bool = True
    depth_tolerance_ms: float = 15.0
    depth_wait_ms: float = 500.0
    depth_calibration: float = 1.0
    track: bool = False
    overlay: bool = True


def node_parameter_names() -> list[str]:
    """The names of :class:`NodeSettings`' parameters."""
    return [f.name for f in fields(NodeSettings)]


def _flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def inference_parameter_names() -> dict[str, Any]:
    """{dotted name: default} of every inference setting (``min_score``, ``decode.threshold``, ...)."""
    return _flatten(InferenceOptions().to_dict())


def plain_value(value: Any) -> Any:
    """A parameter's value as plain Python (a ROS array as a list)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return [plain_value(v) for v in value]


def given_inference_settings(values: Mapping[str, Any], base: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The inference settings the parameters set, nested as a settings file holds them, over
    ``base`` (the command's --config / --set); checked (ConfigError naming the parameter).

    ``values``: {dotted name: value} of the parameters given (unset ones left out); a string
    for a setting whose default is not a string is read as YAML.
    """
    defaults = inference_parameter_names()
    given = dict(base or {})
    for name, value in values.items():
        value = plain_value(value)
        if isinstance(value, str) and not isinstance(defaults.get(name), str):
            nested = parse_assignment(f"{name}={value}")
        else:
            nested = value
            for key in reversed(name.split(".")):
                nested = {key: nested}
        given = merge(given, nested)
    InferenceOptions.from_mapping(given)
    return given


def checked_min_score(value: Any) -> float | None:
    """A new ``min_score`` (None: unset, each object's own again); ConfigError for a non-number."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"min_score must be a number, got {value!r}")
    return finite_float(value, "min_score")


def checked_classes(value: Any, known: Sequence[str]) -> tuple[str, ...] | None:
    """A new class list (None: all of ``known``); ConfigError naming a class the node does not detect."""
    if value is None:
        return None
    names = string_list(plain_value(value), "classes")
    lower = {k.lower(): k for k in known}
    for name in names:
        if name.lower() not in lower:
            raise ConfigError(f"classes: {name!r} is not an object this node detects (known: {', '.join(known)})")
    return tuple(lower[n.lower()] for n in names) or None
