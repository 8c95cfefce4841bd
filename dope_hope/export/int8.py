"""Static INT8 quantization of an exported fp32 ONNX file (onnxruntime ``quantize_static``).

QDQ format with per-channel symmetric INT8 weights and UINT8 activations, calibrated (MinMax by
default) on images of a folder prepared exactly as the predictor prepares them. After
quantization fp32 and INT8 run on up to ``eval_images`` of the calibration images and
:func:`~dope_hope.export.compare.compare_maps` reports the map and keypoint deviation
(in-sample: the same images calibrated the ranges).
"""
from __future__ import annotations

import json
import math
import os
import platform
import tempfile
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from dope_hope.errors import ConfigError, InputFileError
from dope_hope.export.compare import MapDeviation, compare_maps
from dope_hope.export.to_onnx import INT8_MIN_OPSET, _doc, _set_metadata
from dope_hope.io.atomic import atomic_path
from dope_hope.io.images import IMAGE_SUFFIXES, image_files, read_rgb
from dope_hope.model.onnx_contract import OnnxModelInfo
from dope_hope.model.onnx_graph import OnnxGraph
from dope_hope.preprocess import prepare_input, to_rgb8, working_size

CALIBRATION_METHODS = ("minmax", "entropy", "percentile")


# ----------------------------------------------------------------------------- INT8
def calibration_images(folder: str | os.PathLike, limit: int | None = None) -> list[Path]:
    """Sorted RGB image files of a folder (depth/segmentation images of DOPE folders skipped)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(folder, "calibration folder not found")
    files = [p for p in image_files(folder) if not p.name.lower().endswith((".depth.png", ".seg.png"))]
    if not files:
        raise InputFileError(folder, f"no calibration images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    return files[:limit] if limit else files


class ImageFolderReader:
    """onnxruntime ``CalibrationDataReader`` over images prepared as the predictor prepares them.

    Each image is read as RGB, fitted, padded and normalized by :mod:`dope_hope.preprocess`
    for ``backend`` (the fp32 model being quantized: its sizes, frame and normalization) and
    converted to the graph input's normalization by :meth:`OnnxGraph.feeds` (isaac-ros: the
    encoder's).
    """

    def __init__(self, backend: OnnxGraph, files: Sequence[Path]):
        self.backend = backend
        self.files = list(files)
        self._iter = None

    def prepare(self, path: Path) -> np.ndarray:
        """(1, 3, H, W) model-normalized batch of one image file, as the predictor makes it."""
        rgb = to_rgb8(read_rgb(path))
        info = self.backend.info
        resized, padded = working_size(rgb.shape[:2], input_hw=info.input_hw,
                                       fixed_input_hw=info.fixed_input_hw, legacy=info.frame == "legacy")
        return prepare_input(rgb, resized, info.mean, info.std, padded).batch

    def feeds(self, path: Path) -> list[dict[str, np.ndarray]]:
        return self.backend.feeds(self.prepare(path))

    def get_next(self) -> dict[str, np.ndarray] | None:
        if self._iter is None:
            self._iter = (f for p in self.files for f in self.feeds(p))
        return next(self._iter, None)

    def rewind(self) -> None:
        self._iter = None


def cpu_int8_support(cpuinfo: str | None = None, machine: str | None = None) -> tuple[bool | None, str]:
    """Whether onnxruntime's INT8 convolutions can beat fp32 on this CPU, and its instruction set.

    onnxruntime's integer kernels gain on x86 with VNNI (AVX-512 VNNI, AVX-VNNI, AMX) and on
    64-bit ARM with the dot-product extension; on AVX2-only x86 they run at about fp32 speed
    (bench/RESULTS.md "CPU inference"). Returns (True | False | None when unknown, a one-line
    description such as "x86-64 AVX2, no VNNI"). ``cpuinfo``/``machine``: for tests
    (default: ``/proc/cpuinfo`` and ``platform.machine()``).
    """
    machine = (machine or platform.machine()).lower()
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text(errors="replace")
        except OSError:
            return None, f"{machine or 'unknown CPU'} (instruction set unknown)"
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        key = line.split(":", 1)[0].strip().lower()
        if key in ("flags", "features"):
            flags.update(line.split(":", 1)[1].split())
            break
    if machine in ("x86_64", "amd64", "i686", "x86"):
        vnni = [f for f in ("amx_int8", "avx512_vnni", "avx_vnni") if f in flags]
        simd = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "SSE"
        if vnni:
            return True, f"x86-64 {simd} with {'/'.join(v.upper() for v in vnni)}"
        return False, f"x86-64 {simd}, no VNNI"
    if machine in ("aarch64", "arm64"):
        if "asimddp" in flags:
            return True, "ARM64 with the dot-product extension"
        return False, "ARM64 without the dot-product extension"
    return None, f"{machine or 'unknown CPU'} (instruction set unknown)"


def float_output_nodes(model_proto) -> list[str]:
    """Names of the last Conv nodes and of the data-movement nodes between them and the outputs.

    These (the last 1x1 convs of the final stage, plus the isaac-ros layout's concat, channel
    gather and stride-4 average pool) stay in float during INT8 quantization: the maps come
    out unquantized (no 1/255-of-range output step on the belief peaks) for a negligible
    share of the compute. Order: as found walking back from the outputs.
    """
    producer = {o: n for n in model_proto.graph.node for o in n.output}
    passthrough = {"Slice", "Concat", "Split", "Identity", "Reshape", "Squeeze", "Unsqueeze",
                   "Gather", "AveragePool"}
    found, stack, seen = [], [o.name for o in model_proto.graph.output], set()
    while stack:
        node = producer.get(stack.pop())
        if node is None or node.name in seen:
            continue
        seen.add(node.name)
        if node.op_type == "Conv":
            found.append(node.name)
        elif node.op_type in passthrough:
            found.append(node.name)
            stack.extend(node.input[:1] if node.op_type != "Concat" else node.input)
    return found


def quantize_int8(fp32_path: str | os.PathLike, out: str | os.PathLike, calibration: str | os.PathLike,
                  max_images: int = 32, method: str = "minmax", eval_images: int = 8,
                  activation_uint8: bool = True, threads: int | None = None) -> tuple[OnnxModelInfo, MapDeviation]:
    """Static INT8 quantization (QDQ, per-channel weights) of a dope-hope fp32 ONNX file.

    Args:
        fp32_path: an fp32 file written by :func:`export_model`.
        out: INT8 file to write (atomically; metadata copied, ``precision`` "int8").
        calibration: folder of RGB images (a DOPE-format folder works: depth/seg are skipped).
        max_images: calibration images used (sorted by name).
        method: "minmax", "entropy" or "percentile" (onnxruntime CalibrationMethod).
        eval_images: images on which INT8 is compared with fp32 afterwards.
        activation_uint8: UINT8 activations (x86 CPU recommendation) or INT8 (ARM/TensorRT).
    Returns (metadata, deviation of INT8 from fp32).
    """
    import onnx  # noqa: PLC0415 (onnx / onnxruntime (slow to import) only for INT8)
    from onnxruntime.quantization import (  # noqa: PLC0415 (onnx / onnxruntime (slow to import) only for INT8)
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quant_pre_process,
        quantize_static,
    )

    if method not in CALIBRATION_METHODS:
        raise ConfigError(f"calibration method must be one of {', '.join(CALIBRATION_METHODS)}, got {method!r}")
    fp32 = OnnxGraph(fp32_path, threads=threads, providers=["CPUExecutionProvider"])
    if fp32.info.precision != "fp32":
        raise ConfigError(f"{fp32_path}: already {fp32.info.precision}; quantize the fp32 export")
    if fp32.info.opset < INT8_MIN_OPSET:
        raise ConfigError(f"INT8 (per-channel QDQ) needs opset >= {INT8_MIN_OPSET}, the model has {fp32.info.opset}")
    files = calibration_images(calibration, max_images)
    reader = ImageFolderReader(fp32, files)
    calib = {"minmax": CalibrationMethod.MinMax, "entropy": CalibrationMethod.Entropy,
             "percentile": CalibrationMethod.Percentile}[method]
    settings = {
        "tool": "onnxruntime.quantization.quantize_static", "format": "QDQ", "per_channel": True,
        "weights": "int8 symmetric", "activations": "uint8" if activation_uint8 else "int8",
        "calibration": method, "calibration_images": len(files)}
    with atomic_path(out) as tmp, tempfile.TemporaryDirectory(prefix="dope-hope-quant-") as tmpdir:
        # onnxruntime's recommended pre-processing: shape inference + graph cleanup (folds the
        # exporter's Identity/Constant nodes, so every conv bias is an initializer it can quantize).
        pre = Path(tmpdir) / "preprocessed.onnx"
        quant_pre_process(str(fp32_path), str(pre))
        keep_float = float_output_nodes(onnx.load(str(pre)))
        quantize_static(str(pre), str(tmp), reader, quant_format=QuantFormat.QDQ, per_channel=True,
                        reduce_range=False, nodes_to_exclude=keep_float,
                        activation_type=QuantType.QUInt8 if activation_uint8 else QuantType.QInt8,
                        weight_type=QuantType.QInt8, calibrate_method=calib,
                        calibration_providers=["CPUExecutionProvider"])
        settings["float_nodes"] = keep_float
        info = replace(fp32.info, precision="int8",
                       extra=dict(fp32.info.extra, quantization=json.dumps(settings)))
        proto = onnx.load(str(tmp))
        _set_metadata(proto, info, _doc(info))
        onnx.checker.check_model(proto)
        onnx.save(proto, str(tmp))
        del proto
        int8 = OnnxGraph(tmp, threads=threads, providers=["CPUExecutionProvider"])
        ref, test = [], []
        for path in files[:max(1, eval_images)]:
            batch = reader.prepare(path)
            ref.append(tuple(m[0] for m in fp32.run(batch)))
            test.append(tuple(m[0] for m in int8.run(batch)))
        deviation = compare_maps(ref, test, info.stride)
        del int8
        # Record the measured drift in the file, so that whoever loads it sees what INT8 costs.
        settings["drift"] = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                             for k, v in vars(deviation).items()}
        info = replace(info, extra=dict(info.extra, quantization=json.dumps(settings)))
        proto = onnx.load(str(tmp))
        _set_metadata(proto, info, _doc(info))
        onnx.save(proto, str(tmp))
        del proto
    return info, deviation
