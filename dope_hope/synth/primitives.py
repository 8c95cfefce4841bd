"""Procedural distractor shapes: boxes, cylinders, spheres, capsules and bottles with texture
coordinates.

trimesh builds the shapes; it gives them no uv, so each triangle gets a box (tri-planar)
projection: the two coordinates across the dominant axis of its normal, in tiles of
``tile_m`` metres. Vertices are split per triangle for that, and the smooth normals of the
shared-vertex mesh are carried over so that curved shapes stay smooth.
"""
from __future__ import annotations

import numpy as np
import trimesh

#: Primitive kinds understood by :func:`make_primitive`.
PRIMITIVE_KINDS = ("box", "cylinder", "sphere", "capsule", "bottle")

#: Bottle profile: (radius, z) as fractions of (body radius, height), bottom to top: a body,
#: a shoulder and a neck of 0.4 radii; revolved about z and centred on its bounding box.
BOTTLE_PROFILE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.62], [0.75, 0.74], [0.4, 0.8],
                           [0.4, 1.0], [0.0, 1.0]])


def primitive_shape(kind: str, dims: np.ndarray) -> trimesh.Trimesh:
    """The untextured shape, centred at the origin, metres.

    dims: box (3,) extents; cylinder and bottle (radius, height); sphere (radius,); capsule
    (radius, height of the straight part).
    """
    if kind == "box":
        return trimesh.creation.box(extents=dims)
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=float(dims[0]), height=float(dims[1]), sections=24)
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=2, radius=float(dims[0]))
    if kind == "capsule":
        return trimesh.creation.capsule(height=float(dims[1]), radius=float(dims[0]), count=[16, 12])
    if kind == "bottle":
        profile = BOTTLE_PROFILE * np.array([float(dims[0]), float(dims[1])]) - [0.0, float(dims[1]) / 2.0]
        return trimesh.creation.revolve(profile, sections=24)
    raise ValueError(f"unknown primitive kind {kind!r}; expected one of {PRIMITIVE_KINDS}")


def sample_dims(rng: np.random.Generator, kind: str, size_m: tuple[float, float]) -> np.ndarray:
    """Random dimensions for ``kind`` with every extent in ``size_m`` (metres)."""
    lo, hi = size_m
    if kind == "box":
        return rng.uniform(lo, hi, size=3)
    if kind in ("cylinder", "capsule", "bottle"):
        return np.array([rng.uniform(lo, hi) / 2.0, rng.uniform(lo, hi)])
    return np.array([rng.uniform(lo, hi) / 2.0])


def dims_for_radius(kind: str, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Dimensions whose bounding sphere (about the centre) has roughly ``radius`` metres."""
    if kind == "box":
        d = rng.uniform(0.5, 1.0, size=3)
        return d / np.linalg.norm(d) * 2.0 * radius
    if kind in ("cylinder", "bottle"):
        a = rng.uniform(0.2, 1.2)  # height / diameter
        r = radius / np.hypot(1.0, a)
        return np.array([r, 2.0 * r * a])
    if kind == "capsule":
        r = radius * rng.uniform(0.4, 0.8)
        return np.array([r, 2.0 * (radius - r)])
    return np.array([radius])


def box_uv(vertices: np.ndarray, faces: np.ndarray, tile_m: float) -> np.ndarray:
    """(3F, 2) tri-planar texture coordinates, one per triangle corner (the order of
    :func:`split_mesh`'s vertices).

    Args:
        vertices: (V, 3) metres; faces: (F, 3); tile_m: metres per texture repeat.
    """
    tri = vertices[faces]                                   # (F, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    axis = np.argmax(np.abs(n), axis=1)                     # dominant normal axis per face
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]         # the two in-plane axes
    uv = np.take_along_axis(tri, keep[:, None, :].repeat(3, axis=1), axis=2) / tile_m
    return uv.reshape(-1, 2)


def corner_normals(shape: trimesh.Trimesh, flat_axis: int | None = None,
                   flat_cos: float = 0.99) -> np.ndarray:
    """(3F, 3) normals per triangle corner: the shape's smooth vertex normals, except on the
    faces whose normal lies along axis ``flat_axis`` (|component| > ``flat_cos``: caps), which
    keep their flat face normal."""
    normals = np.asarray(shape.vertex_normals)[np.asarray(shape.faces)].reshape(-1, 3)
    if flat_axis is not None:
        fn = np.repeat(shape.face_normals, 3, axis=0)
        cap = np.abs(fn[:, flat_axis]) > flat_cos
        normals[cap] = fn[cap]
    return normals


def split_mesh(shape: trimesh.Trimesh, uv: np.ndarray, normals: np.ndarray) -> trimesh.Trimesh:
    """``shape`` with its vertices split per triangle (so that uv and normals can differ on
    each side of an edge): (3F, 2) ``uv`` and (3F, 3) ``normals`` are given per corner."""
    positions = np.asarray(shape.vertices)[np.asarray(shape.faces)].reshape(-1, 3)
    faces = np.arange(len(positions)).reshape(-1, 3)
    return trimesh.Trimesh(vertices=positions, faces=faces, vertex_normals=normals, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv))


def make_primitive(kind: str, dims: np.ndarray, tile_m: float = 0.1) -> trimesh.Trimesh:
    """A primitive with smooth normals (flat on box faces and cylinder / bottle caps) and uv
    coordinates.

    Returns:
        trimesh.Trimesh in metres, centred at the origin; ``visual`` is TextureVisuals with uv
        (the image is attached by the material, see materials.py); vertex normals set.
    """
    shape = primitive_shape(kind, np.asarray(dims, dtype=np.float64))
    uv = box_uv(np.asarray(shape.vertices), np.asarray(shape.faces), tile_m)
    if kind == "box":
        normals = np.repeat(shape.face_normals, 3, axis=0)
    else:  # cylinders and bottles stand along z: flat caps
        normals = corner_normals(shape, flat_axis=2 if kind in ("cylinder", "bottle") else None)
    return split_mesh(shape, uv, normals)
