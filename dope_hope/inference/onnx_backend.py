"""OnnxBackend: run an exported dope-hope ``.onnx`` model with onnxruntime (no checkpoint).

A dope-hope ONNX file is self-describing: everything the predictor needs (object class,
cuboid size, keypoint order, object frame, normalization, map stride, input size) lives in
the model's ``metadata_props`` under the keys of :class:`OnnxModelInfo` (prefix
``dope_hope.``), written by :mod:`dope_hope.export`. Two graph layouts are accepted:

- ``native``: input ``image`` (N, 3, H, W) float32 normalized with the model's mean/std;
  outputs ``belief`` (N, 9, h, w) and ``affinity`` (N, 16, h, w) of the last stage.
- ``isaac-ros``: what Isaac ROS DOPE's TensorRT node + decoder consume: input ``input``
  (1, 3, H, W) normalized with the Isaac ROS image encoder's mean/std (recorded as
  ``dope_hope.input_mean/std``), output ``output`` (1, 25, H/8, W/8) = belief then affinity,
  channels in an Isaac ROS release's vertex order (metadata ``dope_hope.isaac_ros.channel_order``,
  :func:`parse_channel_order`, written by :mod:`dope_hope.export.isaac_ros`; absent = the
  model's order). This backend converts the predictor's batch to that normalization, runs
  images one at a time (batch 1), splits the output and puts the channels back in the model's
  keypoint order (:func:`output_order`).

Anything else (random bytes, a truncated file, an ONNX model with other inputs/outputs or
without dope-hope metadata) raises :class:`~dope_hope.errors.ModelFileError` with one line
naming the file and the problem.
"""
from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.model.info import ModelInfo

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
#: onnxruntime graph optimization levels by name.
OPTIMIZATION_LEVELS = ("disable", "basic", "extended", "all")


@dataclass
class OnnxModelInfo(ModelInfo):
    """The metadata of a dope-hope ONNX file (``metadata_props``, all values strings there).

    The :class:`~dope_hope.model.info.ModelInfo` fields (class_name, size_m, frame,
    keypoint_order, mean, std, input_hw, and min_score: written only when the model records
    one), plus:
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
            if key == "extra" or (key in self._OPTIONAL_FLOAT_FIELDS and value is None):
                continue
            if key in self._OPTIONAL_FLOAT_FIELDS:
                value = repr(float(value))
            if key in self._JSON_FIELDS:
                value = json.dumps(None if value is None else [float(v) if key not in (
                    "input_hw", "fixed_input_hw") else int(v) for v in value])
            out[f"{META_PREFIX}{key}"] = str(value)
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
        names = [f for f in cls.__dataclass_fields__ if f != "extra"]
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
        known = {f"{META_PREFIX}{n}" for n in names} | {f"{META_PREFIX}format", f"{META_PREFIX}format_version"}
        values["extra"] = {k[len(META_PREFIX):]: v for k, v in meta.items()
                           if k.startswith(META_PREFIX) and k not in known}
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


def _ort_problem(exc: BaseException, limit: int = 160) -> str:
    """One line from an onnxruntime load error (its prefixes and C++ source location dropped)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    # "[ONNXRuntimeError] : 7 : INVALID_PROTOBUF : Load model from X failed:<detail>"
    if "failed:" in text:
        text = text.split("failed:", 1)[1].strip()
    # "/onnxruntime_src/.../model.cc:256 onnxruntime::Model::Model(...) <detail>"
    text = re.sub(r"^/\S+:\d+\s+[^(]*\([^)]*\)\s*", "", text)
    if type(exc).__name__ == "InvalidProtobuf" or "Protobuf parsing failed" in text:
        return "not a readable ONNX model: truncated or corrupt (protobuf parsing failed)"
    return f"onnxruntime cannot load it: {text[:limit]}"


def default_providers() -> list[str]:
    """CUDA (if this onnxruntime build has it) then CPU."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in available else []) + ["CPUExecutionProvider"]


class OnnxBackend:
    """:class:`dope_hope.inference.predictor.MapBackend` over an exported ``.onnx`` file (onnxruntime).

    Args:
        path: the ``.onnx`` file (native or isaac-ros layout, fp32 or INT8).
        threads: onnxruntime intra-op threads (None: onnxruntime's default, all cores).
        providers: execution providers in order of preference (None: CUDA when this
            onnxruntime has it, then CPU). Unavailable ones are dropped with a warning.
        optimization: graph optimization level, one of "disable", "basic", "extended", "all".
        spinning: let idle intra-op threads spin between runs (onnxruntime's default). Off by
            default: between two images the single-threaded decode / PnP / -LS runs, and
            spinning threads would take its core (bench/RESULTS.md "Video stream").

    Attributes: the MapBackend metadata (stride, class_name, size_m (3,) m, keypoint_order,
    frame, mean, std, input_hw) plus ``fixed_input_hw`` ((H, W) for a static graph, else
    None), ``info`` (:class:`OnnxModelInfo`), ``layout``, ``source`` (the path), ``session``
    (built once, reused by every :meth:`run`) and ``providers`` (those in use).
    """

    def __init__(self, path: str | os.PathLike, threads: int | None = None,
                 providers: Sequence[str] | None = None, optimization: str = "all", spinning: bool = False):
        import onnxruntime as ort

        self.path = Path(path)
        self.source = str(path)
        from dope_hope.inference.backends import require_model_file

        require_model_file(self.path, "ONNX file")
        if optimization not in OPTIMIZATION_LEVELS:
            raise ConfigError(f"optimization must be one of {', '.join(OPTIMIZATION_LEVELS)}, "
                              f"got {optimization!r}")
        if threads is not None and int(threads) < 0:
            raise ConfigError(f"threads must be >= 0, got {threads!r}")
        opts = ort.SessionOptions()
        opts.graph_optimization_level = {
            "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
            "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
            "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
            "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        }[optimization]
        if threads:
            opts.intra_op_num_threads = int(threads)
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
        opts.log_severity_level = 3  # errors only: a bad file becomes our one-line error
        available = set(ort.get_available_providers())
        wanted = list(providers) if providers else default_providers()
        usable = [p for p in wanted if p in available]
        if len(usable) < len(wanted):
            missing = [p for p in wanted if p not in available]
            warnings.warn(f"onnxruntime providers not available here, skipped: {', '.join(missing)}",
                          RuntimeWarning, stacklevel=2)
        if "CPUExecutionProvider" not in usable:
            usable.append("CPUExecutionProvider")
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=usable)
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise ModelFileError(self.path, _ort_problem(exc)) from None
        self.providers = self.session.get_providers()
        self._check_io()
        meta = self.session.get_modelmeta().custom_metadata_map
        self.info = OnnxModelInfo.from_metadata(meta, self.path)
        if self.info.layout != self.layout:
            raise ModelFileError(self.path, f"metadata says layout {self.info.layout!r} but the graph "
                                            f"has the {self.layout!r} inputs/outputs")
        i = self.info
        graph_hw = tuple(self.session.get_inputs()[0].shape[2:])
        if all(isinstance(v, int) for v in graph_hw) and graph_hw != tuple(i.fixed_input_hw or ()):
            said = "any size" if i.fixed_input_hw is None else f"{i.fixed_input_hw[0]}x{i.fixed_input_hw[1]}"
            raise ModelFileError(self.path, f"metadata says the input is {said} but the graph takes "
                                            f"{graph_hw[0]}x{graph_hw[1]} only (fixed_input_hw disagrees "
                                            "with the graph)")
        self.stride: int = i.stride
        self.class_name: str = i.class_name
        self.size_m: np.ndarray = np.asarray(i.size_m, dtype=np.float64)
        self.keypoint_order: str = i.keypoint_order
        self.frame: str = i.frame
        self.mean: tuple[float, float, float] = tuple(i.mean)
        self.std: tuple[float, float, float] = tuple(i.std)
        self.input_hw: tuple[int, int] | None = i.input_hw
        self.fixed_input_hw: tuple[int, int] | None = i.fixed_input_hw
        # x_graph = x_model * a + b converts the predictor's batch to the graph's normalization.
        m, s = np.asarray(i.mean, np.float32), np.asarray(i.std, np.float32)
        im, is_ = np.asarray(i.input_mean, np.float32), np.asarray(i.input_std, np.float32)
        self._a = (s / is_).reshape(1, 3, 1, 1)
        self._b = ((m - im) / is_).reshape(1, 3, 1, 1)
        self._identity_input = bool(np.allclose(m, im) and np.allclose(s, is_))
        #: graph output channel c holds model map channel _order[c] (isaac-ros); None = same order.
        order = output_order(parse_channel_order(i.extra.get(CHANNEL_ORDER_KEY)))
        self._order = None if np.array_equal(order, np.arange(order.size)) else order

    def describe(self) -> str:
        """One line: the file's precision and, for INT8, its keypoint drift from the fp32 model
        as measured at export (``dope-hope export --int8`` records it in the metadata)."""
        if self.info.precision != "int8":
            return f"{self.path.name}: ONNX {self.info.precision}"
        try:
            drift = json.loads(self.info.extra.get("quantization", "{}")).get("drift") or {}
        except (json.JSONDecodeError, AttributeError):
            drift = {}
        if not drift.get("keypoints_compared"):
            return f"{self.path.name}: ONNX INT8 (no keypoint drift recorded at export)"
        return (f"{self.path.name}: ONNX INT8, keypoints vs fp32 at export: median "
                f"{drift['median_px']:.2f} px, p95 {drift['p95_px']:.2f} px over "
                f"{drift['keypoints_compared']} keypoints of {drift['images']} images")

    def _check_io(self) -> None:
        ins = tuple(x.name for x in self.session.get_inputs())
        outs = tuple(x.name for x in self.session.get_outputs())
        for layout, (want_in, want_out) in LAYOUT_NAMES.items():
            if ins == want_in and outs == want_out:
                self.layout = layout
                break
        else:
            raise ModelFileError(self.path, f"not a dope-hope model: inputs {list(ins)}, outputs "
                                            f"{list(outs)} (expected image -> belief, affinity or "
                                            "the isaac-ros input -> output)")
        shape = self.session.get_inputs()[0].shape
        out_shapes = [o.shape for o in self.session.get_outputs()]
        channels = [NUM_BELIEF, NUM_AFFINITY] if self.layout == "native" else [NUM_BELIEF + NUM_AFFINITY]
        ok = len(shape) == 4 and shape[1] == 3 and all(
            len(s) == 4 and s[1] == c for s, c in zip(out_shapes, channels))
        if not ok:
            raise ModelFileError(self.path, f"not a dope-hope model: input shape {shape}, output shapes "
                                            f"{out_shapes} (expected (N, 3, H, W) -> {channels} channels)")

    def graph_input(self, batch: np.ndarray) -> np.ndarray:
        """(N, 3, H, W) normalized with ``mean/std`` -> the graph input's normalization."""
        x = np.ascontiguousarray(batch, dtype=np.float32)
        if self._identity_input:
            return x
        return (x * self._a + self._b).astype(np.float32)

    def feeds(self, batch: np.ndarray) -> list[dict[str, np.ndarray]]:
        """onnxruntime feed dicts for a model-normalized batch (one per image for isaac-ros)."""
        x = self.graph_input(batch)
        name = self.session.get_inputs()[0].name
        if self.layout == "isaac-ros":
            return [{name: x[i:i + 1]} for i in range(len(x))]
        return [{name: x}]

    def run(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3, H, W) float32 normalized with ``mean/std`` -> belief (N, 9, h, w), affinity (N, 16, h, w)."""
        batch = np.asarray(batch)
        if batch.ndim != 4 or batch.shape[1] != 3:
            raise ValueError(f"expected an (N, 3, H, W) batch, got shape {batch.shape}")
        if self.fixed_input_hw is not None and tuple(batch.shape[2:]) != tuple(self.fixed_input_hw):
            raise ValueError(f"{self.path.name} takes {self.fixed_input_hw[0]}x{self.fixed_input_hw[1]} "
                             f"inputs only, got {batch.shape[2]}x{batch.shape[3]}")
        results = [self.session.run(None, feed) for feed in self.feeds(batch)]
        if self.layout == "isaac-ros":
            out = np.concatenate([r[0] for r in results], axis=0)
            maps = out if self._order is None else np.empty_like(out)
            if self._order is not None:
                maps[:, self._order] = out
            return maps[:, :NUM_BELIEF], maps[:, NUM_BELIEF:]
        belief, affinity = results[0]
        return belief, affinity

    def __repr__(self) -> str:
        size = "dynamic" if self.fixed_input_hw is None else f"{self.fixed_input_hw[0]}x{self.fixed_input_hw[1]}"
        return (f"OnnxBackend({self.path.name!r}, class_name={self.class_name!r}, layout={self.layout!r}, "
                f"precision={self.info.precision!r}, input={size}, providers={self.providers})")
