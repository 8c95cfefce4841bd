""":func:`export_checkpoint`: checkpoint -> verified ONNX file (+ optional INT8), what ``dope-hope export`` runs."""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from dope_hope.errors import ConfigError, InputFileError
from dope_hope.export.int8 import list_images, quantize_int8
from dope_hope.export.isaac_ros import ISAAC_ROS_CURRENT, isaac_ros_release
from dope_hope.export.to_onnx import OPSET, ExportResult, export_model, select_object
from dope_hope.model.info import ModelInfo


def export_checkpoint(weights: str | os.PathLike, out: str | os.PathLike, height: int | None = None,
                      width: int | None = None, dynamic: bool = False, layout: str = "native",
                      int8: bool = False, calibration: str | os.PathLike | None = None,
                      opset: int = OPSET, isaac_encoder: str | None = None, calibration_images: int = 32,
                      calibration_method: str = "minmax",
                      isaac_ros_version: str = ISAAC_ROS_CURRENT,
                      object_name: str | None = None) -> ExportResult:
    """Load a checkpoint and export it (see :func:`export_model`, :func:`quantize_int8`):
    every object of the model in one file, or ``object_name``'s channels only (the isaac-ros
    layout of a multi-object model needs one).

    With ``int8`` the fp32 graph goes to a temporary file and ``out`` receives the INT8 model.
    """
    from dope_hope.model.checkpoint import load_model

    t0 = time.perf_counter()
    weights, out = Path(weights), Path(out)
    if (height is None) != (width is None):
        raise ConfigError("give both --height and --width (or neither)")
    if dynamic and height is not None:
        raise ConfigError("--dynamic and --height/--width exclude each other")
    if int8 and calibration is None:
        raise ConfigError("--int8 needs --calibration DIR (a folder of representative images)")
    if calibration is not None and not int8:
        raise ConfigError("--calibration is only used with --int8")
    if out.suffix.lower() != ".onnx":
        raise ConfigError(f"--out must end in .onnx, got {out.name}")
    if weights.suffix.lower() == ".onnx":
        raise InputFileError(weights, "already an ONNX model; export takes a dope-hope checkpoint")
    if int8:
        list_images(calibration)  # fail before the (slow) export if the folder is unusable
    if layout == "isaac-ros":
        isaac_ros_release(isaac_ros_version)  # a bad version fails before the model loads
    model, ckpt = load_model(weights)
    select_object(ModelInfo.from_checkpoint(ckpt, weights), layout, object_name)  # before any work
    hw = None if height is None else (height, width)
    if not int8:
        info, verify = export_model(model, ckpt, out, layout, hw, dynamic, opset, isaac_encoder, weights.name,
                                    isaac_ros_version=isaac_ros_version, object_name=object_name)
        deviation = None
    else:
        with tempfile.TemporaryDirectory(prefix="dope-hope-export-") as tmpdir:
            fp32_path = Path(tmpdir) / f"{out.stem}.fp32.onnx"
            _, verify = export_model(model, ckpt, fp32_path, layout, hw, dynamic, opset, isaac_encoder,
                                     weights.name, isaac_ros_version=isaac_ros_version, object_name=object_name)
            del model
            info, deviation = quantize_int8(fp32_path, out, calibration, calibration_images,
                                            calibration_method)
    return ExportResult(path=out, info=info, verify_max_abs=verify, int8=deviation,
                        seconds=time.perf_counter() - t0, size_bytes=out.stat().st_size)
