"""Object meshes: HOPE textured OBJ (centimetres) and BOP PLY (millimetres), loaded in metres.

Every mesh leaves this module in metres, as one ``trimesh.Trimesh`` (multi-part files are
concatenated) with its texture kept (``TextureVisuals``: per-vertex uv + material image) so
that pyrender can render it. Also the derived quantities other modules need: a deterministic
surface point sample (ADD-style metrics), the axis-aligned cuboid and the diameter.
:func:`read_ply` is the exception: the vertices (and triangles) of a PLY file exactly as
stored (file units, file order), which is what the BOP toolkit computes its errors on.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.distance import pdist

from dope_hope.errors import ConfigError, InputFileError
from dope_hope.geometry import UNIT_SCALE, unit_hint
from dope_hope.io.paths import require_file

#: File unit assumed when ``units`` is not given (HOPE OBJ: cm; BOP PLY: mm).
DEFAULT_UNITS: dict[str, str] = {".obj": "cm", ".ply": "mm"}


#: The largest side of an object's box, metres, that is plausible: outside this range the
#: file's unit is almost surely not the one it was read in (a 5 cm can in metres read as
#: centimetres is 0.5 mm; in millimetres read as centimetres, 5 m).
PLAUSIBLE_SIZE_M = (0.005, 5.0)


def likely_unit(size_m: np.ndarray, units: str) -> str | None:
    """The unit in which a mesh read in ``units`` with box ``size_m`` (3,) m has the most
    plausible size (its largest side closest to 10 cm within :data:`PLAUSIBLE_SIZE_M`), or
    None when no unit makes it plausible."""
    largest_file = float(np.max(size_m)) / UNIT_SCALE[units]
    lo, hi = PLAUSIBLE_SIZE_M
    fits = [u for u in UNIT_SCALE if lo <= largest_file * UNIT_SCALE[u] <= hi]
    return min(fits, key=lambda u: abs(np.log10(largest_file * UNIT_SCALE[u] / 0.1)), default=None)


def check_plausible_size(size_m: np.ndarray, units: str, source: str | os.PathLike) -> None:
    """InputFileError naming ``source`` when a mesh box ``size_m`` (3,) m, read in ``units``,
    is implausible for an object (largest side outside :data:`PLAUSIBLE_SIZE_M`), with the
    unit the file is likely in. The one rule of a mesh's unit; :func:`load_mesh` applies it."""
    size = np.asarray(size_m, dtype=np.float64)
    largest = float(np.max(size))
    lo, hi = PLAUSIBLE_SIZE_M
    if lo <= largest <= hi:
        return
    shown = " x ".join(f"{v / UNIT_SCALE[units]:.4g}" for v in size)
    what = f"small for an object (largest side under {lo * 1000:g} mm)" if largest < lo else \
        f"large for an object (largest side over {hi:g} m)"
    likely = likely_unit(size, units)
    hint = (f"the file is likely in {likely}: {unit_hint(likely)}" if likely is not None
            else "no unit (m, cm, mm) makes it an object's size")
    raise InputFileError(source, f"mesh box {shown} {units} (read in {units}) is too {what}; {hint}")


def check_solid_box(size_m: np.ndarray, units: str, source: str | os.PathLike) -> None:
    """InputFileError naming ``source`` when a mesh box ``size_m`` (3,) m has a side of zero
    (a flat mesh): an object's cuboid needs three positive sides."""
    size = np.asarray(size_m, dtype=np.float64)
    if np.all(size > 0):
        return
    shown = " x ".join(f"{v / UNIT_SCALE[units]:.4g}" for v in size)
    flat = ", ".join("xyz"[k] for k in np.flatnonzero(size <= 0))
    raise InputFileError(source, f"mesh is flat: its box is {shown} {units}, zero along {flat}; an object's "
                                 "cuboid needs three positive sides")


def file_vertices(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Every vertex of a mesh file as stored (file units, NaN where an OBJ coordinate is not a
    number), read without trimesh, whose loader drops a non-finite vertex and its faces:
    (vertices (N, 3) float64, the OBJ line number of each (N,) or None for other formats).
    A file that cannot be read this way gives (0, 3) vertices: load_mesh's trimesh load says why."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".obj":
            rows, lines = [], []
            with open(path, "rb") as f:
                for number, line in enumerate(f, 1):
                    if line[:2] in (b"v ", b"v\t"):
                        try:
                            rows.append([float(v) for v in line.split()[1:4]])
                        except ValueError:
                            rows.append([np.nan] * 3)
                        lines.append(number)
            return np.asarray(rows, dtype=np.float64).reshape(-1, 3), np.asarray(lines, dtype=np.int64)
        if suffix == ".ply":
            return read_ply(path)[0], None
        return np.asarray(trimesh.load(str(path), force="mesh", process=False).vertices, dtype=np.float64), None
    except Exception:  # noqa: BLE001 - an unreadable file: load_mesh's trimesh load says why
        return np.zeros((0, 3)), None


def first_nonfinite_vertex(path: str | os.PathLike) -> str | None:
    """Where a mesh file holds a vertex coordinate that is not a finite number ("line 12
    ('v nan 1 2')" of an OBJ, "vertex 7 ([...])" of a PLY or another format), else None."""
    vertices, lines = file_vertices(path)
    bad = np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))
    if not len(bad):
        return None
    if lines is None:
        return f"vertex {int(bad[0])} ({np.round(vertices[bad[0]], 6).tolist()})"
    with open(path, "rb") as f:
        text = f.read().splitlines()[int(lines[bad[0]]) - 1].strip().decode(errors="replace")[:60]
    return f"line {int(lines[bad[0]])} ({text!r})"


def check_finite_vertices(path: str | os.PathLike) -> None:
    """InputFileError naming the line (OBJ) or index of a vertex of ``path`` that is not a
    finite number (:func:`first_nonfinite_vertex`); the one rule, which :func:`load_mesh` applies."""
    bad_vertex = first_nonfinite_vertex(path)
    if bad_vertex is not None:
        raise InputFileError(path, f"{bad_vertex} is not a finite number (a mesh with a hole where it was "
                                   "would be read)")


def load_mesh(path: str | os.PathLike, units: str | None = None, check_size: bool = True) -> trimesh.Trimesh:
    """Load a mesh file as one ``trimesh.Trimesh`` in metres.

    Args:
        path: ``.obj`` (HOPE textured model, centimetres by default) or ``.ply`` (BOP model,
            millimetres by default); other trimesh formats need ``units``.
        units: unit of the file's coordinates, "m", "cm" or "mm" (overrides the default).
        check_size: refuse a box implausible in ``units`` (:func:`check_plausible_size`).

    Returns:
        The mesh, vertices (V, 3) in metres; texture visuals kept when the file has them.

    Raises:
        InputFileError: missing, unreadable or empty file, an unknown unit, a vertex that is
        not a finite number (its line or index named: trimesh would drop it and its faces), a
        surface of zero area, or (``check_size``) a flat box or a box no object has in that unit.
    """
    path = Path(path)
    if units is None:
        units = DEFAULT_UNITS.get(path.suffix.lower())
        if units is None:
            raise InputFileError(path, f"no default unit for '{path.suffix}' meshes; "
                                       f"pass units= one of {sorted(UNIT_SCALE)}")
    if units not in UNIT_SCALE:
        raise InputFileError(path, f"unknown mesh unit {units!r}; use one of {sorted(UNIT_SCALE)}")
    require_file(path, "mesh file")
    check_finite_vertices(path)
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
    if not loaded.area > 0:
        raise InputFileError(path, f"mesh has no surface: its {len(loaded.faces)} triangle(s) have zero area")
    if check_size:
        check_solid_box(mesh_cuboid(loaded)[0] * UNIT_SCALE[units], units, path)
        check_plausible_size(mesh_cuboid(loaded)[0] * UNIT_SCALE[units], units, path)
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


def _ply_header(path: Path, data: bytes) -> tuple[str, int, list[tuple[str, int, list]]]:
    """(format, body offset, [(element, count, [(name, type code | (count code, item code))])])."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputFileError(path, "not a PLY file (no 'ply' ... 'end_header' header)")
    nl = data.find(b"\n", end)
    body = nl + 1 if nl >= 0 else len(data)
    fmt, elements = "", []
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        w = line.split()
        if len(w) >= 2 and w[0] == "format":
            fmt = w[1]
        elif len(w) >= 3 and w[0] == "element":
            if not w[2].isdigit():
                raise InputFileError(path, f"bad element count in {line.strip()!r}")
            elements.append((w[1], int(w[2]), []))
        elif w and w[0] == "property" and elements:
            known = len(w) == 3 and w[1] in _PLY_TYPES or (
                len(w) == 5 and w[1] == "list" and w[2] in _PLY_TYPES and w[3] in _PLY_TYPES)
            if not known:
                raise InputFileError(path, f"unsupported property {line.strip()!r}")
            kind = _PLY_TYPES[w[1]] if len(w) == 3 else (_PLY_TYPES[w[2]], _PLY_TYPES[w[3]])
            elements[-1][2].append((w[-1], kind))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputFileError(path, f"unknown PLY format {fmt!r}")
    return fmt, body, elements


#: Items of the face list properties the BOP toolkit reads (triangles only).
_PLY_FACE_LISTS = {"vertex_indices": 3, "vertex_index": 3, "texcoord": 6}


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Every vertex (and triangle) of a PLY file, in file order and file units, as the BOP
    toolkit's ``inout.load_ply`` reads them.

    ASCII coordinates are parsed as float64 from the text, binary ones widened exactly from
    their stored type. Unlike :func:`load_mesh` nothing is merged, dropped, reordered or
    scaled, and a point cloud (no ``face`` element) is fine.

    Args:
        path: the ``.ply`` file (ascii, binary_little_endian or binary_big_endian) with the
            ``vertex`` element first, as in every BOP model; faces must be triangles.

    Returns:
        (vertices (N, 3) float64 x, y, z in file units (BOP models: millimetres), faces
        (M, 3) int64 vertex indices or None when the file has no faces).

    Raises:
        InputFileError: missing file, not a PLY, no x/y/z vertex properties, an element
        before ``vertex``, a face that is not a triangle, or fewer items than announced.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "PLY file not found")
    data = path.read_bytes()
    fmt, body, elements = _ply_header(path, data)
    if not elements or elements[0][0] != "vertex":
        raise InputFileError(path, "the first element must be 'vertex'")
    _, n_vert, vprops = elements[0]
    names = [n for n, _ in vprops]
    if not {"x", "y", "z"} <= set(names) or any(isinstance(k, tuple) for _, k in vprops):
        raise InputFileError(path, "vertex element needs x, y, z and no list properties")
    face = elements[1] if len(elements) > 1 and elements[1][0] == "face" else None
    fprops = face[2] if face else []
    if face and not any(n in ("vertex_indices", "vertex_index") for n, _ in fprops):
        raise InputFileError(path, "face element without vertex_indices")
    for n, k in fprops:
        if isinstance(k, tuple) and n not in _PLY_FACE_LISTS:
            raise InputFileError(path, f"unsupported face list property {n!r}")
    layout = _PlyLayout(body, n_vert, vprops, [names.index(a) for a in "xyz"], face[1] if face else 0, fprops)
    if fmt == "ascii":
        return _read_ply_ascii(path, data, layout)
    return _read_ply_binary(path, data, layout, "<" if fmt == "binary_little_endian" else ">")


@dataclass(frozen=True)
class _PlyLayout:
    """What a PLY header announces: body offset, vertex count and properties, the x/y/z
    columns, face count (0: no faces) and face properties."""

    body: int
    n_vert: int
    vprops: list
    cols: list[int]
    n_face: int
    fprops: list

    def face_index_property(self) -> int:
        return next(i for i, (n, _) in enumerate(self.fprops) if n in ("vertex_indices", "vertex_index"))


def _read_ply_ascii(path: Path, data: bytes, ply: _PlyLayout) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`read_ply` of an ascii body: coordinates parsed as float64 from the text."""
    lines = data[ply.body:].decode("ascii", errors="replace").splitlines()
    rows = [ln.split() for ln in lines[:ply.n_vert]]
    if len(rows) < ply.n_vert or any(len(r) < len(ply.vprops) for r in rows):
        raise InputFileError(path, f"expected {ply.n_vert} vertex lines of {len(ply.vprops)} values")
    try:
        verts = np.array([[float(r[c]) for c in ply.cols] for r in rows], dtype=np.float64)
        faces = None
        if ply.n_face:
            frows = [ln.split() for ln in lines[ply.n_vert:ply.n_vert + ply.n_face]]
            if len(frows) < ply.n_face:
                raise InputFileError(path, f"expected {ply.n_face} face lines")
            idx = ply.face_index_property()
            offset = sum(1 + _PLY_FACE_LISTS[n] if isinstance(k, tuple) else 1 for n, k in ply.fprops[:idx])
            if any(len(r) < offset + 4 or int(r[offset]) != 3 for r in frows):
                raise InputFileError(path, "only triangular faces are supported")
            faces = np.array([[int(v) for v in r[offset + 1:offset + 4]] for r in frows], dtype=np.int64)
    except ValueError as exc:
        raise InputFileError(path, f"not a number ({exc})") from None
    return verts.reshape(ply.n_vert, 3), faces


def _read_ply_binary(path: Path, data: bytes, ply: _PlyLayout, order: str) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`read_ply` of a binary body (``order``: "<" or ">"): coordinates widened exactly."""
    vdtype = np.dtype([(f"p{k}", order + t) for k, (_, t) in enumerate(ply.vprops)])
    if len(data) - ply.body < ply.n_vert * vdtype.itemsize:
        raise InputFileError(path, f"file ends before its {ply.n_vert} vertices")
    v = np.frombuffer(data, dtype=vdtype, count=ply.n_vert, offset=ply.body)
    verts = np.stack([v[f"p{c}"].astype(np.float64) for c in ply.cols], axis=1).reshape(ply.n_vert, 3)
    if not ply.n_face:
        return verts, None
    fields = []
    for k, (n, kind) in enumerate(ply.fprops):
        if isinstance(kind, tuple):
            fields += [(f"n{k}", order + kind[0]), (f"l{k}", order + kind[1], (_PLY_FACE_LISTS[n],))]
        else:
            fields.append((f"s{k}", order + kind))
    fdtype = np.dtype(fields)
    start = ply.body + ply.n_vert * vdtype.itemsize
    if len(data) - start < ply.n_face * fdtype.itemsize:
        raise InputFileError(path, f"file ends before its {ply.n_face} triangles (or a face is "
                                   f"not a triangle)")
    f = np.frombuffer(data, dtype=fdtype, count=ply.n_face, offset=start)
    for k, (n, kind) in enumerate(ply.fprops):
        if isinstance(kind, tuple) and np.any(f[f"n{k}"] != _PLY_FACE_LISTS[n]):
            raise InputFileError(path, "only triangular faces are supported")
    return verts, f[f"l{ply.face_index_property()}"].astype(np.int64)


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
    """Evenly spread surface points: farthest-point subsample of a dense surface sample (of
    the points themselves for a point cloud, e.g. ``trimesh.PointCloud``).

    Args:
        mesh: mesh (or point cloud) in metres.
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
    if len(getattr(mesh, "faces", ())) == 0:  # a point cloud: spread over its points
        if return_normals:
            raise ValueError("a point cloud has no face normals")
        pts = np.asarray(mesh.vertices, dtype=np.float64)
        return pts if n >= len(pts) else pts[_farthest_point_indices(pts, n)]
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


#: A mesh's box may differ from the object's known cuboid by at most this factor per extent.
MESH_SIZE_TOLERANCE = 1.25


def check_mesh_box(mesh_size: np.ndarray, expected_size: np.ndarray, source: str, class_name: str,
                   reference: str, any_axis_order: bool = False, units: str | None = None) -> None:
    """ConfigError unless a mesh's box (3,) m matches the object's known cuboid (3,) m within
    MESH_SIZE_TOLERANCE per extent: a wrong mesh or wrong --mesh-units would silently change
    every pose or error computed with it.

    Args:
        source: the mesh, for the message; reference: where ``expected_size`` comes from
            ("the model's cuboid", "the cuboid the dataset records", ...).
        any_axis_order: compare the sorted extents (a reference whose axes may be another
            frame's, e.g. the catalog's against a BOP model).
        units: the unit the mesh file was read in: a box off by a factor of 10, 100 or 1000
            then names the unit the file is likely in.
    """
    size = np.asarray(mesh_size, dtype=np.float64)
    expected = np.asarray(expected_size, dtype=np.float64)
    ratio = np.sort(size) / np.sort(expected) if any_axis_order else size / expected
    if np.any(ratio > MESH_SIZE_TOLERANCE) or np.any(ratio < 1.0 / MESH_SIZE_TOLERANCE):
        hint = "wrong object or wrong mesh units?"
        likely = _unit_off_by(ratio, units)
        if likely is not None:
            hint = f"the file is likely in {likely}, not {units}: {unit_hint(likely)}"
        raise ConfigError(
            f"{source}: mesh box {np.round(size * 100, 2).tolist()} cm does not match {reference} "
            f"{np.round(expected * 100, 2).tolist()} cm for {class_name} ({hint})")


def _unit_off_by(ratio: np.ndarray, units: str | None) -> str | None:
    """The unit a mesh read in ``units`` is in when every extent is off by the same factor
    (within MESH_SIZE_TOLERANCE) that is one unit for another (10, 100, 1000 or their
    inverses), else None."""
    if units not in UNIT_SCALE:
        return None
    for other, scale in UNIT_SCALE.items():
        factor = UNIT_SCALE[units] / scale  # a file in `other` read in `units` is `factor` x its size
        if other != units and np.all(np.abs(np.log(np.asarray(ratio) / factor)) <= np.log(MESH_SIZE_TOLERANCE)):
            return other
    return None


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
