"""ONNX export of a dope-hope model: native or Isaac ROS layout, metadata, verification.

**Exporter.** ``torch.onnx.export(..., dynamo=False)``: the TorchScript exporter. torch 2.14's
default (dynamo) exporter needs ``onnxscript`` (not a dependency) and writes the weights to a
separate ``.onnx.data`` file; the TorchScript one writes ONE self-contained file (DOPE-DR-50
is ~210 MB, far below protobuf's 2 GB limit) and exports every op used here (conv, ReLU, max
pool, concat, bilinear resize, transposed conv, global average pool; BatchNorm is folded
into the convs in eval mode). It is deprecated in torch >= 2.9 and says so with two
``DeprecationWarning`` s, which :func:`_torchscript_export` silences deliberately (by exact
message, nothing else). Default opset **17** (:data:`OPSET`; 11..20 accepted, INT8 needs
>= 13 for per-channel QDQ); the opset is recorded in the metadata. Every export is checked
with ``onnx.checker`` and then *verified*: onnxruntime and PyTorch run the same random input
and the largest map difference must stay below 1e-3 (relative to the map scale), else
:class:`ExportError` and nothing is written. Files are written atomically.

**Native layout** (``layout="native"``): input ``image`` (N, 3, H, W) float32, RGB normalized
with the checkpoint's mean/std (ImageNet); outputs ``belief`` (N, 9, h, w) and ``affinity``
(N, 16, h, w) of the LAST stage only (:class:`LastStageMaps`). The batch axis is always
dynamic; H and W are fixed (``input_hw``, default the training input size) or dynamic
(``dynamic=True``). The file's ``metadata_props`` carry what inference needs
(:class:`dope_hope.model.onnx_contract.OnnxModelInfo`): ``dope_hope.format``, ``format_version``,
``class_name``, ``size_m`` (mesh frame, m), ``frame``, ``keypoint_order``, ``mean``/``std``,
``input_mean``/``input_std``, ``stride``, ``head``, ``arch``, ``layout``, ``input_hw``,
``fixed_input_hw``, ``opset``, ``precision``, ``version``, ``exporter``, ``source``, plus
``config`` (the checkpoint's config as JSON), ``input_layout`` and, for INT8,
``quantization``; isaac-ros files add ``isaac_ros.*`` keys (below).

**Isaac ROS layout** (``layout="isaac-ros"``), for NVIDIA-ISAAC-ROS/isaac_ros_pose_estimation
(package isaac_ros_dope; what each release expects is in :mod:`dope_hope.export.isaac_ros`):

- ``scripts/dope_converter.py`` exports the official network with ``input_names=['input']``,
  ``output_names=['output']``, a ``torch.randn(1, 3, row, col)`` dummy (defaults ``--row 480
  --col 640`` in every release, static shapes) and a forward returning ``torch.cat([out6_2,
  out6_1], 1)``: 9 belief maps, then 16 affinity fields. The launch files bind
  ``input_binding_names ["input"]`` / ``output_binding_names ["output"]``. The Isaac ROS docs
  ("Using DOPE at Different Image Resolutions") state that the exported ONNX does not support
  other image sizes: the size is fixed at export (``dynamic`` is refused here), default 480x640.
- The decoder checks the tensor is (1, 25, h, w), reads channel k as cuboid vertex k (8 =
  centroid) with affinity channels 9 + 2k, 10 + 2k, and maps a peak to the image as ``(peak +
  0.4395) * 8``: stride 8 (:mod:`dope_hope.maps.grid` puts cell j at 8j + 3.5, an offset of
  0.4375: the same to 0.016 px). Its vertex order is release-dependent (3.2 turned it 180
  degrees about z), so the graph's output channels are permuted for ``isaac_ros_version``
  (:func:`dope_hope.export.isaac_ros.channel_order`, recorded as ``isaac_ros.channel_order``): Isaac
  ROS then publishes the **mesh-frame** pose when its ``dope_config.yaml`` ``dimensions`` entry
  holds the mesh-frame extents in cm (``isaac_ros.object_dimensions_cm``; legacy-frame models
  too, whose stock HOPE entries list the legacy frame). :class:`OnnxBackend` undoes the
  permutation, so dope-hope reads the file like any other.
- The image encoder (isaac_ros_dnn_image_encoder) normalizes with the launch arguments
  ``encoder_image_mean`` / ``encoder_image_stddev``; ``isaac_encoder`` defaults to the
  release's launch default (mean = std = 0.5 up to 3.1, ImageNet since 3.2). The conversion to
  this model's normalization is folded into the graph as a fixed per-channel affine op at the
  input, ``x_model = (x_isaac * enc_std + enc_mean - mean) / std`` (:class:`IsaacRosMaps`; an
  exact Mul + Add, not folded into the first conv's weights, whose zero padding would then no
  longer pad with the normalized zero). The batch axis is fixed at 1.
- Maps at stride 4 (lite head 100) are resampled to stride 8 inside the graph by a 2x2 average
  pool: stride-8 cell i is centred (8i + 3.5) exactly between stride-4 cells 2i and 2i + 1, so
  the pool is the bilinear sample there and a symmetric peak keeps its position (measured on
  the demo frames: bench/isaac_ros_lite.py). The file then records ``stride`` 8 and
  ``isaac_ros.resampled_from_stride`` 4. DOPE-DR-400 (stride 1) is refused
  (:class:`~dope_hope.errors.ConfigError`): pooling by 8 would discard exactly what the 400-px
  head is for. Export it in the native layout.

INT8: :mod:`dope_hope.export.int8`.
"""
from __future__ import annotations

import json
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dope_hope.config import SectionSettings, boolean, one_of, or_none, section, whole_number
from dope_hope.errors import ConfigError, DopeHopeError
from dope_hope.export.compare import MapDeviation
from dope_hope.export.isaac_ros import ENCODERS as ISAAC_ENCODERS
from dope_hope.export.isaac_ros import (
    ISAAC_ROS_CURRENT,
    channel_order,
    isaac_ros_release,
)
from dope_hope.io.atomic import atomic_path
from dope_hope.model.info import ModelInfo, group_channels
from dope_hope.model.onnx_contract import (
    CHANNEL_ORDER_KEY,
    LAYOUT_NAMES,
    LAYOUTS,
    OnnxModelInfo,
    output_order,
)
from dope_hope.preprocess import check_working_side
from dope_hope.version import __version__

#: Default ONNX opset and the range the TorchScript exporter handles here.
OPSET = 17


MIN_OPSET, MAX_OPSET = 11, 20


INT8_MIN_OPSET = 13


#: Isaac ROS DOPE defaults: network input (H, W) (dope_converter.py --row/--col).
ISAAC_ROS_INPUT_HW = (480, 640)


def _opset(value: Any, name: str) -> int:
    opset = whole_number(value, name, 0)
    if not MIN_OPSET <= opset <= MAX_OPSET:
        raise ConfigError(f"{name} must be {MIN_OPSET}..{MAX_OPSET} (TorchScript exporter), got {value!r}")
    return opset


def _input_hw(value: Any, name: str) -> tuple[int, int]:
    if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ConfigError(f"{name} must be [H, W], got {value!r}")
    return check_working_side(value[0], name), check_working_side(value[1], name)


def _text(value: Any, name: str) -> str:
    """A string (what it must look like is checked where it is used, e.g. the Isaac ROS release)."""
    if not isinstance(value, str):
        raise ConfigError(f"{name} must be a string, got {value!r}")
    return value


@dataclass(frozen=True)
class ExportSettings(SectionSettings):
    """What an ONNX file is built as (the ``export`` section of `dope-hope export`'s settings;
    its flags set the same keys).

    layout: "native" or "isaac-ros" (module docstring). input_hw: (H, W), multiples of 8;
    None: the training input size (native) or 480x640 (isaac-ros); with ``dynamic`` it only
    sizes the tracing input. dynamic: native only, H and W dynamic (the batch axis always is).
    opset: ONNX opset (11..20). isaac_encoder: "half" (mean = std = 0.5) or "imagenet", the
    Isaac ROS encoder's normalization (None: the launch default of ``isaac_ros_version``).
    isaac_ros_version: the Isaac ROS release ("3.1", "4.0", ...) whose decoder the output
    channels are ordered for (:mod:`dope_hope.export.isaac_ros`). object_name: export only
    this object's channel group (required for a multi-object model in the isaac-ros layout);
    None: every object of the model.
    """

    SECTION = "export"
    RULES = {"layout": one_of("native", "isaac-ros"), "input_hw": or_none(_input_hw), "dynamic": boolean,
             "opset": _opset, "isaac_encoder": or_none(one_of("half", "imagenet")), "isaac_ros_version": _text,
             "object_name": or_none(_text)}

    layout: str = "native"
    input_hw: tuple[int, int] | None = None
    dynamic: bool = False
    opset: int = OPSET
    isaac_encoder: str | None = None
    isaac_ros_version: str = ISAAC_ROS_CURRENT
    object_name: str | None = None


@dataclass(frozen=True)
class ExportConfig(SectionSettings):
    """The settings of `dope-hope export`: its one section, ``export``."""

    SECTION = ""

    export: ExportSettings = section(ExportSettings)


#: The map stride the Isaac ROS decoder assumes, and the strides resampled to it in-graph.
ISAAC_ROS_STRIDE = 8
ISAAC_ROS_RESAMPLED_STRIDES = (4,)


#: Verification tolerance: max |onnxruntime - torch| <= VERIFY_TOL * max(1, max |torch|).
VERIFY_TOL = 1e-3


class ExportError(DopeHopeError):
    """The exported graph does not reproduce the PyTorch model (nothing was written)."""


# ----------------------------------------------------------------------------- wrappers
class LastStageMaps(nn.Module):
    """(N, 3, H, W) -> (belief (N, 9K, h, w), affinity (N, 16K, h, w)) of the last stage, all
    K objects, or only object ``group`` (9 and 16 channels) when given."""

    def __init__(self, model: nn.Module, group: int | None = None):
        super().__init__()
        self.model = model
        self.group = group

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        belief, affinity = self.model(x)[-1]
        if self.group is not None:
            k = self.group
            belief, affinity = belief[:, 9 * k:9 * k + 9], affinity[:, 16 * k:16 * k + 16]
        return belief, affinity


class IsaacRosMaps(nn.Module):
    """Isaac ROS DOPE graph: encoder-normalized (1, 3, H, W) -> (1, 25, H/8, W/8).

    ``x_model = x * (enc_std / std) + (enc_mean - mean) / std`` (fixed per-channel affine op),
    then the network; its last stage's cat(belief (9K), affinity (16K)) is average-pooled by
    ``pool`` (stride-4 maps -> stride 8; 1 = none) and its channels gathered in ``order``
    ((25,) int indices into that concatenation: one object's channels
    (:func:`dope_hope.model.info.group_channels`) in the order of
    :func:`dope_hope.model.onnx_contract.output_order`; None = as the model has them, one object).
    """

    def __init__(self, model: nn.Module, mean: Sequence[float], std: Sequence[float],
                 enc_mean: Sequence[float], enc_std: Sequence[float], order: Sequence[int] | None = None,
                 pool: int = 1):
        super().__init__()
        self.model = model
        self.pool = int(pool)
        m, s = torch.tensor(mean, dtype=torch.float32), torch.tensor(std, dtype=torch.float32)
        em, es = torch.tensor(enc_mean, dtype=torch.float32), torch.tensor(enc_std, dtype=torch.float32)
        self.register_buffer("scale", (es / s).view(1, 3, 1, 1))
        self.register_buffer("shift", ((em - m) / s).view(1, 3, 1, 1))
        identity = order is None or list(order) == list(range(len(order)))
        self.register_buffer("order", None if identity else torch.as_tensor(list(order), dtype=torch.int64))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        belief, affinity = self.model(x * self.scale + self.shift)[-1]
        maps = torch.cat([belief, affinity], 1)
        if self.pool > 1:
            maps = nn.functional.avg_pool2d(maps, self.pool)
        if self.order is not None:
            maps = maps.index_select(1, self.order)
        return maps


@dataclass
class ExportResult:
    """What :func:`export_checkpoint` wrote.

    path: the .onnx file. info: its metadata. verify_max_abs: max |onnxruntime - torch|
    of the fp32 graph on a random input. int8: INT8-vs-fp32 deviation (None for fp32).
    seconds: wall time. size_bytes: file size.
    """

    path: Path
    info: OnnxModelInfo
    verify_max_abs: float
    int8: MapDeviation | None
    seconds: float
    size_bytes: int


# ----------------------------------------------------------------------------- export
def _check_hw(hw: Sequence[int], what: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in hw)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be two integers (H, W), got {hw!r}") from None
    if h < 8 or w < 8 or h % 8 or w % 8:
        raise ConfigError(f"{what} must be multiples of 8 (the network's stride), got {h}x{w}")
    return h, w


def _torchscript_export(module: nn.Module, dummy: torch.Tensor, path: Path, opset: int,
                        input_names: list[str], output_names: list[str],
                        dynamic_axes: dict[str, dict[int, str]] | None) -> None:
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in torch >= 2.9 but is the one that writes a
        # single self-contained file without onnxscript (module docstring): silence exactly
        # its two deprecation notices, nothing else.
        warnings.filterwarnings("ignore", message=r".*legacy TorchScript-based ONNX export",
                                category=DeprecationWarning)
        warnings.filterwarnings("ignore", message=r"The feature will be removed",
                                category=DeprecationWarning)
        torch.onnx.export(module, (dummy,), str(path), dynamo=False, opset_version=opset,
                          input_names=input_names, output_names=output_names,
                          dynamic_axes=dynamic_axes, do_constant_folding=True)


def _set_metadata(model_proto, info: OnnxModelInfo, doc: str) -> None:
    del model_proto.metadata_props[:]
    for key, value in sorted(info.to_metadata().items()):
        entry = model_proto.metadata_props.add()
        entry.key, entry.value = key, value
    model_proto.producer_name = "dope-hope"
    model_proto.producer_version = __version__
    model_proto.doc_string = doc


def _doc(info: OnnxModelInfo) -> str:
    names = LAYOUT_NAMES[info.layout]
    size = "dynamic H, W" if info.fixed_input_hw is None else f"{info.fixed_input_hw[0]}x{info.fixed_input_hw[1]}"
    return (f"dope-hope {info.precision} DOPE belief/affinity network for {', '.join(info.class_names)} "
            f"({info.arch}, head {info.head}, stride {info.stride}, {info.layout} layout: "
            f"{', '.join(names[0])} -> {', '.join(names[1])}, input {size}, RGB normalized "
            f"with mean {list(info.input_mean)} std {list(info.input_std)}). Metadata keys dope_hope.*.")


def select_object(meta: ModelInfo, layout: str, object_name: str | None) -> tuple[ModelInfo, int | None]:
    """(the exported file's model info, the channel group to export or None for all).

    ConfigError (naming ``--object``) for an unknown object, and for a multi-object model in the
    isaac-ros layout without one (Isaac ROS DOPE runs one object per model)."""
    names = ", ".join(meta.class_names)
    if object_name is None:
        if layout == "isaac-ros" and meta.num_objects > 1:
            raise ConfigError(f"--object: the isaac-ros layout holds one object (Isaac ROS DOPE runs one "
                              f"per model); name one of this model's objects: {names}")
        return meta, None
    try:
        k = meta.object_index(object_name)
    except KeyError:
        raise ConfigError(f"--object: {object_name!r} is not an object of this model (its objects: {names})") from None
    return meta.select(object_name), k


def model_info(checkpoint: dict[str, Any], model: nn.Module, settings: ExportSettings,
               fixed_input_hw: tuple[int, int] | None, source: str = "") -> OnnxModelInfo:
    """The :class:`OnnxModelInfo` of a checkpoint exported as ``settings`` say (all its
    objects, or ``settings.object_name`` only: :func:`select_object`).

    isaac-ros: ``stride`` is the graph output's (8, after any resampling); ``isaac_encoder``
    None = the release's launch default.
    """
    layout, opset, isaac_encoder = settings.layout, settings.opset, settings.isaac_encoder
    isaac_ros_version, object_name = settings.isaac_ros_version, settings.object_name
    meta, _ = select_object(ModelInfo.from_checkpoint(checkpoint, source or "<checkpoint>"), layout, object_name)
    mean, std = meta.mean, meta.std
    stride = int(model.stride)
    extra = {
        "config": json.dumps(checkpoint.get("config"), default=str, sort_keys=True),
        "input_layout": "NCHW float32 RGB, (rgb / 255 - input_mean) / input_std",
    }
    input_mean, input_std = mean, std
    if layout == "isaac-ros":
        release = isaac_ros_release(isaac_ros_version)
        isaac_encoder = release.encoder if isaac_encoder is None else isaac_encoder
        if isaac_encoder not in ISAAC_ENCODERS:
            raise ConfigError(f"isaac encoder normalization must be one of {', '.join(ISAAC_ENCODERS)}, "
                              f"got {isaac_encoder!r}")
        input_mean, input_std = ISAAC_ENCODERS[isaac_encoder]
        extra["isaac_ros.version"] = release.version
        extra["isaac_ros.encoder"] = isaac_encoder
        extra[CHANNEL_ORDER_KEY] = json.dumps(channel_order(meta.frame, release).tolist())
        # Mesh-frame extents: with the channel order above Isaac ROS publishes mesh-frame poses.
        extra["isaac_ros.object_dimensions_cm"] = json.dumps([round(float(v) * 100.0, 4) for v in meta.size_m])
        if stride != ISAAC_ROS_STRIDE:
            extra["isaac_ros.resampled_from_stride"] = str(stride)
            stride = ISAAC_ROS_STRIDE
    return OnnxModelInfo(
        class_name=meta.class_name, size_m=meta.size_m,
        frame=meta.frame, keypoint_order=meta.keypoint_order, mean=tuple(mean), std=tuple(std),
        input_mean=tuple(float(v) for v in input_mean), input_std=tuple(float(v) for v in input_std),
        stride=stride, head=int(getattr(model, "head", 0)), arch=str(getattr(model, "arch", "")),
        layout=layout, input_hw=meta.input_hw, fixed_input_hw=fixed_input_hw, opset=int(opset),
        precision="fp32", version=__version__,
        exporter=f"torch.onnx.export(dynamo=False) TorchScript exporter, torch {torch.__version__}",
        source=source, extra=extra, min_score=meta.min_score, objects=meta.objects)


def export_model(model: nn.Module, checkpoint: dict[str, Any], out: str | os.PathLike,
                 settings: ExportSettings = ExportSettings(), source: str = "",
                 seed: int = 0) -> tuple[OnnxModelInfo, float]:
    """Export ``model`` (fp32) to ``out`` atomically as ``settings`` say; returns (metadata,
    verify max |d|).

    Args:
        model: a DopeNetwork (any module with ``stride`` returning per-stage map pairs).
        checkpoint: its checkpoint dict (object, keypoint order, normalization, config).
        source: the checkpoint's file name (metadata). seed: the tracing input's.
    Raises ConfigError for impossible options, ExportError if the graph does not reproduce
    the model.
    """
    import onnx  # noqa: PLC0415 (onnx (slow to import) only when a file is exported)

    layout, input_hw, dynamic, opset = settings.layout, settings.input_hw, settings.dynamic, settings.opset

    if layout not in LAYOUTS:
        raise ConfigError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    if not MIN_OPSET <= int(opset) <= MAX_OPSET:
        raise ConfigError(f"opset must be {MIN_OPSET}..{MAX_OPSET} (TorchScript exporter), got {opset}")
    stride = int(model.stride)
    if layout == "isaac-ros":
        if stride != ISAAC_ROS_STRIDE and stride not in ISAAC_ROS_RESAMPLED_STRIDES:
            raise ConfigError(
                f"the isaac-ros layout needs maps at 1/8 of the input (Isaac ROS DOPE's decoder scales "
                f"peaks by 8); this model's maps are at stride {stride} (head "
                f"{getattr(model, 'head', '?')}), and pooling them by {ISAAC_ROS_STRIDE // stride} would "
                f"discard what that head is for: export it with --layout native")
        if dynamic:
            raise ConfigError("the isaac-ros layout has a fixed input size (Isaac ROS builds a static "
                              "TensorRT engine); give --height/--width instead of --dynamic")
    if input_hw is None:
        train_hw = ModelInfo.from_checkpoint(checkpoint, source or "<checkpoint>").input_hw
        input_hw = ISAAC_ROS_INPUT_HW if layout == "isaac-ros" else (train_hw or (400, 400))
    h, w = _check_hw(input_hw, "export input size")
    fixed = None if dynamic else (h, w)
    full = ModelInfo.from_checkpoint(checkpoint, source or "<checkpoint>")
    _, group = select_object(full, layout, settings.object_name)
    info = model_info(checkpoint, model, settings, fixed, source)

    was_training = model.training
    model.eval()  # the wrapper must be in eval mode too: BatchNorm with running statistics
    try:
        if layout == "native":
            wrapper: nn.Module = LastStageMaps(model, group).eval()
            dyn = {"image": {0: "N"}, "belief": {0: "N"}, "affinity": {0: "N"}}
            if dynamic:
                dyn = {"image": {0: "N", 2: "H", 3: "W"}, "belief": {0: "N", 2: "h", 3: "w"},
                       "affinity": {0: "N", 2: "h", 3: "w"}}
        else:
            order = output_order(json.loads(info.extra[CHANNEL_ORDER_KEY]))
            order = group_channels(group or 0, full.num_objects)[order]
            wrapper = IsaacRosMaps(model, info.mean, info.std, info.input_mean, info.input_std,
                                   order=order.tolist(), pool=ISAAC_ROS_STRIDE // stride).eval()
            dyn = None
        in_names, out_names = (list(v) for v in LAYOUT_NAMES[layout])
        gen = torch.Generator().manual_seed(seed)
        dummy = torch.randn(1, 3, h, w, generator=gen)
        with atomic_path(out) as tmp:
            _torchscript_export(wrapper, dummy, tmp, int(opset), in_names, out_names, dyn)
            proto = onnx.load(str(tmp))
            _set_metadata(proto, info, _doc(info))
            onnx.checker.check_model(proto)
            onnx.save(proto, str(tmp))
            del proto
            verify = _verify(wrapper, tmp, dummy, layout)
    finally:
        model.train(was_training)
    return info, verify


def _verify(wrapper: nn.Module, path: Path, x: torch.Tensor, layout: str) -> float:
    """max |onnxruntime - torch| on ``x`` (graph-normalized input); ExportError if too large."""
    import onnxruntime as ort  # noqa: PLC0415 (onnxruntime (slow to import) only to verify an export)

    with torch.inference_mode():
        ref = wrapper(x)
    ref = torch.cat(list(ref), 1) if isinstance(ref, (tuple, list)) else ref
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
    got = np.concatenate(got, 1)
    ref = ref.numpy()
    err = float(np.abs(got - ref).max())
    scale = max(1.0, float(np.abs(ref).max()))
    if not np.isfinite(err) or err > VERIFY_TOL * scale:
        raise ExportError(f"{path.name}: onnxruntime differs from PyTorch by {err:.3g} (maps up to "
                          f"{scale:.3g}); the export is wrong, nothing written")
    return err


# ----------------------------------------------------------------------------- top level
