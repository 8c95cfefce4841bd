"""Camera intrinsics for an image: from a camera file, or from the image's own annotation.

**Camera file** (:func:`read_camera_file`, ``dope-hope infer --camera K.json``): a JSON object
in any of these forms (pixels; ``width``/``height`` optional, checked against the image)::

    {"fx": 615.0, "fy": 615.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480}
    {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]}          (or 9 numbers, row-major)
    {"cam_K": [fx, 0, cx, 0, fy, cy, 0, 0, 1]}             (a BOP scene_camera entry)
    {"camera_data": {"intrinsics": {"fx", "fy", "cx", "cy"}, "width", "height"}}  (DOPE)
    {"intrinsics": {"fx", "fy", "cx", "cy"}}                (a DOPE camera_data block)
    {"camera": {"intrinsics": 3x3, "width", "height"}}      (HOPE)
    {"camera_settings": [{"intrinsic_settings": {...}, "captured_image_size": {...}}]}  (NDDS)

**Sibling annotation** (:func:`find_image_camera`), tried in this order for ``DIR/NAME``:

1. DOPE / project JSON ``DIR/<stem>.json`` (``000123.png`` -> ``000123.json``; NDDS files
   without intrinsics fall back to ``DIR/_camera_settings.json`` inside the reader);
2. HOPE ``DIR/NNNN.json`` for ``NNNN_rgb.jpg`` / ``.png``;
3. BOP ``SCENE/scene_camera.json`` (entry ``int(stem)``) for ``SCENE/rgb/NNNNNN.png``
   (or ``gray/``).

Each also names the registered depth image when there is one (DOPE ``NNNNNN.depth.png``,
HOPE ``NNNN_depth.png``, BOP ``SCENE/depth/NNNNNN.png``) and its scale. Intrinsics are never
guessed: no camera found is reported as such (None here, CameraError in the CLI).
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import InputFileError
from dope_hope.geometry import intrinsics_matrix
from dope_hope.io.jsonfields import JsonFields, load_json_object

_HOPE_RGB = re.compile(r"^(?P<stem>.+)_rgb\.(jpg|jpeg|png)$", re.IGNORECASE)
_BOP_IMAGE_FOLDERS = ("rgb", "gray")


@dataclass
class ImageCamera:
    """Intrinsics of one image and where they came from.

    K: (3, 3). width, height: image size the K belongs to, pixels (None = not recorded).
    source: the file K was read from. depth_path: registered depth image, or None.
    depth_scale_m: metres per depth unit recorded with it (None = not recorded).
    """

    K: np.ndarray
    width: int | None
    height: int | None
    source: Path
    depth_path: Path | None = None
    depth_scale_m: float | None = None

    def check_size(self, image: str | os.PathLike, width: int, height: int) -> None:
        """Raise InputFileError when the recorded size differs from the image's."""
        if self.width is not None and self.height is not None and (self.width, self.height) != (width, height):
            raise InputFileError(self.source, f"camera is for {self.width}x{self.height} images, "
                                              f"but {Path(image).name} is {width}x{height}")


def _intrinsics(f: JsonFields, value: Any, field: str) -> np.ndarray:
    """A {fx, fy, cx, cy} object, a 3x3 matrix or 9 numbers -> validated (3, 3) K."""
    if isinstance(value, dict):
        K = intrinsics_matrix(*(f.number(f.get(value, k, field), f"{field}.{k}") for k in ("fx", "fy", "cx", "cy")))
    else:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise f.fail(field, "expected {fx, fy, cx, cy}, a 3x3 matrix or 9 numbers") from None
        if arr.size != 9:
            raise f.fail(field, f"expected a 3x3 matrix or 9 numbers, got {arr.size} values")
        K = arr.reshape(3, 3)
    if not np.all(np.isfinite(K)):
        raise f.fail(field, "contains NaN or infinity")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise f.fail(field, "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    return K


def _size(f: JsonFields, node: dict, where: str) -> tuple[int | None, int | None]:
    out = []
    for key in ("width", "height"):
        v = node.get(key)
        out.append(None if v is None else f.positive_int(v, f"{where}{key}"))
    return out[0], out[1]


def parse_camera(data: Any, path: str | os.PathLike) -> tuple[np.ndarray, int | None, int | None]:
    """(K, width, height) from a parsed camera JSON object (forms in the module docstring)."""
    f = JsonFields(path)
    if not isinstance(data, dict):
        raise f.fail("top level", f"expected a JSON object, got {type(data).__name__}")
    if all(k in data for k in ("fx", "fy", "cx", "cy")):
        return (_intrinsics(f, data, "camera"), *_size(f, data, ""))
    for key in ("K", "cam_K", "intrinsics"):
        if data.get(key) is not None:
            return (_intrinsics(f, data[key], key), *_size(f, data, ""))
    for key in ("camera_data", "camera"):
        node = data.get(key)
        if isinstance(node, dict) and node.get("intrinsics") is not None:
            return (_intrinsics(f, node["intrinsics"], f"{key}.intrinsics"), *_size(f, node, f"{key}."))
    cams = data.get("camera_settings")
    if isinstance(cams, list) and cams and isinstance(cams[0], dict):
        K = _intrinsics(f, f.get(cams[0], "intrinsic_settings", "camera_settings[0]"),
                        "camera_settings[0].intrinsic_settings")
        size = cams[0].get("captured_image_size") or {}
        return (K, *_size(f, size, "camera_settings[0].captured_image_size."))
    raise f.fail("top level", "no camera intrinsics: expected fx/fy/cx/cy, K, cam_K, intrinsics, "
                              "camera_data.intrinsics, camera.intrinsics or camera_settings")


def read_camera_file(path: str | os.PathLike) -> ImageCamera:
    """Read a camera JSON file (any form of the module docstring)."""
    path = Path(path)
    K, w, h = parse_camera(load_json_object(path, "camera file"), path)
    return ImageCamera(K=K, width=w, height=h, source=path)


def _from_dope(image: Path) -> ImageCamera | None:
    ann = image.with_suffix(".json")
    if not ann.is_file():
        return None
    from dope_hope.io.dope_json import read_dope_json

    frame = read_dope_json(ann)
    if frame.K is None:
        return None
    return ImageCamera(K=frame.K, width=frame.width, height=frame.height, source=ann,
                       depth_path=frame.depth_path, depth_scale_m=frame.depth_scale_m)


def _from_hope(image: Path) -> ImageCamera | None:
    m = _HOPE_RGB.match(image.name)
    if m is None:
        return None
    ann = image.with_name(m.group("stem") + ".json")
    if not ann.is_file():
        return None
    from dope_hope.io.hope_json import read_hope_json

    frame = read_hope_json(ann)
    return ImageCamera(K=frame.K, width=frame.width, height=frame.height, source=ann,
                       depth_path=frame.depth_path, depth_scale_m=frame.depth_scale_m)


def _from_bop(image: Path) -> ImageCamera | None:
    if image.parent.name not in _BOP_IMAGE_FOLDERS or not image.stem.isdigit():
        return None
    scene = image.parent.parent
    cam_file = scene / "scene_camera.json"
    if not cam_file.is_file():
        return None
    from dope_hope.io.bop import read_scene_camera

    cams = read_scene_camera(cam_file)
    im_id = int(image.stem)
    if im_id not in cams:
        raise InputFileError(cam_file, f"no entry for image {im_id} ({image.name})")
    K, depth_scale_m = cams[im_id]
    depth = next((p for p in (scene / "depth" / (image.stem + s) for s in (".png", ".tif"))
                  if p.is_file()), None)
    return ImageCamera(K=K, width=None, height=None, source=cam_file, depth_path=depth,
                       depth_scale_m=depth_scale_m)


def find_image_camera(image: str | os.PathLike) -> ImageCamera | None:
    """The camera of an image from its sibling annotation (DOPE, HOPE, BOP), or None.

    A sibling annotation that exists but is malformed raises its reader's InputFileError.
    """
    image = Path(image)
    for finder in (_from_dope, _from_hope, _from_bop):
        cam = finder(image)
        if cam is not None:
            return cam
    return None


def camera_search_description(image: str | os.PathLike) -> str:
    """Which sibling files :func:`find_image_camera` looks for (for error messages)."""
    image = Path(image)
    names = [image.with_suffix(".json").name]
    m = _HOPE_RGB.match(image.name)
    if m is not None:
        names.append(m.group("stem") + ".json")
    if image.parent.name in _BOP_IMAGE_FOLDERS:
        names.append("../scene_camera.json")
    return ", ".join(names)
