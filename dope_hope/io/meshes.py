"""Object meshes: HOPE textured OBJ (centimetres) and BOP PLY (millimetres), loaded in metres.

Every mesh leaves this module in metres, as one ``trimesh.Trimesh`` (multi-part files are
concatenated) with its texture kept (``TextureVisuals``: per-vertex uv + material image) so
that pyrender can render it. Also the derived quantities other modules need: a deterministic
surface point sample (ADD-style metrics), the axis-aligned cuboid and the diameter.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.distance import pdist

from dope_hope.errors import InputFileError

#: Metres per file unit.
UNIT_SCALE: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: File unit assumed when ``units`` is not given (HOPE OBJ: cm; BOP PLY: mm).
DEFAULT_UNITS: dict[str, str] = {".obj": "cm", ".ply": "mm"}


def load_mesh(path: str | os.PathLike, units: str | None = None) -> trimesh.Trimesh:
    """Load a mesh file as one ``trimesh.Trimesh`` in metres.

    Args:
        path: ``.obj`` (HOPE textured model, centimetres by default) or ``.ply`` (BOP model,
            millimetres by default); other trimesh formats need ``units``.
        units: unit of the file's coordinates, "m", "cm" or "mm" (overrides the default).

    Returns:
        The mesh, vertices (V, 3) in metres; texture visuals kept when the file has them.

    Raises:
        InputFileError: missing, unreadable or empty file, or an unknown unit.
    """
    path = Path(path)
    if units is None:
        units = DEFAULT_UNITS.get(path.suffix.lower())
        if units is None:
            raise InputFileError(path, f"no default unit for '{path.suffix}' meshes; "
                                       f"pass units= one of {sorted(UNIT_SCALE)}")
    if units not in UNIT_SCALE:
        raise InputFileError(path, f"unknown mesh unit {units!r}; use one of {sorted(UNIT_SCALE)}")
    if not path.is_file():
        raise InputFileError(path, "mesh file not found")
    try:
        loaded = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # trimesh raises many types for a corrupt file
        raise InputFileError(path, f"not a readable mesh ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene):  # force="mesh" normally concatenates already
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputFileError(path, "mesh file has no triangles")
    if not np.all(np.isfinite(loaded.vertices)):
        raise InputFileError(path, "mesh has non-finite vertex coordinates")
    if UNIT_SCALE[units] != 1.0:
        loaded.apply_scale(UNIT_SCALE[units])
    loaded.metadata["source_path"] = str(path)
    loaded.metadata["source_units"] = units
    return loaded


def _farthest_point_indices(points: np.ndarray, n: int) -> np.ndarray:
    """Greedy farthest-point sampling, (M, 3) -> (n,) indices.

    Hand-written because none of the installed libraries (scipy, trimesh, OpenCV, torch)
    provides FPS; vectorized over the M candidates, one numpy pass per selected point.
    Starts from the point farthest from the centroid, so the result is deterministic.
    """
    pts = np.asarray(points, dtype=np.float64)
    first = int(np.argmax(np.einsum("ij,ij->i", pts - pts.mean(0), pts - pts.mean(0))))
    chosen = np.empty(n, dtype=np.int64)
    chosen[0] = first
    d2 = np.einsum("ij,ij->i", pts - pts[first], pts - pts[first])
    for i in range(1, n):
        nxt = int(np.argmax(d2))
        chosen[i] = nxt
        diff = pts - pts[nxt]
        np.minimum(d2, np.einsum("ij,ij->i", diff, diff), out=d2)
    return chosen


def sample_surface_points(mesh: trimesh.Trimesh, n: int, seed: int = 0,
                          oversample: int = 20, return_normals: bool = False):
    """Evenly spread surface points: farthest-point subsample of a dense surface sample.

    Args:
        mesh: mesh in metres.
        n: number of points (the HOPE paper's ADD-H uses 500).
        seed: seed of the dense area-weighted sample (same seed -> same points).
        oversample: dense sample size is ``max(oversample * n, 10000)``.
        return_normals: also return the normal of the face each point lies on.

    Returns:
        (n, 3) float64, metres, on the mesh surface; with ``return_normals`` a tuple
        (points, (n, 3) unit face normals).
    """
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    dense_count = max(oversample * n, 10000)
    dense, faces = trimesh.sample.sample_surface(mesh, dense_count, seed=seed)
    dense = np.asarray(dense, dtype=np.float64)
    keep = np.arange(len(dense)) if n >= len(dense) else _farthest_point_indices(dense, n)
    if not return_normals:
        return dense[keep]
    return dense[keep], np.asarray(mesh.face_normals, dtype=np.float64)[faces[keep]]


def mesh_cuboid(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounding box in the mesh frame.

    Returns:
        size (3,) full extents along x, y, z and center (3,), metres.
    """
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    return hi - lo, (hi + lo) / 2.0


def mesh_diameter(mesh: trimesh.Trimesh | np.ndarray) -> float:
    """Largest distance between two vertices (exact: taken over the convex hull's vertices).

    Args:
        mesh: a mesh or an (N, 3) point array, metres.

    Returns:
        Diameter, metres.
    """
    pts = np.asarray(mesh.vertices if hasattr(mesh, "vertices") else mesh, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    try:
        pts = pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):  # flat or degenerate point set: use all points
        pts = np.unique(pts, axis=0)
    return float(pdist(pts).max()) if len(pts) >= 2 else 0.0
