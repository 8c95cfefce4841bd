"""ONNX export of a dope-hope checkpoint: native or Isaac ROS layout, fp32 or static INT8.

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
(:class:`dope_hope.onnx_backend.OnnxModelInfo`): ``dope_hope.format``, ``format_version``,
``class_name``, ``size_m`` (mesh frame, m), ``frame``, ``keypoint_order``, ``mean``/``std``,
``input_mean``/``input_std``, ``stride``, ``head``, ``arch``, ``layout``, ``input_hw``,
``fixed_input_hw``, ``opset``, ``precision``, ``version``, ``exporter``, ``source``, plus
``config`` (the checkpoint's config as JSON), ``input_layout`` and, for INT8,
``quantization``; isaac-ros files add ``isaac_ros.*`` keys (below).

**Isaac ROS layout** (``layout="isaac-ros"``), checked against NVIDIA-ISAAC-ROS/
isaac_ros_pose_estimation (package isaac_ros_dope):

- ``scripts/dope_converter.py`` exports the official network with ``input_names=['input']``,
  ``output_names=['output']``, a ``torch.randn(1, 3, row, col)`` dummy (defaults ``--row 480
  --col 640``, static shapes) and a forward returning ``torch.cat([out6_2, out6_1], 1)``: the
  9 last-stage belief maps, then the 16 affinity fields. ``launch/isaac_ros_dope_tensor_rt
  .launch.py`` binds ``input_binding_names ["input"]`` / ``output_binding_names ["output"]``
  with ``network_image_width 640`` / ``height 480``. The Isaac ROS docs ("Using DOPE at
  Different Image Resolutions") state that the exported ONNX does not support other image
  sizes: the size is fixed at export (so ``dynamic`` is refused here).
- ``gxf/dope/dope_decoder.cpp`` checks the tensor is (1, 25, h, w) (``kNumTensors = 1``,
  ``kInputMapsChannels = 25``), reads channels 0..8 as belief maps (8 corners + centroid)
  and 9 + 2k, 10 + 2k as corner k's affinity, and maps a peak to the image as
  ``(peak + kOffsetDueToUpsampling 0.4395) * kImageToMapScale 8``: stride 8 only (our
  :mod:`dope_hope.mapgrid` puts cell j at 8j + 3.5, i.e. an offset of 0.4375: the same to
  0.016 px). Older ``src/dope_decoder_node.cpp`` hard-codes 60 x 80 maps (640x480 input).
  Its ``CuboidVertices`` corner order (x: + - - + + - - +, y: - - + + - - + +, z: + + + + -
  - - -) is exactly :data:`dope_hope.geometry.CUBOID_CORNER_SIGNS`; its ``dimensions`` are
  the cuboid extents in centimetres (``config/dope_config.yaml``, HOPE entries in the legacy
  frame, e.g. Ketchup [14.86, 4.34, 6.45]), recorded here as
  ``isaac_ros.object_dimensions_cm`` (legacy-frame extents for legacy models, mesh-frame
  extents otherwise).
- The image encoder (isaac_ros_dnn_image_encoder) normalizes with launch arguments
  ``encoder_image_mean`` / ``encoder_image_stddev``: ``[0.5, 0.5, 0.5]`` / ``[0.5, 0.5, 0.5]``
  in ``isaac_ros_dope_tensor_rt.launch.py`` (the default here, ``isaac_encoder="half"``);
  the newer launch fragment ``isaac_ros_dope_core.launch.py`` defaults to ImageNet
  mean/std (``isaac_encoder="imagenet"``). The conversion to this model's normalization is
  folded into the graph as a fixed per-channel affine op at the input,
  ``x_model = (x_isaac * enc_std + enc_mean - mean) / std`` (:class:`IsaacRosMaps`; an
  exact Mul + Add, not folded into the first conv's weights, whose zero padding would then
  no longer pad with the normalized zero). The batch axis is fixed at 1.
- A model whose maps are not at 1/8 (DOPE-DR-400, stride 1; lite head 100, stride 4) is
  **refused** for this layout (:class:`~dope_hope.errors.ConfigError`): the decoder hard-codes
  the x8 scale, and pooling full-resolution maps down by 8 would discard exactly what the
  400-px head is for. Export those in the native layout.

**INT8** (:func:`quantize_int8`): onnxruntime static quantization (``quantize_static``) in
QDQ format with per-channel symmetric INT8 weights and UINT8 activations (onnxruntime's
recommendation for x86 CPUs; ``reduce_range`` off, for VNNI CPUs), calibrated (MinMax by
default) on images of a folder prepared exactly as the predictor prepares them
(:meth:`dope_hope.predictor.DopePredictor.prepare` over the fp32 file's
:class:`~dope_hope.onnx_backend.OnnxBackend`). After quantization fp32 and INT8 run on up to
``eval_images`` of the calibration images and :func:`compare_maps` reports the map and
keypoint deviation (in-sample: the same images calibrated the ranges).
"""
from __future__ import annotations

import json
import os
import tempfile
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dope_hope import __version__
from dope_hope.errors import ConfigError, DopeHopeError, InputFileError
from dope_hope.io.atomic import atomic_path
from dope_hope.io.images import IMAGE_SUFFIXES, image_files
from dope_hope.onnx_backend import LAYOUT_NAMES, LAYOUTS, OnnxBackend, OnnxModelInfo

#: Default ONNX opset and the range the TorchScript exporter handles here.
OPSET = 17
MIN_OPSET, MAX_OPSET = 11, 20
INT8_MIN_OPSET = 13
#: Isaac ROS DOPE defaults: network input (H, W) (dope_converter.py --row/--col).
ISAAC_ROS_INPUT_HW = (480, 640)
#: Isaac ROS image-encoder normalizations (mean, std) by name (see the module docstring).
ISAAC_ENCODERS: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "half": ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5)),
    "imagenet": ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225)),
}
CALIBRATION_METHODS = ("minmax", "entropy", "percentile")
#: Verification tolerance: max |onnxruntime - torch| <= VERIFY_TOL * max(1, max |torch|).
VERIFY_TOL = 1e-3


class ExportError(DopeHopeError):
    """The exported graph does not reproduce the PyTorch model (nothing was written)."""


# ----------------------------------------------------------------------------- wrappers
class LastStageMaps(nn.Module):
    """(N, 3, H, W) -> (belief (N, 9, h, w), affinity (N, 16, h, w)) of the last stage."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        belief, affinity = self.model(x)[-1]
        return belief, affinity


class IsaacRosMaps(nn.Module):
    """Isaac ROS DOPE graph: encoder-normalized (1, 3, H, W) -> (1, 25, H/8, W/8).

    ``x_model = x * (enc_std / std) + (enc_mean - mean) / std`` (fixed per-channel affine op),
    then the network; output = cat(belief (9), affinity (16)) of the last stage.
    """

    def __init__(self, model: nn.Module, mean: Sequence[float], std: Sequence[float],
                 enc_mean: Sequence[float], enc_std: Sequence[float]):
        super().__init__()
        self.model = model
        m, s = torch.tensor(mean, dtype=torch.float32), torch.tensor(std, dtype=torch.float32)
        em, es = torch.tensor(enc_mean, dtype=torch.float32), torch.tensor(enc_std, dtype=torch.float32)
        self.register_buffer("scale", (es / s).view(1, 3, 1, 1))
        self.register_buffer("shift", ((em - m) / s).view(1, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        belief, affinity = self.model(x * self.scale + self.shift)[-1]
        return torch.cat([belief, affinity], 1)


# ----------------------------------------------------------------------------- results
@dataclass
class MapDeviation:
    """How far a model's maps and decoded keypoints are from a reference's.

    images: number of images compared. max_abs / mean_abs: over all belief + affinity
    values; belief_max_abs: belief maps only. instances_ref / instances_test: decoded
    instances; instances_matched: pairs matched by centroid. keypoints_compared: keypoints
    found in both of a matched pair; keypoints_lost / keypoints_added: found in only the
    reference / only the test instance. median_px / max_px: keypoint distance, image px
    (NaN when nothing was compared); p95_px: its 95th percentile. peaks_*: the same per
    belief peak, without grouping (every sub-pixel peak of the reference above the decode
    threshold, matched one-to-one to the test's peaks of the same channel within one map
    cell): meaningful even for maps that decode no instance (e.g. untrained weights).
    """

    images: int
    max_abs: float
    mean_abs: float
    belief_max_abs: float
    instances_ref: int
    instances_test: int
    instances_matched: int
    keypoints_compared: int
    keypoints_lost: int
    keypoints_added: int
    median_px: float
    max_px: float
    p95_px: float = float("nan")
    peaks_ref: int = 0
    peaks_matched: int = 0
    peak_median_px: float = float("nan")
    peak_max_px: float = float("nan")

    def summary(self) -> str:
        """One line for reports."""
        kp = (f"keypoints: median {self.median_px:.3f} px, p95 {self.p95_px:.3f} px, max "
              f"{self.max_px:.3f} px over {self.keypoints_compared} ({self.keypoints_lost} lost, "
              f"{self.keypoints_added} added; instances {self.instances_matched}/{self.instances_ref} matched)"
              if self.keypoints_compared else
              f"keypoints: none to compare (reference decodes {self.instances_ref} instances)")
        peaks = (f"; peaks: median {self.peak_median_px:.3f} px, max {self.peak_max_px:.3f} px, "
                 f"{self.peaks_matched}/{self.peaks_ref} matched" if self.peaks_ref else "")
        return (f"maps max |d| {self.max_abs:.4g}, mean |d| {self.mean_abs:.3g} "
                f"(belief max {self.belief_max_abs:.4g}) over {self.images} images; {kp}{peaks}")


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


# ----------------------------------------------------------------------------- comparison
def _match_instances(ref, test, max_px: float):
    from scipy.optimize import linear_sum_assignment

    if not ref or not test:
        return []
    a = np.array([r.keypoints[8] for r in ref])
    b = np.array([t.keypoints[8] for t in test])
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    d = np.where(np.isfinite(d), d, 1e9)
    rows, cols = linear_sum_assignment(d)
    return [(r, c) for r, c in zip(rows, cols) if d[r, c] <= max_px]


def _peak_distances(ref_belief: np.ndarray, test_belief: np.ndarray, stride: int,
                    threshold: float, smooth_sigma: float) -> tuple[int, np.ndarray]:
    """(number of reference peaks, distances of the matched ones in image px)."""
    from scipy.optimize import linear_sum_assignment

    from dope_hope.decode import find_peaks

    pr = find_peaks(ref_belief, threshold=threshold, smooth_sigma=smooth_sigma)
    pt = find_peaks(test_belief, threshold=threshold, smooth_sigma=smooth_sigma)
    out = []
    for c in np.unique(pr.channel):
        a, b = pr.xy[pr.channel == c], pt.xy[pt.channel == c]
        if not len(b):
            continue
        d = np.linalg.norm(a[:, None] - b[None], axis=2)
        rows, cols = linear_sum_assignment(d)
        keep = d[rows, cols] <= 1.0  # map cells
        out.append(d[rows, cols][keep] * stride)
    return len(pr.channel), (np.concatenate(out) if out else np.zeros(0))


def compare_maps(reference: Sequence[tuple[np.ndarray, np.ndarray]],
                 test: Sequence[tuple[np.ndarray, np.ndarray]], stride: int,
                 match_px: float | None = None, **decode_options: Any) -> MapDeviation:
    """Map and keypoint deviation of ``test`` from ``reference`` (one (belief, affinity) per image).

    Maps: (9, h, w) and (16, h, w) per image (a leading batch of 1 is dropped). Keypoints:
    both are decoded with :func:`dope_hope.decode.decode_maps` (``decode_options``),
    instances are matched one-to-one by centroid (within ``match_px`` image px, default 4
    map cells), and the distance of every keypoint found in both is measured, image px.
    Belief peaks are also compared one by one, without grouping (:class:`MapDeviation`).
    """
    from dope_hope.decode import DEFAULT_SMOOTH_SIGMA, DEFAULT_THRESHOLD, decode_maps

    if len(reference) != len(test) or not reference:
        raise ValueError("compare_maps needs the same non-zero number of reference and test images")
    match_px = 4.0 * stride if match_px is None else float(match_px)
    max_abs = belief_max = 0.0
    abs_sum, count = 0.0, 0
    n_ref = n_test = n_match = lost = added = 0
    dists: list[np.ndarray] = []
    n_peaks, peak_d = 0, []
    for (rb, ra), (tb, ta) in zip(reference, test):
        rb, ra, tb, ta = (np.asarray(x, np.float32).reshape(x.shape[-3:]) for x in (rb, ra, tb, ta))
        db, da = np.abs(rb - tb), np.abs(ra - ta)
        belief_max = max(belief_max, float(db.max()))
        max_abs = max(max_abs, belief_max, float(da.max()))
        abs_sum += float(db.sum(dtype=np.float64) + da.sum(dtype=np.float64))
        count += db.size + da.size
        ri = decode_maps(rb, ra, stride, **decode_options)
        ti = decode_maps(tb, ta, stride, **decode_options)
        n_ref, n_test = n_ref + len(ri), n_test + len(ti)
        for r, c in _match_instances(ri, ti, match_px):
            n_match += 1
            pr, pt = ri[r].present, ti[c].present
            both = pr & pt
            lost += int((pr & ~pt).sum())
            added += int((pt & ~pr).sum())
            dists.append(np.linalg.norm(ri[r].keypoints[both] - ti[c].keypoints[both], axis=1))
        n, pd = _peak_distances(rb, tb, stride, decode_options.get("threshold", DEFAULT_THRESHOLD),
                                decode_options.get("smooth_sigma", DEFAULT_SMOOTH_SIGMA))
        n_peaks += n
        peak_d.append(pd)
    d = np.concatenate(dists) if dists else np.zeros(0)
    p = np.concatenate(peak_d)
    return MapDeviation(
        images=len(reference), max_abs=max_abs, mean_abs=abs_sum / max(count, 1), belief_max_abs=belief_max,
        instances_ref=n_ref, instances_test=n_test, instances_matched=n_match,
        keypoints_compared=int(d.size), keypoints_lost=lost, keypoints_added=added,
        median_px=float(np.median(d)) if d.size else float("nan"),
        max_px=float(d.max()) if d.size else float("nan"),
        p95_px=float(np.percentile(d, 95)) if d.size else float("nan"),
        peaks_ref=n_peaks, peaks_matched=int(p.size),
        peak_median_px=float(np.median(p)) if p.size else float("nan"),
        peak_max_px=float(p.max()) if p.size else float("nan"))


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
    return (f"dope-hope {info.precision} DOPE belief/affinity network for {info.class_name} "
            f"({info.arch}, head {info.head}, stride {info.stride}, {info.layout} layout: "
            f"{', '.join(names[0])} -> {', '.join(names[1])}, input {size}, RGB normalized "
            f"with mean {list(info.input_mean)} std {list(info.input_std)}). Metadata keys dope_hope.*.")


def model_info(checkpoint: dict[str, Any], model: nn.Module, layout: str,
               fixed_input_hw: tuple[int, int] | None, opset: int, isaac_encoder: str = "half",
               source: str = "") -> OnnxModelInfo:
    """The :class:`OnnxModelInfo` of a checkpoint exported in ``layout``."""
    from dope_hope.predictor import metadata_from_checkpoint

    meta = metadata_from_checkpoint(checkpoint, source or "<checkpoint>")
    mean, std = meta["mean"], meta["std"]
    input_mean, input_std = (mean, std) if layout == "native" else ISAAC_ENCODERS[isaac_encoder]
    extra = {
        "config": json.dumps(checkpoint.get("config"), default=str, sort_keys=True),
        "input_layout": "NCHW float32 RGB, (rgb / 255 - input_mean) / input_std",
    }
    if layout == "isaac-ros":
        size = np.asarray(meta["size_m"], dtype=np.float64)
        if meta["frame"] == "legacy":  # Isaac ROS lists the legacy-frame extents (dope_config.yaml)
            from dope_hope.geometry import LEGACY_TO_MESH

            size = np.abs(LEGACY_TO_MESH).T @ size
        extra["isaac_ros.object_dimensions_cm"] = json.dumps([round(float(v) * 100.0, 4) for v in size])
        extra["isaac_ros.encoder"] = isaac_encoder
    return OnnxModelInfo(
        class_name=meta["class_name"], size_m=tuple(float(v) for v in meta["size_m"]),
        frame=meta["frame"], keypoint_order=meta["keypoint_order"], mean=tuple(mean), std=tuple(std),
        input_mean=tuple(float(v) for v in input_mean), input_std=tuple(float(v) for v in input_std),
        stride=int(model.stride), head=int(getattr(model, "head", 0)), arch=str(getattr(model, "arch", "")),
        layout=layout, input_hw=meta["input_hw"], fixed_input_hw=fixed_input_hw, opset=int(opset),
        precision="fp32", version=__version__,
        exporter=f"torch.onnx.export(dynamo=False) TorchScript exporter, torch {torch.__version__}",
        source=source, extra=extra)


def export_model(model: nn.Module, checkpoint: dict[str, Any], out: str | os.PathLike,
                 layout: str = "native", input_hw: Sequence[int] | None = None,
                 dynamic: bool = False, opset: int = OPSET, isaac_encoder: str = "half",
                 source: str = "", seed: int = 0) -> tuple[OnnxModelInfo, float]:
    """Export ``model`` (fp32) to ``out`` atomically; returns (metadata, verify max |d|).

    Args:
        model: a DopeNetwork (any module with ``stride`` returning per-stage map pairs).
        checkpoint: its checkpoint dict (object, keypoint order, normalization, config).
        layout: "native" or "isaac-ros" (see the module docstring).
        input_hw: (H, W), multiples of 8. Default: the training input size (native) or
            480x640 (isaac-ros). With ``dynamic`` it only sizes the tracing input.
        dynamic: native only: H and W dynamic (the batch axis always is).
        opset: ONNX opset (11..20).
        isaac_encoder: "half" (mean = std = 0.5) or "imagenet": the Isaac ROS encoder's.
    Raises ConfigError for impossible options, ExportError if the graph does not reproduce
    the model.
    """
    import onnx

    if layout not in LAYOUTS:
        raise ConfigError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    if not MIN_OPSET <= int(opset) <= MAX_OPSET:
        raise ConfigError(f"opset must be {MIN_OPSET}..{MAX_OPSET} (TorchScript exporter), got {opset}")
    if isaac_encoder not in ISAAC_ENCODERS:
        raise ConfigError(f"isaac encoder normalization must be one of {', '.join(ISAAC_ENCODERS)}, "
                          f"got {isaac_encoder!r}")
    stride = int(model.stride)
    if layout == "isaac-ros":
        if stride != 8:
            raise ConfigError(
                f"the isaac-ros layout needs maps at 1/8 of the input (Isaac ROS DOPE's decoder scales "
                f"peaks by 8); this model's maps are at stride {stride} (head "
                f"{getattr(model, 'head', '?')}): export it with --layout native")
        if dynamic:
            raise ConfigError("the isaac-ros layout has a fixed input size (Isaac ROS builds a static "
                              "TensorRT engine); give --height/--width instead of --dynamic")
    if input_hw is None:
        from dope_hope.predictor import metadata_from_checkpoint

        train_hw = metadata_from_checkpoint(checkpoint, source or "<checkpoint>")["input_hw"]
        input_hw = ISAAC_ROS_INPUT_HW if layout == "isaac-ros" else (train_hw or (400, 400))
    h, w = _check_hw(input_hw, "export input size")
    fixed = None if dynamic else (h, w)
    info = model_info(checkpoint, model, layout, fixed, int(opset), isaac_encoder, source)

    was_training = model.training
    model.eval()  # the wrapper must be in eval mode too: BatchNorm with running statistics
    try:
        if layout == "native":
            wrapper: nn.Module = LastStageMaps(model).eval()
            dyn = {"image": {0: "N"}, "belief": {0: "N"}, "affinity": {0: "N"}}
            if dynamic:
                dyn = {"image": {0: "N", 2: "H", 3: "W"}, "belief": {0: "N", 2: "h", 3: "w"},
                       "affinity": {0: "N", 2: "h", 3: "w"}}
        else:
            enc_mean, enc_std = ISAAC_ENCODERS[isaac_encoder]
            wrapper = IsaacRosMaps(model, info.mean, info.std, enc_mean, enc_std).eval()
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
    import onnxruntime as ort

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


# ----------------------------------------------------------------------------- INT8
def list_images(folder: str | os.PathLike, limit: int | None = None) -> list[Path]:
    """Sorted RGB image files of a folder (depth/segmentation images of DOPE folders skipped)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(folder, "calibration folder not found")
    files = [p for p in image_files(folder) if not p.name.lower().endswith((".depth.png", ".seg.png"))]
    if not files:
        raise InputFileError(folder, f"no calibration images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    return files[:limit] if limit else files


class ImageFolderReader:
    """onnxruntime ``CalibrationDataReader`` over images prepared like the predictor does.

    Each image is read as RGB, resized/padded/normalized by
    :meth:`dope_hope.predictor.DopePredictor.prepare` for ``backend`` (the fp32 model being
    quantized) and converted to the graph input's normalization by
    :meth:`OnnxBackend.feeds` (isaac-ros: the encoder's).
    """

    def __init__(self, backend: OnnxBackend, files: Sequence[Path]):
        from dope_hope.predictor import DopePredictor

        self.backend = backend
        self.predictor = DopePredictor(backend)
        self.files = list(files)
        self._iter = None

    def prepare(self, path: Path) -> np.ndarray:
        """(1, 3, H, W) model-normalized batch of one image file, as the predictor makes it."""
        from dope_hope.io.images import read_rgb

        return self.predictor.prepare(read_rgb(path)).batch

    def feeds(self, path: Path) -> list[dict[str, np.ndarray]]:
        return self.backend.feeds(self.prepare(path))

    def get_next(self) -> dict[str, np.ndarray] | None:
        if self._iter is None:
            self._iter = (f for p in self.files for f in self.feeds(p))
        return next(self._iter, None)

    def rewind(self) -> None:
        self._iter = None


def output_convs(model_proto) -> list[str]:
    """Names of the Conv nodes whose outputs reach the graph outputs through data-movement ops.

    These (the last 1x1 convs of the final stage) stay in float during INT8 quantization: the
    maps come out unquantized (no 1/255-of-range output step on the belief peaks) for a
    negligible share of the compute.
    """
    producer = {o: n for n in model_proto.graph.node for o in n.output}
    passthrough = {"Slice", "Concat", "Split", "Identity", "Reshape", "Squeeze", "Unsqueeze"}
    found, stack, seen = [], [o.name for o in model_proto.graph.output], set()
    while stack:
        node = producer.get(stack.pop())
        if node is None or node.name in seen:
            continue
        seen.add(node.name)
        if node.op_type == "Conv":
            found.append(node.name)
        elif node.op_type in passthrough:
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
    import onnx
    from onnxruntime.quantization import (CalibrationMethod, QuantFormat, QuantType, quant_pre_process,
                                          quantize_static)

    if method not in CALIBRATION_METHODS:
        raise ConfigError(f"calibration method must be one of {', '.join(CALIBRATION_METHODS)}, got {method!r}")
    fp32 = OnnxBackend(fp32_path, threads=threads, providers=["CPUExecutionProvider"])
    if fp32.info.precision != "fp32":
        raise ConfigError(f"{fp32_path}: already {fp32.info.precision}; quantize the fp32 export")
    if fp32.info.opset < INT8_MIN_OPSET:
        raise ConfigError(f"INT8 (per-channel QDQ) needs opset >= {INT8_MIN_OPSET}, the model has {fp32.info.opset}")
    files = list_images(calibration, max_images)
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
        keep_float = output_convs(onnx.load(str(pre)))
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
        int8 = OnnxBackend(tmp, threads=threads, providers=["CPUExecutionProvider"])
        ref, test = [], []
        for path in files[:max(1, eval_images)]:
            batch = reader.prepare(path)
            ref.append(tuple(m[0] for m in fp32.run(batch)))
            test.append(tuple(m[0] for m in int8.run(batch)))
        deviation = compare_maps(ref, test, info.stride)
        del int8
    return info, deviation


# ----------------------------------------------------------------------------- top level
def export_checkpoint(weights: str | os.PathLike, out: str | os.PathLike, height: int | None = None,
                      width: int | None = None, dynamic: bool = False, layout: str = "native",
                      int8: bool = False, calibration: str | os.PathLike | None = None,
                      opset: int = OPSET, isaac_encoder: str = "half", calibration_images: int = 32,
                      calibration_method: str = "minmax") -> ExportResult:
    """Load a checkpoint and export it (see :func:`export_model`, :func:`quantize_int8`).

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
    model, ckpt = load_model(weights)
    hw = None if height is None else (height, width)
    if not int8:
        info, verify = export_model(model, ckpt, out, layout, hw, dynamic, opset, isaac_encoder, weights.name)
        deviation = None
    else:
        with tempfile.TemporaryDirectory(prefix="dope-hope-export-") as tmpdir:
            fp32_path = Path(tmpdir) / f"{out.stem}.fp32.onnx"
            _, verify = export_model(model, ckpt, fp32_path, layout, hw, dynamic, opset, isaac_encoder,
                                     weights.name)
            del model
            info, deviation = quantize_int8(fp32_path, out, calibration, calibration_images,
                                            calibration_method)
    return ExportResult(path=out, info=info, verify_max_abs=verify, int8=deviation,
                        seconds=time.perf_counter() - t0, size_bytes=out.stat().st_size)
