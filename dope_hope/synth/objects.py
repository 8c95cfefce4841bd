"""Procedural target objects: grocery-like shapes wearing packaging textures.

Pretraining (``dope-hope synth --procedural``) renders a new object in every frame, so that a
network learns "the cuboid keypoints of a grocery object" rather than one object. The shapes
(:data:`SHAPE_LABELS`): the three HOPE categories (boxes, cans, squeeze bottles, at the sizes
of a random HOPE object of the category, each extent jittered) and shapes beyond them (jars
with lids, squeezed tubes, pillow pouches, rounded boxes and irregular bodies, at sizes of
their own). All follow the HOPE frame conventions (:mod:`dope_hope.catalog`): the model frame
is centred on the bounding box, y is the vertical axis of round and elongated shapes. Each
shape is annotated with the symmetric labels of one HOPE category (:data:`SHAPE_LABELS`: the
category whose symmetry group its cuboid is labelled with). Textures are
:func:`~dope_hope.synth.textures.label_image` sheets: a box, pouch or body shows a different
sheet region on each side (projected along its dominant axis); a can, bottle, jar or tube
wraps one label around its side (u = angle, v = height), its caps (and the top of a bottle's
neck, a jar's lid) take a plain cap colour.

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
#: Procedural shape -> the HOPE category whose symmetric corner labels it is annotated with
#: (the shape's cuboid has at least that category's symmetry, up to its texture and details).
SHAPE_LABELS = {"cuboid": "cuboid", "cylinder": "cylinder", "bottle": "bottle",
                "jar": "cylinder", "tube": "bottle", "pouch": "cuboid", "rounded_box": "cuboid",
                "body": "cuboid"}
#: Size ranges (metres) of the shapes beyond the HOPE categories: (width x, height y, depth z);
#: a jar's and a tube's depth follows its width.
SHAPE_SIZES = {"jar": ((0.05, 0.13), (0.05, 0.16), None),
               "tube": ((0.025, 0.06), (0.10, 0.22), None),
               "pouch": ((0.08, 0.20), (0.10, 0.26), (0.015, 0.05)),
               "rounded_box": ((0.04, 0.25), (0.04, 0.30), (0.02, 0.15)),
               "body": ((0.03, 0.18), (0.03, 0.18), (0.03, 0.18))}


@dataclass
class ProceduralObject:
    """A generated object: its category (a HOPE category name) and its renderable asset."""

    category: str
    asset: MeshAsset


def _atlas_uv(shape: trimesh.Trimesh) -> np.ndarray:
    """(3F, 2) uv of a centred shape projected box-wise: each triangle, by the dominant axis
    and sign of its normal, maps into one cell of the 2 x 3 atlas (+x, -x, +y, -y, +z, -z),
    its in-plane coordinates scaled over the shape's bounding box."""
    tri = np.asarray(shape.vertices)[np.asarray(shape.faces)]           # (F, 3, 3)
    fn = np.asarray(shape.face_normals)
    axis = np.argmax(np.abs(fn), axis=1)
    face_id = 2 * axis + (fn[np.arange(len(fn)), axis] < 0)            # +x, -x, +y, -y, +z, -z
    lo, hi = shape.bounds
    keep = np.array([[2, 1], [0, 2], [0, 1]])[axis]                    # in-plane axes (u, v)
    rows = np.arange(len(tri))[:, None]
    a, b = keep[:, 0][:, None], keep[:, 1][:, None]
    span = np.maximum(hi - lo, 1e-9)
    local_u = np.clip((tri[rows, np.arange(3)[None], a] - lo[a]) / span[a], 0, 1)   # (F, 3)
    local_v = np.clip((tri[rows, np.arange(3)[None], b] - lo[b]) / span[b], 0, 1)
    cells = np.asarray(_BOX_CELLS)[face_id]                            # (F, 2) row, col
    uv = np.stack([(cells[:, 1:2] + local_u) / 3.0, (cells[:, 0:1] + local_v) / 2.0], axis=-1)
    return uv.reshape(-1, 2)


def box_mesh(size_m: np.ndarray) -> trimesh.Trimesh:
    """Box of extents ``size_m`` (3,) metres, centred; each face maps one cell of the 2 x 3 atlas."""
    shape = trimesh.creation.box(extents=np.asarray(size_m, dtype=np.float64))
    return split_mesh(shape, _atlas_uv(shape), np.repeat(shape.face_normals, 3, axis=0))


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


def _fit_box(shape: trimesh.Trimesh, size_m: np.ndarray) -> trimesh.Trimesh:
    """``shape`` scaled per axis to the extents ``size_m`` (3,) metres and centred on its
    bounding box (in place; returned)."""
    shape.apply_scale(np.asarray(size_m, dtype=np.float64) / np.maximum(shape.extents, 1e-9))
    shape.apply_translation(-shape.bounds.mean(axis=0))
    return shape


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
    shape = _revolved(profile, size_m, sections)
    height = float(shape.extents[1])
    y_range = (-height / 2, -height / 2 + cap_from * height)
    return split_mesh(shape, _wrapped_uv(shape, y_range), _cap_normals(shape))


def _revolved(profile: np.ndarray, size_m: np.ndarray, sections: int) -> trimesh.Trimesh:
    """A solid of revolution of the (N, 2) (radius, height) ``profile`` standing along y,
    scaled to the extents ``size_m`` (3,) and centred on its bounding box."""
    return _fit_box(_y_up(trimesh.creation.revolve(profile, sections=sections)), size_m)


def jar_mesh(size_m: np.ndarray, rng: np.random.Generator, sections: int = 32) -> trimesh.Trimesh:
    """A jar along y with extents ``size_m``: a round body, a rounded or square shoulder and a
    screw lid (its top 10-22 % of the height, narrower than the body); metres."""
    lid_h = rng.uniform(0.10, 0.22)
    lid_r = rng.uniform(0.32, 0.48)
    shoulder = rng.uniform(0.0, 0.12)                                  # 0: a square shoulder
    top = 1.0 - lid_h
    pts = [(0.0, 0.0), (0.47, 0.0), (0.5, 0.03), (0.5, top - shoulder)]
    for s in np.linspace(0.3, 1.0, 3) if shoulder > 0 else ():
        pts.append((0.5 - (0.5 - lid_r * 0.95) * s ** 2, top - shoulder + shoulder * s))
    pts += [(lid_r * 0.95, top), (lid_r, top + 0.01), (lid_r, 0.985), (lid_r - 0.02, 1.0), (0.0, 1.0)]
    shape = _revolved(np.array(pts), size_m, sections)
    height = float(shape.extents[1])
    y_range = (-height / 2, -height / 2 + top * height)
    return split_mesh(shape, _wrapped_uv(shape, y_range), _cap_normals(shape))


def tube_mesh(size_m: np.ndarray, rng: np.random.Generator, sections: int = 32) -> trimesh.Trimesh:
    """A squeeze tube along y with extents ``size_m``: a round cap at the bottom, a body that
    flattens towards a crimped seam at the top (its depth along z shrinks to 5-15 %), which
    has the bottle category's 180° symmetry about y; metres."""
    cap_h = rng.uniform(0.06, 0.12)
    cap_r = rng.uniform(0.45, 0.7)
    pts = [(0.0, 0.0), (0.5 * cap_r, 0.0), (0.5 * cap_r, cap_h), (0.5, cap_h + 0.02)]
    pts += [(0.5, h) for h in np.linspace(cap_h + 0.1, 0.96, 8)] + [(0.5, 1.0), (0.0, 1.0)]
    shape = _y_up(trimesh.creation.revolve(np.array(pts), sections=sections))
    v = np.asarray(shape.vertices).copy()
    body = np.clip((v[:, 1] - (cap_h + 0.02)) / (1.0 - cap_h - 0.02), 0.0, 1.0)
    flat = rng.uniform(0.05, 0.15)
    v[:, 2] *= 1.0 - (1.0 - flat) * body ** 1.3                        # flatten towards the seam
    v[:, 0] *= 1.0 + 0.25 * body ** 2                                  # and widen a little
    shape = _fit_box(trimesh.Trimesh(vertices=v, faces=shape.faces, process=False), size_m)
    height = float(shape.extents[1])
    y_range = (-height / 2 + cap_h * height, height / 2)
    uv = _wrapped_uv(shape, y_range)
    tri_y = np.asarray(shape.vertices)[np.asarray(shape.faces)][..., 1].reshape(-1)
    uv[tri_y < y_range[0]] = (0.5, 1.0 - CAP_ROWS / 2.0)               # the cap: the cap colour
    return split_mesh(shape, uv, corner_normals(shape))


def superquadric_mesh(size_m: np.ndarray, exponents: tuple[float, float],
                      subdivisions: int = 3) -> trimesh.Trimesh:
    """A superellipsoid of extents ``size_m`` (3,) metres: ``exponents`` (e1, e2) near 0 give
    a box, 1 an ellipsoid, in between rounded boxes and pillows; centred, atlas uv."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    d = np.asarray(sphere.vertices)
    e1, e2 = exponents
    lat = np.arcsin(np.clip(d[:, 1], -1, 1))                           # y is the pole
    lon = np.arctan2(d[:, 2], d[:, 0])

    def power(x: np.ndarray, e: float) -> np.ndarray:
        return np.sign(x) * np.abs(x) ** e

    v = np.stack([power(np.cos(lat), e1) * power(np.cos(lon), e2), power(np.sin(lat), e1),
                  power(np.cos(lat), e1) * power(np.sin(lon), e2)], axis=1)
    shape = _fit_box(trimesh.Trimesh(vertices=v, faces=sphere.faces, process=False), size_m)
    return split_mesh(shape, _atlas_uv(shape), corner_normals(shape))


def body_mesh(size_m: np.ndarray, rng: np.random.Generator, subdivisions: int = 3) -> trimesh.Trimesh:
    """An irregular smooth body of extents ``size_m`` (3,) metres: a sphere whose radius is
    bumped by 3-6 random smooth lobes and dents (no symmetry), centred, atlas uv."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    d = np.asarray(sphere.vertices)
    radius = np.ones(len(d))
    for _ in range(int(rng.integers(3, 7))):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        width = rng.uniform(0.3, 0.9)
        radius += rng.uniform(-0.35, 0.6) * np.exp(-np.sum((d - direction) ** 2, axis=1) / width ** 2)
    shape = _fit_box(trimesh.Trimesh(vertices=d * np.clip(radius, 0.3, None)[:, None],
                                     faces=sphere.faces, process=False), size_m)
    return split_mesh(shape, _atlas_uv(shape), corner_normals(shape))


def shape_size(rng: np.random.Generator, shape: str) -> np.ndarray:
    """(3,) extents, metres, of a shape beyond the HOPE categories (:data:`SHAPE_SIZES`, each
    range sampled log-uniformly); a jar and a tube take a depth equal to their width."""
    ranges = SHAPE_SIZES[shape]
    size = np.empty(3)
    for i, r in enumerate(ranges):
        if r is not None:
            size[i] = np.exp(rng.uniform(np.log(r[0]), np.log(r[1])))
    if ranges[2] is None:
        size[2] = size[0]
    return size


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


def _shape_mesh(rng: np.random.Generator, shape: str, size: np.ndarray) -> trimesh.Trimesh:
    """The mesh of ``shape`` with extents ``size`` (metres)."""
    if shape == "cuboid":
        return box_mesh(size)
    if shape == "cylinder":
        return can_mesh(size)
    if shape == "bottle":
        return bottle_mesh(size, rng)
    if shape == "jar":
        return jar_mesh(size, rng)
    if shape == "tube":
        return tube_mesh(size, rng)
    if shape == "pouch":
        return superquadric_mesh(size, (rng.uniform(0.15, 0.35), rng.uniform(0.1, 0.25)))
    if shape == "rounded_box":
        return superquadric_mesh(size, (rng.uniform(0.08, 0.3), rng.uniform(0.08, 0.3)))
    return body_mesh(size, rng)


def sample_object(rng: np.random.Generator, weights: dict[str, float], size_jitter: float = 0.25,
                  texture_px: int = 256, name: str = "Object",
                  scale: tuple[float, float] = (1.0, 1.0)) -> ProceduralObject:
    """A random object of a shape drawn with ``weights`` (:data:`SHAPE_LABELS` name -> weight).

    Args:
        rng: the object's random stream.
        weights: e.g. ``{"cuboid": 1, "cylinder": 1, "bottle": 1}`` (the HOPE categories) or
            any of :data:`SHAPE_LABELS`.
        size_jitter: relative extent jitter of the HOPE categories (see :func:`sample_size`).
        texture_px: height of the texture sheet (width: twice that for round shapes, 1.5x else).
        name: the asset's (annotation class) name.
        scale: range of a log-uniform factor on the whole object's size ((1, 1): none, and no
            number drawn, so the objects of earlier configs are unchanged).

    Returns:
        The object; its ``category`` is the HOPE category whose labels it takes.
    """
    shapes = [c for c in (*CATEGORIES, *(k for k in SHAPE_LABELS if k not in CATEGORIES))
              if float(weights.get(c, 0.0)) > 0]                       # HOPE order first: seeds keep their objects
    p = np.array([float(weights[c]) for c in shapes])
    shape = shapes[int(rng.choice(len(shapes), p=p / p.sum()))]
    size = sample_size(rng, shape, size_jitter) if shape in CATEGORIES else shape_size(rng, shape)
    mesh = _shape_mesh(rng, shape, size)
    round_shape = SHAPE_LABELS[shape] != "cuboid"
    texture = label_image(rng, texture_px, int((2 if round_shape else 1.5) * texture_px))
    if round_shape:
        cap = (random_color(rng) * 255).astype(np.uint8)
        texture[: int(np.ceil(CAP_ROWS * texture_px))] = cap
    if tuple(scale) != (1.0, 1.0):
        mesh.apply_scale(float(np.exp(rng.uniform(np.log(scale[0]), np.log(scale[1])))))
    cuboid_size, cuboid_center, bound = bounding_shape(mesh)
    asset = MeshAsset(path=Path(f"<procedural {shape}>"), name=name, mesh=mesh, texture=texture,
                      colors=None, cuboid_size=cuboid_size, cuboid_center=cuboid_center, shape=bound,
                      cacheable=False)
    return ProceduralObject(category=SHAPE_LABELS[shape], asset=asset)
