"""The dope-hope ONNX file contract: graph layouts, tensor names, output channel order and
the ``metadata_props`` keys (:class:`OnnxModelInfo`), shared by the writer
(:mod:`dope_hope.export`) and the reader (:mod:`dope_hope.model.onnx_graph`,
:class:`dope_hope.inference.onnx_backend.OnnxBackend`). No onnx / onnxruntime import here.

A dope-hope ONNX file is self-describing: everything the predictor needs (the objects with
their class, cuboid size and symmetries, keypoint order, object frame, normalization, map
stride, input size) lives in the model's ``metadata_props`` under the keys of
:class:`OnnxModelInfo` (prefix ``dope_hope.``). Two graph layouts:

- ``native``: input ``image`` (N, 3, H, W) float32 normalized with the model's mean/std;
  outputs ``belief`` (N, 9K, h, w) and ``affinity`` (N, 16K, h, w) of the last stage for a
  model of K objects (``dope_hope.objects``: a JSON list of ``{class_name, size_m, frame,
  symmetries[, min_score]}`` in channel-group order; a file without the key is the one object
  ``class_name`` / ``size_m``, as every file written before the key existed).
- ``isaac-ros``: what Isaac ROS DOPE's TensorRT node + decoder consume, always ONE object:
  input ``input`` (1, 3, H, W) normalized with the Isaac ROS image encoder's mean/std
  (recorded as ``dope_hope.input_mean/std``), output ``output`` (1, 25, H/8, W/8) = belief then
  affinity, channels in an Isaac ROS release's vertex order (metadata
  ``dope_hope.isaac_ros.channel_order``, :func:`parse_channel_order`; absent = the model's
  order). :func:`output_order` maps graph channels back to the model's keypoint order.
"""
from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, asdict, dataclass, field
from typing import Any

import numpy as np

from dope_hope.errors import ModelFileError
from dope_hope.model.info import ModelInfo, objects_from_entries

#: ``metadata_props`` key prefix and the format marker of a dope-hope ONNX file.
META_PREFIX = "dope_hope."
ONNX_FORMAT = "dope-hope-onnx"
ONNX_FORMAT_VERSION = 1
LAYOUTS = ("native", "isaac-ros")
#: Graph tensor names per layout: (inputs, outputs).
LAYOUT_NAMES = {
    "native": (("image",), ("belief", "affinity")),
    "isaac-ros": (("input",), ("output",)),
}
NUM_BELIEF, NUM_AFFINITY = 9, 16
#: ``extra`` key of an isaac-ros file's belief channel order (JSON list of 9 ints).
CHANNEL_ORDER_KEY = "isaac_ros.channel_order"
#: Metadata key (after the prefix) of the object list (JSON).
OBJECTS_KEY = "objects"


@dataclass
class OnnxModelInfo(ModelInfo):
    """The metadata of a dope-hope ONNX file (``metadata_props``, all values strings there).

    The :class:`~dope_hope.model.info.ModelInfo` fields (class_name, size_m, frame,
    keypoint_order, mean, std, input_hw, objects (key ``objects``, JSON), and min_score:
    written only when the model records one), plus:
    input_mean, input_std: the normalization the GRAPH input expects (= mean/std for the
        native layout; the Isaac ROS encoder's for the isaac-ros layout, converted in-graph).
    stride: image px per map cell. head: 50 | 400 | 100. arch: "dope" | "lite".
    layout: "native" | "isaac-ros". input_hw: (H, W) training input size or None.
    fixed_input_hw: (H, W) the only size the graph takes, or None (dynamic H, W).
    opset: ONNX opset. precision: "fp32" | "int8". version: dope-hope version that wrote it.
    exporter, source: free text (exporter used; the weights file exported).
    extra: other ``dope_hope.*`` keys (e.g. isaac_ros.object_dimensions_cm, quantization).
    """

    input_mean: tuple[float, float, float]
    input_std: tuple[float, float, float]
    stride: int
    head: int
    arch: str
    layout: str
    fixed_input_hw: tuple[int, int] | None
    opset: int
    precision: str = "fp32"
    version: str = ""
    exporter: str = ""
    source: str = ""
    extra: dict[str, str] = field(default_factory=dict)

    _JSON_FIELDS = ("size_m", "mean", "std", "input_mean", "input_std", "input_hw", "fixed_input_hw")
    _INT_FIELDS = ("stride", "head", "opset")
    #: Optional numbers: written only when set (a file without the key reads as None).
    _OPTIONAL_FLOAT_FIELDS = ("min_score",)

    def to_metadata(self) -> dict[str, str]:
        """``{"dope_hope.<key>": str}`` for ``metadata_props`` (lists as JSON)."""
        out = {f"{META_PREFIX}format": ONNX_FORMAT,
               f"{META_PREFIX}format_version": str(ONNX_FORMAT_VERSION)}
        for key, value in asdict(self).items():
            if key in ("extra", OBJECTS_KEY) or (key in self._OPTIONAL_FLOAT_FIELDS and value is None):
                continue
            if key in self._OPTIONAL_FLOAT_FIELDS:
                value = repr(float(value))
            if key in self._JSON_FIELDS:
                value = json.dumps(None if value is None else [float(v) if key not in (
                    "input_hw", "fixed_input_hw") else int(v) for v in value])
            out[f"{META_PREFIX}{key}"] = str(value)
        out[f"{META_PREFIX}{OBJECTS_KEY}"] = json.dumps(self.objects_metadata(), sort_keys=True)
        for key, value in self.extra.items():
            out[f"{META_PREFIX}{key}"] = str(value)
        return out

    @classmethod
    def from_metadata(cls, meta: Mapping[str, str], path: str | os.PathLike) -> OnnxModelInfo:
        """Parse and validate ``metadata_props``; ModelFileError (one line) if anything is off."""
        if meta.get(f"{META_PREFIX}format") != ONNX_FORMAT:
            raise ModelFileError(path, "an ONNX model without dope-hope metadata (no "
                                       f"'{META_PREFIX}format'); export it with `dope-hope export`")
        try:
            version = int(meta.get(f"{META_PREFIX}format_version", "0"))
        except ValueError:
            version = 0
        if version < 1 or version > ONNX_FORMAT_VERSION:
            raise ModelFileError(path, f"dope-hope ONNX format version {version!r} is not "
                                       f"supported (this dope-hope reads 1..{ONNX_FORMAT_VERSION})")
        names = [f for f in cls.__dataclass_fields__ if f not in ("extra", OBJECTS_KEY)]
        values: dict[str, Any] = {}
        for name in names:
            key = f"{META_PREFIX}{name}"
            if key not in meta:
                if cls.__dataclass_fields__[name].default is not MISSING:  # optional key
                    continue
                raise ModelFileError(path, f"dope-hope metadata lacks '{key}'")
            raw = meta[key]
            try:
                if name in cls._JSON_FIELDS:
                    v = json.loads(raw)
                    values[name] = None if v is None else tuple(
                        int(x) if name.endswith("_hw") else float(x) for x in v)
                elif name in cls._INT_FIELDS:
                    values[name] = int(raw)
                elif name in cls._OPTIONAL_FLOAT_FIELDS:
                    values[name] = float(raw)
                else:
                    values[name] = raw
            except (ValueError, TypeError):
                raise ModelFileError(path, f"dope-hope metadata '{key}' = {raw[:40]!r} is malformed") from None
        known = {f"{META_PREFIX}{n}" for n in names} | {f"{META_PREFIX}format", f"{META_PREFIX}format_version",
                                                        f"{META_PREFIX}{OBJECTS_KEY}"}
        values["extra"] = {k[len(META_PREFIX):]: v for k, v in meta.items()
                           if k.startswith(META_PREFIX) and k not in known}
        raw_objects = meta.get(f"{META_PREFIX}{OBJECTS_KEY}")
        if raw_objects is not None:  # absent: the one object class_name / size_m (older files)
            try:
                entries = json.loads(raw_objects)
            except ValueError:
                entries = None
            if not isinstance(entries, list) or not entries:
                raise ModelFileError(path, f"dope-hope metadata '{META_PREFIX}{OBJECTS_KEY}' = "
                                           f"{raw_objects[:40]!r} is not a non-empty JSON list")
            values[OBJECTS_KEY], frame = objects_from_entries(entries, path)
            if frame != values.get("frame"):
                raise ModelFileError(path, f"dope-hope metadata: the objects' frame {frame!r} differs "
                                           f"from the model's {values.get('frame')!r}")
        info = cls(**values)
        info.validate(path)
        return info

    def validate(self, path: str | os.PathLike) -> None:
        """:meth:`ModelInfo.validate`, then the ONNX fields; ModelFileError if inconsistent."""
        super().validate(path)

        def bad(problem: str):
            raise ModelFileError(path, f"dope-hope metadata: {problem}")

        if self.layout not in LAYOUTS:
            bad(f"layout {self.layout!r} is not one of {', '.join(LAYOUTS)}")
        for name in ("input_mean", "input_std"):
            v = getattr(self, name)
            if v is None or len(v) != 3 or not np.all(np.isfinite(v)):
                bad(f"{name} must hold 3 finite numbers, got {v}")
        if min(self.input_std) <= 0:
            bad("input_std must be positive")
        if self.stride not in (1, 4, 8):
            bad(f"stride {self.stride} is not 1, 4 or 8")
        if self.fixed_input_hw is not None and (len(self.fixed_input_hw) != 2 or min(self.fixed_input_hw) < 1):
            bad(f"fixed_input_hw must be [H, W] or null, got {self.fixed_input_hw}")
        if self.layout == "isaac-ros" and (self.fixed_input_hw is None or self.stride != 8):
            bad("an isaac-ros model must have a fixed input size and stride 8")
        if self.layout == "isaac-ros" and self.num_objects != 1:
            bad(f"an isaac-ros model holds one object, this one lists {self.num_objects}")
        try:
            parse_channel_order(self.extra.get(CHANNEL_ORDER_KEY))
        except (ValueError, TypeError) as exc:
            bad(f"{CHANNEL_ORDER_KEY}: {exc}")


def parse_channel_order(text: str | None) -> np.ndarray:
    """(9,) int belief order of an isaac-ros file: graph channel k = model channel ``order[k]``.

    ``text``: the ``isaac_ros.channel_order`` metadata (JSON); None (files written before it
    existed) = identity. ValueError unless a permutation of the corners 0..7 followed by 8.
    """
    if text is None:
        return np.arange(NUM_BELIEF)
    order = np.asarray(json.loads(text), dtype=np.int64)
    if order.shape != (NUM_BELIEF,) or order[-1] != NUM_BELIEF - 1 or \
            sorted(order[:-1].tolist()) != list(range(NUM_BELIEF - 1)):
        raise ValueError(f"not a permutation of the 8 corners followed by 8: {text[:60]}")
    return order


def output_order(order: Sequence[int]) -> np.ndarray:
    """(25,) int: graph output channel c = model map channel ``cat(belief, affinity)[idx[c]]``
    for a belief ``order`` (9,); corner k's affinity pair (2k, 2k + 1) moves with it."""
    order = np.asarray(order, dtype=np.int64)
    corners = order[:NUM_BELIEF - 1]
    affinity = np.stack([2 * corners, 2 * corners + 1], axis=1).reshape(-1)
    return np.concatenate([order, NUM_BELIEF + affinity])


def output_channels(layout: str, num_objects: int) -> list[int]:
    """Channels of each graph output: native [9K, 16K], isaac-ros [25] (one object)."""
    if layout == "native":
        return [NUM_BELIEF * num_objects, NUM_AFFINITY * num_objects]
    return [NUM_BELIEF + NUM_AFFINITY]
