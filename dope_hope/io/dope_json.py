"""DOPE-format annotation files (``NNNNNN.json`` beside ``NNNNNN.png``), read into metres.

Four variants are read (project, NDDS/FAT, BlenderProc, NViSII: their objects in
:mod:`dope_hope.io.dope_objects`); :func:`write_dope_json` writes only the first.

**project** (``"format": "dope-hope"``)::

    {"format": "dope-hope", "units": "cm", "keypoint_order": "dope-current",
     "depth_scale_m": 0.001,
     "camera_data": {"intrinsics": {"fx", "fy", "cx", "cy"}, "width", "height"},
     "objects": [{"class", "location" (3, cm), "quaternion_xyzw" (4,),
                  "projected_cuboid" (9 x [u, v] px), "visibility" (fraction),
                  "visible_pixels" (count; only when no fraction is known),
                  "bounding_box": {"top_left": [u, v], "bottom_right": [u, v]},  (pixels, x first)
                  "instance_id" (id in the .seg.png), "keypoint_order" (only if != file's)}]}

``location`` / ``quaternion_xyzw`` are the mesh-frame pose (``x_c = R x + t``); the box is
(x_min, y_min) / (x_max, y_max), i.e. ``bbox_xyxy``.

Cameras: the project, NViSII and BlenderProc variants carry ``camera_data.intrinsics`` (a
BlenderProc file from before mid-2024 wrote zeros as ``cx``, ``cy``: such intrinsics are not
used); NDDS/FAT files usually leave ``camera_data`` empty and a sibling
``_camera_settings.json`` gives K; the cuboid sizes of an NDDS folder's classes are in its
``_object_settings.json`` (:func:`read_ndds_object_settings`).

Sibling files: ``NNNNNN.png``/``.jpg``, ``NNNNNN.depth.png`` (uint16 mm, z-depth) or
``.depth.exr`` (NViSII: metres along the ray, see :func:`read_frame_depth_m`),
``NNNNNN.seg.png``/``.seg.exr`` (instance ids = ``instance_id``).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.annotation import FrameAnnotation
from dope_hope.errors import InputFileError
from dope_hope.geometry import (
    KEYPOINT_ORDER,
    NUM_KEYPOINTS,
    intrinsics_matrix,
    matrix_to_quaternion_xyzw,
)
from dope_hope.io.atomic import atomic_write_text
from dope_hope.io.dope_objects import FORMAT_NAME, detect_variant, read_objects
from dope_hope.io.images import IMAGE_SUFFIXES, image_size, read_depth_m
from dope_hope.io.jsonfields import JsonFields as _Fields
from dope_hope.io.jsonfields import load_json_object as _load_json

NDDS_OBJECT_SETTINGS = "_object_settings.json"
_RESERVED_KEYS = {"format", "units", "keypoint_order", "camera_data", "objects", "depth_scale_m"}


# --------------------------------------------------------------------------- siblings
def _frame_stem(path: Path) -> Path:
    return path.with_suffix("")


def _first_existing(candidates: list[Path]) -> Path | None:
    return next((c for c in candidates if c.is_file()), None)


def find_image(json_path: str | os.PathLike) -> Path | None:
    """``NNNNNN.png`` / ``.jpg`` beside ``NNNNNN.json``, or None."""
    stem = _frame_stem(Path(json_path))
    return _first_existing([stem.with_name(stem.name + s) for s in IMAGE_SUFFIXES[:3]])


def _siblings(path: Path) -> tuple[Path | None, Path | None, Path | None]:
    stem = _frame_stem(path)
    depth = _first_existing([stem.with_name(stem.name + s) for s in (".depth.png", ".depth.exr")])
    seg = _first_existing([stem.with_name(stem.name + s) for s in (".seg.png", ".seg.exr")])
    return find_image(path), depth, seg


def _image_size(image: Path | None) -> tuple[int | None, int | None]:
    """(width, height) from the image header, or (None, None) when absent or unreadable (the
    image reader reports that when the image is used)."""
    if image is None:
        return None, None
    try:
        return image_size(image)
    except InputFileError:
        return None, None


# --------------------------------------------------------------------------- camera
def _read_intrinsics(f: _Fields, camera: Any) -> tuple[np.ndarray | None, int | None, int | None]:
    if camera is None or camera == {}:
        return None, None, None
    if not isinstance(camera, dict):
        raise f.fail("camera_data", f"expected an object, got {type(camera).__name__}")
    K = None
    if camera.get("intrinsics") is not None:
        intr = camera["intrinsics"]
        vals = [f.number(f.get(intr, k, "camera_data.intrinsics"), f"camera_data.intrinsics.{k}")
                for k in ("fx", "fy", "cx", "cy")]
        if vals[0] <= 0 or vals[1] <= 0:
            raise f.fail("camera_data.intrinsics", f"focal lengths must be positive, got {vals[:2]}")
        K = intrinsics_matrix(*vals)
    w, h = (None if camera.get(k) is None else f.positive_int(camera[k], f"camera_data.{k}")
            for k in ("width", "height"))
    return K, w, h


def _read_camera_settings(folder: Path) -> tuple[np.ndarray | None, int | None, int | None]:
    """NDDS/FAT ``_camera_settings.json`` in the folder (first camera), if any."""
    path = folder / "_camera_settings.json"
    if not path.is_file():
        return None, None, None
    f = _Fields(path)
    cams = f.get(_load_json(path), "camera_settings", "")
    if not isinstance(cams, list) or not cams:
        raise f.fail("camera_settings", "expected a non-empty list")
    intr = f.get(cams[0], "intrinsic_settings", "camera_settings[0]")
    vals = [f.number(f.get(intr, k, "camera_settings[0].intrinsic_settings"),
                     f"camera_settings[0].intrinsic_settings.{k}") for k in ("fx", "fy", "cx", "cy")]
    size = cams[0].get("captured_image_size")
    if size is None:
        return intrinsics_matrix(*vals), None, None
    where = "camera_settings[0].captured_image_size"
    if not isinstance(size, dict):  # NDDS writes {"width": W, "height": H}
        raise f.fail(where, f'expected an object {{"width": W, "height": H}}, got {type(size).__name__}')
    w, h = (None if size.get(k) is None else f.positive_int(size[k], f"{where}.{k}") for k in ("width", "height"))
    return intrinsics_matrix(*vals), w, h



# --------------------------------------------------------------------------- public API
def read_dope_json(path: str | os.PathLike) -> FrameAnnotation:
    """Read one DOPE-format annotation (project, NDDS/FAT, NViSII or BlenderProc variant).

    Returns:
        FrameAnnotation in metres; R, t the mesh-frame (NViSII: object-frame) pose;
        ``projected_cuboid`` (9, 2) pixels as in the file, its order in ``keypoint_order``;
        sibling image/depth/seg paths when they exist.

    Raises:
        InputFileError: missing file, malformed JSON, missing field or wrong shape; the
        message names the file and the field.
    """
    path = Path(path)
    data = _load_json(path)
    f = _Fields(path)
    variant = detect_variant(data)
    K, width, height = _read_intrinsics(f, data.get("camera_data"))
    if K is None and variant == "ndds":
        K, width, height = _read_camera_settings(path.parent)
    if variant == "blenderproc" and K is not None and K[0, 2] == 0.0 and K[1, 2] == 0.0:
        K = None  # an older generator wrote K[2][0], K[2][1] as cx, cy
    objects = read_objects(f, data, variant, K)
    image, depth, seg = _siblings(path)
    if width is None or height is None:
        width, height = _image_size(image)
    depth_scale = 0.001
    if depth is not None and depth.suffix.lower() == ".exr":
        depth_scale = 1.0
    if data.get("depth_scale_m") is not None:
        depth_scale = f.positive_number(data["depth_scale_m"], "depth_scale_m")
    return FrameAnnotation(source=path, K=K, width=width, height=height, objects=objects,
                           image_path=image, depth_path=depth, seg_path=seg,
                           depth_scale_m=depth_scale)


def read_frame_depth_m(frame: FrameAnnotation) -> np.ndarray:
    """The frame's depth image as (H, W) float32 z-depth in metres (0 = no measurement).

    ``.depth.png``: uint16 times ``frame.depth_scale_m``. ``.depth.exr`` (NViSII): the
    renderer stores the distance along each pixel's ray, converted here to z with K.
    """
    if frame.depth_path is None:
        raise InputFileError(frame.source, "no depth image beside the annotation")
    depth = read_depth_m(frame.depth_path, frame.depth_scale_m)
    if frame.depth_path.suffix.lower() != ".exr":
        return depth
    if frame.K is None:
        raise InputFileError(frame.source, "camera_data.intrinsics: needed to turn the EXR "
                                           "ray distances into z-depth")
    h, w = depth.shape
    u = (np.arange(w) - frame.K[0, 2]) / frame.K[0, 0]
    v = (np.arange(h) - frame.K[1, 2]) / frame.K[1, 1]
    ray = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2).astype(np.float32)
    return depth / ray


def frame_to_dict(frame: FrameAnnotation, extra: dict | None = None) -> dict:
    """The project-format JSON document of a frame (centimetres)."""
    orders = {o.keypoint_order for o in frame.objects}
    file_order = orders.pop() if len(orders) == 1 else KEYPOINT_ORDER
    camera: dict[str, Any] = {}
    if frame.K is not None:
        K = np.asarray(frame.K, dtype=np.float64)
        camera["intrinsics"] = {"fx": float(K[0, 0]), "fy": float(K[1, 1]),
                                "cx": float(K[0, 2]), "cy": float(K[1, 2])}
    if frame.width is not None:
        camera["width"] = int(frame.width)
    if frame.height is not None:
        camera["height"] = int(frame.height)
    objects = []
    for o in frame.objects:
        d: dict[str, Any] = {
            "class": o.class_name,
            "location": [float(v) * 100.0 for v in np.asarray(o.t).reshape(3)],
            "quaternion_xyzw": [float(v) for v in matrix_to_quaternion_xyzw(o.R)],
        }
        if o.projected_cuboid is not None:
            d["projected_cuboid"] = np.asarray(o.projected_cuboid, dtype=np.float64).reshape(
                NUM_KEYPOINTS, 2).tolist()
        if o.visibility is not None:
            d["visibility"] = float(o.visibility)
        elif o.visible_pixels is not None:
            d["visible_pixels"] = int(o.visible_pixels)
        if o.bbox_xyxy is not None:
            b = [float(v) for v in np.asarray(o.bbox_xyxy).reshape(4)]
            d["bounding_box"] = {"top_left": b[:2], "bottom_right": b[2:]}
        if o.instance_id is not None:
            d["instance_id"] = int(o.instance_id)
        if o.keypoint_order != file_order:
            d["keypoint_order"] = o.keypoint_order
        objects.append(d)
    doc: dict[str, Any] = {"format": FORMAT_NAME, "units": "cm", "keypoint_order": file_order,
                           "depth_scale_m": float(frame.depth_scale_m),
                           "camera_data": camera, "objects": objects}
    if extra:
        clash = _RESERVED_KEYS.intersection(extra)
        if clash:
            raise ValueError(f"extra keys {sorted(clash)} would overwrite annotation fields")
        doc.update(extra)
    return doc


def write_dope_json(path: str | os.PathLike, frame: FrameAnnotation,
                    extra: dict | None = None) -> None:
    """Write a frame atomically in the project format (location in cm, as DOPE does).

    Args:
        path: target ``NNNNNN.json``.
        frame: the annotation (metres inside).
        extra: additional top-level keys (e.g. generator settings); JSON-serializable, must
            not reuse the annotation's own keys.
    """
    atomic_write_text(path, json.dumps(frame_to_dict(frame, extra), indent=1) + "\n")


def read_ndds_object_settings(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """NDDS/FAT ``_object_settings.json``: {class: (3,) cuboid size, metres}.

    Each ``exported_objects`` entry's ``cuboid_dimensions`` (cm) are the extents along x, y, z
    of the object frame the folder's annotations are read in (checked on the official cracker
    samples: the box fitted to their projected cuboids is 16.4036 x 21.3437 x 7.18 cm, the
    official ``cuboid_dimensions`` and DOPE config size).
    """
    f = _Fields(path)
    objs = f.get(_load_json(path, "NDDS object settings file"), "exported_objects", "")
    if not isinstance(objs, list):
        raise f.fail("exported_objects", f"expected a list, got {type(objs).__name__}")
    out: dict[str, np.ndarray] = {}
    for i, o in enumerate(objs):
        where = f"exported_objects[{i}]"
        cls = f.get(o, "class", where)
        if not isinstance(cls, str) or not cls:
            raise f.fail(f"{where}.class", f"expected a non-empty string, got {cls!r}")
        size = f.array(f.get(o, "cuboid_dimensions", where), f"{where}.cuboid_dimensions", (3,))
        if np.any(size <= 0):
            raise f.fail(f"{where}.cuboid_dimensions", f"expected 3 positive extents (cm), got {size.tolist()}")
        out[cls] = size * 0.01
    return out


def recorded_cuboid_size(json_path: str | os.PathLike, class_name: str) -> np.ndarray | None:
    """(3,) cuboid size in metres (the annotations' object frame) that a dataset records for a
    class (case-insensitive), or None.

    Sources: the frame's own ``"cuboid": {"class", "size_m", ...}`` (``dope-hope synth``; a list
    of them for frames of several target objects), else
    the folder's NDDS ``_object_settings.json``.

    Raises:
        InputFileError: a malformed ``_object_settings.json``.
    """
    json_path = Path(json_path)
    want = class_name.lower()
    try:
        doc = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        doc = None
    cub = doc.get("cuboid") if isinstance(doc, dict) else None
    for entry in cub if isinstance(cub, list) else [cub]:
        if not isinstance(entry, dict) or str(entry.get("class", "")).lower() != want:
            continue
        try:
            size = np.asarray(entry.get("size_m"), dtype=np.float64).reshape(3)
        except (TypeError, ValueError):
            size = None
        if size is not None and np.all(np.isfinite(size)) and np.all(size > 0):
            return size
    settings = json_path.parent / NDDS_OBJECT_SETTINGS
    if settings.is_file():
        sizes = {k.lower(): v for k, v in read_ndds_object_settings(settings).items()}
        return sizes.get(want)
    return None


def list_dope_frames(folder: str | os.PathLike) -> list[Path]:
    """Sorted ``*.json`` annotation paths in ``folder`` that have an image beside them.

    ``NNNNNN.json`` pairs with ``NNNNNN.png`` / ``.jpg`` / ``.jpeg``; settings files such as
    ``_camera_settings.json`` (no image) are skipped.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(folder, "dataset folder not found")
    return sorted(p for p in folder.glob("*.json") if p.is_file() and find_image(p) is not None)
