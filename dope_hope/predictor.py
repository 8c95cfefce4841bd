"""DopePredictor: an image (+ K, optional depth) -> mesh-frame 6-DoF detections of one object.

One predictor owns one network (one object class per model, as DOPE); several predictors can
run on one image (:func:`predict_many`). The pipeline of :meth:`DopePredictor.predict`:

1. **Image layout** (:func:`to_rgb8`): any (H, W), (H, W, 1|2|3|4) array, uint8 / uint16 /
   float in [0, 1], RGB order. Grayscale is replicated to three channels; a uint16 image is
   reduced to 8 bits and an alpha channel with non-opaque pixels is dropped - both with a
   ``warnings.warn`` because information is lost.
2. **Working size** (:meth:`DopePredictor.working_size`): the image is resized keeping its
   aspect ratio (``cv2.INTER_AREA`` down, ``INTER_LINEAR`` up). ``height=int``: that height.
   ``height=None`` (default): the scale the model was trained at - the image is fitted inside
   the checkpoint's training input size (``config.input.size``, the "contain" fit of the
   training/validation transform); official DOPE weights (legacy frame) and models without a
   recorded input size use height 400, the official DOPE inference height. The resized image
   is then **padded** at the right/bottom to a multiple of 8 (with zeros after normalization,
   i.e. the normalization mean colour, as the training letterbox), so the origin stays put and
   K only scales: ``K_net = geometry.scale_intrinsics(K, W'/W, H'/H)`` with the exact integer
   sizes (pixel centres at integer coordinates: ``u' = s (u + 0.5) - 0.5``). A backend with a
   fixed input size (``fixed_input_hw``) gets the image fitted inside and padded up to it.
3. **Maps** from the backend (:class:`MapBackend`, last stage), normalized with the model's
   recorded mean/std.
4. **Decode and PnP** in network-image pixels with ``K_net``, so the pixel thresholds mean
   the same whatever the original resolution. ``pose_search="hypotheses"`` (default): each
   centroid keeps every corner peak whose affinity points at it
   (:func:`dope_hope.decode.corner_candidates`, up to 3 per corner type) and
   :func:`dope_hope.pose.solve_pnp_candidates` finds the pose that explains most of them, so a
   second peak of map k on another corner of the box (the lite models' commonest error) or a
   spurious centroid sharing the true corners no longer costs the detection (demo scenes
   found, 120 scenes: 89 -> 104 with the 40-minute model, 99 -> 109 with the shipped one;
   bench/demo_pose_search.py). Two centroids explaining the same peaks give one detection, the
   higher-scoring. ``pose_search="groups"``: DOPE's decoding, one corner per type and
   centroid (:func:`dope_hope.decode.decode_maps`), then :func:`dope_hope.pose.solve_pnp`.
   The cuboid is the model's: the checkpoint's size (mesh frame) or, with ``mesh=``, the
   mesh's own bounding box (size and
   centre; a size differing from the checkpoint's by more than 25 % is refused as a unit
   mistake). **Legacy frame** (official HOPE weights): PnP runs on the legacy cuboid
   (``LEGACY_TO_MESH^T`` applied to the mesh box, keypoints in the legacy order) and the
   rotation is converted with :func:`geometry.legacy_rotation_to_mesh`, so every returned pose
   is a mesh-frame pose; keypoints are reordered into the current order.
5. **Back to the original image**: keypoints ``u = (u' + 0.5) / s - 0.5``; the pose needs no
   change (K_net and K describe the same camera).
6. **Depth line search** ("-LS", optional, :func:`dope_hope.pose.depth_line_search`) with the
   original K and a depth image of the original size. Model points: ``ls_points`` farthest-point
   samples of the mesh surface when ``mesh=`` is given, else of the **cuboid's surface** (an
   approximation: for a non-box object the box's front face lies in front of the real surface
   by up to half the box depth, which biases the refined distance away from the camera's
   expectation; pass the mesh for non-box objects).
7. **Depth ICP** ("-ICP", optional, ``icp=True``, needs the depth; :func:`dope_hope.icp.icp_refine`):
   after the line search, point-to-plane ICP of ``icp_points`` model points (with normals)
   against the depth pixels under the object refines all six DoF, from the pose and from it
   turned by +-90 / 180 deg about each model axis; kept only when it does not fit the depth
   worse. Without ``mesh=`` only the catalog's boxes are allowed (the cuboid's surface is
   theirs). ICP needs the object's depth within a few centimetres: when the line search
   refused (e.g. its optimum sat on the 0.8 / 1.25 bound because the keypoints put the object
   at a wrong distance), the ICP stage first repeats it over :data:`ICP_LS_SEARCH`. The line
   search only rescales t and keeps the keypoints' rotation; ICP also corrects the rotation,
   which is where lite models err most (HOPE Ketchup e2e, bench/RESULTS.md: recall at 2 cm
   MeanSSD 11.6 % with -LS, 38.4 % with -LS + ICP on the same maps).

Every detection is a :class:`Detection`; :meth:`Detection.to_json` writes one record of the
predictions JSON-lines format (:mod:`dope_hope.io.predictions`) that ``dope-hope evaluate``
reads.
"""
from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from dope_hope.decode import corner_candidates, decode_maps
from dope_hope.errors import CameraError, ConfigError, ModelFileError, UnknownObjectError
from dope_hope.geometry import (
    KEYPOINT_ORDER,
    LEGACY_KEYPOINT_ORDER,
    LEGACY_TO_MESH,
    NUM_KEYPOINTS,
    cuboid_keypoints,
    legacy_keypoints_to_current,
    legacy_rotation_to_mesh,
    matrix_to_quaternion_xyzw,
    project_points,
    scale_intrinsics,
)
from dope_hope.icp import icp_refine
from dope_hope.pose import PoseEstimate, depth_line_search, solve_pnp, solve_pnp_candidates

#: Official DOPE inference height (``config_pose.yaml`` ``downscale_height``), pixels.
DEFAULT_HEIGHT = 400
#: The network input must have H and W divisible by this (the trunk's stride).
INPUT_MULTIPLE = 8
#: Model points used by the depth line search.
DEFAULT_LS_POINTS = 1000
#: Model points (with normals) used by the depth ICP.
DEFAULT_ICP_POINTS = 2000
#: Scale range of the line search the ICP stage repeats when the default one refused.
ICP_LS_SEARCH = (0.5, 2.0)
#: A mesh's box may differ from the checkpoint's cuboid by at most this factor per extent.
MESH_SIZE_TOLERANCE = 1.25
BACKENDS = ("auto", "torch", "onnx")
POSE_SEARCHES = ("hypotheses", "groups")


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
            from dope_hope.onnx_backend import OnnxBackend
        except ModuleNotFoundError as exc:
            if exc.name != "dope_hope.onnx_backend":
                raise
            raise ConfigError("the ONNX backend (dope_hope.onnx_backend) is not available") from None
        # "cpu" keeps onnxruntime on the CPU; "cuda..." lets it take CUDA when it has it.
        providers = None if str(device).startswith("cuda") else ["CPUExecutionProvider"]
        return OnnxBackend(path, threads=threads, providers=providers)
    if is_onnx:
        raise ModelFileError(path, "an ONNX model; use backend 'onnx' or 'auto'")
    if threads:
        import torch

        torch.set_num_threads(int(threads))
    return TorchBackend.load(path, device=device)


# ----------------------------------------------------------------------------- images
def to_rgb8(image: np.ndarray) -> np.ndarray:
    """Any image array -> (H, W, 3) uint8 RGB (see the module docstring for what is accepted).

    Warns (``UserWarning``) when information is lost: 16 -> 8 bits, a non-opaque alpha dropped.
    Raises ValueError for other layouts / dtypes.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (2, 3, 4)):
        raise ValueError(f"expected an (H, W), (H, W, 1), (H, W, 2), (H, W, 3) or (H, W, 4) "
                         f"image, got shape {img.shape}")
    if img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"empty image of shape {img.shape}")
    if img.dtype == np.uint16:
        warnings.warn("16-bit image reduced to 8 bits per channel (the network takes 8-bit RGB)",
                      UserWarning, stacklevel=3)
        img = (img / 257.0 + 0.5).astype(np.uint8)
    elif np.issubdtype(img.dtype, np.floating):
        finite = img[np.isfinite(img)]
        if finite.size != img.size or (finite.size and (finite.min() < -1e-6 or finite.max() > 1 + 1e-6)):
            raise ValueError("a float image must hold finite values in [0, 1]")
        img = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ValueError(f"unsupported image dtype {img.dtype} (use uint8, uint16 or float in [0, 1])")
    if img.ndim == 3 and img.shape[2] in (2, 4):
        alpha = img[:, :, -1]
        if np.any(alpha != 255):
            frac = float(np.mean(alpha != 255))
            warnings.warn(f"alpha channel dropped ({100 * frac:.1f} % of the pixels are not opaque; "
                          "their colour is used as is)", UserWarning, stacklevel=3)
        img = img[:, :, :-1]
        if img.shape[2] == 1:
            img = img[:, :, 0]
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img)


def _round_up(n: int, multiple: int) -> int:
    return int(math.ceil(n / multiple) * multiple)


@dataclass
class NetworkInput:
    """An image prepared for the network.

    batch: (1, 3, Hp, Wp) float32 normalized, padded (zeros) right/bottom.
    resized_hw: (H', W') of the resized image content inside the batch.
    original_hw: (H, W) of the original image.
    scale: (sx, sy) = (W'/W, H'/H).
    """

    batch: np.ndarray
    resized_hw: tuple[int, int]
    original_hw: tuple[int, int]
    scale: tuple[float, float]

    def to_network_px(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) original-image pixels -> network-input pixels."""
        s = np.asarray(self.scale)
        return s * (np.asarray(uv, dtype=np.float64) + 0.5) - 0.5

    def to_original_px(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) network-input pixels -> original-image pixels (NaN stays NaN)."""
        s = np.asarray(self.scale)
        return (np.asarray(uv, dtype=np.float64) + 0.5) / s - 0.5

    def network_K(self, K: np.ndarray) -> np.ndarray:
        """(3, 3) intrinsics of the network input for the original image's K."""
        return scale_intrinsics(K, *self.scale)

    def maps_on_image(self, maps: np.ndarray, stride: int) -> np.ndarray:
        """(C, h, w) maps of this input -> (C, H', W') on the resized image (padding cropped).

        Bilinear, cell ``j`` centred at network pixel ``j*stride + (stride-1)/2`` (mapgrid);
        the result covers exactly the original image's field of view (for display).
        """
        m = np.asarray(maps, dtype=np.float32)
        Hp, Wp = self.batch.shape[2:]
        Hr, Wr = self.resized_hw
        if stride != 1:
            up = cv2.resize(np.ascontiguousarray(m.transpose(1, 2, 0)), (m.shape[2] * stride, m.shape[1] * stride),
                            interpolation=cv2.INTER_LINEAR)
            m = up.reshape(up.shape[0], up.shape[1], -1).transpose(2, 0, 1)
        return np.ascontiguousarray(m[:, :Hr, :Wr])


def prepare_input(rgb: np.ndarray, resized_hw: tuple[int, int], mean: Sequence[float],
                  std: Sequence[float], padded_hw: tuple[int, int] | None = None) -> NetworkInput:
    """Resize (H, W, 3) uint8 RGB to ``resized_hw``, normalize, pad to ``padded_hw``.

    ``padded_hw`` defaults to ``resized_hw`` rounded up to multiples of 8.
    """
    H, W = rgb.shape[:2]
    Hr, Wr = int(resized_hw[0]), int(resized_hw[1])
    if (Hr, Wr) != (H, W):
        interp = cv2.INTER_AREA if Hr < H and Wr < W else cv2.INTER_LINEAR
        rgb = cv2.resize(rgb, (Wr, Hr), interpolation=interp)
    if padded_hw is None:
        padded_hw = (_round_up(Hr, INPUT_MULTIPLE), _round_up(Wr, INPUT_MULTIPLE))
    x = rgb.astype(np.float32) / np.float32(255.0)
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    batch = np.zeros((1, 3, int(padded_hw[0]), int(padded_hw[1])), np.float32)
    batch[0, :, :Hr, :Wr] = x.transpose(2, 0, 1)
    return NetworkInput(batch=batch, resized_hw=(Hr, Wr), original_hw=(H, W), scale=(Wr / W, Hr / H))


def check_intrinsics(K: Any) -> np.ndarray:
    """(3, 3) float64 K with positive focal lengths; CameraError otherwise."""
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraError("camera intrinsics K must be a 3x3 matrix of numbers") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise CameraError(f"camera intrinsics K must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise CameraError(f"camera intrinsics K is not a pinhole matrix (fx, fy > 0, last row "
                          f"0 0 1): {K.tolist()}")
    return K


# ----------------------------------------------------------------------------- detections
@dataclass
class Detection:
    """One detected object, mesh-frame pose (``x_c = R x + t``).

    class_name: the model's object. score: pose score in [0, 1] (:func:`pose.solve_pnp`).
    R: (3, 3). t: (3,) metres (after the line search when applied).
    keypoints_2d: (9, 2) detected cuboid keypoints, original-image px, current keypoint order
        (geometry.CUBOID_CORNER_SIGNS, then the centre); NaN where not found.
    keypoint_scores: (9,) belief at each keypoint (0 where missing), same order.
    inliers: (9,) bool, keypoints consistent with the pose, same order.
    projected_2d: (9, 2) the cuboid keypoints projected under (R, t), original-image px.
    reprojection_error_px: mean inlier reprojection error, original-image px.
    cuboid_size_m, cuboid_center_m: the mesh-frame box used, metres.
    ls_applied / ls_reason / ls_scale: outcome of the depth line search ("no depth image"
        when none was given).
    icp_applied / icp_reason / icp_fit: outcome of the depth ICP ("not requested" without
        ``icp=True``); icp_fit: soft fraction of the depth points under the object that lie on
        the model surface under the returned pose (1 = all; :func:`dope_hope.icp.icp_refine`;
        NaN when not evaluated).
    """

    class_name: str
    score: float
    R: np.ndarray
    t: np.ndarray
    keypoints_2d: np.ndarray
    keypoint_scores: np.ndarray
    inliers: np.ndarray
    projected_2d: np.ndarray
    reprojection_error_px: float
    cuboid_size_m: np.ndarray
    cuboid_center_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ls_applied: bool = False
    ls_reason: str = "no depth image"
    ls_scale: float = 1.0
    icp_applied: bool = False
    icp_reason: str = "not requested"
    icp_fit: float = float("nan")

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """(4,) scalar-last quaternion of R (w >= 0)."""
        return matrix_to_quaternion_xyzw(self.R)

    def to_json(self, image: str | None = None, **extra: Any) -> dict[str, Any]:
        """One record of the predictions JSON-lines format (:mod:`dope_hope.io.predictions`,
        read by :mod:`dope_hope.evaluate`): ``image``, ``class``, ``score``, ``R`` (3x3 rows),
        ``t`` (m), ``ls_applied``, plus ``quaternion_xyzw``, ``ls_reason``, ``ls_scale``,
        ``keypoints_2d`` (9 x [u, v] original px, null where missing), ``keypoint_scores``,
        ``reprojection_error_px``, ``cuboid_size_m`` and, with ICP requested, ``icp_applied``,
        ``icp_reason`` and ``icp_fit``, which the evaluation ignores.

        ``image`` names the frame (omitted when None: then pass ``scene_id``/``im_id``);
        ``extra`` adds keys (e.g. ``time``, ``scene_id``). The result is strict JSON (no NaN).
        """
        from dope_hope.io.predictions import prediction_record

        kp = [[None if not math.isfinite(v) else round(float(v), 3) for v in row]
              for row in np.asarray(self.keypoints_2d, dtype=np.float64)]
        rec = prediction_record(
            "" if image is None else image, self.class_name, self.score, self.R, self.t,
            ls_applied=self.ls_applied,
            quaternion_xyzw=[float(v) for v in self.quaternion_xyzw],
            ls_reason=self.ls_reason, ls_scale=float(self.ls_scale), keypoints_2d=kp,
            keypoint_scores=[round(float(v), 4) for v in self.keypoint_scores],
            reprojection_error_px=round(float(self.reprojection_error_px), 4),
            cuboid_size_m=[float(v) for v in self.cuboid_size_m], **extra)
        if self.icp_reason != "not requested":
            rec.update(icp_applied=self.icp_applied, icp_reason=self.icp_reason,
                       icp_fit=None if not math.isfinite(self.icp_fit) else round(float(self.icp_fit), 4))
        if image is None:
            del rec["image"]
        return rec


# ----------------------------------------------------------------------------- predictor
class DopePredictor:
    """A network for one object and everything to turn images into :class:`Detection` s.

    Args:
        weights: a dope-hope checkpoint (``.pth``/``.pt``), an exported ``.onnx`` model, or a
            ready :class:`MapBackend` instance.
        backend: "auto" (ONNX for ``.onnx``, else torch), "torch" or "onnx".
        device: torch device, or "cuda..." to ask onnxruntime for its CUDA provider.
        height: network working height in pixels, or None for the model's training scale
            (see the module docstring).
        mesh: optional mesh file (or loaded ``trimesh.Trimesh`` in metres) of the object: its
            box replaces the checkpoint's cuboid and its surface feeds the depth line search.
        mesh_units: units of the mesh file ("m", "cm", "mm"; default by suffix).
        pose_search: "hypotheses" (default) or "groups" (see the module docstring, step 4).
        decode_options: keyword arguments of :func:`dope_hope.decode.corner_candidates`
            ("hypotheses") or :func:`dope_hope.decode.decode_maps` ("groups").
        pnp_options: keyword arguments of :func:`dope_hope.pose.solve_pnp`.
        hypothesis_options: keyword arguments of :func:`dope_hope.pose.solve_pnp_candidates`
            (``hypothesis_threshold_px``, ``max_hypotheses``).
        line_search_options: keyword arguments of :func:`dope_hope.pose.depth_line_search`.
        icp: with a depth image, refine each pose by ICP after the line search (step 7); needs
            ``mesh=`` unless the object is a box of the HOPE catalog (ConfigError otherwise).
        icp_options: keyword arguments of :func:`dope_hope.icp.icp_refine`.
        icp_points: number of model points (with normals) for ICP.
        min_score: drop detections whose pose score is lower.
        ls_points: number of model points for the line search.
        threads: CPU threads (torch.set_num_threads / onnxruntime intra-op threads).
    """

    def __init__(
        self,
        weights: str | os.PathLike | MapBackend,
        backend: str = "auto",
        device: str = "cpu",
        height: int | None = None,
        mesh: Any = None,
        mesh_units: str | None = None,
        pose_search: str = "hypotheses",
        decode_options: dict[str, Any] | None = None,
        pnp_options: dict[str, Any] | None = None,
        hypothesis_options: dict[str, Any] | None = None,
        line_search_options: dict[str, Any] | None = None,
        icp: bool = False,
        icp_options: dict[str, Any] | None = None,
        icp_points: int = DEFAULT_ICP_POINTS,
        min_score: float = 0.0,
        ls_points: int = DEFAULT_LS_POINTS,
        threads: int | None = None,
    ):
        if height is not None and (int(height) != height or height < INPUT_MULTIPLE):
            raise ConfigError(f"height must be an integer >= {INPUT_MULTIPLE}, got {height!r}")
        if isinstance(weights, (str, os.PathLike)):
            self.backend: MapBackend = open_backend(weights, backend, device, threads)
        elif hasattr(weights, "run") and hasattr(weights, "stride"):
            self.backend = weights
        else:
            raise ConfigError(f"weights must be a file path or a MapBackend, got {type(weights).__name__}")
        if pose_search not in POSE_SEARCHES:
            raise ConfigError(f"pose_search must be one of {', '.join(POSE_SEARCHES)}, got {pose_search!r}")
        self.height = None if height is None else int(height)
        self.pose_search = pose_search
        self.decode_options = dict(decode_options or {})
        self.pnp_options = dict(pnp_options or {})
        self.hypothesis_options = dict(hypothesis_options or {})
        self.line_search_options = dict(line_search_options or {})
        self.icp = bool(icp)
        self.icp_options = dict(icp_options or {})
        self.icp_points = int(icp_points)
        self.min_score = float(min_score)
        self.ls_points = int(ls_points)
        b = self.backend
        self.class_name = str(b.class_name)
        self.legacy = b.frame == "legacy" or b.keypoint_order == LEGACY_KEYPOINT_ORDER
        self.mean = tuple(float(v) for v in b.mean)
        self.std = tuple(float(v) for v in b.std)
        self.stride = int(b.stride)
        self.mesh = None
        size = np.asarray(b.size_m, dtype=np.float64).reshape(3)
        center = np.zeros(3)
        if mesh is not None:
            self.mesh, size, center = self._load_mesh(mesh, mesh_units, size)
        self.cuboid_size_m = size
        self.cuboid_center_m = center
        if self.icp and self.mesh is None:
            self._check_icp_surface()
        #: (9, 3) mesh-frame cuboid keypoints, current order.
        self.cuboid_mesh = cuboid_keypoints(size, center)
        if self.legacy:
            # The same box in the legacy frame (p_legacy = L^T p_mesh), listed in the legacy
            # order: corner k at CUBOID_CORNER_SIGNS[k] * legacy extents / 2.
            size_leg = np.abs(LEGACY_TO_MESH).T @ size
            self.cuboid_pnp = cuboid_keypoints(size_leg, LEGACY_TO_MESH.T @ center)
        else:
            self.cuboid_pnp = self.cuboid_mesh
        self._model_points: np.ndarray | None = None
        self._icp_model: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ setup helpers
    def _load_mesh(self, mesh: Any, units: str | None, ckpt_size: np.ndarray):
        from dope_hope.io.meshes import load_mesh, mesh_cuboid

        source = "<mesh>"
        if isinstance(mesh, (str, os.PathLike)):
            source = str(mesh)
            mesh = load_mesh(mesh, units=units)
        size, center = mesh_cuboid(mesh)
        ratio = size / ckpt_size
        if np.any(ratio > MESH_SIZE_TOLERANCE) or np.any(ratio < 1.0 / MESH_SIZE_TOLERANCE):
            raise ConfigError(
                f"{source}: mesh box {np.round(size * 100, 2).tolist()} cm does not match the "
                f"model's cuboid {np.round(ckpt_size * 100, 2).tolist()} cm for {self.class_name} "
                "(wrong object or wrong mesh units?)")
        return mesh, size, center

    def _surface(self):
        """The mesh, else the cuboid's surface (see the module docstring), metres."""
        if self.mesh is not None:
            return self.mesh
        import trimesh

        box = trimesh.creation.box(extents=self.cuboid_size_m)
        box.apply_translation(self.cuboid_center_m)
        return box

    def _check_icp_surface(self) -> None:
        """Without a mesh ICP fits the cuboid's surface to the depth: right for a box only."""
        from dope_hope.catalog import get_object

        try:
            category = get_object(self.class_name).category
        except UnknownObjectError:
            category = "object outside the HOPE catalog"
        if category != "cuboid":
            raise ConfigError(f"ICP for {self.class_name} ({category}) needs its mesh (mesh= / --mesh): "
                              "without one it would fit the cuboid's surface, which is right for boxes only")

    @property
    def model_points(self) -> np.ndarray:
        """(ls_points, 3) mesh-frame surface points for the line search, metres (cached)."""
        if self._model_points is None:
            from dope_hope.io.meshes import sample_surface_points

            self._model_points = sample_surface_points(self._surface(), self.ls_points, seed=0)
        return self._model_points

    @property
    def icp_model(self) -> tuple[np.ndarray, np.ndarray]:
        """((icp_points, 3) mesh-frame surface points, metres; their (icp_points, 3) unit
        normals) for ICP (cached)."""
        if self._icp_model is None:
            from dope_hope.io.meshes import sample_surface_points

            if self.mesh is None:
                self._check_icp_surface()
            self._icp_model = sample_surface_points(self._surface(), self.icp_points, seed=0,
                                                    oversample=10, return_normals=True)
        return self._icp_model

    def working_size(self, image_hw: tuple[int, int]) -> tuple[tuple[int, int], tuple[int, int]]:
        """((H', W') resized content, (Hp, Wp) padded network input) for an image of (H, W)."""
        H, W = int(image_hw[0]), int(image_hw[1])
        fixed = getattr(self.backend, "fixed_input_hw", None)
        if fixed is not None:
            s = min(fixed[0] / H, fixed[1] / W)
            if self.height is not None:
                s = min(s, self.height / H)
            hw = (max(1, min(fixed[0], round(H * s))), max(1, min(fixed[1], round(W * s))))
            return hw, (int(fixed[0]), int(fixed[1]))
        input_hw = getattr(self.backend, "input_hw", None)
        if self.height is not None:
            s = self.height / H
        elif input_hw is None or self.legacy:
            s = DEFAULT_HEIGHT / H
        else:
            s = min(input_hw[0] / H, input_hw[1] / W)
        hw = (max(1, round(H * s)), max(1, round(W * s)))
        return hw, (_round_up(hw[0], INPUT_MULTIPLE), _round_up(hw[1], INPUT_MULTIPLE))

    # ------------------------------------------------------------------ inference
    def prepare(self, image: np.ndarray) -> NetworkInput:
        """Image of any layout -> :class:`NetworkInput` at the working size."""
        rgb = to_rgb8(image)
        resized, padded = self.working_size(rgb.shape[:2])
        return prepare_input(rgb, resized, self.mean, self.std, padded)

    def infer_maps(self, image: np.ndarray | NetworkInput) -> tuple[np.ndarray, np.ndarray, NetworkInput]:
        """Run the network: (belief (9, h, w), affinity (16, h, w), the NetworkInput)."""
        net_in = image if isinstance(image, NetworkInput) else self.prepare(image)
        belief, affinity = self.backend.run(net_in.batch)
        belief, affinity = np.asarray(belief)[0], np.asarray(affinity)[0]
        Hp, Wp = net_in.batch.shape[2:]
        if belief.shape != (NUM_KEYPOINTS, Hp // self.stride, Wp // self.stride) or \
                affinity.shape != (2 * (NUM_KEYPOINTS - 1),) + belief.shape[1:]:
            raise ModelFileError(getattr(self.backend, "source", "<model>"),
                                 f"network returned maps {belief.shape} / {affinity.shape} for an "
                                 f"input of {Hp}x{Wp} at stride {self.stride}")
        return belief, affinity, net_in

    def predict(self, image: np.ndarray, K: np.ndarray, depth: np.ndarray | None = None,
                depth_scale_m: float = 0.001, calibration: float = 1.0) -> list[Detection]:
        """Detect this predictor's object in one image.

        Args:
            image: (H, W[, C]) RGB image array (see :func:`to_rgb8`).
            K: (3, 3) intrinsics of ``image``.
            depth: optional (H, W) depth registered to the image: integer units of
                ``depth_scale_m`` metres, or float metres; enables the line search.
            depth_scale_m: metres per integer depth unit (0.001 = millimetres).
            calibration: depth multiplier (HOPE RealSense frames: pose.HOPE_REALSENSE_DEPTH_CALIBRATION).

        Returns:
            Detections sorted by decreasing score, mesh-frame poses.
        """
        K = check_intrinsics(K)
        belief, affinity, net_in = self.infer_maps(image)
        return self.detections_from_maps(belief, affinity, net_in, K, depth, depth_scale_m, calibration)

    def detections_from_maps(self, belief: np.ndarray, affinity: np.ndarray, net_in: NetworkInput,
                             K: np.ndarray, depth: np.ndarray | None = None,
                             depth_scale_m: float = 0.001, calibration: float = 1.0) -> list[Detection]:
        """Decode + PnP (+ line search) the maps of :meth:`infer_maps` (see :meth:`predict`)."""
        K = check_intrinsics(K)
        K_net = net_in.network_K(K)
        mean_scale = math.sqrt(net_in.scale[0] * net_in.scale[1])
        out: list[Detection] = []
        for est in self._poses(belief, affinity, K_net):
            if est.score < self.min_score:
                continue
            R, t = est.R, est.t
            kp, scores, inliers = est.keypoints, est.keypoint_scores, est.inliers
            if self.legacy:
                R = legacy_rotation_to_mesh(R)
                kp = legacy_keypoints_to_current(kp)
                scores = legacy_keypoints_to_current(scores[:, None])[:, 0]
                inliers = legacy_keypoints_to_current(inliers[:, None])[:, 0]
            det = Detection(
                class_name=self.class_name, score=float(est.score), R=R, t=t.copy(),
                keypoints_2d=net_in.to_original_px(kp), keypoint_scores=np.asarray(scores, float),
                inliers=np.asarray(inliers, bool), projected_2d=np.zeros((NUM_KEYPOINTS, 2)),
                reprojection_error_px=float(est.reprojection_error_px / mean_scale),
                cuboid_size_m=self.cuboid_size_m.copy(), cuboid_center_m=self.cuboid_center_m.copy(),
            )
            if depth is not None:
                ls = depth_line_search(R, t, self.model_points, depth, K, depth_scale_m=depth_scale_m,
                                       calibration=calibration, image_hw=net_in.original_hw,
                                       **self.line_search_options)
                det.t, det.ls_applied, det.ls_reason, det.ls_scale = ls.t, ls.applied, ls.reason, ls.scale
                if self.icp:
                    self._refine_icp(det, depth, K, depth_scale_m, calibration, net_in.original_hw)
            elif self.icp:
                det.icp_reason = "no depth image"
            det.projected_2d = project_points(self.cuboid_mesh, K, det.R, det.t)
            out.append(det)
        out.sort(key=lambda d: -d.score)
        return out

    def refine_icp(self, det: Detection, depth: np.ndarray, K: np.ndarray, depth_scale_m: float = 0.001,
                   calibration: float = 1.0, image_hw: tuple[int, int] | None = None) -> Detection:
        """Step 7 of the module docstring on one detection, whatever ``icp`` was set to: a copy
        of ``det`` (as :meth:`predict` returns it with ``depth``, i.e. after the line search)
        refined by ICP against ``depth``; ``det`` itself is unchanged. Lets a caller keep both
        the -LS and the -LS + ICP pose without decoding the maps twice (``dope-hope demo``).
        ``image_hw``: (H, W) the depth must have, when known."""
        K = check_intrinsics(K)
        out = replace(det)
        self._refine_icp(out, depth, K, depth_scale_m, calibration, image_hw)
        out.projected_2d = project_points(self.cuboid_mesh, K, out.R, out.t)
        return out

    def _refine_icp(self, det: Detection, depth: np.ndarray, K: np.ndarray, depth_scale_m: float,
                    calibration: float, image_hw: tuple[int, int] | None) -> None:
        """Step 7 of the module docstring, in place on ``det`` (after the line search)."""
        if not det.ls_applied:  # ICP needs the depth within a few cm: a wider line search first
            options = {**self.line_search_options, "search": ICP_LS_SEARCH}
            wide = depth_line_search(det.R, det.t, self.model_points, depth, K, depth_scale_m=depth_scale_m,
                                     calibration=calibration, image_hw=image_hw, **options)
            if wide.applied:
                det.t, det.ls_applied, det.ls_scale = wide.t, True, wide.scale
                det.ls_reason = f"ok (search {ICP_LS_SEARCH[0]:g}-{ICP_LS_SEARCH[1]:g}, for ICP)"
        points, normals = self.icp_model
        res = icp_refine(det.R, det.t, points, normals, depth, K, depth_scale_m=depth_scale_m,
                         calibration=calibration, image_hw=image_hw, **self.icp_options)
        det.icp_applied, det.icp_reason = res.applied, res.reason
        det.icp_fit = res.fit_after if res.applied else res.fit_before
        if res.applied:
            det.R, det.t = res.R, res.t

    def _poses(self, belief: np.ndarray, affinity: np.ndarray, K_net: np.ndarray) -> list[PoseEstimate]:
        """Network-image poses of the instances in one image's maps (step 4 of the module
        docstring), best first; keypoints in the network's own order."""
        if self.pose_search == "groups":
            found = [solve_pnp(inst.keypoints, inst.scores, self.cuboid_pnp, K_net, **self.pnp_options)
                     for inst in decode_maps(belief, affinity, self.stride, **self.decode_options)]
            return [e for e in found if e is not None]
        found = [solve_pnp_candidates(c.keypoint_ids, c.xy, c.scores, self.cuboid_pnp, K_net,
                                      **self.hypothesis_options, **self.pnp_options)
                 for c in corner_candidates(belief, affinity, self.stride, **self.decode_options)]
        kept: list[PoseEstimate] = []
        for est in sorted((e for e in found if e is not None), key=lambda e: -e.score):
            if not any(_same_peaks(est, other) for other in kept):
                kept.append(est)
        return kept

    def __repr__(self) -> str:
        return (f"DopePredictor(class_name={self.class_name!r}, stride={self.stride}, "
                f"frame={'legacy' if self.legacy else 'mesh'}, height={self.height})")


def _same_peaks(a: PoseEstimate, b: PoseEstimate) -> bool:
    """True when at least half of ``a``'s inlier keypoints are the very peaks (same type, same
    position) among ``b``'s inliers: two centroids that explain one object."""
    both = a.inliers & b.inliers
    same = both & np.all(np.abs(a.keypoints - b.keypoints) < 1e-6, axis=1)
    return 2 * int(same.sum()) >= int(a.inliers.sum())


def predict_many(predictors: Sequence[DopePredictor], image: np.ndarray, K: np.ndarray,
                 depth: np.ndarray | None = None, depth_scale_m: float = 0.001,
                 calibration: float = 1.0,
                 on_maps: Callable[[DopePredictor, np.ndarray, np.ndarray, NetworkInput], None] | None = None,
                 ) -> list[Detection]:
    """Run several one-object predictors on one image; detections sorted by decreasing score.

    The image is converted once, and resized/normalized once per distinct working size and
    normalization (predictors with equal settings share the network input).
    ``on_maps(predictor, belief, affinity, network_input)`` is called with each model's maps
    (e.g. to draw them).
    """
    K = check_intrinsics(K)
    rgb = to_rgb8(image)
    cache: dict[tuple, NetworkInput] = {}
    out: list[Detection] = []
    for p in predictors:
        resized, padded = p.working_size(rgb.shape[:2])
        key = (resized, padded, p.mean, p.std)
        if key not in cache:
            cache[key] = prepare_input(rgb, resized, p.mean, p.std, padded)
        belief, affinity, net_in = p.infer_maps(cache[key])
        if on_maps is not None:
            on_maps(p, belief, affinity, net_in)
        out.extend(p.detections_from_maps(belief, affinity, net_in, K, depth, depth_scale_m, calibration))
    out.sort(key=lambda d: -d.score)
    return out
