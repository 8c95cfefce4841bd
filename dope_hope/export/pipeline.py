""":func:`export_checkpoint`: checkpoint -> verified ONNX file (+ optional INT8), what ``dope-hope export`` runs."""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from dope_hope.errors import ConfigError, InputFileError
from dope_hope.export.int8 import calibration_images, quantize_int8
from dope_hope.export.isaac_ros import isaac_ros_release
from dope_hope.export.to_onnx import ExportResult, ExportSettings, export_model, select_object
from dope_hope.model.checkpoint import load_model
from dope_hope.model.info import ModelInfo


@dataclass(frozen=True)
class Int8Calibration:
    """Static INT8 quantization of an export: ``images``, a folder of representative images;
    ``count`` of them calibrate the activation ranges by ``method`` (minmax, entropy or
    percentile: :func:`dope_hope.export.int8.quantize_int8`)."""

    images: str | os.PathLike
    count: int = 32
    method: str = "minmax"


def export_checkpoint(weights: str | os.PathLike, out: str | os.PathLike,
                      settings: ExportSettings = ExportSettings(),
                      int8: Int8Calibration | None = None) -> ExportResult:
    """Load a checkpoint and export it as ``settings`` say (:func:`export_model`): every object
    of the model in one file, or ``settings.object_name``'s channels only (the isaac-ros layout
    of a multi-object model needs one); with ``int8`` the fp32 graph goes to a temporary file
    and ``out`` receives the INT8 model (:func:`quantize_int8`).
    """
    t0 = time.perf_counter()
    weights, out = Path(weights), Path(out)
    if settings.dynamic and settings.input_hw is not None:
        raise ConfigError("--dynamic and --height/--width exclude each other")
    if out.suffix.lower() != ".onnx":
        raise ConfigError(f"--out must end in .onnx, got {out.name}")
    if weights.suffix.lower() == ".onnx":
        raise InputFileError(weights, "already an ONNX model; export takes a dope-hope checkpoint")
    if int8 is not None:
        calibration_images(int8.images)  # fail before the (slow) export if the folder is unusable
    if settings.layout == "isaac-ros":
        isaac_ros_release(settings.isaac_ros_version)  # a bad version fails before the model loads
    model, ckpt = load_model(weights)
    select_object(ModelInfo.from_checkpoint(ckpt, weights), settings.layout, settings.object_name)  # before any work
    if int8 is None:
        info, verify = export_model(model, ckpt, out, settings, weights.name)
        deviation = None
    else:
        with tempfile.TemporaryDirectory(prefix="dope-hope-export-") as tmpdir:
            fp32_path = Path(tmpdir) / f"{out.stem}.fp32.onnx"
            _, verify = export_model(model, ckpt, fp32_path, settings, weights.name)
            del model
            info, deviation = quantize_int8(fp32_path, out, int8.images, int8.count, int8.method)
    return ExportResult(path=out, info=info, verify_max_abs=verify, int8=deviation,
                        seconds=time.perf_counter() - t0, size_bytes=out.stat().st_size)
