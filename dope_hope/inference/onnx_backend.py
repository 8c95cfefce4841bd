"""OnnxBackend: run an exported dope-hope ``.onnx`` model with onnxruntime (no checkpoint).

The file contract (layouts, tensor names, metadata keys, output channel order) is
:mod:`dope_hope.model.onnx_contract`; opening and running a file is
:class:`dope_hope.model.onnx_graph.OnnxGraph`. This module adds what the predictor's
:class:`~dope_hope.inference.backends.MapBackend` protocol asks of a backend: the model's
metadata as attributes. The contract's names are re-exported here for callers of this module.
"""
from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from dope_hope.model.info import ObjectInfo
from dope_hope.model.onnx_contract import (  # noqa: F401 - re-exported
    CHANNEL_ORDER_KEY,
    LAYOUT_NAMES,
    LAYOUTS,
    META_PREFIX,
    ONNX_FORMAT,
    ONNX_FORMAT_VERSION,
    OnnxModelInfo,
    output_order,
    parse_channel_order,
)
from dope_hope.model.onnx_graph import OPTIMIZATION_LEVELS, OnnxGraph, default_providers  # noqa: F401


class OnnxBackend(OnnxGraph):
    """:class:`dope_hope.inference.backends.MapBackend` over an exported ``.onnx`` file (onnxruntime).

    Args: those of :class:`~dope_hope.model.onnx_graph.OnnxGraph` (path, threads, providers,
    optimization, spinning).

    Attributes: the MapBackend metadata (stride, class_name, size_m (3,) m, objects,
    keypoint_order, frame, mean, std, input_hw) plus ``fixed_input_hw`` ((H, W) for a static
    graph, else None), ``info`` (:class:`OnnxModelInfo`), ``layout``, ``source`` (the path),
    ``session`` and ``providers`` (those in use).
    """

    def __init__(self, path: str | os.PathLike, threads: int | None = None,
                 providers: Sequence[str] | None = None, optimization: str = "all", spinning: bool = False):
        super().__init__(path, threads=threads, providers=providers, optimization=optimization, spinning=spinning)
        self.source = str(path)
        i = self.info
        self.stride: int = i.stride
        self.class_name: str = i.class_name
        self.size_m: np.ndarray = np.asarray(i.size_m, dtype=np.float64)
        self.objects: tuple[ObjectInfo, ...] = i.objects
        self.keypoint_order: str = i.keypoint_order
        self.frame: str = i.frame
        self.mean: tuple[float, float, float] = tuple(i.mean)
        self.std: tuple[float, float, float] = tuple(i.std)
        self.input_hw: tuple[int, int] | None = i.input_hw

    def __repr__(self) -> str:
        size = "dynamic" if self.fixed_input_hw is None else f"{self.fixed_input_hw[0]}x{self.fixed_input_hw[1]}"
        names = ", ".join(o.class_name for o in self.objects)
        return (f"OnnxBackend({self.path.name!r}, objects=[{names}], layout={self.layout!r}, "
                f"precision={self.info.precision!r}, input={size}, providers={self.providers})")
