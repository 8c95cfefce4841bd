"""Image files: RGB in memory (OpenCV's BGR converted once, here), depth as uint16 or metres."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.io.atomic import atomic_path

#: Suffixes taken as photographs when a folder of images is scanned (backgrounds, calibration).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def image_files(folder: str | os.PathLike, recursive: bool = False) -> list[Path]:
    """Sorted image files (by :data:`IMAGE_SUFFIXES`) in ``folder``; sorted so that indices
    are reproducible. The caller checks that the folder exists and says what it is for."""
    entries = Path(folder).rglob("*") if recursive else Path(folder).iterdir()
    return sorted(p for p in entries if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def read_image_raw(path: str | os.PathLike) -> np.ndarray:
    """Read any image unchanged (bit depth and channels kept); BGR(A) turned into RGB(A)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "image file not found")
    if path.suffix.lower() == ".exr":
        return _read_exr(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputFileError(path, "not a readable image (unknown format or corrupt)")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return img


def _read_exr(path: Path) -> np.ndarray:
    """EXR as float32 (H, W) or (H, W, C) RGB(A), via the OpenEXR bindings: OpenCV's wheels
    are built without OpenEXR (cv2.imread returns None even with OPENCV_IO_ENABLE_OPENEXR)."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path)) as exr:
            channels = {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as exc:  # the bindings raise RuntimeError/OSError for a corrupt file
        raise InputFileError(path, f"not a readable EXR image ({exc})") from None
    for name in ("RGBA", "RGB", "Z", "Y", "R"):
        if name in channels:
            return channels[name].astype(np.float32, copy=False)
    if not channels:
        raise InputFileError(path, "EXR image has no channels")
    return channels[sorted(channels)[0]].astype(np.float32, copy=False)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file from its header only (no decoding), pixels."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "image file not found")
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError) as exc:
        raise InputFileError(path, f"not a readable image ({exc})") from None


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read an image as (H, W, 3) uint8 RGB (grayscale and alpha converted, 16-bit scaled)."""
    img = read_image_raw(path)
    if img.dtype == np.uint16:
        img = (img / 257.0 + 0.5).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputFileError(path, f"unsupported image dtype {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    return np.ascontiguousarray(img)


def write_rgb(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB (or (H, W) gray / uint16) atomically; format from the suffix."""
    path = Path(path)
    img = np.asarray(rgb)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise InputFileError(path, "could not write image")


def read_depth_m(path: str | os.PathLike, depth_scale_m: float = 0.001) -> np.ndarray:
    """Read a depth image as (H, W) float32 metres; 0 / NaN mean "no measurement".

    uint16 PNGs are multiplied by ``depth_scale_m`` (metres per unit; 0.001 for millimetres);
    float images (EXR, float TIFF) are taken as metres; non-finite values and renderer
    sentinels (|d| >= 1e30, e.g. NViSII's -FLT_MAX for "no surface") become 0.
    """
    img = read_image_raw(path)
    if img.ndim == 3:
        img = img[:, :, 0]
    if img.dtype in (np.uint16, np.uint8, np.int32):
        return img.astype(np.float32) * np.float32(depth_scale_m)
    if img.dtype in (np.float32, np.float64):
        d = img.astype(np.float32)
        d[~np.isfinite(d) | (np.abs(d) >= 1e30)] = 0.0
        return d
    raise InputFileError(path, f"unsupported depth dtype {img.dtype}")


def write_depth_mm(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    """Write (H, W) metres as a uint16 millimetre PNG atomically (NaN/<=0 -> 0)."""
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0)
    mm = np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16)
    write_rgb(path, mm)
