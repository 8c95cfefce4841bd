"""BOP format (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md).

Readers for the scene-wise BOP files, everything converted to metres at this boundary
(BOP stores poses, model coordinates and ``depth * depth_scale`` in millimetres):

- ``scene_camera.json``  -> :func:`read_scene_camera`  {im_id: (K (3, 3), depth_scale_m)}
- ``scene_gt.json``      -> :func:`read_scene_gt`      {im_id: [(obj_id, R (3, 3), t (3,) m)]}
  (:func:`read_scene_gt_stored`: the numbers as stored, millimetres, for BOP19 scoring)
- ``scene_gt_info.json`` -> :func:`read_scene_gt_info` {im_id: [GtInfo]}
- ``models_info.json`` / per-model ``model_info.json`` -> :func:`read_models_info` (the
  symmetry fields as stored, in metres; what they mean as transforms: :mod:`dope_hope.symmetry`)
- ``test_targets_bop19.json`` -> :func:`read_test_targets`
- a split folder (``<split>/<scene_id:06d>/{rgb,depth}/<im_id:06d>.png|jpg``) as
  FrameAnnotation objects -> :func:`iter_bop_split` (:func:`find_split_folder` finds it;
  :func:`targeted_frames`: only the images a ``test_targets_bop19.json`` names)
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import numpy as np

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.catalog import HOPE_OBJECTS
from dope_hope.errors import InputFileError
from dope_hope.geometry import UNIT_SCALE, nearest_rotation
from dope_hope.io.images import image_size
from dope_hope.io.jsonfields import JsonFields, load_json, load_json_object

MM = 0.001  # metres per millimetre
#: Largest accepted deviation of a stored 3x3 rotation from orthonormal (Frobenius norm);
#: BOP files store rounded numbers (e.g. 0.866 for cos 30°).
_ROTATION_TOLERANCE = 1e-2
_Item = TypeVar("_Item")


# --------------------------------------------------------------------------- helpers
def _keyed_by_int(f: JsonFields, data: dict, what: str) -> list[tuple[int, Any]]:
    """(int key, value) pairs sorted by key, for files keyed by image / object id strings."""
    out = []
    for key, value in data.items():
        try:
            out.append((int(key), value))
        except ValueError:
            raise f.fail(str(key), f"expected an integer {what} as key") from None
    return sorted(out, key=lambda kv: kv[0])


def _stored_rotation(f: JsonFields, value: Any, field: str) -> np.ndarray:
    """(3, 3) as stored, checked to be within ``_ROTATION_TOLERANCE`` of a rotation."""
    M = f.array(value, field, (9,)).reshape(3, 3)
    if np.linalg.norm(nearest_rotation(M) - M) > _ROTATION_TOLERANCE:
        raise f.fail(field, "not a rotation matrix")
    return M


def _whole_number(f: JsonFields, value: Any, field: str) -> int:
    if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
            or value != int(value)):
        raise f.fail(field, f"expected an integer, got {value!r}")
    return int(value)


def _list(f: JsonFields, value: Any, field: str) -> list:
    if not isinstance(value, list):
        raise f.fail(field, f"expected a list, got {type(value).__name__}")
    return value


def _per_image_lists(path: str | os.PathLike, what: str,
                     parse: Callable[[JsonFields, Any, str], _Item]) -> dict[int, list[_Item]]:
    """A scene file keyed by image id whose values are lists (``scene_gt``, ``scene_gt_info``):
    {im_id: [parse(fields, item, "<im_id>[<j>]")]}, ids sorted, list order kept."""
    f = JsonFields(path)
    return {im_id: [parse(f, item, f"{im_id}[{j}]") for j, item in enumerate(_list(f, items, str(im_id)))]
            for im_id, items in _keyed_by_int(f, load_json_object(path, what), "image id")}


# --------------------------------------------------------------------------- scene files
def read_scene_camera(path: str | os.PathLike) -> dict[int, tuple[np.ndarray, float]]:
    """``scene_camera.json`` -> {im_id: (K (3, 3), depth_scale_m)}.

    ``depth_scale_m`` is metres per depth-image unit (BOP's ``depth_scale`` is millimetres per
    unit; 1.0 when absent, i.e. 0.001 m).
    """
    f = JsonFields(path)
    out = {}
    for im_id, cam in _keyed_by_int(f, load_json_object(path, "scene_camera file"), "image id"):
        K = f.array(f.get(cam, "cam_K", str(im_id)), f"{im_id}.cam_K", (9,)).reshape(3, 3)
        scale = f.number(cam.get("depth_scale", 1.0), f"{im_id}.depth_scale")
        if scale <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise f.fail(str(im_id), "focal lengths and depth_scale must be positive")
        out[im_id] = (K, scale * MM)
    return out


def read_scene_gt_stored(path: str | os.PathLike) -> dict[int, list[tuple[int, np.ndarray, np.ndarray]]]:
    """``scene_gt.json`` as stored -> {im_id: [(obj_id, R (3, 3), t (3,) millimetres)]}, list
    order kept (the index is the ``gt_id`` of the mask files). R is checked to be a rotation
    (within ``_ROTATION_TOLERANCE``) but not re-orthonormalized: the BOP toolkit scores the
    stored numbers."""
    def parse(f: JsonFields, gt: Any, where: str) -> tuple[int, np.ndarray, np.ndarray]:
        R = _stored_rotation(f, f.get(gt, "cam_R_m2c", where), f"{where}.cam_R_m2c")
        t = f.array(f.get(gt, "cam_t_m2c", where), f"{where}.cam_t_m2c", (3,))
        return _whole_number(f, f.get(gt, "obj_id", where), f"{where}.obj_id"), R, t

    return _per_image_lists(path, "scene_gt file", parse)


def read_scene_gt(path: str | os.PathLike) -> dict[int, list[tuple[int, np.ndarray, np.ndarray]]]:
    """``scene_gt.json`` -> {im_id: [(obj_id, R (3, 3) nearest rotation, t (3,) metres)]}, list
    order kept (see :func:`read_scene_gt_stored`)."""
    return {im_id: [(obj_id, nearest_rotation(R), t * MM) for obj_id, R, t in gts]
            for im_id, gts in read_scene_gt_stored(path).items()}


@dataclass(frozen=True)
class GtInfo:
    """One entry of ``scene_gt_info.json``.

    Attributes:
        visib_fract: visible fraction of the object's silhouette, [0, 1].
        px_count_all, px_count_valid, px_count_visib: pixel counts (BOP definitions).
        bbox_obj, bbox_visib: (4,) boxes as stored, (x, y, w, h) pixels with w = x_max - x_min.
    """

    visib_fract: float
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    bbox_obj: np.ndarray
    bbox_visib: np.ndarray

    @property
    def bbox_visib_xyxy(self) -> np.ndarray:
        """(4,) (x_min, y_min, x_max, y_max) of the visible part, pixels."""
        x, y, w, h = self.bbox_visib
        return np.array([x, y, x + w, y + h], dtype=np.float64)


def read_scene_gt_info(path: str | os.PathLike) -> dict[int, list[GtInfo]]:
    """``scene_gt_info.json`` -> {im_id: [GtInfo]} in ``scene_gt.json`` order."""
    def parse(f: JsonFields, info: Any, where: str) -> GtInfo:
        vf = f.number(f.get(info, "visib_fract", where), f"{where}.visib_fract")
        if not 0.0 <= vf <= 1.0:
            raise f.fail(f"{where}.visib_fract", f"expected a fraction in [0, 1], got {vf}")
        counts = [_whole_number(f, info.get(k, 0), f"{where}.{k}")
                  for k in ("px_count_all", "px_count_valid", "px_count_visib")]
        boxes = [f.array(info.get(k, [0, 0, 0, 0]), f"{where}.{k}", (4,))
                 for k in ("bbox_obj", "bbox_visib")]
        return GtInfo(vf, *counts, *boxes)

    return _per_image_lists(path, "scene_gt_info file", parse)


# --------------------------------------------------------------------------- models
def parse_symmetries(f: JsonFields, info: Any, where: str = "") -> tuple[
        list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """The BOP symmetry fields of one model's info entry, numbers as stored (the file's unit):
    the one reader of ``symmetries_discrete`` / ``symmetries_continuous``.

    Returns:
        (discrete: (4, 4) transforms as stored, each checked (bottom row [0, 0, 0, 1], 3x3
        block within ``_ROTATION_TOLERANCE`` of a rotation); continuous: (axis (3,) as stored,
        non-zero; offset (3,), default 0) pairs).
    """
    if not isinstance(info, dict):
        raise f.fail(where or "top level", f"expected an object, got {type(info).__name__}")
    pre = f"{where}." if where else ""
    discrete = []
    for k, m in enumerate(_list(f, info.get("symmetries_discrete", []), f"{pre}symmetries_discrete")):
        field = f"{pre}symmetries_discrete[{k}]"
        T = f.array(m, field, (16,)).reshape(4, 4)
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
            raise f.fail(field, "bottom row must be [0, 0, 0, 1] (row-major 4x4)")
        if np.linalg.norm(nearest_rotation(T[:3, :3]) - T[:3, :3]) > _ROTATION_TOLERANCE:
            raise f.fail(field, "the 3x3 block is not a rotation")
        discrete.append(T)
    continuous = []
    for k, c in enumerate(_list(f, info.get("symmetries_continuous", []),
                                f"{pre}symmetries_continuous")):
        field = f"{pre}symmetries_continuous[{k}]"
        axis = f.array(f.get(c, "axis", field), f"{field}.axis", (3,))
        if np.linalg.norm(axis) < 1e-9:
            raise f.fail(f"{field}.axis", "zero axis")
        continuous.append((axis, f.array(c.get("offset", [0, 0, 0]), f"{field}.offset", (3,))))
    return discrete, continuous


def parse_model_info(f: JsonFields, info: Any, where: str, units: str = "mm") -> dict:
    """One model's info entry -> {diameter_m (float | None), symmetries_discrete (S, 4, 4)
    metres (R the nearest rotation), symmetries_continuous [(axis (3,) unit, offset (3,) m)],
    size_m / min_m (3,) when given, align_axes as stored}."""
    discrete, continuous = parse_symmetries(f, info, where)
    scale = UNIT_SCALE[units]
    pre = f"{where}." if where else ""
    out: dict[str, Any] = {"diameter_m": None}
    if info.get("diameter") is not None:
        out["diameter_m"] = f.positive_number(info["diameter"], f"{pre}diameter") * scale
    if all(info.get(f"size_{a}") is not None for a in "xyz"):
        out["size_m"] = np.array([f.number(info[f"size_{a}"], f"{pre}size_{a}") for a in "xyz"]) * scale
    if all(info.get(f"min_{a}") is not None for a in "xyz"):
        out["min_m"] = np.array([f.number(info[f"min_{a}"], f"{pre}min_{a}") for a in "xyz"]) * scale
    symmetries = []
    for T in discrete:
        S = np.eye(4)
        S[:3, :3] = nearest_rotation(T[:3, :3])
        S[:3, 3] = T[:3, 3] * scale
        symmetries.append(S)
    out["symmetries_discrete"] = np.array(symmetries).reshape(-1, 4, 4)
    out["symmetries_continuous"] = [(axis / np.linalg.norm(axis), offset * scale) for axis, offset in continuous]
    if info.get("align_axes") is not None:
        out["align_axes"] = info["align_axes"]
    return out


def read_models_info(path: str | os.PathLike, units: str = "mm") -> dict[int, dict]:
    """``models_info.json`` ({obj_id: info}) or a single model's ``model_info.json``.

    Args:
        path: the file.
        units: unit of lengths in the file (BOP: "mm"; the per-model infos beside the DOPE
            sample meshes use the mesh's unit, e.g. "m").

    Returns:
        {obj_id: info} (see :func:`parse_model_info`); a single-model file (no integer keys)
        comes back as ``{0: info}`` — 0 is never a BOP obj_id.
    """
    if units not in UNIT_SCALE:
        raise InputFileError(path, f"unknown unit {units!r}; use one of {sorted(UNIT_SCALE)}")
    f = JsonFields(path)
    data = load_json_object(path, "models info file")
    if data and all(str(k).isdigit() for k in data):
        return {obj_id: parse_model_info(f, info, str(obj_id), units)
                for obj_id, info in _keyed_by_int(f, data, "object id")}
    return {0: parse_model_info(f, data, "", units)}


def read_test_targets(path: str | os.PathLike) -> list[tuple[int, int, int, int]]:
    """``test_targets_bop19.json`` -> [(scene_id, im_id, obj_id, inst_count)] in file order."""
    f = JsonFields(path)
    data = load_json(path, "test targets file")
    out = []
    for j, item in enumerate(_list(f, data, "top level")):
        where = f"[{j}]"
        out.append(tuple(_whole_number(f, f.get(item, k, where), f"{where}.{k}")
                         for k in ("scene_id", "im_id", "obj_id", "inst_count")))
    return out  # type: ignore[return-value]


# --------------------------------------------------------------------------- splits
class BopFrame(NamedTuple):
    """One image of a BOP split: its ids and its annotation (``frame``, alias ``annotation``)."""

    scene_id: int
    im_id: int
    frame: FrameAnnotation

    @property
    def annotation(self) -> FrameAnnotation:
        return self.frame

    @property
    def image_path(self) -> Path | None:
        return self.frame.image_path


def _default_class_name(obj_id: int) -> str:
    if 1 <= obj_id <= len(HOPE_OBJECTS):
        return HOPE_OBJECTS[obj_id - 1].name
    return f"obj_{obj_id:06d}"


def _image_file(folder: Path, im_id: int) -> Path | None:
    for suffix in (".png", ".jpg", ".jpeg", ".tif"):
        p = folder / f"{im_id:06d}{suffix}"
        if p.is_file():
            return p
    return None


def list_bop_scenes(split_dir: str | os.PathLike) -> list[int]:
    """Sorted scene ids (6-digit folders holding a ``scene_camera.json``) of a split."""
    split_dir = Path(split_dir)
    if not split_dir.is_dir():
        raise InputFileError(split_dir, "BOP split folder not found")
    return sorted(int(p.name) for p in split_dir.iterdir()
                  if p.is_dir() and p.name.isdigit() and (p / "scene_camera.json").is_file())


def iter_bop_split(split_dir: str | os.PathLike, scene_ids: list[int] | None = None,
                   class_name: Callable[[int], str] = _default_class_name,
                   image_folder: str = "rgb") -> Iterator[BopFrame]:
    """Every image of a BOP split as a FrameAnnotation (metres), scene by scene.

    Objects come from ``scene_gt.json`` (none when the split has no ground truth), with
    visibility and ``bbox_xyxy`` (visible part) from ``scene_gt_info.json`` when present,
    ``instance_id`` = the gt index (the ``NNNNNN_<gt_id>.png`` mask numbering) and
    ``stored_pose`` = (R, t mm) as stored. Class names
    come from ``class_name(obj_id)`` (default: the HOPE catalog, obj_id 1..28).

    Args:
        split_dir: e.g. ``hope/val``.
        scene_ids: scenes to read (default: all, sorted).
        image_folder: "rgb" (or "gray" for grayscale datasets).
    """
    split_dir = Path(split_dir)
    for scene_id in list_bop_scenes(split_dir) if scene_ids is None else scene_ids:
        scene = split_dir / f"{scene_id:06d}"
        cams = read_scene_camera(scene / "scene_camera.json")
        gt_path, info_path = scene / "scene_gt.json", scene / "scene_gt_info.json"
        gts = read_scene_gt_stored(gt_path) if gt_path.is_file() else {}
        infos = read_scene_gt_info(info_path) if info_path.is_file() else {}
        for im_id, (K, depth_scale_m) in cams.items():
            objects = []
            im_infos = infos.get(im_id, [])
            for gt_id, (obj_id, R, t_mm) in enumerate(gts.get(im_id, [])):
                info = im_infos[gt_id] if gt_id < len(im_infos) else None
                objects.append(ObjectAnnotation(
                    class_name=class_name(obj_id), R=nearest_rotation(R), t=t_mm * MM,
                    instance_id=gt_id, visibility=None if info is None else info.visib_fract,
                    bbox_xyxy=None if info is None else info.bbox_visib_xyxy,
                    stored_pose=(R, t_mm)))
            image = _image_file(scene / image_folder, im_id)
            width, height = image_size(image) if image is not None else (None, None)
            frame = FrameAnnotation(
                source=gt_path if gt_path.is_file() else scene / "scene_camera.json",
                K=K, width=width, height=height, objects=objects, image_path=image,
                depth_path=_image_file(scene / "depth", im_id), depth_scale_m=depth_scale_m)
            yield BopFrame(scene_id, im_id, frame)


def find_split_folder(bop_root: str | os.PathLike, dataset: str, split: str) -> Path:
    """BOP_ROOT/DATASET/SPLIT, or BOP_ROOT/SPLIT when BOP_ROOT is the dataset folder."""
    bop_root = Path(bop_root)
    for candidate in (bop_root / dataset / split, bop_root / split):
        if candidate.is_dir():
            return candidate
    raise InputFileError(bop_root / dataset / split, "BOP split folder not found")


#: The BOP19 test targets file in a dataset folder (beside its split folders).
TEST_TARGETS_NAME = "test_targets_bop19.json"


def targeted_frames(split_dir: str | os.PathLike, targets_path: str | os.PathLike | None
                    ) -> tuple[list[BopFrame], dict[tuple[int, int], list[int]] | None]:
    """The frames of a split a BOP test targets file names, and its targets.

    Args:
        split_dir: the split folder.
        targets_path: a ``test_targets_bop19.json``; None: every frame of the split.

    Returns:
        (frames in scene / image order; {(scene_id, im_id): [obj_id, ...]} in file order, or
        None without a targets file).

    Raises:
        InputFileError: a target scene or image the split lacks (naming the targets file).
    """
    split_dir = Path(split_dir)
    if targets_path is None:
        return list(iter_bop_split(split_dir)), None
    wanted: dict[tuple[int, int], list[int]] = {}
    for scene_id, im_id, obj_id, _count in read_test_targets(targets_path):
        wanted.setdefault((scene_id, im_id), []).append(obj_id)
    scene_ids = [s for s in list_bop_scenes(split_dir) if any(k[0] == s for k in wanted)]
    missing = sorted({s for s, _ in wanted} - set(scene_ids))
    if missing:
        raise InputFileError(targets_path, f"targets name scene(s) {missing[:5]} that {split_dir} lacks")
    frames = [bf for bf in iter_bop_split(split_dir, scene_ids) if (bf.scene_id, bf.im_id) in wanted]
    if len(frames) < len(wanted):
        found = {(bf.scene_id, bf.im_id) for bf in frames}
        s, i = sorted(set(wanted) - found)[0]
        raise InputFileError(targets_path, f"target image {i} of scene {s} is not in {split_dir}")
    return frames, wanted
