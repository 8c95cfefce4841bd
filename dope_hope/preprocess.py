"""The network's input, defined once for training, inference and INT8 calibration.

Normalization: RGB in [0, 1] minus ``mean`` over ``std`` (ImageNet statistics by default,
:func:`normalize_rgb`); padding shows the mean colour (:data:`PAD_RGB`, zeros after
normalization). Fitting: an image goes *inside* a box keeping its aspect ratio
(:func:`contain_scale`); :func:`working_size` is the inference-time rule built on it.

:func:`to_rgb8` accepts (H, W), (H, W, 1|2|3|4) arrays, uint8 / uint16 / float in [0, 1], RGB
order; grayscale is replicated, uint16 reduced to 8 bits and non-opaque alpha dropped, each
with a ``warnings.warn``. :func:`prepare_input` resizes keeping the aspect ratio
(``cv2.INTER_AREA`` down, ``INTER_LINEAR`` up), pads right/bottom to a multiple of
:data:`INPUT_MULTIPLE` with the normalization mean (zeros after normalization) and returns a
:class:`NetworkInput` whose ``K`` only scales (pixel centres at integer coordinates:
``u' = s (u + 0.5) - 0.5``).
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from dope_hope.errors import CameraError, ConfigError
from dope_hope.geometry import is_pinhole, scale_intrinsics

#: ImageNet statistics used to normalize RGB in [0, 1] (torchvision convention).
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: The mean colour as uint8 RGB: what padding shows before normalization (zeros after it).
PAD_RGB = tuple(int(round(255 * m)) for m in IMAGENET_MEAN)

#: Official DOPE inference height (``config_pose.yaml`` ``downscale_height``), pixels.
DEFAULT_HEIGHT = 400


#: The network input must have H and W divisible by this (the trunk's stride).
INPUT_MULTIPLE = 8
#: Largest network working height and width, pixels (an image is resized to this; beyond it
#: the resize alone needs gigabytes and no model was trained at such a scale).
MAX_WORKING_SIDE = 4096


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


def normalize_rgb(rgb: np.ndarray, mean: Sequence[float] = IMAGENET_MEAN,
                  std: Sequence[float] = IMAGENET_STD) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (3, H, W) float32 ``(rgb / 255 - mean) / std``."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {rgb.shape}")
    x = rgb.astype(np.float32) / np.float32(255.0)
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def denormalize_rgb(x: np.ndarray, mean: Sequence[float] = IMAGENET_MEAN,
                    std: Sequence[float] = IMAGENET_STD) -> np.ndarray:
    """(3, H, W) float network input -> (H, W, 3) uint8 RGB (the inverse of :func:`normalize_rgb`,
    rounded; for display)."""
    x = np.asarray(x, dtype=np.float32)
    if x.ndim != 3 or x.shape[0] != 3:
        raise ValueError(f"expected a (3, H, W) network input, got shape {x.shape}")
    rgb = x.transpose(1, 2, 0) * np.asarray(std, np.float32) + np.asarray(mean, np.float32)
    return np.ascontiguousarray(np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8))


def contain_scale(src_hw: Sequence[int], box_hw: Sequence[int]) -> float:
    """Largest scale that fits an (H, W) image inside an (Hb, Wb) box, aspect ratio kept."""
    return min(box_hw[0] / src_hw[0], box_hw[1] / src_hw[1])


def working_size(image_hw: Sequence[int], *, height: int | None = None,
                 input_hw: Sequence[int] | None = None, fixed_input_hw: Sequence[int] | None = None,
                 legacy: bool = False, too_large: str = "give a smaller height",
                 ) -> tuple[tuple[int, int], tuple[int, int]]:
    """((H', W') resized content, (Hp, Wp) padded network input) for an (H, W) image.

    ``fixed_input_hw``: the only size the model takes (the image is fitted inside, no taller
    than ``height``). Otherwise ``height`` when given; else the model's training input size
    ``input_hw`` (contain fit); else (official weights, ``legacy``, or no recorded size)
    :data:`DEFAULT_HEIGHT`. The padded size rounds up to multiples of :data:`INPUT_MULTIPLE`.
    A size beyond :data:`MAX_WORKING_SIDE` is a ConfigError ending in ``too_large`` (what to
    change: the height by default; the scale that asked for it).
    """
    H, W = int(image_hw[0]), int(image_hw[1])
    if fixed_input_hw is not None:
        s = contain_scale((H, W), fixed_input_hw)
        if height is not None:
            s = min(s, height / H)
        hw = (max(1, min(fixed_input_hw[0], round(H * s))), max(1, min(fixed_input_hw[1], round(W * s))))
        return hw, (int(fixed_input_hw[0]), int(fixed_input_hw[1]))
    if height is not None:
        s = height / H
    elif input_hw is None or legacy:
        s = DEFAULT_HEIGHT / H
    else:
        s = contain_scale((H, W), input_hw)
    hw = (max(1, round(H * s)), max(1, round(W * s)))
    if max(hw) > MAX_WORKING_SIDE:
        raise ConfigError(f"a {W}x{H} image would be resized to {hw[1]}x{hw[0]} for the network, "
                          f"beyond {MAX_WORKING_SIDE} pixels; {too_large}")
    return hw, (_round_up(hw[0], INPUT_MULTIPLE), _round_up(hw[1], INPUT_MULTIPLE))


def check_working_side(value: Any, name: str = "height") -> int:
    """``value`` as an int if it is a usable network input height or width (a whole number of
    pixels in INPUT_MULTIPLE..MAX_WORKING_SIDE), else ConfigError naming ``name``."""
    try:
        ok = not isinstance(value, bool) and int(value) == value
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok or not INPUT_MULTIPLE <= int(value) <= MAX_WORKING_SIDE:
        raise ConfigError(f"{name} must be a whole number of pixels in {INPUT_MULTIPLE}..{MAX_WORKING_SIDE}, "
                          f"got {value!r}")
    return int(value)


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
    batch = np.zeros((1, 3, int(padded_hw[0]), int(padded_hw[1])), np.float32)
    batch[0, :, :Hr, :Wr] = normalize_rgb(rgb, mean, std)
    return NetworkInput(batch=batch, resized_hw=(Hr, Wr), original_hw=(H, W), scale=(Wr / W, Hr / H))


def check_intrinsics(K: Any) -> np.ndarray:
    """(3, 3) float64 K with positive focal lengths (:func:`dope_hope.geometry.is_pinhole`);
    CameraError otherwise."""
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraError("camera intrinsics K must be a 3x3 matrix of numbers") from None
    if K.shape != (3, 3):
        raise CameraError(f"camera intrinsics K must be a 3x3 matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise CameraError(f"camera intrinsics K holds NaN or infinity: {K.tolist()}")
    if not is_pinhole(K):
        raise CameraError(f"camera intrinsics K is not a pinhole matrix (fx, fy > 0, last row "
                          f"0 0 1): {K.tolist()}")
    return K
