"""Training data: a torch Dataset over DOPE-format folders, with keypoint-aware augmentation.

One frame becomes one item:

* ``image``: (3, H, W) float32, ImageNet-normalized RGB at the training input size;
* ``belief`` (9, h, w) and ``affinity`` (16, h, w): :func:`dope_hope.targets.make_targets` of the
  augmented keypoints at the head's stride (h, w = H / stride, W / stride);
* ``keypoints``: (max_instances, 9, 2) float32 input-image pixels of the instances of the
  class, NaN where padded or where the keypoint left the image (what validation scores);
* ``index`` (int) and ``bad_files`` (list of image files that could not be read and were
  replaced by another frame; the trainer reports each once).

Geometry and pixels move together: one 2x3 affine matrix ``M`` (pixel centres at integer
coordinates, the convention of ``cv2.warpAffine``) maps source pixels to the input image, so a
keypoint ``uv`` lands at ``M @ [u, v, 1]``. The random draws of an item come from
``numpy.random.default_rng((seed, epoch, index))`` only, so an item is a pure function of
(seed, epoch, index) whatever process or worker builds it. A sampler may hand out
``(epoch, index)`` pairs (see :class:`EpochSampler`) so that DataLoader workers need no shared
state.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from dope_hope.errors import ConfigError, DopeHopeError, InputFileError
from dope_hope.geometry import (CENTROID_INDEX, KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER,
                                LEGACY_TO_CURRENT_INDEX, NUM_KEYPOINTS, legacy_keypoints_to_current)
from dope_hope.symmetric_labels import camera_direction, canonical_keypoints

log = logging.getLogger(__name__)

_REPORTED: set[str] = set()


def report_bad_file(path: str | Path, problem: str) -> bool:
    """Log a skipped file once per process (later calls for the same path are silent)."""
    key = str(path)
    if key in _REPORTED:
        return False
    _REPORTED.add(key)
    log.warning("skipping %s: %s", key, problem)
    return True

#: Padding colour (RGB uint8): the ImageNet mean, i.e. zero after normalization.
PAD_RGB = (124, 116, 104)


# --------------------------------------------------------------------------- keypoint order
def convert_keypoint_order(keypoints: np.ndarray, from_order: str, to_order: str) -> np.ndarray:
    """Reorder (..., 9, 2) keypoints between "dope-current" and "dope-legacy".

    The permutation is :data:`dope_hope.geometry.LEGACY_TO_CURRENT_INDEX`.

    Raises:
        ConfigError: an order name that is neither.
    """
    known = (KEYPOINT_ORDER, LEGACY_KEYPOINT_ORDER)
    for name in (from_order, to_order):
        if name not in known:
            raise ConfigError(f"unknown keypoint order {name!r}; known: {', '.join(known)}")
    kp = np.asarray(keypoints)
    if from_order == to_order:
        return kp
    if from_order == LEGACY_KEYPOINT_ORDER:
        return legacy_keypoints_to_current(kp)
    return kp[..., LEGACY_TO_CURRENT_INDEX, :]  # current[LEGACY_TO_CURRENT_INDEX[k]] = legacy[k]


# --------------------------------------------------------------------------- augmentation
@dataclass
class AugmentParams:
    """Augmentation ranges (the config's ``augment`` section; every key optional).

    Attributes:
        enabled: False gives the deterministic validation transform (fit + centre).
        fit: "contain" (whole image inside the input, padded) or "cover" (fills the input,
            the excess cropped) — the base scale before ``scale``.
        upscale: let the base fit enlarge images smaller than the input; False (default)
            keeps their scale and pads them (the random zoom still applies).
        scale: (min, max) zoom factor on top of the base scale, sampled log-uniformly.
        rotation_deg: maximum |in-plane rotation|, degrees.
        translate: maximum shift as a fraction of the input size, on top of the random crop
            position over whatever part of the scaled image exceeds the input.
        brightness, contrast, saturation: factors drawn from [1 - x, 1 + x].
        hue: maximum |hue shift|, fraction of the colour circle (0.5 = half-way).
        noise_std: maximum std of additive Gaussian noise, uint8 units (drawn in [0, max]).
        blur_prob: probability of a Gaussian blur; blur_sigma: its (min, max) sigma, pixels.
        prob_geometric: probability of the random scale/rotation/shift (else fit + centre).
        crop: (H, W) of object-centred training crops, or None (train on the whole input).
            With a crop the training items are this size and centred on a random instance's
            centroid (plus ``crop_jitter``), after the same fit, zoom and rotation as a whole
            frame, so objects keep their size in pixels; validation and inference still see
            whole frames (the network is fully convolutional). A frame that is mostly
            background costs as much as one full of object: crops give each step several
            times more object pixels - the part that teaches which corner is which.
        crop_jitter: maximum offset of that centroid from the crop's centre, fraction of the
            crop size.
    """

    enabled: bool = True
    fit: str = "contain"
    upscale: bool = False
    scale: tuple[float, float] = (0.8, 1.25)
    rotation_deg: float = 15.0
    translate: float = 0.1
    brightness: float = 0.25
    contrast: float = 0.25
    saturation: float = 0.25
    hue: float = 0.03
    noise_std: float = 5.0
    blur_prob: float = 0.2
    blur_sigma: tuple[float, float] = (0.3, 1.2)
    prob_geometric: float = 1.0
    crop: tuple[int, int] | None = None
    crop_jitter: float = 0.25

    @classmethod
    def from_config(cls, section: dict[str, Any] | None, enabled: bool = True) -> AugmentParams:
        """Build from a config's ``augment`` dict; unknown keys raise ConfigError."""
        section = dict(section or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(section) - names)
        if unknown:
            raise ConfigError(f"augment: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}")
        params = cls(**section)
        params.scale = tuple(float(v) for v in params.scale)  # type: ignore[assignment]
        params.blur_sigma = tuple(float(v) for v in params.blur_sigma)  # type: ignore[assignment]
        if params.fit not in ("contain", "cover"):
            raise ConfigError(f"augment.fit must be 'contain' or 'cover', got {params.fit!r}")
        if params.crop is not None:
            crop = tuple(int(v) for v in params.crop)
            if len(crop) != 2 or crop[0] % 8 or crop[1] % 8 or min(crop) <= 0:
                raise ConfigError(f"augment.crop must be [H, W], positive multiples of 8, got {params.crop!r}")
            params.crop = crop  # type: ignore[assignment]
        if not (0 < params.scale[0] <= params.scale[1]):
            raise ConfigError(f"augment.scale must be 0 < min <= max, got {list(params.scale)}")
        params.enabled = bool(params.enabled) and enabled
        return params


def affine_matrix(
    src_hw: tuple[int, int], dst_hw: tuple[int, int], scale: float, angle_deg: float,
    shift_xy: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """2x3 matrix: scale + rotate the source about its centre, put it at the input's centre.

    With pixel centres at integer coordinates the image centre is ``((W-1)/2, (H-1)/2)``; a
    pure resize (``scale = W_dst/W_src``) then gives ``u' = scale (u + 0.5) - 0.5``, the
    convention of :func:`dope_hope.geometry.scale_intrinsics`.
    """
    H, W = src_hw
    Ho, Wo = dst_hw
    a = math.radians(angle_deg)
    A = scale * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    c_src = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
    c_dst = np.array([(Wo - 1) / 2.0 + shift_xy[0], (Ho - 1) / 2.0 + shift_xy[1]])
    return np.hstack([A, (c_dst - A @ c_src)[:, None]])


def apply_affine(M: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(..., 2) points through a 2x3 affine matrix (NaN stays NaN)."""
    uv = np.asarray(uv, dtype=np.float64)
    return uv @ M[:, :2].T + M[:, 2]


def _compose(M2: np.ndarray, M1: np.ndarray) -> np.ndarray:
    """2x3 matrix of ``M2 after M1``."""
    A = np.vstack([M1, [0.0, 0.0, 1.0]])
    return (np.vstack([M2, [0.0, 0.0, 1.0]]) @ A)[:2]


def warp_image(rgb: np.ndarray, M: np.ndarray, dst_hw: tuple[int, int]) -> np.ndarray:
    """Warp (H, W, 3) uint8 by the 2x3 matrix ``M`` into (Ho, Wo, 3); outside = PAD_RGB.

    Strong downscales first go through ``cv2.resize(INTER_AREA)`` (anti-aliasing that
    ``warpAffine`` lacks); the matrix is corrected for the exact resized size so that the
    keypoints, which always use ``M``, stay on their pixels.
    """
    Ho, Wo = dst_hw
    scale = math.sqrt(abs(np.linalg.det(M[:, :2])))
    src = rgb
    if scale < 0.7:
        H, W = rgb.shape[:2]
        W1, H1 = max(1, round(W * scale)), max(1, round(H * scale))
        src = cv2.resize(rgb, (W1, H1), interpolation=cv2.INTER_AREA)
        sx, sy = W1 / W, H1 / H
        # resized -> source pixels (pixel centres at integers): u = (u1 + 0.5) / sx - 0.5
        P_inv = np.array([[1 / sx, 0.0, 0.5 / sx - 0.5], [0.0, 1 / sy, 0.5 / sy - 0.5]])
        M = _compose(M, P_inv)
    return cv2.warpAffine(src, M, (Wo, Ho), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=PAD_RGB)


def crop_size(params: AugmentParams, input_hw: tuple[int, int]) -> tuple[int, int]:
    """(H, W) of augmented training items: ``params.crop`` capped at the input size, or the
    input size without a crop."""
    if params.crop is None:
        return int(input_hw[0]), int(input_hw[1])
    return min(int(params.crop[0]), int(input_hw[0])), min(int(params.crop[1]), int(input_hw[1]))


def sample_affine(
    src_hw: tuple[int, int], dst_hw: tuple[int, int], params: AugmentParams,
    rng: np.random.Generator | None, centres: np.ndarray | None = None,
) -> np.ndarray:
    """The 2x3 matrix for one item: base fit, then (when augmenting) zoom, rotation, crop.

    ``dst_hw`` is the input size the fit refers to; with ``params.crop`` (and augmenting) the
    matrix maps into a crop of that size centred near one of ``centres`` ((I, 2) source
    pixels of the instances' centroids, NaN rows ignored; none: anywhere in the frame).
    """
    H, W = src_hw
    Ho, Wo = dst_hw
    ratios = (Wo / W, Ho / H)
    base = min(ratios) if params.fit == "contain" else max(ratios)
    if not params.upscale:
        base = min(base, 1.0)
    augmenting = rng is not None and params.enabled
    if not augmenting or rng.random() >= params.prob_geometric:
        M = affine_matrix(src_hw, dst_hw, base, 0.0)
    else:
        lo, hi = params.scale
        s = base * math.exp(rng.uniform(math.log(lo), math.log(hi)))
        angle = rng.uniform(-params.rotation_deg, params.rotation_deg)
        # Extent of the rotated, scaled source; the crop may move over whatever exceeds the input.
        a = math.radians(angle)
        ext_w = s * (abs(math.cos(a)) * W + abs(math.sin(a)) * H)
        ext_h = s * (abs(math.sin(a)) * W + abs(math.cos(a)) * H)
        room_x = max(0.0, ext_w - Wo) / 2.0 + params.translate * Wo
        room_y = max(0.0, ext_h - Ho) / 2.0 + params.translate * Ho
        shift = (rng.uniform(-room_x, room_x), rng.uniform(-room_y, room_y))
        M = affine_matrix(src_hw, dst_hw, s, angle, shift)
    if not augmenting or params.crop is None:
        return M
    # Object-centred crop (also of the frames that skip the random geometry).
    Hc, Wc = crop_size(params, dst_hw)
    c = np.empty((0, 2)) if centres is None else np.asarray(centres, np.float64).reshape(-1, 2)
    c = c[np.all(np.isfinite(c), axis=1)]
    if len(c):  # a random instance's centroid near the crop's centre
        centre = apply_affine(M, c[rng.integers(len(c))])
        j = params.crop_jitter
        centre = centre + rng.uniform(-j, j, 2) * (Wc, Hc)
    else:  # no instance: any crop of the warped frame
        centre = np.array([rng.uniform(0, Wo - 1), rng.uniform(0, Ho - 1)])
    M[:, 2] += np.array([(Wc - 1) / 2.0, (Hc - 1) / 2.0]) - centre
    return M


def color_jitter(rgb: np.ndarray, params: AugmentParams, rng: np.random.Generator) -> np.ndarray:
    """Brightness, contrast, saturation, hue, noise and blur on (H, W, 3) uint8 -> uint8."""
    img = rgb.astype(np.float32)
    if params.brightness > 0:
        img *= rng.uniform(1 - params.brightness, 1 + params.brightness)
    gray_w = np.array([0.299, 0.587, 0.114], np.float32)
    if params.contrast > 0:
        mean = float((img @ gray_w).mean())
        img = (img - mean) * rng.uniform(1 - params.contrast, 1 + params.contrast) + mean
    if params.saturation > 0:
        gray = (img @ gray_w)[:, :, None]
        img = gray + (img - gray) * rng.uniform(1 - params.saturation, 1 + params.saturation)
    out = np.clip(img, 0, 255).astype(np.uint8)
    if params.hue > 0:
        shift = rng.uniform(-params.hue, params.hue)
        hsv = cv2.cvtColor(out, cv2.COLOR_RGB2HSV_FULL)  # hue in 0..255 for the full circle
        hsv[:, :, 0] = (hsv[:, :, 0].astype(np.int16) + int(round(shift * 256))) % 256
        out = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB_FULL)
    if params.blur_prob > 0 and rng.random() < params.blur_prob:
        sigma = rng.uniform(*params.blur_sigma)
        out = cv2.GaussianBlur(out, (0, 0), sigmaX=sigma, sigmaY=sigma)
    if params.noise_std > 0:
        std = rng.uniform(0.0, params.noise_std)
        noisy = out.astype(np.float32) + rng.normal(0.0, std, size=out.shape).astype(np.float32)
        out = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
    return out


def augment(
    rgb: np.ndarray, keypoints: np.ndarray, dst_hw: tuple[int, int], params: AugmentParams,
    rng: np.random.Generator | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warp an image and its keypoints with one affine matrix, then jitter colours.

    Args:
        rgb: (H, W, 3) uint8.
        keypoints: (I, 9, 2) source pixels (NaN allowed).
        dst_hw: (Ho, Wo) training input size; smaller sources are padded with PAD_RGB.
        params: ranges; ``params.enabled`` False (or rng None) = fit + centre, no jitter.
        rng: the item's generator.

    Returns:
        image (Ho, Wo, 3) uint8 - or ``params.crop`` sized when augmenting with a crop -,
        keypoints (I, 9, 2) output pixels, M (2, 3).
    """
    kp = np.asarray(keypoints, dtype=np.float64).reshape(-1, NUM_KEYPOINTS, 2)
    M = sample_affine(rgb.shape[:2], dst_hw, params, rng, centres=kp[:, CENTROID_INDEX])
    if rng is not None and params.enabled:
        dst_hw = crop_size(params, dst_hw)
    out = warp_image(rgb, M, dst_hw)
    if rng is not None and params.enabled:
        out = color_jitter(out, params, rng)
    return out, apply_affine(M, keypoints), M


# --------------------------------------------------------------------------- dataset
@dataclass
class FrameRecord:
    """What the dataset keeps per frame (the JSON is parsed once, at init)."""

    json_path: Path
    image_path: Path
    keypoints: np.ndarray  # (I, 9, 2) float64 in the model's keypoint order
    #: (I, 3) unit camera direction in each instance's object frame (NaN without a pose);
    #: what symmetry-aware relabelling (dope_hope.symmetric_labels) decides on.
    view_dirs: np.ndarray | None = None


def recorded_cuboid_size(json_path: str | Path, class_name: str) -> np.ndarray | None:
    """(3,) cuboid size in metres (mesh frame) that a frame's JSON records for the class, or None.

    ``dope-hope synth`` writes ``"cuboid": {"class", "size_m", "center_m", "frame"}``.
    """
    import json

    try:
        doc = json.loads(Path(json_path).read_text())
    except (OSError, ValueError):
        return None
    cub = doc.get("cuboid") if isinstance(doc, dict) else None
    if not isinstance(cub, dict) or str(cub.get("class", "")).lower() != class_name.lower():
        return None
    try:
        size = np.asarray(cub.get("size_m"), dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    return size if np.all(np.isfinite(size)) and np.all(size > 0) else None


def scan_frames(
    folders: Sequence[str | Path], class_name: str, keypoint_order: str = KEYPOINT_ORDER,
    min_visibility: float = 0.0, include_empty: bool = True, progress: bool = False,
) -> tuple[list[FrameRecord], list[tuple[Path, str]]]:
    """Parse every DOPE JSON of the folders once.

    Objects are kept when their class equals ``class_name`` (case-insensitive), they carry a
    projected cuboid and their visibility (when recorded) is positive and >= min_visibility.
    Keypoints are converted to ``keypoint_order``.

    Returns:
        (records, bad) where bad lists (json path, problem) of files that could not be parsed;
        each is logged once, here.

    Raises:
        InputFileError: a folder that does not exist or holds no DOPE frames.
    """
    from dope_hope.io.dope_json import find_image, list_dope_frames, read_dope_json

    want = class_name.lower()
    records: list[FrameRecord] = []
    bad: list[tuple[Path, str]] = []
    paths: list[Path] = []
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            raise InputFileError(folder, "data folder not found")
        found = list_dope_frames(folder)
        if not found:
            raise InputFileError(folder, "no DOPE frames (NNNNNN.json beside an image) in this folder")
        paths.extend(found)
    iterator: Any = paths
    if progress and len(paths) > 2000:
        from tqdm import tqdm
        iterator = tqdm(paths, desc="scanning annotations", unit="file", leave=False)
    for path in iterator:
        try:
            frame = read_dope_json(path)
        except (DopeHopeError, ValueError, KeyError, TypeError, OSError) as exc:
            problem = getattr(exc, "problem", None) or (str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
            bad.append((Path(path), problem))
            report_bad_file(path, f"unreadable annotation ({problem})")
            continue
        kps: list[np.ndarray] = []
        dirs: list[np.ndarray] = []
        for obj in frame.objects:
            if obj.class_name.lower() != want or obj.projected_cuboid is None:
                continue
            if obj.visibility is not None and (obj.visibility <= 0 or obj.visibility < min_visibility):
                continue
            kp = np.asarray(obj.projected_cuboid, dtype=np.float64).reshape(NUM_KEYPOINTS, 2)
            kps.append(convert_keypoint_order(kp, obj.keypoint_order, keypoint_order))
            dirs.append(camera_direction(obj.R, obj.t))
        if not kps and not include_empty:
            continue
        image = frame.image_path if frame.image_path is not None else find_image(path)
        if image is None:
            raise InputFileError(path, "no image beside this annotation")
        records.append(FrameRecord(
            Path(path), Path(image),
            np.stack(kps) if kps else np.zeros((0, NUM_KEYPOINTS, 2)),
            np.stack(dirs) if dirs else np.zeros((0, 3))))
    return records, bad


class DopeDataset(Dataset):
    """Frames of one object class from DOPE-format folders, as network inputs + targets.

    Args:
        records: from :func:`scan_frames` (or :meth:`from_folders`).
        input_hw: (H, W) network input size, pixels (multiples of 8).
        stride: the head's map stride (8 or 1).
        sigma, radius: target parameters, map pixels (config ``targets``).
        augment: ranges; ``augment.enabled`` False for validation.
        seed: base of the per-item RNG ``default_rng((seed, epoch, index))``.
        max_instances: rows of the padded ``keypoints`` output.
    """

    def __init__(
        self, records: list[FrameRecord], input_hw: tuple[int, int], stride: int,
        sigma: float, radius: float, augment: AugmentParams | None = None, seed: int = 0,
        max_instances: int = 8,
    ):
        self.records = records
        self.input_hw = (int(input_hw[0]), int(input_hw[1]))
        if self.input_hw[0] % 8 or self.input_hw[1] % 8:
            raise ConfigError(f"input size {list(self.input_hw)} must be multiples of 8")
        self.stride = int(stride)
        self.sigma = float(sigma)
        self.radius = float(radius)
        self.augment = augment if augment is not None else AugmentParams(enabled=False)
        self.seed = int(seed)
        self.max_instances = int(max_instances)
        self.epoch = 0
        self._bad_images: set[int] = set()

    @classmethod
    def from_folders(cls, folders: Sequence[str | Path], class_name: str, **kwargs: Any) -> DopeDataset:
        """Scan folders (see :func:`scan_frames`) and build the dataset; kwargs go to __init__."""
        records, _ = scan_frames(folders, class_name)
        return cls(records, **kwargs)

    def __len__(self) -> int:
        return len(self.records)

    def set_epoch(self, epoch: int) -> None:
        """Epoch used for plain integer indices (samplers may pass (epoch, index) instead)."""
        self.epoch = int(epoch)

    def item_rng(self, epoch: int, index: int) -> np.random.Generator:
        return np.random.default_rng((self.seed, int(epoch), int(index)))

    def _load(self, index: int) -> np.ndarray | None:
        from dope_hope.io.images import read_rgb

        rec = self.records[index]
        try:
            return read_rgb(rec.image_path)
        except (DopeHopeError, OSError, cv2.error) as exc:
            if index not in self._bad_images:
                self._bad_images.add(index)
                if torch.utils.data.get_worker_info() is None:  # in workers the trainer reports
                    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    report_bad_file(rec.image_path, f"unreadable image ({problem}), replaced by another frame")
            return None

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        epoch, index = (int(key[0]), int(key[1])) if isinstance(key, (tuple, list)) else (self.epoch, int(key))
        n = len(self.records)
        bad_files: list[str] = []
        rgb = None
        src = index
        for attempt in range(n):
            src = (index + attempt) % n
            if src in self._bad_images and attempt < n - 1:
                bad_files.append(str(self.records[src].image_path))
                continue
            rgb = self._load(src)
            if rgb is not None:
                break
            bad_files.append(str(self.records[src].image_path))
        if rgb is None:
            raise InputFileError(self.records[index].image_path, "no readable image in the whole dataset")
        return self.make_item(rgb, self.records[src].keypoints, self.item_rng(epoch, index),
                              index=index, bad_files=bad_files)

    def make_item(self, rgb: np.ndarray, keypoints: np.ndarray, rng: np.random.Generator | None,
                  index: int = -1, bad_files: list[str] | None = None) -> dict[str, Any]:
        """Augment one image + keypoints and build the item dict (see the module docstring)."""
        from dope_hope.model.network import normalize_image
        from dope_hope.targets import make_targets

        img, kp, _ = augment(rgb, keypoints, self.input_hw, self.augment,
                             rng if self.augment.enabled else None)
        H, W = img.shape[:2]  # the input size, or the augmentation's object-centred crop
        belief, affinity = make_targets(kp, (H, W), self.stride, self.sigma, self.radius)
        out_kp = np.full((self.max_instances, NUM_KEYPOINTS, 2), np.nan, np.float32)
        m = min(len(kp), self.max_instances)
        if m:
            vis = kp[:m].copy()
            outside = ~((vis[..., 0] >= -0.5) & (vis[..., 0] < W - 0.5)
                        & (vis[..., 1] >= -0.5) & (vis[..., 1] < H - 0.5))
            vis[outside] = np.nan
            out_kp[:m] = vis
        return {
            "image": normalize_image(img),
            "belief": torch.from_numpy(belief),
            "affinity": torch.from_numpy(affinity),
            "keypoints": torch.from_numpy(out_kp),
            "index": index,
            "bad_files": list(bad_files or []),
        }


def collate(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack tensors, gather ``index`` into a tensor and concatenate ``bad_files``."""
    out: dict[str, Any] = {}
    for key in ("image", "belief", "affinity", "keypoints"):
        out[key] = torch.stack([it[key] for it in items])
    out["index"] = torch.tensor([it["index"] for it in items], dtype=torch.long)
    out["bad_files"] = [f for it in items for f in it["bad_files"]]
    return out


# --------------------------------------------------------------------------- sampling
class EpochSampler(Sampler):
    """Yields ``(epoch, index)``: a shuffle that is a function of (seed, epoch) only.

    Shards like ``DistributedSampler`` (the permutation padded to a multiple of
    ``world_size``, rank r takes every world_size-th entry from r) and can skip the first
    ``skip`` samples of this rank's share, which is how a resumed run continues mid-epoch.
    """

    def __init__(self, n: int, seed: int = 0, shuffle: bool = True, rank: int = 0, world_size: int = 1):
        if n <= 0:
            raise ValueError("EpochSampler needs a non-empty dataset")
        self.n, self.seed, self.shuffle = int(n), int(seed), bool(shuffle)
        self.rank, self.world_size = int(rank), int(world_size)
        self.epoch = 0
        self.skip = 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        self.epoch, self.skip = int(epoch), int(skip)

    def indices(self) -> list[int]:
        """This rank's indices for the current epoch (before skipping)."""
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            order = torch.randperm(self.n, generator=g).tolist()
        else:
            order = list(range(self.n))
        per_rank = math.ceil(self.n / self.world_size)
        total = per_rank * self.world_size
        order = (order * math.ceil(total / self.n))[:total]
        return order[self.rank:total:self.world_size]

    def __iter__(self) -> Iterator[tuple[int, int]]:
        for i in self.indices()[self.skip:]:
            yield (self.epoch, i)

    def __len__(self) -> int:
        return max(0, math.ceil(self.n / self.world_size) - self.skip)


def relabel_symmetric(records: list[FrameRecord], rotations: np.ndarray,
                      permutations: np.ndarray) -> list[FrameRecord]:
    """Records with each instance's keypoints in the canonical order of its view (see
    :mod:`dope_hope.symmetric_labels`); ``rotations``/``permutations`` from
    :func:`~dope_hope.symmetric_labels.corner_permutations`. Instances without a recorded
    pose keep their order."""
    out = []
    for r in records:
        dirs = r.view_dirs if r.view_dirs is not None else np.full((len(r.keypoints), 3), np.nan)
        out.append(replace(r, keypoints=canonical_keypoints(r.keypoints, dirs, rotations, permutations)))
    return out


def split_records(records: list[FrameRecord], val_fraction: float, seed: int) -> tuple[list[FrameRecord], list[FrameRecord]]:
    """Deterministic train/val split (a seeded shuffle of the sorted records); val has >= 1."""
    if len(records) < 2:
        raise ConfigError(f"need at least 2 frames to split off a validation set, got {len(records)}; pass --val")
    n_val = min(len(records) - 1, max(1, int(round(val_fraction * len(records)))))
    order = np.random.default_rng(seed).permutation(len(records))
    val_idx = set(order[:n_val].tolist())
    train = [r for i, r in enumerate(records) if i not in val_idx]
    val = [r for i, r in enumerate(records) if i in val_idx]
    return train, val
