"""Map backends: something that turns a normalized batch into last-stage belief/affinity maps.

:class:`MapBackend` is the protocol the predictor uses; :class:`TorchBackend` runs a
checkpoint with PyTorch; :func:`open_backend` picks torch or onnxruntime
(:mod:`dope_hope.inference.onnx_backend`) from the file. A backend's maps hold one
belief/affinity group per object of the model (:func:`backend_objects`).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.model.checkpoint import load_checkpoint, load_model
from dope_hope.model.info import ModelInfo, ObjectInfo
from dope_hope.model.network import build_model, normalize_batch
from dope_hope.model.onnx_graph import require_model_file

BACKENDS = ("auto", "torch", "onnx")


# ----------------------------------------------------------------------------- backends
@runtime_checkable
class MapBackend(Protocol):
    """What turns a normalized batch into belief maps and affinity fields (torch or ONNX).

    Attributes (metadata recorded with the weights):
        stride: image pixels per map cell (8 for the 50-px head, 4, or 1 for the 400-px head).
        class_name: the object the model detects (the first of a multi-object model).
        size_m: (3,) its cuboid extents in the MESH frame, metres.
        keypoint_order: "dope-current" or "dope-legacy".
        frame: "mesh" or "legacy" (the object frame of the network's keypoints).
        mean, std: 3 floats each, normalization of RGB in [0, 1].
        input_hw: (H, W) training input size, or None when unknown.

    A backend whose network only accepts one input size may also set ``fixed_input_hw``
    (H, W); the predictor then fits and pads every image to it. A backend with ``info`` (a
    :class:`~dope_hope.model.info.ModelInfo`) offers the model's own ``min_score``
    (:func:`model_min_score`) and its objects (:func:`backend_objects`; without ``info``: the
    one object ``class_name``).
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
        """(N, 3, H, W) float32 normalized -> belief (N, 9K, h, w), affinity (N, 16K, h, w)
        for K objects."""
        ...


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
        self.info = ModelInfo.from_checkpoint(checkpoint, self.source)
        i = self.info
        self.class_name: str = i.class_name
        self.size_m: np.ndarray = np.asarray(i.size_m, dtype=np.float64)
        self.objects: tuple[ObjectInfo, ...] = i.objects
        self.keypoint_order: str = i.keypoint_order
        self.frame: str = i.frame
        self.mean: tuple[float, float, float] = i.mean
        self.std: tuple[float, float, float] = i.std
        self.input_hw: tuple[int, int] | None = i.input_hw
        self.stride: int = int(model.stride)
        self.device = device
        self.model = model.to(device).eval()

    @classmethod
    def load(cls, path: str | os.PathLike, device: str = "cpu") -> TorchBackend:
        """Load a dope-hope checkpoint (``weights_only``); ModelFileError for a bad file."""
        model, ckpt = load_model(path, device=device)
        return cls(model, ckpt, device=device, source=path)

    def run(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3, H, W) float32 normalized -> belief (N, 9K, h, w), affinity (N, 16K, h, w)."""
        x = torch.from_numpy(np.ascontiguousarray(batch, dtype=np.float32)).to(self.device)
        with torch.inference_mode():
            belief, affinity = self.model(x)[-1]
        return belief.float().cpu().numpy(), affinity.float().cpu().numpy()

    def texture_features(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) uint8 RGB -> (N, C, H/4, W/4) float32: the network's first layers
        (:meth:`~dope_hope.model.network.DopeNetwork.texture_features`), normalized as its input."""
        x = normalize_batch(torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2), self.mean, self.std)
        with torch.inference_mode():
            return self.model.texture_features(x.to(self.device)).float().cpu().numpy()


def model_min_score(backend: MapBackend) -> float | None:
    """The score threshold recorded with the backend's weights (``info.min_score``), or None
    (none recorded, or a backend without ``info``)."""
    info = getattr(backend, "info", None)
    return None if info is None else info.min_score


def backend_objects(backend: MapBackend) -> tuple[ObjectInfo, ...]:
    """The objects a backend's maps hold, in channel-group order: ``info.objects`` when the
    backend has a :class:`~dope_hope.model.info.ModelInfo`, else its one ``class_name`` /
    ``size_m`` (no symmetries)."""
    info = getattr(backend, "info", None)
    if info is not None and getattr(info, "objects", None):
        return tuple(info.objects)
    size = tuple(float(v) for v in np.asarray(backend.size_m, dtype=np.float64).reshape(3))
    return (ObjectInfo(str(backend.class_name), size),)


def open_backend(weights: str | os.PathLike, backend: str = "auto", device: str = "cpu",
                 threads: int | None = None) -> MapBackend:
    """Open weights with the named backend; "auto" = ONNX for ``.onnx`` files, else torch."""
    if backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    path = Path(weights)
    fmt = require_model_file(path)
    is_onnx = path.suffix.lower() == ".onnx"
    kind = ("onnx" if is_onnx else "torch") if backend == "auto" else backend
    if kind == "onnx" and fmt.startswith("torch"):
        raise ModelFileError(path, "a PyTorch checkpoint, not an ONNX model: use backend 'torch' or "
                                   "'auto' (or export it with dope-hope export)")
    if kind == "onnx":
        try:
            from dope_hope.inference.onnx_backend import OnnxBackend  # noqa: PLC0415 (onnxruntime (slow to import) only for an ONNX model)
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
        import torch  # noqa: PLC0415 (torch only to cap the threads of a torch model)

        torch.set_num_threads(int(threads))
    return TorchBackend.load(path, device=device)


def start_backend(start: str | os.PathLike, class_name: str, size_m: np.ndarray, device: str = "cpu",
                  threads: int | None = None) -> TorchBackend:
    """The one-object checkpoint ``start`` (the shipped pretrained start, or any one-object
    dope-hope checkpoint) as a backend detecting ``class_name`` with cuboid ``size_m`` (3,)
    metres, mesh frame (what :class:`~dope_hope.inference.mesh_start.MeshStartPredictor` runs,
    and whose first layers a trained ONNX model's turns compare by). ModelFileError for a file
    of several objects or a legacy frame."""
    if threads:
        torch.set_num_threads(int(threads))
    ckpt = dict(load_checkpoint(start))
    info = ModelInfo.from_checkpoint(ckpt, start)
    if info.num_objects != 1 or info.legacy:
        raise ModelFileError(start, f"a start must be a one-object mesh-frame model; this one holds "
                                    f"{info.num_objects} object(s) in the {info.frame} frame")
    ckpt.pop("source", None)
    ckpt.pop("objects", None)
    ckpt.pop("min_score", None)  # the start's threshold is no threshold of this object
    ckpt["object"] = {"class_name": str(class_name), "size_m": [float(v) for v in size_m], "frame": "mesh"}
    model = build_model(ckpt["config"], load_backbone=False)
    model.load_state_dict(ckpt["model"], strict=True)
    return TorchBackend(model.eval(), ckpt, device=device, source=start)
