"""Meshes the generator renders: the target object and the distractor mesh library.

Meshes come from :func:`dope_hope.io.meshes.load_mesh` (metres, textures kept). This module
adds what the generator needs on top: the cuboid (mesh AABB), the bounding sphere used for
placement, the texture as an array, and the distractor mesh library (an object's mesh in a
models folder is found by :mod:`dope_hope.io.models_dir`).
"""
from __future__ import annotations

import multiprocessing
import os
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh

from dope_hope.errors import InputFileError
from dope_hope.geometry import UNIT_SCALE
from dope_hope.io.meshes import (
    DEFAULT_UNITS,
    PLAUSIBLE_SIZE_M,
    check_finite_vertices,
    check_plausible_size,
    check_solid_box,
    file_vertices,
    likely_unit,
    load_mesh,
    mesh_cuboid,
)
from dope_hope.io.models_dir import mesh_class_name
from dope_hope.synth.scene import ShapeInfo

#: Mesh file suffixes of the distractor library (--distractors).
MESH_SUFFIXES = (".obj", ".ply")


def texture_image(mesh: trimesh.Trimesh, max_px: int | None = None) -> np.ndarray | None:
    """The mesh's base-colour texture as (h, w, 3 or 4) uint8, or None.

    Reads ``SimpleMaterial.image`` (OBJ map_Kd) or ``PBRMaterial.baseColorTexture``; a texture
    whose longer side exceeds ``max_px`` is downscaled (area interpolation).
    """
    visual = mesh.visual
    if getattr(visual, "kind", None) != "texture" or getattr(visual, "uv", None) is None:
        return None
    mat = visual.material
    img = getattr(mat, "image", None)
    if img is None:
        img = getattr(mat, "baseColorTexture", None)
    if img is None:
        return None
    arr = np.asarray(img.convert("RGBA" if "A" in img.mode else "RGB")) if hasattr(img, "convert") \
        else np.asarray(img)
    arr = np.ascontiguousarray(arr.astype(np.uint8))
    if max_px is not None and max(arr.shape[:2]) > max_px:
        f = max_px / max(arr.shape[:2])
        arr = cv2.resize(arr, (max(1, int(arr.shape[1] * f)), max(1, int(arr.shape[0] * f))),
                         interpolation=cv2.INTER_AREA)
    return arr


def vertex_colors(mesh: trimesh.Trimesh) -> np.ndarray | None:
    """(V, 4) uint8 vertex colours when the mesh has them (e.g. a BOP PLY without texture)."""
    if getattr(mesh.visual, "kind", None) == "vertex":
        return np.asarray(mesh.visual.vertex_colors, dtype=np.uint8)
    return None


def bounding_shape(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, ShapeInfo]:
    """Cuboid size (3,), cuboid centre (3,) and the bounding sphere about that centre (metres)."""
    size, center = mesh_cuboid(mesh)
    radius = float(np.linalg.norm(np.asarray(mesh.vertices) - center, axis=1).max())
    return size, center, ShapeInfo(center=center, radius=radius)


@dataclass
class MeshAsset:
    """A loaded mesh with what rendering and annotation need.

    Attributes:
        path: the file; name: class name (targets) or file stem.
        mesh: trimesh in metres.
        texture: (h, w, 3|4) uint8 base-colour texture or None; colors: (V, 4) uint8 or None.
        cuboid_size, cuboid_center: (3,) AABB in the mesh frame, metres.
        shape: bounding sphere about the cuboid centre.
        cacheable: the renderer may keep its GPU mesh and texture by ``path`` (False for
            procedural objects, made anew each frame).
    """

    path: Path
    name: str
    mesh: trimesh.Trimesh
    texture: np.ndarray | None
    colors: np.ndarray | None
    cuboid_size: np.ndarray
    cuboid_center: np.ndarray
    shape: ShapeInfo
    cacheable: bool = True

    @classmethod
    def load(cls, path: str | os.PathLike, name: str | None = None, units: str | None = None,
             max_texture_px: int | None = None) -> MeshAsset:
        path = Path(path)
        mesh = load_mesh(path, units=units)
        size, center, shape = bounding_shape(mesh)
        if np.any(size <= 0):
            raise InputFileError(path, f"mesh is flat (extents {size.tolist()} m)")
        return cls(path=path, name=name or path.stem, mesh=mesh,
                   texture=texture_image(mesh, max_texture_px), colors=vertex_colors(mesh),
                   cuboid_size=size, cuboid_center=center, shape=shape)


def guess_class_name(mesh_path: str | os.PathLike) -> str:
    """The class a mesh file is of: :func:`dope_hope.io.models_dir.mesh_class_name` (a catalog
    object, else the folder of a generic file name such as ``textured.obj``, else the stem)."""
    return mesh_class_name(mesh_path)


def _as_list(value: Any) -> list[Any]:
    if value is None:
        return []
    return [value] if isinstance(value, (str, os.PathLike)) else list(value)


def list_distractor_meshes(folder: str | os.PathLike,
                           target_path: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
                           target_class: str | Sequence[str] | None = None) -> list[Path]:
    """Mesh files under ``folder`` (recursive, sorted), minus copies of the targets.

    Excluded, so that no unannotated target instance is ever rendered: each target file
    itself, files beside it in its own sub-folder (e.g. ``Ketchup/textured_simple.obj``), and
    files whose name or folder names a target class (one path / class, or several).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(folder, "distractor folder not found")
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    targets = [Path(p).resolve() for p in _as_list(target_path)]
    classes = {c.lower() for c in _as_list(target_class) if c}
    root = folder.resolve()
    out = []
    for f in files:
        r = f.resolve()
        if any(r == tgt or (r.parent == tgt.parent and r.parent != root) for tgt in targets):
            continue
        if classes and guess_class_name(f).lower() in classes:
            continue
        out.append(f)
    if not out:
        raise InputFileError(folder, "no distractor meshes (.obj/.ply) other than the target")
    return out


def distractor_units(files: Sequence[Path]) -> dict[Path, str]:
    """The unit each distractor mesh is read in, checked before any frame (a distractor has no
    flag of its own): its suffix's default (.obj cm, .ply mm) when its box is an object's size
    there (:data:`~dope_hope.io.meshes.PLAUSIBLE_SIZE_M`), else the unit that makes it one, which
    a warning names (in the main process only: the workers read the same). InputFileError
    naming the file for a flat box or one no unit makes an object's, and for a vertex that is
    not a finite number (where ``load_mesh`` would refuse it mid-run)."""
    units: dict[Path, str] = {}
    lo, hi = PLAUSIBLE_SIZE_M
    for path in files:
        default = DEFAULT_UNITS[path.suffix.lower()]
        vertices, _ = file_vertices(path)
        if not np.all(np.isfinite(vertices)):
            check_finite_vertices(path)
        if not len(vertices):
            units[path] = default  # unreadable: load_mesh says why when it is drawn
            continue
        size = np.ptp(vertices, axis=0) * UNIT_SCALE[default]
        check_solid_box(size, default, path)
        unit = default if lo <= float(np.max(size)) <= hi else likely_unit(size, default)
        if unit is None:
            check_plausible_size(size, default, path)
        units[path] = unit
        if unit != default and multiprocessing.parent_process() is None:
            shown = " x ".join(f"{v / UNIT_SCALE[default]:.4g}" for v in size)
            warnings.warn(f"--distractors {path}: box {shown} {default} is no object's size in {default}, its "
                          f"suffix's unit; read in {unit}", stacklevel=2)
    return units


class DistractorLibrary:
    """Lazily loaded distractor meshes with a small LRU cache.

    Args:
        files: mesh files (from :func:`list_distractor_meshes`).
        cache_size: meshes kept loaded.
        max_texture_px: textures are downscaled to at most this side.
        units: each file's unit (default: :func:`distractor_units`, checked here).
    """

    def __init__(self, files: list[Path], cache_size: int = 6, max_texture_px: int = 1024,
                 units: dict[Path, str] | None = None):
        self.files = list(files)
        self.units = distractor_units(self.files) if units is None else dict(units)
        self.cache_size = max(1, int(cache_size))
        self.max_texture_px = int(max_texture_px)
        self._cache: OrderedDict[int, MeshAsset] = OrderedDict()
        self._shapes: dict[int, ShapeInfo] = {}

    def __len__(self) -> int:
        return len(self.files)

    def get(self, i: int) -> MeshAsset:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        asset = MeshAsset.load(self.files[i], units=self.units.get(self.files[i]), max_texture_px=self.max_texture_px)
        self._shapes[i] = asset.shape
        self._cache[i] = asset
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return asset

    def shape(self, i: int) -> ShapeInfo:
        """Bounding sphere of mesh i (loads it once; the sphere is remembered after eviction)."""
        if i not in self._shapes:
            self.get(i)
        return self._shapes[i]
