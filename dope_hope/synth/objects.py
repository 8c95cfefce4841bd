"""Procedural target objects: boxes, cans and bottles of HOPE sizes wearing packaging textures.

Pretraining (``dope-hope synth --procedural``) renders a new object in every frame, so that a
network learns "the cuboid keypoints of a grocery object" rather than one object. Shapes
follow the HOPE categories and frame conventions (:mod:`dope_hope.catalog`): the model frame is
centred on the bounding box, y is the vertical axis of cans and bottles; a category's sizes
are those of a random HOPE object of it, each extent jittered. Textures are
:func:`~dope_hope.synth.textures.label_image` sheets: a box shows a different sheet region on
each face; a can or bottle wraps one label around its side (u = angle, v = height), its caps
(and the top of a bottle's neck) take a plain cap colour.

Every object comes from one ``numpy.random.Generator``: the same generator state gives the
same object.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from dope_hope.catalog import CATEGORIES, HOPE_OBJECTS
from dope_hope.synth.assets import MeshAsset, bounding_shape
from dope_hope.synth.primitives import corner_normals, split_mesh
from dope_hope.synth.textures import label_image, random_color

#: Fraction of a can / bottle texture's height (top rows) holding the cap colour.
CAP_ROWS = 0.12
#: Box texture atlas: faces (+x, -x, +y, -y, +z, -z) take the cells of a 2 x 3 grid.
_BOX_CELLS = ((0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2))


@dataclass
class ProceduralObject:
    """A generated object: its category (a HOPE category name) and its renderable asset."""

    category: str
    asset: MeshAsset


def box_mesh(size_m: np.ndarray) -> trimesh.Trimesh:
    """Box of extents ``size_m`` (3,) metres, centred; each face maps one cell of the 2 x 3 atlas."""
    shape = trimesh.creation.box(extents=np.asarray(size_m, dtype=np.float64))
    tri = np.asarray(shape.vertices)[np.asarray(shape.faces)]           # (F, 3, 3)
    fn = np.asarray(shape.face_normals)
    axis = np.argmax(np.abs(fn), axis=1)
    face_id = 2 * axis + (fn[np.arange(len(fn)), axis] < 0)            # +x, -x, +y, -y, +z, -z
    half = np.asarray(size_m, dtype=np.float64) / 2.0
    keep = np.array([[2, 1], [0, 2], [0, 1]])[axis]                    # in-plane axes (u, v)
    uv = np.empty((len(tri), 3, 2))
    for f in range(len(tri)):
        a, b = keep[f]
        local = np.stack([(tri[f, :, a] + half[a]) / (2 * half[a]), (tri[f, :, b] + half[b]) / (2 * half[b])], 1)
        row, col = _BOX_CELLS[face_id[f]]
        uv[f, :, 0] = (col + np.clip(local[:, 0], 0, 1)) / 3.0
        uv[f, :, 1] = (row + np.clip(local[:, 1], 0, 1)) / 2.0
    return split_mesh(shape, uv.reshape(-1, 2), np.repeat(fn, 3, axis=0))


def _wrapped_uv(shape: trimesh.Trimesh, y_range: tuple[float, float]) -> np.ndarray:
    """(3F, 2) cylindrical uv about the y axis: u = angle / 2 pi (seam-safe per triangle), v =
    height fraction over ``y_range`` scaled below the cap rows (v = 0: the texture's bottom
    row, as in OBJ files); triangles of the caps and above ``y_range`` take the cap rows."""
    tri = np.asarray(shape.vertices)[np.asarray(shape.faces)]
    u = (np.arctan2(tri[..., 0], tri[..., 2]) / (2 * np.pi)) % 1.0     # (F, 3)
    wrap = (u.max(axis=1) - u.min(axis=1)) > 0.5
    u[wrap] = np.where(u[wrap] < 0.5, u[wrap] + 1.0, u[wrap])
    lo, hi = y_range
    v = np.clip((tri[..., 1] - lo) / max(hi - lo, 1e-9), 0, 1) * (1.0 - CAP_ROWS)
    fn = np.asarray(shape.face_normals)
    cap = (np.abs(fn[:, 1]) > 0.95) | (tri[..., 1].mean(axis=1) > hi)
    v[cap] = 1.0 - CAP_ROWS / 2.0
    return np.stack([u, v], axis=-1).reshape(-1, 2)


def _cap_normals(shape: trimesh.Trimesh) -> np.ndarray:
    """(3F, 3) corner normals of a can or bottle standing along y: smooth, flat on its caps."""
    return corner_normals(shape, flat_axis=1, flat_cos=0.95)


def _y_up(shape: trimesh.Trimesh) -> trimesh.Trimesh:
    """Turn a shape built about z (trimesh's axis of revolution) to stand along y."""
    shape = shape.copy()
    shape.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return shape


def can_mesh(size_m: np.ndarray, sections: int = 32) -> trimesh.Trimesh:
    """Cylinder along y with extents ``size_m`` (x and z: the diameters, y: the height), metres."""
    size = np.asarray(size_m, dtype=np.float64)
    shape = _y_up(trimesh.creation.cylinder(radius=0.5, height=1.0, sections=sections))
    shape.apply_scale(size)  # unit diameter and height -> the extents (elliptic when x != z)
    shape.apply_translation(-shape.bounds.mean(axis=0))
    return split_mesh(shape, _wrapped_uv(shape, (-size[1] / 2, size[1] / 2)), _cap_normals(shape))


def bottle_profile(rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A bottle's (N, 2) (radius, height) outline for a unit height and unit body width, from
    bottom centre to top centre, and the height where its neck begins."""
    shoulder = rng.uniform(0.55, 0.75)
    neck_r = rng.uniform(0.18, 0.35)
    neck_h = rng.uniform(0.78, 0.88)
    base_r = rng.uniform(0.85, 1.0)
    pts = [(0.0, 0.0), (0.5 * base_r, 0.0), (0.5, 0.08), (0.5, shoulder)]
    for s in np.linspace(0.25, 1.0, 4):                                # rounded shoulder
        pts.append((0.5 - (0.5 - 0.5 * neck_r) * s ** 1.5, shoulder + (neck_h - shoulder) * s))
    pts += [(0.5 * neck_r, 1.0), (0.0, 1.0)]
    return np.array(pts), neck_h


def bottle_mesh(size_m: np.ndarray, rng: np.random.Generator, sections: int = 32) -> trimesh.Trimesh:
    """A squeeze-bottle shape along y with extents ``size_m`` (x wider than z: an elliptic
    body, which has the bottle category's 180° symmetry about y), metres."""
    profile, neck_h = bottle_profile(rng)
    cap_from = neck_h + 0.4 * (1.0 - neck_h)  # the cap: the upper 60 % of the neck
    shape = _y_up(trimesh.creation.revolve(profile, sections=sections))
    shape.apply_scale(np.asarray(size_m, dtype=np.float64) / shape.extents)
    shape.apply_translation(-shape.bounds.mean(axis=0))
    height = float(shape.extents[1])
    y_range = (-height / 2, -height / 2 + cap_from * height)
    return split_mesh(shape, _wrapped_uv(shape, y_range), _cap_normals(shape))


def sample_size(rng: np.random.Generator, category: str, jitter: float) -> np.ndarray:
    """(3,) extents, metres: a random HOPE object's of ``category``, each scaled by a
    log-uniform factor in [1 / (1 + jitter), 1 + jitter]; cans get a round cross-section and
    bottles one wider along x than along z."""
    objects = [o for o in HOPE_OBJECTS if o.category == category]
    size = objects[int(rng.integers(0, len(objects)))].size_array.astype(np.float64)
    size = size * np.exp(rng.uniform(-np.log1p(jitter), np.log1p(jitter), size=3))
    if category == "cylinder":
        size[0] = size[2] = (size[0] + size[2]) / 2.0
    elif category == "bottle" and size[2] > size[0]:
        size[[0, 2]] = size[[2, 0]]
    return size


def sample_object(rng: np.random.Generator, weights: dict[str, float], size_jitter: float = 0.25,
                  texture_px: int = 256, name: str = "Object") -> ProceduralObject:
    """A random object of a category drawn with ``weights`` (HOPE category -> weight).

    Args:
        rng: the object's random stream.
        weights: e.g. ``{"cuboid": 1, "cylinder": 1, "bottle": 1}``.
        size_jitter: relative extent jitter (see :func:`sample_size`).
        texture_px: height of the texture sheet (width: twice that for cans and bottles, 1.5x for boxes).
        name: the asset's (annotation class) name.
    """
    cats = [c for c in CATEGORIES if float(weights.get(c, 0.0)) > 0]
    p = np.array([float(weights[c]) for c in cats])
    category = cats[int(rng.choice(len(cats), p=p / p.sum()))]
    size = sample_size(rng, category, size_jitter)
    if category == "cuboid":
        mesh = box_mesh(size)
        texture = label_image(rng, texture_px, int(1.5 * texture_px))
    else:
        mesh = can_mesh(size) if category == "cylinder" else bottle_mesh(size, rng)
        texture = label_image(rng, texture_px, 2 * texture_px)
        cap = (random_color(rng) * 255).astype(np.uint8)
        texture[: int(np.ceil(CAP_ROWS * texture_px))] = cap
    cuboid_size, cuboid_center, shape = bounding_shape(mesh)
    asset = MeshAsset(path=Path(f"<procedural {category}>"), name=name, mesh=mesh, texture=texture,
                      colors=None, cuboid_size=cuboid_size, cuboid_center=cuboid_center, shape=shape,
                      cacheable=False)
    return ProceduralObject(category=category, asset=asset)
