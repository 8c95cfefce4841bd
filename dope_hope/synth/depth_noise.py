"""RealSense D4xx-like corruption of a perfect depth image.

An active-stereo camera measures disparity ``d = fx * b / z`` (pixels) and reports
``z = fx * b / d``. The model here, applied in that order:

1. disparity noise: Gaussian with ``subpixel_sigma_px``, so the depth error grows as
   ``sigma_z = z^2 * sigma_d / (fx * b)`` (0.6 mm at 0.5 m, 4.6 mm at 1.4 m for a D415 at
   640x480);
2. disparity quantization to ``disparity_step_px`` (sub-pixel steps of the stereo matcher);
3. missing pixels: a band around depth discontinuities (matching fails there), background
   surfaces hidden from the right imager (the "stereo shadow" left of near objects), dark
   and saturated-bright (specular) surfaces, random isolated dropouts, and the range limits.

Missing pixels are 0 (what the camera reports). The function is pure numpy/OpenCV, vectorized.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np


def _luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W) float32 luminance in [0, 1] (Rec. 601 weights)."""
    x = rgb.astype(np.float32) / 255.0
    return 0.299 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2]


def depth_edges(depth_m: np.ndarray, threshold: float) -> np.ndarray:
    """(H, W) bool: pixels next to a relative depth jump ``|dz| / z > threshold``.

    Borders between measured and missing (0) pixels count as edges.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    valid = d > 0
    edges = np.zeros(d.shape, dtype=bool)
    for axis in (0, 1):
        a = np.moveaxis(d, axis, 0)
        va = np.moveaxis(valid, axis, 0)
        jump = np.zeros(a.shape, dtype=bool)
        both = va[1:] & va[:-1]
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(a[1:] - a[:-1]) / np.minimum(a[1:], a[:-1])
        step = (both & (rel > threshold)) | (va[1:] != va[:-1])
        jump[1:] |= step
        jump[:-1] |= step
        edges |= np.moveaxis(jump, 0, axis)
    return edges & valid


def stereo_shadow(disparity_px: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that the right imager cannot see (occluded by a nearer surface).

    A pixel at column u is seen by the right imager at ``u - d(u)``; it is hidden if a pixel
    further right lands at or left of that column (it is nearer, larger disparity).
    Missing pixels (disparity <= 0) occlude nothing.
    """
    d = np.asarray(disparity_px, dtype=np.float64)
    H, W = d.shape
    u = np.arange(W, dtype=np.float64)[None, :]
    r = np.where(d > 0, u - d, np.inf)
    # minimum of r over the columns strictly to the right (suffix minimum, shifted by one)
    suffix = np.minimum.accumulate(r[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([suffix[:, 1:], np.full((H, 1), np.inf)], axis=1)
    return (d > 0) & (right_min < r - 0.5)


@dataclass(frozen=True)
class RealSenseNoise:
    """How :func:`add_realsense_noise` corrupts depth (defaults: a RealSense D415).

    Attributes:
        baseline_m: stereo baseline (D415: 0.055 m, D435: 0.050 m).
        subpixel_sigma_px: disparity noise std (pixels).
        disparity_step_px: disparity quantization step (pixels); 0 disables it.
        edge_threshold: relative depth jump that makes a depth edge.
        edge_width_px: (min, max) half-width of the band around edges that may be dropped.
        edge_drop_prob: probability that a pixel in that band is dropped.
        stereo_shadow_enabled: drop surfaces hidden from the right imager.
        dark_threshold, dark_drop_prob: luminance below which pixels drop with that probability.
        specular_threshold, specular_drop_prob: same for luminance above (saturated highlights).
        dropout_prob: probability of a random isolated missing pixel.
        min_depth_m, max_depth_m: measurement range; outside it depth is 0.
        stereo_fx_px: focal length (pixels) of the images the stereo matcher works on, which
            sets the size of the disparity noise and quantization (e.g. 615 for a D415 at
            640x480 whose depth was resized to this image); default: ``K``'s fx. Shadows and
            edge bands are always in this image's pixels.
    """

    baseline_m: float = 0.055
    subpixel_sigma_px: float = 0.08
    disparity_step_px: float = 1.0 / 32.0
    edge_threshold: float = 0.02
    edge_width_px: tuple[int, int] = (1, 3)
    edge_drop_prob: float = 0.8
    stereo_shadow_enabled: bool = True
    dark_threshold: float = 0.06
    dark_drop_prob: float = 0.6
    specular_threshold: float = 0.96
    specular_drop_prob: float = 0.6
    dropout_prob: float = 0.002
    min_depth_m: float = 0.16
    max_depth_m: float = 10.0
    stereo_fx_px: float | None = None


def add_realsense_noise(depth_m: np.ndarray, rgb: np.ndarray | None, K: np.ndarray,
                        rng: np.random.Generator | int | None = None,
                        settings: RealSenseNoise | None = None, **overrides: Any) -> np.ndarray:
    """Corrupt a perfect depth image like a RealSense D415 would.

    Args:
        depth_m: (H, W) depth in metres; 0 or NaN = no measurement.
        rgb: (H, W, 3) uint8 colour image registered to the depth (dark / specular dropouts),
            or None to skip those.
        K: (3, 3) intrinsics of the depth image (fx sets the disparity scale).
        rng: generator or seed (same rng state -> same output).
        settings: the noise model (default :class:`RealSenseNoise`'s).
        overrides: fields of :class:`RealSenseNoise` replaced in ``settings`` (e.g. the
            config's ``depth_noise`` section through :func:`noise_kwargs`).

    Returns:
        (H, W) float32 metres, 0 where missing.
    """
    n = replace(settings or RealSenseNoise(), **overrides)
    if not isinstance(rng, np.random.Generator):
        rng = np.random.default_rng(rng)
    z = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    valid = z > 0
    H, W = z.shape
    fb_image = float(K[0, 0]) * float(n.baseline_m)
    fb = (float(n.stereo_fx_px) if n.stereo_fx_px else float(K[0, 0])) * float(n.baseline_m)

    # Draw every random field up front (fixed order -> reproducible whatever the options).
    disp_noise = rng.normal(0.0, 1.0, (H, W))
    edge_u, dark_u, spec_u, drop_u = rng.random((4, H, W))
    width = int(rng.integers(n.edge_width_px[0], n.edge_width_px[1] + 1))

    disparity = np.where(valid, fb / np.where(valid, z, 1.0), 0.0)
    noisy = disparity + n.subpixel_sigma_px * disp_noise
    if n.disparity_step_px > 0:
        noisy = np.round(noisy / n.disparity_step_px) * n.disparity_step_px
    keep = valid & (noisy > 0)
    out = np.where(keep, fb / np.where(keep, noisy, 1.0), 0.0)

    drop = np.zeros((H, W), dtype=bool)
    edges = depth_edges(z, n.edge_threshold)
    if width > 0 and edges.any():
        kernel = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
        band = cv2.dilate(edges.astype(np.uint8), kernel) > 0
    else:
        band = edges
    drop |= band & (edge_u < n.edge_drop_prob)
    if n.stereo_shadow_enabled:
        drop |= stereo_shadow(disparity * (fb_image / fb))
    if rgb is not None:
        lum = _luminance(np.asarray(rgb))
        drop |= (lum < n.dark_threshold) & (dark_u < n.dark_drop_prob)
        drop |= (lum > n.specular_threshold) & (spec_u < n.specular_drop_prob)
    drop |= drop_u < n.dropout_prob
    drop |= (out < n.min_depth_m) | (out > n.max_depth_m)
    out[drop] = 0.0
    return out.astype(np.float32)


def noise_kwargs(cfg: Any) -> dict[str, Any]:
    """Keyword arguments of :func:`add_realsense_noise` from the synth settings' ``depth_noise``
    section (:class:`~dope_hope.config.SectionSettings`)."""
    kw = cfg.to_dict()
    kw["stereo_shadow_enabled"] = bool(kw.pop("stereo_shadow", True))
    kw["edge_width_px"] = tuple(int(v) for v in kw["edge_width_px"])
    return kw
