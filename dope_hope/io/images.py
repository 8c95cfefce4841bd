"""Image files: RGB in memory (OpenCV's BGR converted once, here), depth as uint16 or metres.

OpenCV's codecs print their complaints (``libpng error: ...``, libjpeg's ``Premature end of
JPEG file``) straight to the process's stderr; reads catch those lines and turn them into the
one-line error of the file, or drop them when the image decoded whole.
"""
from __future__ import annotations

import contextlib
import glob
import os
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.io.atomic import atomic_write_bytes
from dope_hope.io.paths import path_kind, require_file

#: Suffixes of image files, the one list: folders of images (``infer`` inputs, backgrounds,
#: INT8 calibration) and a DOPE frame's image beside its JSON (the first three, in this order).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
#: Name endings of auxiliary images in dataset folders (not colour frames).
AUX_SUFFIXES = (".depth.png", ".depth.exr", ".seg.png", ".seg.exr", "_depth.png", "_seg.png",
                "_mask.png", ".mask.png", ".cs.png")
#: Characters that make an input a glob pattern.
GLOB_CHARS = set("*?[")


def image_files(folder: str | os.PathLike, recursive: bool = False) -> list[Path]:
    """Sorted image files (by :data:`IMAGE_SUFFIXES`) in ``folder``; sorted so that indices
    are reproducible. The caller checks that the folder exists and says what it is for."""
    entries = Path(folder).rglob("*") if recursive else Path(folder).iterdir()
    return sorted(p for p in entries if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def is_colour_image(path: Path) -> bool:
    """An input image by name: an :data:`IMAGE_SUFFIXES` suffix, not an auxiliary image of a
    dataset (:data:`AUX_SUFFIXES`), not hidden."""
    name = path.name.lower()
    return path.suffix.lower() in IMAGE_SUFFIXES and not name.endswith(AUX_SUFFIXES) and not name.startswith(".")


def _glob_base(pattern: str) -> Path:
    """The fixed folder prefix of a glob pattern."""
    parts = Path(pattern).parts
    fixed = []
    for part in parts[:-1]:
        if GLOB_CHARS & set(part):
            break
        fixed.append(part)
    return Path(*fixed) if fixed else Path(".")


def collect_images(inputs: list[str]) -> list[tuple[Path, str]]:
    """(image path, record name) for each input image, in order, without duplicates.

    A record name is the image's path relative to its input's base (the folder, the glob's
    fixed prefix, the loose files' common folder); when the inputs have different bases,
    relative to the bases' common folder instead, so that names never repeat
    (``a/000000.png``, ``b/000000.png``).
    """
    found: list[tuple[Path, Path]] = []  # (path, base folder for the name)
    loose: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.is_file() and is_colour_image(f))
            if not files:
                raise InputFileError(p, "folder holds no images (" + ", ".join(IMAGE_SUFFIXES) + ")")
            found += [(f, p) for f in files]
        elif p.is_file():
            loose.append(p)
        elif path_kind(p) is not None:
            require_file(p, "image file")  # a named pipe, a socket...: says so
        elif GLOB_CHARS & set(item):
            files = sorted(Path(f) for f in glob.glob(item, recursive=True)
                           if Path(f).is_file() and is_colour_image(Path(f)))
            if not files:
                raise InputFileError(item, "no images match this pattern")
            found += [(f, _glob_base(item)) for f in files]
        else:
            raise InputFileError(p, "image file not found")
    if loose:
        base = Path(os.path.commonpath([str(f.resolve().parent) for f in loose]))
        found += [(f, base) for f in loose]
    bases = {str(b.resolve()) for _, b in found}
    if len(bases) > 1:
        common = Path(os.path.commonpath(sorted(bases)))
        found = [(f, common) for f, _ in found]
    out, seen = [], set()
    for f, base in found:
        key = f.resolve()
        if key in seen:
            continue
        seen.add(key)
        try:
            name = f.resolve().relative_to(base.resolve()).as_posix()
        except ValueError:
            name = f.name
        out.append((f, name))
    return out


#: libjpeg warnings that mean pixels are missing or invented (the decoder fills them in).
_DAMAGED_JPEG = ("Premature end of JPEG file", "Corrupt JPEG data: premature end",
                 "Corrupt JPEG data: bad Huffman", "Corrupt JPEG data: found marker")
_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def native_stderr_lines() -> Iterator[list[str]]:
    """Capture what C libraries write to file descriptor 2 inside the block (the list is
    filled when the block ends). Python's own sys.stderr is flushed first and not captured
    differently; one block at a time per process."""
    lines: list[str] = []
    with _STDERR_LOCK, tempfile.TemporaryFile() as sink:
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        saved = os.dup(2)
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines += [ln.strip() for ln in sink.read().decode("utf-8", "replace").splitlines() if ln.strip()]


def read_image_raw(path: str | os.PathLike) -> np.ndarray:
    """Read any image unchanged (bit depth and channels kept); BGR(A) turned into RGB(A).

    Raises InputFileError for a missing, unreadable, truncated or corrupt file (a JPEG that
    libjpeg had to complete with invented pixels included).
    """
    path = require_file(path, "image file")
    if path.suffix.lower() == ".exr":
        return _read_exr(path)
    with native_stderr_lines() as messages:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        why = messages[-1] if messages else "unknown format or corrupt"
        raise InputFileError(path, f"not a readable image ({why})")
    damaged = next((m for m in messages if m.startswith(_DAMAGED_JPEG)), None)
    if damaged is not None:
        raise InputFileError(path, f"truncated or corrupt image ({damaged})")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return img


def _read_exr(path: Path) -> np.ndarray:
    """EXR as float32 (H, W) or (H, W, C) RGB(A), via the OpenEXR bindings: OpenCV's wheels
    are built without OpenEXR (cv2.imread returns None even with OPENCV_IO_ENABLE_OPENEXR)."""
    import OpenEXR  # noqa: PLC0415 (OpenEXR only for .exr files)

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
    from PIL import Image, UnidentifiedImageError  # noqa: PLC0415 (Pillow reads the header alone)

    path = require_file(path, "image file")
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
    """Write (H, W, 3) uint8 RGB (or (H, W) gray / uint16) atomically; format from the suffix.

    Encoded in memory and written by Python, so that a failed write (disk full...) raises
    OutputPathError with the reason (cv2.imwrite only returns False).
    """
    path = Path(path)
    img = np.asarray(rgb)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    try:
        ok, data = cv2.imencode(path.suffix or ".png", img)
    except cv2.error:
        ok = False
    if not ok:
        raise InputFileError(path, f"cannot encode a {img.dtype} image of shape {img.shape} as "
                                   f"{path.suffix or 'PNG'}")
    atomic_write_bytes(path, data.tobytes())


def read_depth_m(path: str | os.PathLike, depth_scale_m: float = 0.001) -> np.ndarray:
    """Read a depth image as (H, W) float32 metres; 0 / NaN mean "no measurement".

    uint16 PNGs are multiplied by ``depth_scale_m`` (metres per unit; 0.001 for millimetres);
    float images (EXR, float TIFF) are taken as metres; non-finite values and renderer
    sentinels (|d| >= 1e30, e.g. NViSII's -FLT_MAX for "no surface") become 0.
    """
    if not (np.isfinite(depth_scale_m) and depth_scale_m > 0):
        raise InputFileError(path, f"depth scale must be a positive number of metres per unit, got {depth_scale_m}")
    img = read_image_raw(path)
    if img.dtype == np.uint8:
        raise InputFileError(path, "an 8-bit image, not a depth map (expected uint16 depth units, "
                                   "or float metres)")
    if img.ndim == 3 and np.issubdtype(img.dtype, np.integer):
        raise InputFileError(path, f"a {img.shape[2]}-channel image, not a depth map (expected one "
                                   "uint16 channel of depth units)")
    if img.ndim == 3:
        img = img[:, :, 0]
    if img.dtype in (np.uint16, np.int32):
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
