"""Keypoint-aware augmentation: one affine warp for pixels and keypoints, colour jitter, crops.

One 2x3 affine matrix ``M`` (pixel centres at integer coordinates, the convention of
``cv2.warpAffine``) maps source pixels to the input image, so a keypoint ``uv`` lands at
``M @ [u, v, 1]``. Random draws come from the generator the caller passes.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from dope_hope.config import (
    SectionSettings,
    boolean,
    fraction,
    nonnegative_float,
    one_of,
    pair,
    positive_float,
    whole_number,
)
from dope_hope.errors import ConfigError
from dope_hope.geometry import CENTROID_INDEX, NUM_KEYPOINTS
from dope_hope.preprocess import PAD_RGB, contain_scale

#: Samples in :func:`noise_bank` (16 MiB of float32: a 1280x1024 RGB image's noise fits) and
#: its seed.
NOISE_BANK_SIZE = 1 << 22
NOISE_BANK_SEED = 20181029


# --------------------------------------------------------------------------- augmentation
@dataclass(frozen=True)
class AugmentParams(SectionSettings):
    """Augmentation ranges (the config's ``augment`` section; every key optional, checked on
    construction: a bad value is a ConfigError naming ``augment.KEY``).

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

    SECTION = "augment"

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
        """Build from a config's ``augment`` dict (:meth:`from_mapping`); ``enabled`` False
        turns the augmentation off whatever the section says."""
        params = cls.from_mapping(section)
        return params if enabled else replace(params, enabled=False)


def _crop(value: Any, name: str) -> tuple[int, int] | None:
    if value is None:
        return None
    if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ConfigError(f"{name} must be [H, W], positive multiples of 8, got {value!r}")
    crop = tuple(whole_number(v, name, 0) for v in value)
    if crop[0] % 8 or crop[1] % 8 or min(crop) <= 0:
        raise ConfigError(f"{name} must be [H, W], positive multiples of 8, got {value!r}")
    return crop  # type: ignore[return-value]


AugmentParams.RULES = {
    "enabled": boolean, "fit": one_of("contain", "cover"), "upscale": boolean,
    "scale": pair(positive_float), "rotation_deg": nonnegative_float, "translate": nonnegative_float,
    "brightness": nonnegative_float, "contrast": nonnegative_float, "saturation": nonnegative_float,
    "hue": nonnegative_float, "noise_std": nonnegative_float, "blur_prob": fraction,
    "blur_sigma": pair(nonnegative_float), "prob_geometric": fraction, "crop": _crop,
    "crop_jitter": nonnegative_float,
}


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
    base = contain_scale(src_hw, dst_hw) if params.fit == "contain" else max(ratios)
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


def photometric_jitter(rgb: np.ndarray, params: AugmentParams, rng: np.random.Generator) -> np.ndarray:
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
        bank = noise_bank()
        if out.size <= bank.size:  # a random stretch of the bank
            start = int(rng.integers(0, bank.size - out.size + 1))
            unit = bank[start : start + out.size].reshape(out.shape)
        else:
            unit = rng.standard_normal(out.shape, dtype=np.float32)
        noisy = out.astype(np.float32) + np.float32(std) * unit
        out = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
    return out


@functools.cache
def noise_bank() -> np.ndarray:
    """(NOISE_BANK_SIZE,) float32 standard normal samples, the same in every process, that the
    sensor noise of :func:`photometric_jitter` is cut from: drawing an image's samples afresh
    costs ~0.4 ms for a 128x128 crop, half of the whole colour jitter."""
    return np.random.default_rng(NOISE_BANK_SEED).standard_normal(NOISE_BANK_SIZE, dtype=np.float32)


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
        out = photometric_jitter(out, params, rng)
    return out, apply_affine(M, keypoints), M
