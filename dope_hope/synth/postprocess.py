"""Compositing over the background and post-render image corruption (jitter, blur, noise,
then the camera's own artefacts: :mod:`dope_hope.synth.sensor`)."""
from __future__ import annotations

import cv2
import numpy as np

from dope_hope.config import SectionSettings
from dope_hope.synth.sensor import sensor_artifacts


def composite(background: np.ndarray, color: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Objects over a background: ``color + (1 - alpha) * background``.

    Args:
        background: (H, W, 3) uint8.
        color: (H, W, 3) uint8 rendered colours, premultiplied by coverage (the renderer
            clears to transparent black, so MSAA edge pixels are already weighted).
        alpha: (H, W) float coverage in [0, 1].

    Returns:
        (H, W, 3) uint8.
    """
    out = color.astype(np.float32) + (1.0 - alpha[..., None]) * background.astype(np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def color_jitter(rng: np.random.Generator, img: np.ndarray, cfg: SectionSettings) -> np.ndarray:
    """Brightness, contrast, saturation and hue jitter of an RGB uint8 image."""
    x = img.astype(np.float32)
    x = x * rng.uniform(*cfg.brightness)
    mean = x.mean()
    x = (x - mean) * rng.uniform(*cfg.contrast) + mean
    x = np.clip(x, 0, 255)
    hsv = cv2.cvtColor(x.astype(np.uint8), cv2.COLOR_RGB2HSV).astype(np.float32)
    hsv[..., 0] = (hsv[..., 0] + rng.uniform(*cfg.hue_deg) / 2.0) % 180.0  # OpenCV hue: 0..180
    hsv[..., 1] = np.clip(hsv[..., 1] * rng.uniform(*cfg.saturation), 0, 255)
    return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)


def post_process(rng: np.random.Generator, img: np.ndarray, cfg: SectionSettings) -> np.ndarray:
    """Colour jitter, Gaussian blur and Gaussian pixel noise, each with its probability, then
    the sensor artefacts (:func:`dope_hope.synth.sensor.sensor_artifacts`: optics, exposure,
    shot/read noise, JPEG).

    Every random number is drawn whether or not the effect applies, so that one effect's
    probability does not shift the others' draws; the sensor artefacts draw from a third child
    generator, so switching them off gives the images of the first three steps unchanged.
    """
    do_jitter, do_blur, do_noise = rng.random(3) < (cfg.jitter_prob, cfg.blur_prob, cfg.noise_prob)
    jitter_rng, blur_sigma, noise_sigma = rng.spawn(1)[0], rng.uniform(*cfg.blur_sigma_px), \
        rng.uniform(*cfg.noise_sigma)
    noise_rng = rng.spawn(1)[0]
    out = img
    if do_jitter:
        out = color_jitter(jitter_rng, out, cfg)
    if do_blur:
        out = cv2.GaussianBlur(out, (0, 0), sigmaX=float(blur_sigma))
    if do_noise:
        noisy = out.astype(np.float32) + noise_rng.normal(0.0, noise_sigma, out.shape).astype(np.float32)
        out = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
    out = sensor_artifacts(rng.spawn(1)[0], np.ascontiguousarray(out), cfg)
    return np.ascontiguousarray(out)
