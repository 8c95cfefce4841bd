"""Object models for evaluation: points, diameter, symmetries and cuboid of each class.

:func:`load_models` builds one :class:`ObjectModel` per class from a mesh (``--mesh``, a BOP
models folder) or, without one, from the catalog's cuboid; symmetries come from
``models_info.json`` (BOP), the object's declaration (:mod:`dope_hope.io.symmetries`) or the
catalog category. Each also carries a :class:`BopModel`:
the model as BOP19 scoring uses it (every vertex of the file, millimetres).
"""
from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError
from dope_hope.evaluation import metrics

#: Number of model points for the ADD family (the HOPE paper: 500).
NUM_MODEL_POINTS = 500

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
    """

    points: np.ndarray
    faces: np.ndarray | None
    diameter: float
    symmetries: np.ndarray
    exact: bool = False


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


def _catalog_entry(name: str):
    from dope_hope.catalog import get_object

    try:
        return get_object(name)
    except UnknownObjectError:
        return None


def parse_mesh_args(mesh_args: Sequence[str]) -> dict[str | None, Path]:
    """``--mesh [NAME=]PATH`` values -> {class name or None: path}.

    Without ``NAME=``, the class is the catalog object named by the file stem or by its
    folder (``Ketchup.obj``, ``Ketchup/textured.obj``); None if neither names one.
    """
    out: dict[str | None, Path] = {}
    for arg in mesh_args:
        if "=" in arg and not Path(arg).exists():
            name, path = arg.split("=", 1)
            obj = _catalog_entry(name)
            out[obj.name if obj else name] = Path(path)
            continue
        p = Path(arg)
        obj = _catalog_entry(p.stem) or _catalog_entry(p.parent.name)
        out[obj.name if obj else None] = p
    return out


def _named_paths(args: Sequence[str], class_names: Sequence[str], flag: str) -> dict[str, Path]:
    """``[NAME=]PATH`` values of ``flag`` by class (a bare path: the only class)."""
    named = parse_mesh_args(args)
    if None in named:
        if len(class_names) == 1 and len(named) == 1:
            return {class_names[0]: named[None]}
        raise ConfigError(f"{flag} {named[None]}: cannot tell which object it is; "
                          f"write {flag} NAME=PATH (classes: {', '.join(class_names)})")
    return named  # type: ignore[return-value]


def load_models(class_names: Sequence[str], mesh_args: Sequence[str] = (),
                models_dir: str | os.PathLike | None = None, mesh_units: str | None = None,
                n_points: int = NUM_MODEL_POINTS, cyl_step_deg: float = 1.0,
                symmetry_args: Sequence[str] = ()) -> dict[str, ObjectModel]:
    """Model points, diameter and symmetries of every class.

    Sources, in order: ``--mesh`` files; ``--models-dir`` (BOP ``models_info.json`` +
    ``obj_XXXXXX.ply`` in mm, or HOPE ``<Name>/textured.obj`` / ``<Name>.obj`` in cm); else a
    **procedural** stand-in: points on the surface of the catalog cuboid (reported as such).
    Symmetries: BOP ``models_info`` when used, else the object's declaration
    (``--symmetries [NAME=]FILE`` or ``model_info.json`` beside its mesh;
    :mod:`dope_hope.io.symmetries`), both discretized as the toolkit does from the numbers as
    written (:func:`metrics.symmetries_from_models_info`); else the catalog category's
    (cylinders in ``cyl_step_deg`` steps) about the mesh's box centre.
    The tables use ``n_points`` surface samples; BOP19 scoring (``ObjectModel.bop``) every
    vertex of the file, as the toolkit (a PLY is read as stored: :func:`io.meshes.read_ply`).

    Raises:
        InputFileError / UnknownObjectError: unreadable mesh; a class neither in the catalog
        nor given a mesh.
    """
    import trimesh

    from dope_hope.catalog import category_symmetries
    from dope_hope.io.meshes import (UNIT_SCALE, load_mesh, mesh_cuboid, mesh_diameter, read_ply,
                                     sample_surface_points)
    from dope_hope.io.symmetries import declared_symmetries

    meshes = _named_paths(mesh_args, class_names, "--mesh")
    declared = _named_paths(symmetry_args, class_names, "--symmetries")
    models_info: dict[int, dict] = {}
    mdir = Path(models_dir) if models_dir is not None else None
    if mdir is not None:
        if not mdir.is_dir():
            raise InputFileError(mdir, "models folder not found")
        info_path = mdir / "models_info.json"
        if info_path.is_file():
            try:
                models_info = {int(k): v for k, v in
                               json.loads(info_path.read_text(encoding="utf-8")).items()}
            except (ValueError, json.JSONDecodeError, AttributeError) as exc:
                raise InputFileError(info_path, f"malformed models_info.json ({exc})") from None
    out: dict[str, ObjectModel] = {}
    for name in class_names:
        obj = _catalog_entry(name)
        category = obj.category if obj else "other"
        obj_id = obj.obj_id if obj else None
        mesh, source, info, path, ply, in_dir = None, "", None, None, None, False
        if name in meshes:
            path = meshes[name]
        elif mdir is not None:
            candidates = []
            if obj_id is not None:
                candidates.append(mdir / f"obj_{obj_id:06d}.ply")
            candidates += [mdir / name / "textured.obj", mdir / f"{name}.obj", mdir / f"{name}.ply"]
            path = next((c for c in candidates if c.is_file()), None)
            in_dir = path is not None
        if path is not None:
            path = Path(path)
            source = f"mesh {path}"
            if path.suffix.lower() == ".ply":
                ply = read_ply(path)  # as stored (BOP19 scoring); faces may be absent
                if in_dir and obj_id in models_info:
                    info = models_info[obj_id]
                    source += " + models_info.json"
            if ply is not None and ply[1] is None:
                scale = UNIT_SCALE[mesh_units or "mm"]
                mesh = trimesh.PointCloud(ply[0] * scale)
                source += " (point cloud: no VSD)"
            else:
                mesh = load_mesh(path, units=mesh_units)
        if mesh is None:
            if obj is None:
                raise UnknownObjectError(f"class {name!r} is not a HOPE object and no mesh was "
                                         f"given for it (--mesh {name}=PATH)")
            mesh = trimesh.creation.box(extents=obj.size_array)
            source = "procedural cuboid (catalog size; no mesh given)"
        points = sample_surface_points(mesh, n_points)
        if info is not None and declared.get(name) is not None:
            raise ConfigError(f"--symmetries for {name} would be ignored: its models_info.json entry "
                              f"(--models-dir) declares the symmetries BOP scoring uses; drop one of the two")
        decl = None if info is not None else declared_symmetries(declared.get(name), path, mesh_units, obj_id)
        if info is not None:
            syms = metrics.symmetries_from_models_info(info, BOP19_MAX_SYM_DISC_STEP,
                                                       source=mdir / "models_info.json", where=str(obj_id))
            diameter = 0.001 * float(info["diameter"]) if "diameter" in info else mesh_diameter(mesh)
        elif decl is not None:
            syms = metrics.symmetries_from_models_info(decl.entry, BOP19_MAX_SYM_DISC_STEP,
                                                       unit=decl.unit_m, source=decl.source)
            diameter = decl.diameter_m or mesh_diameter(mesh)
            source += f" + symmetries {decl.source}"
        else:
            syms = (category_symmetries(category, step_deg=cyl_step_deg) if obj else np.eye(4)[None])
            syms = _centred_symmetries(syms, mesh_cuboid(mesh)[1])
            diameter = mesh_diameter(mesh)
        if ply is not None:  # the file's vertices as stored; to mm unless in mm (BOP)
            to_mm = UNIT_SCALE[mesh_units or "mm"] / UNIT_SCALE["mm"]
            verts, faces = (ply[0] if to_mm == 1.0 else ply[0] * to_mm), ply[1]
        else:
            verts, faces = 1000.0 * np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
        exact = info is not None and "diameter" in info and (mesh_units or "mm") == "mm"
        if exact:
            bop = BopModel(verts, faces, info["diameter"],
                           metrics.symmetries_from_models_info(info, BOP19_MAX_SYM_DISC_STEP, unit=1.0,
                                                               source=mdir / "models_info.json",
                                                               where=str(obj_id)),
                           exact=True)
        elif decl is not None:  # the declaration's numbers, in mm (as stored for a BOP one)
            bop = BopModel(verts, faces, 1000.0 * diameter,
                           metrics.symmetries_from_models_info(decl.entry, BOP19_MAX_SYM_DISC_STEP,
                                                               unit=1000.0 * decl.unit_m, source=decl.source))
        else:
            syms_mm = syms.copy()
            syms_mm[:, :3, 3] *= 1000.0
            bop = BopModel(verts, faces, 1000.0 * diameter, syms_mm)
        out[name] = ObjectModel(name=name, obj_id=obj_id, category=category, points=points,
                                diameter=diameter, symmetries=syms, mesh=mesh, source=source,
                                procedural=source.startswith("procedural"), bop=bop)
    return out
