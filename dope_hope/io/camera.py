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

or a ROS ``camera_info`` YAML file (``.yaml`` / ``.yml``): the calibration file that
``camera_calibration`` writes (``image_width``, ``image_height``, ``camera_matrix``,
``distortion_model``, ``distortion_coefficients``, ``rectification_matrix``,
``projection_matrix``, each matrix as ``{rows, cols, data}``), or a ``sensor_msgs/CameraInfo``
message as ``rostopic echo`` / ``ros2 topic echo`` prints it (``width``, ``height``, ``K`` /
``k``, ``D`` / ``d``, ``R`` / ``r``, ``P`` / ``p``). Such a camera describes the camera's raw
images: with non-zero distortion coefficients every frame is rectified as ROS ``image_proc``
does (``cv2.initUndistortRectifyMap(K, D, R, P[:, :3])``, :class:`Rectification`) and
``P[:, :3]`` is the K of the rectified frames; with zero distortion K is ``camera_matrix``.

**Sibling annotation** (:func:`find_image_camera`; the layouts are :mod:`dope_hope.io.layouts`'s),
tried in this order for ``DIR/NAME``:

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from dope_hope.errors import InputFileError
from dope_hope.geometry import intrinsics_matrix, is_pinhole
from dope_hope.io.bop import read_scene_camera
from dope_hope.io.dope_json import read_dope_json
from dope_hope.io.hope_json import read_hope_json
from dope_hope.io.jsonfields import JsonFields, load_json_object, read_text_file
from dope_hope.io.layouts import LAYOUTS, annotation_file, annotation_search_description


@dataclass
class ImageCamera:
    """Intrinsics of one image and where they came from.

    K: (3, 3). width, height: image size the K belongs to, pixels (None = not recorded).
    source: the file K was read from. depth_path: registered depth image, or None.
    depth_scale_m: metres per depth unit recorded with it (None = not recorded).
    rectification: how to undistort the camera's raw frames (ROS camera_info with non-zero
        distortion), or None; K is then the rectified frames' K.
    """

    K: np.ndarray
    width: int | None
    height: int | None
    source: Path
    depth_path: Path | None = None
    depth_scale_m: float | None = None
    rectification: Rectification | None = None

    def check_size(self, image: str | os.PathLike, width: int, height: int) -> None:
        """Raise InputFileError when the recorded size differs from the image's."""
        if self.width is not None and self.height is not None and (self.width, self.height) != (width, height):
            raise InputFileError(self.source, f"camera is for {self.width}x{self.height} images, "
                                              f"but {Path(image).name} is {width}x{height}")


@dataclass
class Rectification:
    """Undistortion of a camera's raw frames (a ROS camera_info's K, D, R, P), as ``image_proc``.

    K_raw: (3, 3) raw-image intrinsics. D: (4|5|8|12|14,) OpenCV distortion coefficients
    (``plumb_bob`` / ``rational_polynomial``). R: (3, 3) rectification rotation.
    K_new: (3, 3) intrinsics of the rectified frames (``P[:, :3]``).
    """

    K_raw: np.ndarray
    D: np.ndarray
    R: np.ndarray
    K_new: np.ndarray
    _maps: dict = field(default_factory=dict, repr=False)

    def _map(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        if (width, height) not in self._maps:

            self._maps[(width, height)] = cv2.initUndistortRectifyMap(
                self.K_raw, self.D, self.R, self.K_new, (width, height), cv2.CV_32FC1)
        return self._maps[(width, height)]

    def image(self, image: np.ndarray) -> np.ndarray:
        """(H, W[, C]) raw frame -> the rectified frame (bilinear)."""
        mx, my = self._map(image.shape[1], image.shape[0])
        return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) raw depth registered to the raw frame -> rectified (nearest: no mixed depths)."""
        mx, my = self._map(depth.shape[1], depth.shape[0])
        return cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)


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
    if not is_pinhole(K):
        raise f.fail(field, "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    return K


def _camera_image_size(f: JsonFields, node: dict, where: str) -> tuple[int | None, int | None]:
    out = []
    for key in ("width", "height"):
        v = node.get(key)
        out.append(None if v is None else f.positive_int(v, f"{where}{key}"))
    return out[0], out[1]


#: Keys of a ROS camera_info: calibration-file names, then the message's (ROS 1, ROS 2).
_ROS_KEYS = {"K": ("camera_matrix", "K", "k"), "D": ("distortion_coefficients", "D", "d"),
             "R": ("rectification_matrix", "R", "r"), "P": ("projection_matrix", "P", "p"),
             "width": ("image_width", "width"), "height": ("image_height", "height")}
#: distortion_model values OpenCV's pinhole model (cv2.initUndistortRectifyMap) implements.
ROS_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
_OPENCV_DISTORTION_SIZES = (4, 5, 8, 12, 14)


def _ros_value(data: dict, what: str) -> tuple[str, Any]:
    """(key found, value) of one camera_info entry (``{rows, cols, data}`` unwrapped)."""
    for key in _ROS_KEYS[what]:
        if data.get(key) is not None:
            v = data[key]
            return key, (v.get("data") if isinstance(v, dict) else v)
    return _ROS_KEYS[what][0], None


def _ros_matrix(f: JsonFields, data: dict, what: str, shape: tuple[int, int]) -> np.ndarray | None:
    key, v = _ros_value(data, what)
    if v is None:
        return None
    try:
        arr = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise f.fail(key, "expected numbers") from None
    if arr.size != shape[0] * shape[1]:
        raise f.fail(key, f"expected {shape[0]}x{shape[1]} = {shape[0] * shape[1]} numbers, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise f.fail(key, "contains NaN or infinity")
    return arr.reshape(shape)


def is_ros_camera_info(data: Any) -> bool:
    """True for a parsed ROS camera_info (calibration file or message), see the module docstring."""
    return isinstance(data, dict) and (data.get("camera_matrix") is not None or any(
        data.get(k) is not None for k in ("D", "d", "P", "p")) or data.get("k") is not None)


def parse_ros_camera_info(data: dict, path: str | os.PathLike
                          ) -> tuple[np.ndarray, int | None, int | None, Rectification | None]:
    """(K of the frames the predictor sees, width, height, rectification or None) of a ROS
    camera_info (module docstring): K = camera_matrix without distortion; with non-zero D,
    frames are rectified and K = P[:, :3] (camera_matrix when P is absent)."""
    f = JsonFields(path)
    K_key, _ = _ros_value(data, "K")
    K = _ros_matrix(f, data, "K", (3, 3))
    if K is None:
        raise f.fail("camera_matrix", "missing field (the 3x3 intrinsics; also read as K or k)")
    K = _intrinsics(f, K, K_key)
    size = []
    for what in ("width", "height"):
        key, v = _ros_value(data, what)
        size.append(None if v is None else f.positive_int(v, key))
    width, height = size
    D_key, D_raw = _ros_value(data, "D")
    try:
        D = np.zeros(0) if D_raw is None else np.asarray(D_raw, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise f.fail(D_key, "expected numbers") from None
    if not np.all(np.isfinite(D)):
        raise f.fail(D_key, "contains NaN or infinity")
    if not np.any(D):
        return K, width, height, None
    model = data.get("distortion_model", "plumb_bob")
    if model not in ROS_DISTORTION_MODELS:
        raise f.fail("distortion_model", f"{model!r} is not supported with non-zero distortion "
                                         f"(supported: {', '.join(ROS_DISTORTION_MODELS)})")
    if D.size not in _OPENCV_DISTORTION_SIZES:
        raise f.fail(D_key, f"expected 4, 5, 8, 12 or 14 coefficients, got {D.size}")
    R = _ros_matrix(f, data, "R", (3, 3))
    P = _ros_matrix(f, data, "P", (3, 4))
    K_new = K if P is None else _intrinsics(f, P[:, :3], _ros_value(data, "P")[0] + "[:, :3]")
    rect = Rectification(K_raw=K, D=D, R=np.eye(3) if R is None else R, K_new=K_new)
    return K_new, width, height, rect


def parse_camera(data: Any, path: str | os.PathLike) -> tuple[np.ndarray, int | None, int | None]:
    """(K, width, height) from a parsed camera JSON object (the JSON forms of the module
    docstring; a ROS camera_info goes to :func:`parse_ros_camera_info`)."""
    f = JsonFields(path)
    if not isinstance(data, dict):
        raise f.fail("top level", f"expected a JSON object, got {type(data).__name__}")
    if all(k in data for k in ("fx", "fy", "cx", "cy")):
        return (_intrinsics(f, data, "camera"), *_camera_image_size(f, data, ""))
    for key in ("K", "cam_K", "intrinsics"):
        if data.get(key) is not None:
            return (_intrinsics(f, data[key], key), *_camera_image_size(f, data, ""))
    for key in ("camera_data", "camera"):
        node = data.get(key)
        if isinstance(node, dict) and node.get("intrinsics") is not None:
            return (_intrinsics(f, node["intrinsics"], f"{key}.intrinsics"), *_camera_image_size(f, node, f"{key}."))
    cams = data.get("camera_settings")
    if isinstance(cams, list) and cams and isinstance(cams[0], dict):
        K = _intrinsics(f, f.get(cams[0], "intrinsic_settings", "camera_settings[0]"),
                        "camera_settings[0].intrinsic_settings")
        size = cams[0].get("captured_image_size") or {}
        return (K, *_camera_image_size(f, size, "camera_settings[0].captured_image_size."))
    raise f.fail("top level", "no camera intrinsics: expected fx/fy/cx/cy, K, cam_K, intrinsics, "
                              "camera_data.intrinsics, camera.intrinsics or camera_settings")


def _load_yaml_object(path: Path) -> dict:
    try:
        data = yaml.safe_load(read_text_file(path, "camera file"))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        raise InputFileError(path, f"malformed YAML ({where}{getattr(exc, 'problem', None) or exc})") from None
    if not isinstance(data, dict):
        raise InputFileError(path, f"top level: expected a YAML mapping, got {type(data).__name__}")
    return data


def read_camera_file(path: str | os.PathLike) -> ImageCamera:
    """Read a camera file: JSON (any form of the module docstring) or a ROS camera_info
    YAML (``.yaml`` / ``.yml``)."""
    path = Path(path)
    data = (_load_yaml_object(path) if path.suffix.lower() in (".yaml", ".yml")
            else load_json_object(path, "camera file"))
    if is_ros_camera_info(data):
        K, w, h, rect = parse_ros_camera_info(data, path)
        return ImageCamera(K=K, width=w, height=h, source=path, rectification=rect)
    K, w, h = parse_camera(data, path)
    return ImageCamera(K=K, width=w, height=h, source=path)


def _from_dope(image: Path) -> ImageCamera | None:
    ann = annotation_file(image, "dope")
    if ann is None:
        return None

    frame = read_dope_json(ann)
    if frame.K is None:
        return None
    return ImageCamera(K=frame.K, width=frame.width, height=frame.height, source=ann,
                       depth_path=frame.depth_path, depth_scale_m=frame.depth_scale_m)


def _from_hope(image: Path) -> ImageCamera | None:
    ann = annotation_file(image, "hope")
    if ann is None:
        return None

    frame = read_hope_json(ann)
    return ImageCamera(K=frame.K, width=frame.width, height=frame.height, source=ann,
                       depth_path=frame.depth_path, depth_scale_m=frame.depth_scale_m)


def _from_bop(image: Path) -> ImageCamera | None:
    cam_file = annotation_file(image, "bop")
    if cam_file is None:
        return None
    scene = cam_file.parent

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
    finders = {"dope": _from_dope, "hope": _from_hope, "bop": _from_bop}
    for layout in LAYOUTS:
        cam = finders[layout](image)
        if cam is not None:
            return cam
    return None


def camera_search_description(image: str | os.PathLike) -> str:
    """Which sibling files :func:`find_image_camera` looks for (for error messages)."""
    return annotation_search_description(image)
