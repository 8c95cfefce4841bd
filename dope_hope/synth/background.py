"""Backgrounds: random crops of photographs or procedural images, with table-top clutter
drawn over them (:mod:`dope_hope.synth.clutter`), flipped and colour-shifted."""
from __future__ import annotations

import os
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from dope_hope.config import SectionSettings
from dope_hope.errors import InputFileError
from dope_hope.io.images import IMAGE_SUFFIXES, image_files, read_rgb
from dope_hope.synth.clutter import clutter_image
from dope_hope.synth.textures import procedural_image


def background_images(photos: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """Image files of ``photos``: one path or several, each a folder (searched recursively,
    sorted so that indices are reproducible) or an image file, in the order given."""
    paths = [photos] if isinstance(photos, (str, os.PathLike)) else list(photos)
    files: list[Path] = []
    for path in map(Path, paths):
        if path.is_file():
            if path.suffix.lower() not in IMAGE_SUFFIXES:
                raise InputFileError(path, f"not an image ({', '.join(IMAGE_SUFFIXES)})")
            files.append(path)
            continue
        if not path.is_dir():
            raise InputFileError(path, "background folder not found")
        found = image_files(path, recursive=True)
        if not found:
            raise InputFileError(path, f"no images ({', '.join(IMAGE_SUFFIXES)}) in the background folder")
        files += found
    return files


def color_shift(rng: np.random.Generator, img: np.ndarray, cfg: SectionSettings) -> np.ndarray:
    """Random brightness, contrast and per-channel gain/offset. (H, W, 3) uint8 -> same."""
    x = img.astype(np.float32)
    mean = x.mean()
    contrast = rng.uniform(*cfg.contrast)
    brightness = rng.uniform(*cfg.brightness)
    gain = rng.uniform(*cfg.channel_gain, size=3).astype(np.float32)
    offset = rng.uniform(-cfg.channel_offset, cfg.channel_offset, size=3).astype(np.float32)
    x = ((x - mean) * contrast + mean) * brightness * gain + offset
    return np.clip(x + 0.5, 0, 255).astype(np.uint8)


def random_crop(rng: np.random.Generator, img: np.ndarray, width: int, height: int,
                scale: tuple[float, float]) -> np.ndarray:
    """Crop a random window with the target aspect ratio and resize it to (height, width).

    ``scale`` is the window's side as a fraction of the largest window of that aspect ratio.
    """
    H, W = img.shape[:2]
    aspect = width / height
    max_w = min(W, H * aspect)
    s = rng.uniform(*scale)
    cw = max(1, int(round(max_w * s)))
    ch = max(1, int(round(cw / aspect)))
    cw, ch = min(cw, W), min(ch, H)
    x0 = int(rng.integers(0, W - cw + 1))
    y0 = int(rng.integers(0, H - ch + 1))
    crop = img[y0:y0 + ch, x0:x0 + cw]
    interp = cv2.INTER_AREA if cw > width else cv2.INTER_LINEAR
    return cv2.resize(crop, (width, height), interpolation=interp)


class BackgroundSource:
    """Draws backgrounds for frames.

    Args:
        cfg: the ``background`` section of the synth config.
        photos: photographs to crop from (a folder, an image file, or several of either:
            :func:`background_images`), or None for procedural backgrounds only.
    """

    def __init__(self, cfg: SectionSettings,
                 photos: str | os.PathLike | Sequence[str | os.PathLike] | None = None):
        self.cfg = cfg
        self.files = background_images(photos) if photos is not None else []
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()

    def _load(self, i: int) -> np.ndarray:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        img = read_rgb(self.files[i])
        # Keep memory bounded: cache a copy no larger than needed for the largest crop.
        limit = int(self.cfg.max_cached_side_px)
        if max(img.shape[:2]) > limit:
            f = limit / max(img.shape[:2])
            img = cv2.resize(img, (max(1, int(img.shape[1] * f)), max(1, int(img.shape[0] * f))),
                             interpolation=cv2.INTER_AREA)
        self._cache[i] = img
        while len(self._cache) > int(self.cfg.cache_images):
            self._cache.popitem(last=False)
        return img

    def photo_patch(self, rng: np.random.Generator, px: int) -> np.ndarray:
        """A square crop of a random photograph (side 5-30 % of its shorter side), (px, px, 3) uint8."""
        img = self._load(int(rng.integers(0, len(self.files))))
        side = max(2, int(min(img.shape[:2]) * rng.uniform(0.05, 0.3)))
        y0 = int(rng.integers(0, img.shape[0] - side + 1))
        x0 = int(rng.integers(0, img.shape[1] - side + 1))
        return cv2.resize(img[y0:y0 + side, x0:x0 + side], (px, px), interpolation=cv2.INTER_AREA)

    def sample(self, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
        """One background, (height, width, 3) uint8 RGB.

        The clutter draws from a child generator of ``rng``, spawned only when
        ``clutter_prob`` > 0: switching clutter off leaves every draw of ``rng`` (and of its
        later children) as it was.
        """
        cfg = self.cfg
        clutter_rng = rng.spawn(1)[0] if float(cfg.clutter_prob) > 0 else None
        use_photo = bool(self.files) and rng.random() >= cfg.procedural_prob_with_images
        if use_photo:
            img = self._load(int(rng.integers(0, len(self.files))))
            img = random_crop(rng, img, width, height, tuple(cfg.crop_scale))
        else:
            img = procedural_image(rng, height, width, cfg.procedural_weights.to_dict())
        if clutter_rng is not None and clutter_rng.random() < cfg.clutter_prob:
            img = clutter_image(clutter_rng, img, cfg.clutter, self.photo_patch if self.files else None)
        if rng.random() < cfg.flip_prob:
            img = img[:, ::-1]
        if rng.random() < cfg.vflip_prob:
            img = img[::-1]
        return color_shift(rng, np.ascontiguousarray(img), cfg.color_shift)
