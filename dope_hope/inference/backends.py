"""Map backends: something that turns a normalized batch into last-stage belief/affinity maps.

:class:`MapBackend` is the protocol the predictor uses; :class:`TorchBackend` runs a
checkpoint with PyTorch; :func:`open_backend` picks torch or onnxruntime
(:mod:`dope_hope.inference.onnx_backend`) from the file.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.geometry import (
    KEYPOINT_ORDER,
    LEGACY_KEYPOINT_ORDER,
)

BACKENDS = ("auto", "torch", "onnx")


# ----------------------------------------------------------------------------- backends
@runtime_checkable
class MapBackend(Protocol):
    """What turns a normalized batch into belief maps and affinity fields (torch or ONNX).

    Attributes (metadata recorded with the weights):
        stride: image pixels per map cell (8 for the 50-px head, 4, or 1 for the 400-px head).
        class_name: the object the model detects.
        size_m: (3,) cuboid extents in the MESH frame, metres.
        keypoint_order: "dope-current" or "dope-legacy".
        frame: "mesh" or "legacy" (the object frame of the network's keypoints).
        mean, std: 3 floats each, normalization of RGB in [0, 1].
        input_hw: (H, W) training input size, or None when unknown.

    A backend whose network only accepts one input size may also set ``fixed_input_hw``
    (H, W); the predictor then fits and pads every image to it.
    """

    stride: int
    class_name: str
    size_m: np.ndarray
    keypoint_order: str
    frame: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    input_hw: tuple[int, int] | None

    def run(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3, H, W) float32 normalized -> belief (N, 9, h, w), affinity (N, 16, h, w)."""
        ...


def metadata_from_checkpoint(ckpt: dict[str, Any], path: str | os.PathLike = "<checkpoint>") -> dict[str, Any]:
    """Backend metadata of a loaded checkpoint dict (see :class:`MapBackend`), validated.

    Returns ``{class_name, size_m, keypoint_order, frame, mean, std, input_hw}``; the stride
    comes from the built network. Raises ModelFileError for inconsistent or missing fields.
    """
    obj = ckpt.get("object") or {}
    try:
        size = np.asarray(obj.get("size_m"), dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise ModelFileError(path, "checkpoint 'object.size_m' must hold 3 extents in metres") from None
    if not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise ModelFileError(path, f"checkpoint cuboid size {size.tolist()} is not positive")
    frame = obj.get("frame", "mesh")
    order = ckpt.get("keypoint_order", KEYPOINT_ORDER)
    expected = LEGACY_KEYPOINT_ORDER if frame == "legacy" else KEYPOINT_ORDER
    if frame not in ("mesh", "legacy") or order != expected:
        raise ModelFileError(path, f"checkpoint frame {frame!r} with keypoint order {order!r} is "
                                   f"not supported (expected {expected!r})")
    norm = ckpt.get("normalization") or {}
    try:
        mean = tuple(float(v) for v in norm["mean"])
        std = tuple(float(v) for v in norm["std"])
    except (KeyError, TypeError, ValueError):
        raise ModelFileError(path, "checkpoint 'normalization' must hold mean and std") from None
    if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise ModelFileError(path, f"checkpoint normalization mean {mean} / std {std} is invalid")
    input_hw = None
    size_in = ((ckpt.get("config") or {}).get("input") or {}).get("size")
    if isinstance(size_in, (list, tuple)) and len(size_in) == 2:
        input_hw = (int(size_in[0]), int(size_in[1]))
    return {"class_name": str(obj.get("class_name")), "size_m": size, "keypoint_order": order,
            "frame": frame, "mean": mean, "std": std, "input_hw": input_hw}


class TorchBackend:
    """:class:`MapBackend` running a PyTorch network (its LAST stage) under inference mode.

    Args:
        model: a :class:`~dope_hope.model.network.DopeNetwork` (or any module with ``stride``
            whose forward returns a list of (belief, affinity) per stage).
        checkpoint: the checkpoint dict it came from (metadata: object, order, normalization).
        device: torch device string.
        source: where the weights came from (for messages).
    """

    def __init__(self, model, checkpoint: dict[str, Any], device: str = "cpu",
                 source: str | os.PathLike = "<model>"):
        self.source = str(source)
        meta = metadata_from_checkpoint(checkpoint, self.source)
        self.class_name: str = meta["class_name"]
        self.size_m: np.ndarray = meta["size_m"]
        self.keypoint_order: str = meta["keypoint_order"]
        self.frame: str = meta["frame"]
        self.mean: tuple[float, float, float] = meta["mean"]
        self.std: tuple[float, float, float] = meta["std"]
        self.input_hw: tuple[int, int] | None = meta["input_hw"]
        self.stride: int = int(model.stride)
        self.device = device
        self.model = model.to(device).eval()

    @classmethod
    def load(cls, path: str | os.PathLike, device: str = "cpu") -> TorchBackend:
        """Load a dope-hope checkpoint (``weights_only``); ModelFileError for a bad file."""
        from dope_hope.model.checkpoint import load_model

        model, ckpt = load_model(path, device=device)
        return cls(model, ckpt, device=device, source=path)

    def run(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3, H, W) float32 normalized -> belief (N, 9, h, w), affinity (N, 16, h, w)."""
        import torch

        x = torch.from_numpy(np.ascontiguousarray(batch, dtype=np.float32)).to(self.device)
        with torch.inference_mode():
            belief, affinity = self.model(x)[-1]
        return belief.float().cpu().numpy(), affinity.float().cpu().numpy()


def open_backend(weights: str | os.PathLike, backend: str = "auto", device: str = "cpu",
                 threads: int | None = None) -> MapBackend:
    """Open weights with the named backend; "auto" = ONNX for ``.onnx`` files, else torch."""
    if backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    path = Path(weights)
    if not path.is_file():
        raise ModelFileError(path, "weights file not found")
    is_onnx = path.suffix.lower() == ".onnx"
    kind = ("onnx" if is_onnx else "torch") if backend == "auto" else backend
    if kind == "onnx":
        try:
            from dope_hope.inference.onnx_backend import OnnxBackend
        except ModuleNotFoundError as exc:
            if exc.name != "dope_hope.inference.onnx_backend":
                raise
            raise ConfigError("the ONNX backend (dope_hope.inference.onnx_backend) is not available") from None
        # "cpu" keeps onnxruntime on the CPU; "cuda..." lets it take CUDA when it has it.
        providers = None if str(device).startswith("cuda") else ["CPUExecutionProvider"]
        return OnnxBackend(path, threads=threads, providers=providers)
    if is_onnx:
        raise ModelFileError(path, "an ONNX model; use backend 'onnx' or 'auto'")
    if threads:
        import torch

        torch.set_num_threads(int(threads))
    return TorchBackend.load(path, device=device)
