"""Colour-camera artefacts as a RealSense colour image has them: optics, sensor noise, JPEG.

Applied to the composited RGB after the colour jitter / blur / noise of
:func:`dope_hope.synth.postprocess.post_process` (which calls :func:`sensor_artifacts` with
the ``post`` section of the synth config). In the order light takes:

1. optics, in linear light: defocus (a disc kernel), linear motion blur, lateral chromatic
   aberration (red and blue scaled about the image centre against green) and vignetting
   (a cos^4-like fall-off towards the corners);
2. exposure (a gain in stops, highlights clip) and white balance (red and blue gains);
3. signal-dependent noise: variance ``shot * x + read**2`` for linear signal ``x`` in [0, 1]
   (photon shot noise plus read noise), per pixel and channel;
4. back to sRGB, then JPEG compression at a random quality (the camera's MJPEG / a saved JPEG).

Every random number is drawn whether or not its effect applies, so that one effect's
probability does not shift the others' draws.
"""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from dope_hope.config import SectionSettings

#: The ``post`` keys of this module: each effect's probability key, in the order applied.
EFFECT_PROBS = ("defocus_prob", "motion_blur_prob", "chromatic_prob", "vignetting_prob",
                "exposure_prob", "shot_noise_prob", "jpeg_prob")

_V = np.arange(256, dtype=np.float64) / 255.0
#: The sRGB transfer function (IEC 61966-2-1) inverted: uint8 code -> linear in [0, 1].
_TO_LINEAR = np.where(_V <= 0.04045, _V / 12.92, ((_V + 0.055) / 1.055) ** 2.4).astype(np.float32)


def to_linear(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 sRGB -> float32 linear in [0, 1]."""
    return _TO_LINEAR[img]


_LUT_STEPS = 1 << 16
_L = np.arange(_LUT_STEPS, dtype=np.float64) / (_LUT_STEPS - 1)
#: The sRGB transfer function sampled at 2^16 linear levels -> uint8 code (a table: 5x faster).
_TO_SRGB = np.round(255.0 * np.where(_L <= 0.0031308, 12.92 * _L,
                                     1.055 * np.power(_L, 1.0 / 2.4) - 0.055)).astype(np.uint8)


def to_srgb(x: np.ndarray) -> np.ndarray:
    """float linear (H, W, 3) -> uint8 sRGB (clipped; the sRGB transfer function, by table)."""
    idx = np.clip(x, 0.0, 1.0) * np.float32(_LUT_STEPS - 1) + np.float32(0.5)
    return _TO_SRGB[idx.astype(np.int32)]


def disc_kernel(radius_px: float) -> np.ndarray:
    """Normalized (2k+1, 2k+1) pillbox of ``radius_px`` with anti-aliased rim (defocus PSF)."""
    k = int(np.ceil(radius_px))
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1].astype(np.float32)
    w = np.clip(radius_px + 0.5 - np.hypot(xx, yy), 0.0, 1.0)
    return w / w.sum()


def motion_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """Normalized line PSF of ``length_px`` at ``angle_rad`` (image x right, y down)."""
    k = int(np.ceil(length_px / 2.0)) + 1
    ker = np.zeros((2 * k + 1, 2 * k + 1), np.float32)
    d = np.array([np.cos(angle_rad), np.sin(angle_rad)]) * length_px / 2.0
    p0 = np.round((k - d[0]) * 16), np.round((k - d[1]) * 16)
    p1 = np.round((k + d[0]) * 16), np.round((k + d[1]) * 16)
    cv2.line(ker, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), 1.0, 1, cv2.LINE_AA, shift=4)
    s = float(ker.sum())
    if s <= 0:
        ker[k, k] = 1.0
        s = 1.0
    return ker / s


def chromatic_aberration(x: np.ndarray, shift_px: float) -> np.ndarray:
    """Red channel magnified and blue shrunk about the centre so that each moves ``shift_px``
    at the image corner (lateral chromatic aberration). float (H, W, 3) -> same."""
    H, W = x.shape[:2]
    corner = float(np.hypot((W - 1) / 2.0, (H - 1) / 2.0))
    out = x.copy()
    for ch, sign in ((0, 1.0), (2, -1.0)):
        s = 1.0 + sign * shift_px / max(corner, 1.0)
        cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
        M = np.array([[s, 0.0, cx * (1 - s)], [0.0, s, cy * (1 - s)]], np.float32)
        out[..., ch] = cv2.warpAffine(np.ascontiguousarray(x[..., ch]), M, (W, H), flags=cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REFLECT)
    return out


@lru_cache(maxsize=8)
def _radius_squared(height: int, width: int) -> np.ndarray:
    """(H, W) float32 squared distance from the image centre, 1 at the corners."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = (xx - (width - 1) / 2.0) ** 2 + (yy - (height - 1) / 2.0) ** 2
    r2 /= max(float(r2.max()), 1.0)
    r2.setflags(write=False)
    return r2


def vignetting_gain(height: int, width: int, strength: float) -> np.ndarray:
    """(H, W, 1) float32 gain: 1 at the centre, ``1 - strength`` at the corners (cos^4 shape:
    cos^4(atan(r tan_max)) = (1 + r^2 tan_max^2)^-2)."""
    tan2 = np.sqrt(1.0 / max(1.0 - strength, 1e-3)) - 1.0  # tan_max^2: corner gain 1 - strength
    g = 1.0 / (1.0 + _radius_squared(height, width) * np.float32(tan2)) ** 2
    return g[..., None].astype(np.float32)


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """JPEG round trip (OpenCV, 4:2:0 chroma subsampling) of an (H, W, 3) uint8 RGB image."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 RGB
        return img
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def sensor_artifacts(rng: np.random.Generator, img: np.ndarray, cfg: SectionSettings) -> np.ndarray:
    """Optics, exposure, white balance, shot/read noise and JPEG (module docstring).

    Args:
        rng: the frame's generator for these effects.
        img: (H, W, 3) uint8 RGB.
        cfg: the ``post`` section of the synth config (keys of :data:`EFFECT_PROBS` and their ranges).

    Returns:
        (H, W, 3) uint8 RGB; ``img`` itself when no effect applies.
    """
    do = rng.random(len(EFFECT_PROBS)) < np.array([float(getattr(cfg, k)) for k in EFFECT_PROBS])
    do_defocus, do_motion, do_chroma, do_vignette, do_exposure, do_noise, do_jpeg = do
    defocus_r = rng.uniform(*cfg.defocus_radius_px)
    motion_len, motion_angle = rng.uniform(*cfg.motion_blur_px), rng.uniform(0.0, np.pi)
    chroma_px = rng.uniform(*cfg.chromatic_px)
    vignette = rng.uniform(*cfg.vignetting)
    ev, wb = rng.uniform(*cfg.exposure_ev), rng.uniform(*cfg.white_balance, size=2)
    shot, read = rng.uniform(*cfg.shot_noise), rng.uniform(*cfg.read_noise)
    quality = int(rng.integers(int(cfg.jpeg_quality[0]), int(cfg.jpeg_quality[1]) + 1))
    noise_rng = rng.spawn(1)[0]

    out = img
    if do_defocus or do_motion or do_chroma or do_vignette or do_exposure or do_noise:
        x = to_linear(img)
        if do_defocus:
            x = cv2.filter2D(x, -1, disc_kernel(defocus_r), borderType=cv2.BORDER_REFLECT)
        if do_motion:
            x = cv2.filter2D(x, -1, motion_kernel(motion_len, motion_angle), borderType=cv2.BORDER_REFLECT)
        if do_chroma:
            x = chromatic_aberration(x, chroma_px)
        if do_vignette:
            x = x * vignetting_gain(x.shape[0], x.shape[1], vignette)
        if do_exposure:
            gain = np.array([wb[0], 1.0, wb[1]], np.float32) * np.float32(2.0 ** ev)
            x = np.minimum(x * gain, np.float32(1.0))
        if do_noise:
            sigma = np.maximum(x, np.float32(0.0))
            sigma *= np.float32(shot)
            sigma += np.float32(read * read)
            np.sqrt(sigma, out=sigma)
            sigma *= noise_rng.standard_normal(x.shape, dtype=np.float32)
            x = x + sigma
        out = to_srgb(x)
    if do_jpeg:
        out = jpeg(np.ascontiguousarray(out), quality)
    return out
