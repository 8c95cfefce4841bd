"""Object models for evaluation: points, diameter, symmetries and cuboid of each class.

:func:`load_models` builds one :class:`ObjectModel` per class from its mesh (found by
:func:`dope_hope.io.models_dir.find_object_mesh`: ``--mesh``, then ``--models-dir``) or,
without one, from the catalog's cuboid. Symmetries: the object's declaration
(:mod:`dope_hope.io.symmetries`: a BOP ``models_info.json`` entry or ``model_info.json``
beside the mesh, or ``--symmetries``; the one ``dope-hope demo`` writes for its box), else
the catalog category's. Each also carries a :class:`BopModel`: the model as BOP19 scoring
uses it (every vertex of the file, millimetres).
"""
from __future__ import annotations

import os
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError
from dope_hope.evaluation import metrics

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
        procedural: True when the points are sampled on the catalog cuboid (no mesh given).
        bop: the model for BOP19 scoring (all vertices, millimetres).
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


def _centred_symmetries(syms: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Symmetries about ``center`` instead of the origin: ``T(c) S T(-c)``."""
    if np.allclose(center, 0.0, atol=1e-6):
        return syms
    T = np.eye(4)
    T[:3, 3] = center
    Ti = np.eye(4)
    Ti[:3, 3] = -center
    return np.einsum("ij,sjk,kl->sil", T, syms, Ti)


def load_models(class_names: Sequence[str], mesh_args: Sequence[str] = (),
                models_dir: str | os.PathLike | None = None, mesh_units: str | None = None,
                n_points: int = NUM_MODEL_POINTS, cyl_step_deg: float = 1.0,
                symmetry_args: Sequence[str] = (),
                recorded_sizes: dict[str, tuple[np.ndarray, Path]] | None = None,
                mesh_required: Collection[str] | None = None) -> dict[str, ObjectModel]:
    """Model points, diameter and symmetries of every class.

    Mesh: ``--mesh [NAME=]PATH``, then ``--models-dir`` (the search order of
    :mod:`dope_hope.io.models_dir`; a given folder without the mesh of a class in
    ``mesh_required``, default every class, is an error: evaluate requires the classes of
    the ground truth); else a **procedural** stand-in: points on the surface of the catalog
    cuboid (reported as such). Symmetries and diameter: the object's declaration
    (:func:`dope_hope.io.symmetries.declared_symmetries`: a BOP ``models_info.json`` entry
    beside the mesh, else ``--symmetries [NAME=]FILE``, else ``model_info.json`` beside the
    mesh; lengths in the mesh's unit), discretized as the toolkit does from the numbers as
    written (:func:`metrics.symmetries_from_models_info`); else the catalog category's
    (cylinders in ``cyl_step_deg`` steps) about the mesh's box centre; a class outside the
    catalog without a declaration has only the identity. The tables use ``n_points`` surface
    samples; BOP19 scoring (``ObjectModel.bop``) every vertex of the file, as the toolkit (a
    PLY is read as stored: :func:`io.meshes.read_ply`); a BOP PLY in mm with its
    ``models_info.json`` entry (diameter included) is the toolkit's exact input.

    A mesh without a BOP entry must match the box recorded for its object
    (io.meshes.check_mesh_box, extents in any axis order): the dataset's (``recorded_sizes``:
    class -> (size (3,) m, file)), else the catalog's, so that a wrong --mesh-units or another
    object's mesh is refused instead of scored.

    Raises:
        InputFileError / ConfigError / UnknownObjectError: unreadable mesh or declaration;
        ``models_dir`` without the mesh of a required class (and no ``--mesh`` for it); a
        bare ``--mesh PATH`` of an unknown class among several; ``--symmetries`` for an object
        whose ``models_info.json`` entry declares them; a class neither in the catalog nor
        given a mesh. ConfigError: a mesh whose box does not match.
    """
    import trimesh

    from dope_hope.catalog import category_symmetries, get_object
    from dope_hope.io.meshes import (
        UNIT_SCALE,
        check_mesh_box,
        load_mesh,
        mesh_cuboid,
        mesh_diameter,
        read_ply,
        sample_surface_points,
    )
    from dope_hope.io.models_dir import bop_obj_id, find_object_mesh, parse_mesh_args
    from dope_hope.io.symmetries import declared_symmetries, find_declaration

    meshes = parse_mesh_args(mesh_args, class_names)
    declared = parse_mesh_args(symmetry_args, class_names, flag="--symmetries")
    if models_dir is not None and not os.path.isdir(models_dir):
        raise InputFileError(models_dir, "models folder not found")
    out: dict[str, ObjectModel] = {}
    for name in class_names:
        try:
            obj = get_object(name)
        except UnknownObjectError:
            obj = None
        category = obj.category if obj else "other"
        obj_id = bop_obj_id(name)
        # an explicit models folder must hold the objects scored (no silent stand-in)
        required = models_dir is not None and (mesh_required is None or name in mesh_required)
        path = find_object_mesh(name, models_dir, meshes, required=required)
        ply, decl, bop_entry, units = None, None, False, mesh_units or "mm"
        if path is not None:
            path = Path(path)
            source = f"mesh {path}"
            if path.suffix.lower() == ".ply":
                ply = read_ply(path)  # as stored (BOP19 scoring); faces may be absent
            if ply is not None and ply[1] is None:
                mesh = trimesh.PointCloud(ply[0] * UNIT_SCALE[units])
                source += " (point cloud: no VSD)"
            else:
                mesh = load_mesh(path, units=mesh_units)
                units = mesh.metadata["source_units"]
            decl = declared_symmetries(None, path, units, obj_id)
            bop_entry = decl is not None and find_declaration(path).name == "models_info.json"
            if bop_entry and declared.get(name) is not None:
                raise ConfigError(f"--symmetries for {name} would be ignored: its models_info.json entry "
                                  f"({decl.source}) declares the symmetries BOP scoring uses; drop one of "
                                  f"the two")
            if bop_entry:
                pass  # the dataset's own model, described by its models_info.json entry
            elif recorded_sizes and name in recorded_sizes:
                size, where = recorded_sizes[name]
                check_mesh_box(mesh_cuboid(mesh)[0], size, str(path), name,
                               f"the cuboid {Path(where).name} records", any_axis_order=True)
            elif obj is not None:
                check_mesh_box(mesh_cuboid(mesh)[0], obj.size_array, str(path), name,
                               "the HOPE catalog's cuboid", any_axis_order=True)
        elif obj is None:
            raise UnknownObjectError(f"class {name!r} is not a HOPE object and no mesh was "
                                     f"given for it (--mesh {name}=PATH)")
        else:
            mesh = trimesh.creation.box(extents=obj.size_array)
            source = "procedural cuboid (catalog size; no mesh given)"
        if not bop_entry and declared.get(name) is not None:
            decl = declared_symmetries(declared[name], path, units, obj_id)
        points = sample_surface_points(mesh, n_points)
        if decl is not None:
            syms = metrics.symmetries_from_models_info(decl.entry, BOP19_MAX_SYM_DISC_STEP,
                                                       unit=decl.unit_m, source=decl.source)
            diameter = decl.diameter_m or mesh_diameter(mesh)
            source += f" + symmetries {decl.source}"
        else:
            syms = (category_symmetries(category, step_deg=cyl_step_deg) if obj else np.eye(4)[None])
            syms = _centred_symmetries(syms, mesh_cuboid(mesh)[1])
            diameter = mesh_diameter(mesh)
        if ply is not None:  # the file's vertices as stored; to mm unless in mm (BOP)
            to_mm = UNIT_SCALE[units] / UNIT_SCALE["mm"]
            verts, faces = (ply[0] if to_mm == 1.0 else ply[0] * to_mm), ply[1]
        else:
            verts, faces = 1000.0 * np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
        if decl is not None:  # the declaration's numbers, in mm (as stored for a BOP one)
            exact = bop_entry and ply is not None and "diameter" in decl.entry and decl.units == "mm"
            bop = BopModel(verts, faces, decl.entry["diameter"] if exact else 1000.0 * diameter,
                           metrics.symmetries_from_models_info(decl.entry, BOP19_MAX_SYM_DISC_STEP,
                                                               unit=1000.0 * decl.unit_m, source=decl.source),
                           exact=exact, path=path)
        else:
            syms_mm = syms.copy()
            syms_mm[:, :3, 3] *= 1000.0
            bop = BopModel(verts, faces, 1000.0 * diameter, syms_mm, path=path)
        out[name] = ObjectModel(name=name, obj_id=obj_id, category=category, points=points,
                                diameter=diameter, symmetries=syms, mesh=mesh, source=source,
                                procedural=path is None, bop=bop)
    return out
