"""Object models for evaluation: points, diameter, symmetries and cuboid of each class.

:func:`load_models` builds one :class:`ObjectModel` per class from its mesh (found by
:func:`dope_hope.io.models_dir.find_object_mesh`: ``--mesh``, then ``--models-dir``) or,
without one, from the catalog's cuboid. Symmetries: the object's declaration
(:func:`dope_hope.symmetry.resolve.resolve_symmetries`: a BOP ``models_info.json`` entry
beside the mesh, ``--symmetries``, ``model_info.json`` beside the mesh (the one
``dope-hope demo`` writes for its box)), else the catalog category's, else those found on
the mesh (:mod:`dope_hope.symmetry.detect`). Each also carries a :class:`BopModel`: the model as BOP19 scoring
uses it (every vertex of the file, millimetres).
"""
from __future__ import annotations

import os
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from dope_hope.catalog import get_object
from dope_hope.errors import InputFileError, UnknownObjectError
from dope_hope.geometry import UNIT_SCALE, value_for_object
from dope_hope.io.meshes import (
    check_mesh_box,
    check_plausible_size,
    load_mesh,
    mesh_cuboid,
    mesh_diameter,
    read_ply,
    sample_surface_points,
)
from dope_hope.io.models_dir import bop_obj_id, check_run_object, find_object_mesh, parse_mesh_args
from dope_hope.io.symmetries import SymmetryDeclaration
from dope_hope.symmetry.resolve import ObjectSymmetries, resolve_symmetries
from dope_hope.symmetry.transforms import category_symmetries, centred_symmetries, symmetries_from_models_info

#: Number of model points for the ADD family (the HOPE paper: 500).
NUM_MODEL_POINTS = 500

#: BOP19's ``max_sym_disc_step`` (continuous symmetries discretized for evaluation).
BOP19_MAX_SYM_DISC_STEP = 0.01


# =========================================================================== object models
@dataclass
class BopModel:
    """What BOP19 scoring needs of an object, in millimetres as the BOP toolkit uses them.

    Attributes:
        points: (N, 3) every vertex of the model file (a BOP ``obj_XXXXXX.ply`` as stored;
            other meshes: their vertices x 1000), mm.
        faces: (M, 3) vertex indices of the triangles (VSD rendering), None for a point cloud.
        diameter: ``models_info.json``'s diameter as stored, else 1000 x the vertex diameter, mm.
        symmetries: (S, 4, 4) model-frame transforms, mm, identity first.
        exact: True when points, diameter and symmetries are the toolkit's own inputs (a BOP
            PLY with its ``models_info.json`` entry).
        path: the model file (None for a procedural stand-in).
    """

    points: np.ndarray
    faces: np.ndarray | None
    diameter: float
    symmetries: np.ndarray
    exact: bool = False
    path: Path | None = None


@dataclass
class ObjectModel:
    """What the metrics need of one object.

    Attributes:
        name, obj_id, category: identity ("other" for a class outside the catalog).
        points: (N, 3) model points, metres.
        diameter: metres.
        symmetries: (S, 4, 4) model-frame symmetry transforms, metres, identity first.
        mesh: trimesh in metres (a ``trimesh.PointCloud`` for a PLY without faces).
        source: where points / mesh come from, for the report.
        procedural: True when the points are sampled on a cuboid (the catalog's or the
            recorded one; no mesh given).
        bop: the model for BOP19 scoring (all vertices, millimetres).
        found_symmetries: what was found on the mesh when its symmetries come from it (one
            line: ``detected on the mesh: ...``), else "".
    """

    name: str
    obj_id: int | None
    category: str
    points: np.ndarray
    diameter: float
    symmetries: np.ndarray
    mesh: Any = None
    source: str = ""
    procedural: bool = False
    bop: BopModel | None = None
    found_symmetries: str = ""


@dataclass
class _LoadedMesh:
    """A class's mesh as loaded: the trimesh (metres), the file's vertices as stored (a PLY:
    (points, faces or None); None for other formats), the file's unit and a description."""

    mesh: Any
    ply: tuple[np.ndarray, np.ndarray | None] | None
    units: str
    source: str


def _load_mesh_file(path: Path, mesh_units: str | None) -> _LoadedMesh:
    """Read one mesh for the metrics (a PLY without faces becomes a point cloud: no VSD)."""
    ply, units, source = None, mesh_units or "mm", f"mesh {path}"
    if path.suffix.lower() == ".ply":
        ply = read_ply(path)  # as stored (BOP19 scoring); faces may be absent
    if ply is not None and ply[1] is None:
        cloud = trimesh.PointCloud(ply[0] * UNIT_SCALE[units])
        check_plausible_size(np.ptp(cloud.vertices, axis=0), units, path)
        return _LoadedMesh(cloud, ply, units,
                           source + " (point cloud: no VSD)")
    mesh = load_mesh(path, units=mesh_units)
    return _LoadedMesh(mesh, ply, mesh.metadata["source_units"], source)


def _check_box(name: str, loaded: _LoadedMesh, path: Path, obj: Any,
               recorded_sizes: dict[str, tuple[np.ndarray, Path]] | None) -> None:
    """A mesh without a BOP entry must match the box recorded for its object (the dataset's,
    else the catalog's; extents in any axis order)."""
    if recorded_sizes and name in recorded_sizes:
        size, where = recorded_sizes[name]
        check_mesh_box(mesh_cuboid(loaded.mesh)[0], size, str(path), name,
                       f"the cuboid {Path(where).name} records", any_axis_order=True, units=loaded.units)
    elif obj is not None:
        check_mesh_box(mesh_cuboid(loaded.mesh)[0], obj.size_array, str(path), name,
                       "the HOPE catalog's cuboid", any_axis_order=True, units=loaded.units)


def _declared_model_symmetries(decl: SymmetryDeclaration, mesh: Any) -> tuple[np.ndarray, float]:
    """A declaration's symmetries discretized as the BOP toolkit does ((S, 4, 4) metres) and
    the diameter (the declaration's, else the mesh's), metres."""
    syms = symmetries_from_models_info(decl.entry, BOP19_MAX_SYM_DISC_STEP, unit=decl.unit_m, source=decl.source)
    return syms, decl.diameter_m or mesh_diameter(mesh)


def _bop_model(loaded: _LoadedMesh, path: Path | None, found: ObjectSymmetries, syms: np.ndarray,
               diameter: float) -> BopModel:
    """The model for BOP19 scoring: the file's vertices (to mm unless in mm), the declaration's
    numbers in mm (as stored for a BOP one), else the metre symmetries and diameter x 1000."""
    if loaded.ply is not None:  # the file's vertices as stored; to mm unless in mm (BOP)
        to_mm = UNIT_SCALE[loaded.units] / UNIT_SCALE["mm"]
        verts, faces = (loaded.ply[0] if to_mm == 1.0 else loaded.ply[0] * to_mm), loaded.ply[1]
    else:
        verts, faces = 1000.0 * np.asarray(loaded.mesh.vertices, np.float64), np.asarray(loaded.mesh.faces)
    decl = found.declaration
    if decl is not None:
        exact = (found.from_bop_table and loaded.ply is not None and "diameter" in decl.entry
                 and decl.units == "mm")
        return BopModel(verts, faces, decl.entry["diameter"] if exact else 1000.0 * diameter,
                        symmetries_from_models_info(decl.entry, BOP19_MAX_SYM_DISC_STEP,
                                                    unit=1000.0 * decl.unit_m, source=decl.source),
                        exact=exact, path=path)
    syms_mm = syms.copy()
    syms_mm[:, :3, 3] *= 1000.0
    return BopModel(verts, faces, 1000.0 * diameter, syms_mm, path=path)


@dataclass
class _ModelArgs:
    """What :func:`load_models` was asked, shared by every class."""

    mesh_units: str | Mapping[str, str] | None
    n_points: int
    cyl_step_deg: float
    declared: dict[str, Any]
    recorded_sizes: dict[str, tuple[np.ndarray, Path]] | None


def _object_model(name: str, path: Path | None, models: _ModelArgs) -> ObjectModel:
    """One class's :class:`ObjectModel` (see :func:`load_models`)."""
    try:
        obj = get_object(name)
    except UnknownObjectError:
        obj = None
    category, obj_id = (obj.category if obj else "other"), bop_obj_id(name)
    explicit = models.declared.get(name)
    if path is not None:
        loaded = _load_mesh_file(path, value_for_object(models.mesh_units, name))
        found = resolve_symmetries(name, path, explicit, loaded.units, obj_id)
        if not found.from_bop_table:  # a BOP entry describes the dataset's own model
            _check_box(name, loaded, path, obj, models.recorded_sizes)
    elif obj is None and not (models.recorded_sizes and name in models.recorded_sizes):
        raise UnknownObjectError(f"class {name!r} is not a HOPE object and no mesh was "
                                 f"given for it (--mesh {name}=PATH)")
    else:
        size, whose = (obj.size_array, "catalog") if obj is not None else (models.recorded_sizes[name][0], "recorded")
        loaded = _LoadedMesh(trimesh.creation.box(extents=np.asarray(size, dtype=np.float64)), None,
                             value_for_object(models.mesh_units, name) or "mm",
                             f"procedural cuboid ({whose} size; no mesh given)")
        found = resolve_symmetries(name, None, explicit, loaded.units, obj_id)
    points = sample_surface_points(loaded.mesh, models.n_points)
    source = loaded.source
    if found.declaration is not None:
        syms, diameter = _declared_model_symmetries(found.declaration, loaded.mesh)
        source += f" + symmetries {found.describe() if found.detected else found.declaration.source}"
    else:
        syms = (category_symmetries(category, step_deg=models.cyl_step_deg) if obj else np.eye(4)[None])
        syms = centred_symmetries(syms, mesh_cuboid(loaded.mesh)[1])
        diameter = mesh_diameter(loaded.mesh)
        if found.detected is not None:
            source += f" + symmetries {found.describe()}"
    return ObjectModel(name=name, obj_id=obj_id, category=category, points=points, diameter=diameter,
                       symmetries=syms, mesh=loaded.mesh, source=source, procedural=path is None,
                       bop=_bop_model(loaded, path, found, syms, diameter),
                       found_symmetries=found.describe() if found.detected is not None else "")


def load_models(class_names: Sequence[str], mesh_args: Sequence[str] = (),
                models_dir: str | os.PathLike | None = None,
                mesh_units: str | Mapping[str, str] | None = None,
                n_points: int = NUM_MODEL_POINTS, cyl_step_deg: float = 1.0,
                symmetry_args: Sequence[str] = (),
                recorded_sizes: dict[str, tuple[np.ndarray, Path]] | None = None,
                mesh_required: Collection[str] | None = None) -> dict[str, ObjectModel]:
    """Model points, diameter and symmetries of every class.

    Mesh: ``--mesh [NAME=]PATH``, then ``--models-dir`` (the search order of
    :mod:`dope_hope.io.models_dir`; a given folder without the mesh of a class in
    ``mesh_required``, default every class, is an error: evaluate requires the classes of
    the ground truth); else a **procedural** stand-in: points on the surface of
    the catalog cuboid, else (a class outside the catalog) of the one ``recorded_sizes``
    gives (reported as such). ``mesh_units``: the unit of every mesh file, or
    {class: unit} (a class not in it: the unit of key "" if any, else by the file's suffix),
    or None (by suffix). Symmetries and diameter: the object's declaration
    (:func:`dope_hope.symmetry.resolve.resolve_symmetries`: a BOP ``models_info.json`` entry
    beside the mesh, else ``--symmetries [NAME=]FILE``, else ``model_info.json`` beside the
    mesh; lengths in the mesh's unit), discretized as the toolkit does from the numbers as
    written (:func:`dope_hope.symmetry.transforms.symmetries_from_models_info`); else the
    catalog category's (cylinders in ``cyl_step_deg`` steps) about the mesh's box centre; a
    class outside the catalog without a declaration has those found on its mesh
    (:mod:`dope_hope.symmetry.detect`, discretized as a declaration), else only the identity. The tables use
    ``n_points`` surface samples; BOP19 scoring (``ObjectModel.bop``) every vertex of the
    file, as the toolkit (a PLY is read as stored: :func:`io.meshes.read_ply`); a BOP PLY in
    mm with its ``models_info.json`` entry (diameter included) is the toolkit's exact input.

    A mesh without a BOP entry must match the box recorded for its object
    (io.meshes.check_mesh_box, extents in any axis order): the dataset's (``recorded_sizes``:
    class -> (size (3,) m, file)), else the catalog's, so that a wrong --mesh-units or another
    object's mesh is refused instead of scored.

    Raises:
        InputFileError / ConfigError / UnknownObjectError: unreadable mesh or declaration;
        a NAME in ``--mesh`` / ``--symmetries`` NAME=... or ``mesh_units`` that is not a class;
        ``models_dir`` without the mesh of a required class (and no ``--mesh`` for it); a
        bare ``--mesh PATH`` of an unknown class among several; ``--symmetries`` for an object
        whose ``models_info.json`` entry declares them; a class neither in the catalog, nor
        given a mesh, nor in ``recorded_sizes``. ConfigError: a mesh whose box does not match.
    """
    meshes = parse_mesh_args(mesh_args, class_names)
    if isinstance(mesh_units, Mapping):  # NAME=UNIT: NAME must be an object scored
        mesh_units = {(check_run_object(k, class_names, "--mesh-units", f"{k}={u}") if k else ""): u
                      for k, u in mesh_units.items()}
    args = _ModelArgs(mesh_units, n_points, cyl_step_deg,
                      parse_mesh_args(symmetry_args, class_names, flag="--symmetries"), recorded_sizes)
    if models_dir is not None and not os.path.isdir(models_dir):
        raise InputFileError(models_dir, "models folder not found")
    out: dict[str, ObjectModel] = {}
    for name in class_names:
        # an explicit models folder must hold the objects scored (no silent stand-in)
        required = models_dir is not None and (mesh_required is None or name in mesh_required)
        path = find_object_mesh(name, models_dir, meshes, required=required)
        out[name] = _object_model(name, None if path is None else Path(path), args)
    return out
