"""HOPE-Image / HOPE-Video annotations (``NNNN.json`` beside ``NNNN_rgb.jpg``), in metres.

File layout read here::

    {"camera": {"intrinsics": 3x3, "width": W, "height": H,
                "extrinsics": 4x4 (ignored), "depth_scale": mm per unit (optional)},
     "objects": [{"class": "Ketchup", "pose": 4x4 model -> camera, translation in cm}]}

Siblings: ``NNNN_rgb.jpg`` (or ``.png``) and ``NNNN_depth.png`` (uint16). The depth scale is
taken from ``depth_scale_m`` (metres per unit) or ``depth_scale`` (BOP convention,
millimetres per unit) at the top level or under ``camera``; otherwise 0.001 (millimetres).
The files carry no projected cuboid, visibility or box: those stay None.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.errors import InputFileError
from dope_hope.geometry import is_pinhole, nearest_rotation
from dope_hope.io.jsonfields import JsonFields as _Fields
from dope_hope.io.jsonfields import load_json_object as _load_json

#: Largest accepted deviation of the pose's 3x3 block from a rotation (Frobenius norm).
_ROTATION_TOLERANCE = 1e-3
_RGB_SUFFIXES = ("_rgb.jpg", "_rgb.png", "_rgb.jpeg")


def _sibling(path: Path, suffixes: tuple[str, ...]) -> Path | None:
    stem = path.with_suffix("").name
    return next((p for p in (path.with_name(stem + s) for s in suffixes) if p.is_file()), None)


def _depth_scale_m(f: _Fields, data: dict, camera: dict) -> float:
    for where, node in (("", data), ("camera.", camera)):
        if node.get("depth_scale_m") is not None:
            return f.positive_number(node["depth_scale_m"], f"{where}depth_scale_m")
        if node.get("depth_scale") is not None:
            return f.positive_number(node["depth_scale"], f"{where}depth_scale") * 0.001
    return 0.001


def _pose_matrix(f: _Fields, value, field: str) -> tuple[np.ndarray, np.ndarray]:
    T = f.array(value, field, (4, 4), "rows", "columns")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise f.fail(field, f"bottom row must be [0, 0, 0, 1] (translation in the last column), "
                            f"got {T[3].tolist()}")
    R = nearest_rotation(T[:3, :3])
    if np.linalg.norm(R - T[:3, :3]) > _ROTATION_TOLERANCE:
        raise f.fail(field, "the 3x3 block is not a rotation")
    return R, T[:3, 3] * 0.01


def read_hope_json(path: str | os.PathLike) -> FrameAnnotation:
    """Read one HOPE annotation file.

    Returns:
        FrameAnnotation with K (3, 3), width/height, objects (class, R (3, 3), t (3,) metres),
        image/depth sibling paths and depth_scale_m.

    Raises:
        InputFileError: missing file, malformed JSON, missing field or wrong shape, naming
        the file and the field.
    """
    path = Path(path)
    data = _load_json(path)
    f = _Fields(path)
    camera = f.get(data, "camera", "")
    K = f.array(f.get(camera, "intrinsics", "camera"), "camera.intrinsics", (3, 3), "rows", "columns")
    if not is_pinhole(K):
        raise f.fail("camera.intrinsics", "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    size = [None if camera.get(k) is None else f.positive_int(camera[k], f"camera.{k}")
            for k in ("width", "height")]
    objs = data.get("objects") or []
    if not isinstance(objs, list):
        raise f.fail("objects", f"expected a list, got {type(objs).__name__}")
    objects = []
    for i, o in enumerate(objs):
        where = f"objects[{i}]"
        cls = f.get(o, "class", where)
        if not isinstance(cls, str) or not cls:
            raise f.fail(f"{where}.class", f"expected a non-empty string, got {cls!r}")
        R, t = _pose_matrix(f, f.get(o, "pose", where), f"{where}.pose")
        objects.append(ObjectAnnotation(class_name=cls, R=R, t=t))
    return FrameAnnotation(source=path, K=K, width=size[0], height=size[1], objects=objects,
                           image_path=_sibling(path, _RGB_SUFFIXES),
                           depth_path=_sibling(path, ("_depth.png",)),
                           depth_scale_m=_depth_scale_m(f, data, camera))


def list_hope_frames(folder: str | os.PathLike) -> list[Path]:
    """Sorted ``NNNN.json`` paths in ``folder`` that have an ``NNNN_rgb.jpg``/``.png`` beside."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(folder, "HOPE scene folder not found")
    return sorted(p for p in folder.glob("*.json")
                  if p.is_file() and _sibling(p, _RGB_SUFFIXES) is not None)
