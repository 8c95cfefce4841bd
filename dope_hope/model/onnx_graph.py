"""OnnxGraph: open a dope-hope ``.onnx`` file with onnxruntime and run it to the model's maps.

The reading half of the file contract (:mod:`dope_hope.model.onnx_contract`): the session is
built once, the graph's inputs/outputs are checked against the layout and the object count of
the metadata, and :meth:`OnnxGraph.run` returns belief / affinity maps in the model's own
channel order whatever the layout (isaac-ros: the predictor's batch converted to the
encoder's normalization, images run one at a time, the output split and un-permuted). Used by
the predictor's backend (:class:`dope_hope.inference.onnx_backend.OnnxBackend`) and by INT8
calibration (:mod:`dope_hope.export.int8`).

Anything else (random bytes, a truncated file, an ONNX model with other inputs/outputs or
without dope-hope metadata) raises :class:`~dope_hope.errors.ModelFileError` with one line
naming the file and the problem.
"""
from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dope_hope.errors import ConfigError, DopeHopeError, ModelFileError
from dope_hope.io.paths import require_file, weights_format
from dope_hope.model.onnx_contract import (
    CHANNEL_ORDER_KEY,
    LAYOUT_NAMES,
    NUM_BELIEF,
    OnnxModelInfo,
    output_channels,
    output_order,
    parse_channel_order,
)

#: onnxruntime graph optimization levels by name.
OPTIMIZATION_LEVELS = ("disable", "basic", "extended", "all")


def require_model_file(path: Path, what: str = "weights file") -> str:
    """ModelFileError unless ``path`` is a regular file; returns its io.paths.weights_format."""
    try:
        require_file(path, what)
    except DopeHopeError as exc:
        raise ModelFileError(path, exc.problem) from None
    return weights_format(path)


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
    import onnxruntime as ort  # noqa: PLC0415 (onnxruntime (slow to import) only when a graph runs)

    available = ort.get_available_providers()
    return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in available else []) + ["CPUExecutionProvider"]


def _session_options(threads: int | None, optimization: str, spinning: bool):
    import onnxruntime as ort  # noqa: PLC0415 (onnxruntime (slow to import) only when a graph runs)

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
    return opts


class OnnxGraph:
    """A dope-hope ``.onnx`` file opened with onnxruntime.

    Args:
        path: the ``.onnx`` file (native or isaac-ros layout, fp32 or INT8).
        threads: onnxruntime intra-op threads (None: onnxruntime's default, all cores).
        providers: execution providers in order of preference (None: CUDA when this
            onnxruntime has it, then CPU). Unavailable ones are dropped with a warning.
        optimization: graph optimization level, one of "disable", "basic", "extended", "all".
        spinning: let idle intra-op threads spin between runs (onnxruntime's default). Off by
            default: between two images the single-threaded decode / PnP / -LS runs, and
            spinning threads would take its core (bench/RESULTS.md "Video stream").

    Attributes: ``info`` (:class:`OnnxModelInfo`), ``layout``, ``path``, ``session`` (built
    once, reused by every :meth:`run`), ``providers`` (those in use), ``fixed_input_hw``.
    """

    def __init__(self, path: str | os.PathLike, threads: int | None = None,
                 providers: Sequence[str] | None = None, optimization: str = "all", spinning: bool = False):
        import onnxruntime as ort  # noqa: PLC0415 (onnxruntime (slow to import) only when a graph runs)

        self.path = Path(path)
        require_model_file(self.path, "ONNX file")
        opts = _session_options(threads, optimization, spinning)
        available = set(ort.get_available_providers())
        wanted = list(providers) if providers else default_providers()
        usable = [p for p in wanted if p in available]
        if len(usable) < len(wanted):
            missing = [p for p in wanted if p not in available]
            warnings.warn(f"onnxruntime providers not available here, skipped: {', '.join(missing)}",
                          RuntimeWarning, stacklevel=3)
        if "CPUExecutionProvider" not in usable:
            usable.append("CPUExecutionProvider")
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=usable)
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise ModelFileError(self.path, _ort_problem(exc)) from None
        self.providers = self.session.get_providers()
        self.layout = self._graph_layout()
        meta = self.session.get_modelmeta().custom_metadata_map
        self.info = OnnxModelInfo.from_metadata(meta, self.path)
        if self.info.layout != self.layout:
            raise ModelFileError(self.path, f"metadata says layout {self.info.layout!r} but the graph "
                                            f"has the {self.layout!r} inputs/outputs")
        self._check_shapes()
        i = self.info
        graph_hw = tuple(self.session.get_inputs()[0].shape[2:])
        if all(isinstance(v, int) for v in graph_hw) and graph_hw != tuple(i.fixed_input_hw or ()):
            said = "any size" if i.fixed_input_hw is None else f"{i.fixed_input_hw[0]}x{i.fixed_input_hw[1]}"
            raise ModelFileError(self.path, f"metadata says the input is {said} but the graph takes "
                                            f"{graph_hw[0]}x{graph_hw[1]} only (fixed_input_hw disagrees "
                                            "with the graph)")
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

    def _graph_layout(self) -> str:
        ins = tuple(x.name for x in self.session.get_inputs())
        outs = tuple(x.name for x in self.session.get_outputs())
        for layout, (want_in, want_out) in LAYOUT_NAMES.items():
            if ins == want_in and outs == want_out:
                return layout
        raise ModelFileError(self.path, f"not a dope-hope model: inputs {list(ins)}, outputs "
                                        f"{list(outs)} (expected image -> belief, affinity or "
                                        "the isaac-ros input -> output)")

    def _check_shapes(self) -> None:
        shape = self.session.get_inputs()[0].shape
        out_shapes = [o.shape for o in self.session.get_outputs()]
        channels = output_channels(self.layout, self.info.num_objects)
        ok = len(shape) == 4 and shape[1] == 3 and all(
            len(s) == 4 and s[1] == c for s, c in zip(out_shapes, channels))
        if not ok:
            raise ModelFileError(self.path, f"not a dope-hope model: input shape {shape}, output shapes "
                                            f"{out_shapes} (expected (N, 3, H, W) -> {channels} channels "
                                            f"for {self.info.num_objects} object(s))")

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
        """(N, 3, H, W) float32 normalized with ``mean/std`` -> belief (N, 9K, h, w), affinity
        (N, 16K, h, w) for K objects, in the model's channel order."""
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
