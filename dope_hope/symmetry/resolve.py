"""Which symmetries an object has: the one resolution order.

Training labels (``targets.symmetry auto``), ``dope-hope demo`` and the evaluation
(``dope-hope evaluate``, BOP AR) all ask :func:`resolve_symmetries`. The first that exists wins:

1. the object's entry in a BOP ``models_info.json`` beside its mesh (the dataset's own
   description; naming another declaration as well is refused);
2. a declaration named by the user (``--symmetries``);
3. ``model_info.json`` beside the mesh;
4. the built-in declaration of the demo box (:mod:`dope_hope.demo_object`);
5. the HOPE catalog's category of the object (unless its mesh's box is not the catalog's
   cuboid: another object of the same name, such as a milk carton called "Milk");
6. the symmetries found on its mesh (:func:`dope_hope.symmetry.detect.detect_mesh_file_symmetries`:
   geometry only, within its stated tolerance), for any other object with a mesh file.

An object with none of these (no mesh, or a mesh with no symmetry) has none: the evaluation
scores it with the identity only; ``targets.symmetry auto`` keeps its labels, or refuses an
object without a mesh.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from dope_hope.catalog import CATEGORIES, get_object
from dope_hope.demo_object import DEMO_CLASS_NAME, demo_symmetries
from dope_hope.errors import ConfigError, UnknownObjectError
from dope_hope.io.meshes import MESH_SIZE_TOLERANCE
from dope_hope.io.models_dir import bop_obj_id
from dope_hope.io.symmetries import (
    SymmetryDeclaration,
    bop_table_declaration,
    mesh_units,
    model_info_declaration,
    read_declaration,
)
from dope_hope.symmetry.detect import DetectedSymmetries, detect_mesh_file_symmetries, mesh_file_size
from dope_hope.symmetry.transforms import category_symmetries, declaration_transforms


@dataclass(frozen=True)
class ObjectSymmetries:
    """Where an object's symmetries come from.

    Attributes:
        declaration: the declaration that applies, or None.
        category: the HOPE category when no declaration applies and the object is in the
            catalog, else None.
        from_bop_table: True when ``declaration`` is the object's ``models_info.json`` entry.
        detected: what was found on the mesh when that applies (``declaration`` then holds it
            in millimetres, None when nothing was found).
    """

    declaration: SymmetryDeclaration | None
    category: str | None
    from_bop_table: bool = False
    detected: DetectedSymmetries | None = None

    def describe(self) -> str:
        """Where they come from, for reports: ``declared in FILE``, ``C category``, ``detected
        on the mesh: ...``, ``none``."""
        if self.detected is not None:
            return f"detected on the mesh: {self.detected.text()}"
        if self.declaration is not None:
            return f"declared in {self.declaration.source}"
        return f"{self.category} category" if self.category else "none"


def resolve_symmetries(name: str, mesh_path: str | os.PathLike | None = None,
                       explicit: str | os.PathLike | None = None, units: str | None = None,
                       obj_id: int | None = None, detect: bool = True) -> ObjectSymmetries:
    """The symmetries of object ``name`` in the order of the module docstring.

    Args:
        name: class name (catalog lookup, demo box).
        mesh_path: its mesh file, where declarations beside it are looked for.
        explicit: a declaration file named by the user.
        units: length unit of the declarations (default: the mesh's, by suffix; else mm).
        obj_id: BOP obj_id of the object (default: the catalog's, or ``obj_NNNNNN``).
        detect: False skips step 6 (no symmetries found on the mesh).

    Raises:
        ConfigError: ``explicit`` for an object whose ``models_info.json`` entry declares them.
        InputFileError: a malformed declaration (file and field named).
    """
    if obj_id is None:
        obj_id = bop_obj_id(name)
    if mesh_path is not None:
        table = bop_table_declaration(mesh_path, units, obj_id)
        if table is not None:
            if explicit is not None:
                raise ConfigError(f"--symmetries for {name} would be ignored: its models_info.json entry "
                                  f"({table.source}) declares the symmetries BOP scoring uses; drop one of "
                                  f"the two")
            return ObjectSymmetries(table, None, from_bop_table=True)
    if explicit is not None:
        unit = mesh_units(mesh_path, units) if mesh_path is not None else (units or "mm")
        return ObjectSymmetries(read_declaration(explicit, unit, obj_id), None)
    beside = model_info_declaration(mesh_path, units, obj_id) if mesh_path is not None else None
    if beside is not None:
        return ObjectSymmetries(beside, None)
    if name.lower() == DEMO_CLASS_NAME.lower():
        return ObjectSymmetries(demo_symmetries(), None)
    has_mesh = mesh_path is not None and os.path.isfile(mesh_path)
    try:
        obj = get_object(name)
    except UnknownObjectError:
        obj = None
    if obj is not None and not (has_mesh and detect and _another_object(obj.size_array, mesh_path, units)):
        return ObjectSymmetries(None, obj.category)
    if not has_mesh or not detect:
        return ObjectSymmetries(None, None)
    try:
        found = detect_mesh_file_symmetries(mesh_path, units)
    except ValueError:  # a point cloud: no surface to test
        return ObjectSymmetries(None, None)
    return ObjectSymmetries(found.declaration("mm") if found.any else None, None, detected=found)


def _another_object(catalog_size: np.ndarray, mesh_path: str | os.PathLike, units: str | None) -> bool:
    """True when a mesh's box is not the catalog cuboid of the object it is named after (extents
    in any order, beyond ``io.meshes.MESH_SIZE_TOLERANCE``): another object of that name."""
    ratio = np.sort(mesh_file_size(mesh_path, units)) / np.sort(catalog_size)
    return bool(np.any(ratio > MESH_SIZE_TOLERANCE) or np.any(ratio < 1.0 / MESH_SIZE_TOLERANCE))


def label_symmetries(setting: Any, object_name: str, declaration_file: str | os.PathLike | None = None,
                     mesh: str | os.PathLike | None = None,
                     units: str | None = None) -> tuple[np.ndarray, str] | None:
    """Symmetries whose corner permutations relabel the keypoints (config ``targets.symmetry``):
    ``((S, 4, 4) model-frame transforms, where they come from)``, or None.

    "none" (default, the official DOPE labels); "auto": :func:`resolve_symmetries` with
    ``declaration_file`` (``--symmetries``) and ``mesh`` (a mesh on which none are found gives
    the identity alone: the labels stay); or a category name: "cuboid",
    "bottle", "cylinder". Continuous symmetries are sampled every 90 degrees (the only turns
    that can permute box corners).

    Raises:
        ConfigError: an unknown setting; a declaration file with a setting other than auto;
            auto for an object outside the catalog with neither a declaration nor a mesh.
    """
    value = "none" if setting in (None, False) else str(setting).lower()
    if declaration_file is not None and value != "auto":
        raise ConfigError(f"--symmetries {declaration_file}: targets.symmetry is {value}; add "
                          "--set targets.symmetry=auto to relabel with the declared symmetries")
    if value == "none":
        return None
    if value == "auto":
        found = resolve_symmetries(object_name, mesh, declaration_file, units)
        if found.declaration is not None:
            return declaration_transforms(found.declaration, step_deg=90.0), found.describe()
        if found.detected is not None:
            return np.eye(4)[None], found.describe()
        if found.category is None:
            raise ConfigError(f"targets.symmetry auto: {object_name!r} is not a HOPE object, declares "
                              "no symmetries and has no mesh to find them on (--mesh, --symmetries FILE); set "
                              f"targets.symmetry to one of {', '.join(CATEGORIES)} or none")
        return category_symmetries(found.category, step_deg=90.0), found.describe()
    if value not in CATEGORIES:
        raise ConfigError(f"targets.symmetry must be none, auto or one of {', '.join(CATEGORIES)}; got {setting!r}")
    return category_symmetries(value, step_deg=90.0), f"{value} category"
