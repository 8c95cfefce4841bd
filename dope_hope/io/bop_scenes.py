"""BOP-format datasets as annotated training frames (projected cuboids, visibility).

A BOP dataset folder is a split (``<split>/<scene_id:06d>/``, e.g. ``train_pbr``, a real
``train`` split or BlenderProc's BOP writer output) or one scene folder, each scene with
``scene_camera.json``, ``scene_gt.json``, ``rgb/`` (or ``gray/``) and optionally
``scene_gt_info.json``, ``mask/`` and ``mask_visib/``. The files are read by
:mod:`dope_hope.io.bop` (metres from here on); this module adds what training needs:

- ``projected_cuboid``: the 9 keypoints (``geometry.KEYPOINT_ORDER``) of the model's
  axis-aligned box from ``models_info.json`` (``min_x``, ``size_x``, ... in mm, converted to
  metres), projected with the image's K and pose;
- ``visibility``: ``visib_fract`` of ``scene_gt_info.json``; without it the pixels of
  ``mask_visib/<im_id>_<gt_id>.png`` over those of ``mask/<im_id>_<gt_id>.png``, or the
  ``mask_visib`` pixel count alone (``visible_pixels``) when there is no full mask; a scene
  with neither ``visib_fract`` nor ``mask_visib/`` is refused (naming the folder), as is a mask
  of another size than its image;
- ``class_name``: see :func:`bop_class_name`.

``models_info.json`` is looked for in ``<dataset>/models/`` beside the split (the BOP layout
``<dataset>/{models, train_pbr, ...}``), then ``models/`` inside the folder, or given.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from dope_hope.annotation import FrameAnnotation
from dope_hope.errors import InputFileError
from dope_hope.geometry import KEYPOINT_ORDER, cuboid_keypoints, project_points
from dope_hope.io.bop import iter_bop_split, list_bop_scenes, parse_symmetries, read_models_info
from dope_hope.io.images import read_image_raw
from dope_hope.io.jsonfields import JsonFields, load_json_object
from dope_hope.io.models_dir import bop_obj_id

#: Where models_info.json is looked for, relative to a split folder.
MODELS_INFO_PLACES = ("../models/models_info.json", "models/models_info.json",
                      "../models_eval/models_info.json", "../../models/models_info.json")


def is_bop_scene(folder: str | os.PathLike) -> bool:
    """True for one BOP scene folder (``scene_camera.json`` and ``scene_gt.json``)."""
    folder = Path(folder)
    return (folder / "scene_camera.json").is_file() and (folder / "scene_gt.json").is_file()


def is_bop_dataset(folder: str | os.PathLike) -> bool:
    """True for a BOP split (6-digit scene folders with their files) or one scene folder."""
    folder = Path(folder)
    if not folder.is_dir():
        return False
    if is_bop_scene(folder):
        return True
    return any(is_bop_scene(folder / f"{s:06d}") for s in list_bop_scenes(folder))


def find_models_info(folder: str | os.PathLike) -> Path | None:
    """The ``models_info.json`` that belongs to a BOP split or scene folder, or None (looked
    for in :data:`MODELS_INFO_PLACES`, from the split: a scene folder's parent)."""
    folder = Path(folder)
    split = folder.parent if is_bop_scene(folder) else folder
    for rel in MODELS_INFO_PLACES:
        path = (split / rel).resolve()
        if path.is_file():
            return path
    return None


def model_boxes(models_info: str | os.PathLike) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{obj_id: (size (3,), centre (3,))} metres: the axis-aligned box of each model from a BOP
    ``models_info.json`` (``min_*`` and ``size_*`` in mm).

    Raises:
        InputFileError: an entry without ``min_x/y/z`` and ``size_x/y/z``.
    """
    out = {}
    for obj_id, info in read_models_info(models_info, units="mm").items():
        if "size_m" not in info or "min_m" not in info:
            raise InputFileError(models_info, f"obj_id {obj_id}: needs min_x/y/z and size_x/y/z (the model's box)")
        out[obj_id] = (info["size_m"], info["min_m"] + info["size_m"] / 2.0)
    return out


def bop_class_name(obj_id: int, class_names: Sequence[str] = ()) -> str:
    """The class of BOP ``obj_id`` in a run of ``class_names``: the run's object whose BOP id it
    is (a class named ``obj_NNNNNN``, or a HOPE object named as in the catalog, which has
    the HOPE dataset's ids), else ``obj_NNNNNN``."""
    for name in class_names:
        if bop_obj_id(name) == obj_id:
            return name
    return f"obj_{obj_id:06d}"


def recorded_box_size(scene_gt: str | os.PathLike, class_name: str) -> np.ndarray | None:
    """(3,) box size in metres of ``class_name``'s model (its BOP id: ``obj_NNNNNN`` or the HOPE
    catalog's) in the ``models_info.json`` of the BOP dataset holding ``scene_gt``, or None."""
    obj_id = bop_obj_id(class_name)
    info = find_models_info(Path(scene_gt).parent)
    if obj_id is None or info is None:
        return None
    box = model_boxes(info).get(obj_id)
    return None if box is None else box[0]


def recorded_symmetry_fields(scene_gt: str | os.PathLike, class_name: str) -> dict | None:
    """The BOP symmetry fields (``symmetries_discrete`` / ``symmetries_continuous``, as stored:
    mm) of ``class_name``'s model in the ``models_info.json`` of the BOP dataset holding
    ``scene_gt``, or None when it declares none."""
    obj_id = bop_obj_id(class_name)
    path = find_models_info(Path(scene_gt).parent)
    if obj_id is None or path is None:
        return None
    entry = load_json_object(path, "models info file").get(str(obj_id))
    if not isinstance(entry, dict):
        return None
    parse_symmetries(JsonFields(path), entry, str(obj_id))  # checked by the one reader
    fields = {k: entry[k] for k in ("symmetries_discrete", "symmetries_continuous") if entry.get(k)}
    return fields or None


def _mask_pixels(path: Path, size: tuple[int, int] | None) -> int | None:
    """Non-zero pixels of a mask file (None: no file); InputFileError naming the file when
    it is not ``size`` (W, H), the image's."""
    if not path.is_file():
        return None
    mask = read_image_raw(path)
    if size is not None and (mask.shape[1], mask.shape[0]) != tuple(size):
        raise InputFileError(path, f"mask is {mask.shape[1]}x{mask.shape[0]} pixels, its image "
                                   f"{size[0]}x{size[1]}")
    return int(np.count_nonzero(mask))


def _visibility_from_masks(scene: Path, im_id: int, gt_id: int,
                           size: tuple[int, int] | None = None) -> tuple[float | None, int | None]:
    """(fraction, None) from mask_visib / mask; (None, visible pixels) with mask_visib alone.

    Raises:
        InputFileError: no ``mask_visib/`` folder (naming it: without it and without
        ``scene_gt_info.json`` nothing says how much of an instance is visible); a mask file
        missing from it, or not of the image's size (W, H).
    """
    name = f"{im_id:06d}_{gt_id:06d}.png"
    folder = scene / "mask_visib"
    if not folder.is_dir():
        raise InputFileError(folder, "missing: the visibility of each instance comes from mask_visib/ "
                                     "(or scene_gt_info.json's visib_fract), and this scene has neither")
    visib = _mask_pixels(folder / name, size)
    if visib is None:
        raise InputFileError(folder / name, "mask file not found (the visible mask of instance "
                                            f"{gt_id} of image {im_id})")
    full = _mask_pixels(scene / "mask" / name, size)
    if full is not None and full > 0:
        return min(1.0, visib / full), None
    return None, visib


def iter_bop_frames(folder: str | os.PathLike, class_name: Callable[[int], str] = bop_class_name,
                    models_info: str | os.PathLike | None = None,
                    image_folder: str = "rgb") -> Iterator[FrameAnnotation]:
    """Every image of a BOP split or scene folder with its objects' projected cuboids and
    visibility (module docstring), scene by scene, images in id order.

    Args:
        folder: a split (``train_pbr``) or one scene folder.
        class_name: obj_id -> class (default :func:`bop_class_name` with no run objects).
        models_info: the models' ``models_info.json`` (default: :func:`find_models_info`).
        image_folder: "rgb" (or "gray").

    Raises:
        InputFileError: not a BOP folder; no models_info.json; an object it does not list.
    """
    folder = Path(folder)
    if not is_bop_dataset(folder):
        raise InputFileError(folder, "not a BOP dataset (no <scene>/scene_camera.json + scene_gt.json)")
    info_path = Path(models_info) if models_info is not None else find_models_info(folder)
    if info_path is None:
        raise InputFileError(folder, "no models_info.json (looked in " + ", ".join(MODELS_INFO_PLACES)
                             + "): the models' boxes give the cuboid keypoints")
    if is_bop_scene(folder) and not folder.name.isdigit():
        raise InputFileError(folder, "a BOP scene folder is named by its scene id (e.g. 000000)")
    boxes = model_boxes(info_path)
    keypoints = {obj_id: cuboid_keypoints(size, center) for obj_id, (size, center) in boxes.items()}
    split, scenes = (folder.parent, [int(folder.name)]) if is_bop_scene(folder) else (folder, None)
    # the split reader names each object by its obj_id here; the class follows below
    for item in iter_bop_split(split, scenes, class_name=str, image_folder=image_folder):
        frame, scene = item.frame, split / f"{item.scene_id:06d}"
        frame.scene_id, frame.im_id = item.scene_id, item.im_id
        for gt_id, obj in enumerate(frame.objects):
            obj_id = int(obj.class_name)
            if obj_id not in keypoints:
                raise InputFileError(info_path, f"no entry for obj_id {obj_id} (scene {item.scene_id}, "
                                                f"image {item.im_id})")
            obj.class_name = class_name(obj_id)
            obj.projected_cuboid = project_points(keypoints[obj_id], frame.K, obj.R, obj.t)
            obj.keypoint_order = KEYPOINT_ORDER
            if obj.visibility is None:
                size = None if frame.width is None or frame.height is None else (frame.width, frame.height)
                obj.visibility, obj.visible_pixels = _visibility_from_masks(scene, item.im_id, gt_id, size)
        yield frame
