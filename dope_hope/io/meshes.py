"""Object meshes: HOPE textured OBJ (centimetres) and BOP PLY (millimetres), loaded in metres.

Every mesh leaves this module in metres, as one ``trimesh.Trimesh`` (multi-part files are
concatenated) with its texture kept (``TextureVisuals``: per-vertex uv + material image) so
that pyrender can render it. Also the derived quantities other modules need: a deterministic
surface point sample (ADD-style metrics), the axis-aligned cuboid and the diameter.
:func:`read_ply_vertices` is the exception: the vertices of a PLY file exactly as stored
(file units, file order), which is what the BOP toolkit's errors are computed on.
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


#: PLY scalar types -> numpy type codes (both the PLY 1.0 names and the sized aliases).
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}


def read_ply_vertices(path: str | os.PathLike) -> np.ndarray:
    """Every vertex of a PLY file, in file order and file units, as the BOP toolkit reads them.

    ASCII coordinates are parsed as float64 from the text, binary ones widened exactly from
    their stored type (``inout.load_ply``); faces and other properties are not read, so a
    point cloud (no ``face`` element) is fine. Unlike :func:`load_mesh` nothing is merged,
    dropped, reordered or scaled.

    Args:
        path: the ``.ply`` file (ascii, binary_little_endian or binary_big_endian); the
            ``vertex`` element must come first, as in every BOP model.

    Returns:
        (N, 3) float64 x, y, z, file units (BOP models: millimetres).

    Raises:
        InputFileError: missing file, not a PLY, no x/y/z vertex properties, an element
        before ``vertex``, or fewer vertices than the header announces.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "PLY file not found")
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputFileError(path, "not a PLY file (no 'ply' ... 'end_header' header)")
    body_start = data.index(b"\n", end) + 1 if b"\n" in data[end:] else len(data)
    fmt, count, props, element = None, 0, [], None
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) >= 3:
            if element is None and words[1] != "vertex":
                raise InputFileError(path, f"element {words[1]!r} comes before 'vertex' "
                                           f"(the vertices must be the first element)")
            element = words[1]
            if element == "vertex":
                count = int(words[2]) if words[2].isdigit() else -1
                if count < 0:
                    raise InputFileError(path, f"bad vertex count {words[2]!r}")
        elif words[0] == "property" and element == "vertex":
            if len(words) < 3 or words[1] == "list" or words[1] not in _PLY_TYPES:
                raise InputFileError(path, f"unsupported vertex property {line.strip()!r}")
            props.append((words[2], _PLY_TYPES[words[1]]))
    names = [n for n, _ in props]
    if element is None or not {"x", "y", "z"} <= set(names):
        raise InputFileError(path, "no vertex element with x, y, z properties")
    cols = [names.index(a) for a in "xyz"]
    if fmt == "ascii":
        lines = data[body_start:].decode("ascii", errors="replace").splitlines()
        rows = [ln.split() for ln in lines[:count]]
        if len(rows) < count or any(len(r) < len(props) for r in rows):
            raise InputFileError(path, f"expected {count} vertex lines of {len(props)} values")
        try:
            return np.array([[float(r[c]) for c in cols] for r in rows], dtype=np.float64
                            ).reshape(count, 3)
        except ValueError as exc:
            raise InputFileError(path, f"vertex coordinates: not a number ({exc})") from None
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt or "")
    if order is None:
        raise InputFileError(path, f"unknown PLY format {fmt!r}")
    dtype = np.dtype([(f"p{k}", order + t) for k, (_, t) in enumerate(props)])
    if len(data) - body_start < count * dtype.itemsize:
        raise InputFileError(path, f"file ends before its {count} vertices")
    verts = np.frombuffer(data, dtype=dtype, count=count, offset=body_start)
    return np.stack([verts[f"p{c}"].astype(np.float64) for c in cols], axis=1)


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
