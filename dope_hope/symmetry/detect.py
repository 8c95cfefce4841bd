"""The geometric symmetries of a mesh, found from the mesh itself (BOP's fields, no file needed).

A rigid transform ``T`` (``x' = R (x - c) + c``: a rotation about an axis through the point
``c``) is a **symmetry within tolerance** when the mesh and its transformed copy lie on each
other: the distance from the transformed surface to the surface, both ways (``T`` and
``T^-1``), over :data:`SAMPLE_POINTS` area-weighted surface samples, is on average (the ADD-S
measure) at most ``tolerance.mean_m`` and nowhere (the sampled Hausdorff distance) more than
``tolerance.max_m``. Defaults: 0.8 mm on average and 10 mm at most (:class:`SymmetryTolerance`),
so a can whose opening breaks its turn symmetry by 7 mm on 1 % of its surface is "continuous",
a loaf whose halves differ by 1.2 mm on average is not flipped, and a hexagonal head turned by
90° (10 mm at its corners) is not a 4-fold symmetry. Distances are exact point-to-triangle
distances to the faces of the nearest dense surface samples (``scipy.spatial.cKDTree``), an
upper bound of the true distance, so what is reported holds.

Candidates, about axes through the box centre (the axis-aligned cuboid the labels use: the
mesh frame's x, y, z); for a mesh modelled tilted in its own frame, the principal axes of
its surface through its surface centroid; and, for a surface whose second moments are equal
every way (a regular tetrahedron, cube, octahedron: principal axes say nothing there), the
axes from the surface centroid through the convex hull's vertices (a tetrahedron's 120° turns
about them). :attr:`DetectedSymmetries.axes_tried` says which were tried:

- **continuous** about an axis: all of 12 turns by ``k * 360° / 13`` (k = 1..12; 13 is prime,
  so no n-fold prism with n < 13 passes) are symmetries;
- **discrete** n-fold turns (n in :data:`DISCRETE_ORDERS`: 180° flips, 90° about the axis of a
  square cross-section, 60° of a hexagon, ...), then every product of the turns found (the
  diagonal flips of a square section), each checked again.

The result is what BOP's ``models_info.json`` declares (bop_toolkit ``misc.
get_symmetry_transformations`` reads it): ``symmetries_continuous`` (axis, offset) and
``symmetries_discrete`` (4x4, identity left out; with a continuous axis only the turns it does
not already hold, e.g. a cylinder's one flip about a perpendicular axis). BOP's own tables were
made by hand and consider texture (a visual symmetry); this detection is **geometry only**: a
soda can's label makes it visually asymmetric, which a declaration file beside the mesh states
(it takes precedence: :func:`dope_hope.symmetry.resolve.resolve_symmetries`).
"""
from __future__ import annotations

import hashlib
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from dope_hope.io.meshes import DEFAULT_UNITS, UNIT_SCALE, load_mesh, mesh_cuboid
from dope_hope.io.symmetries import SymmetryDeclaration

#: Surface samples whose distances decide (area-weighted, fixed seed).
SAMPLE_POINTS = 1000
#: Dense surface samples that index the faces near a point.
DENSE_POINTS = 30000
#: Faces of this many nearest dense samples are searched for a point's closest face.
NEAREST_FACES = 8
#: Turns of the continuous test, degrees: k * 360 / 13, k = 1..12.
CONTINUOUS_ANGLES_DEG = tuple(360.0 * k / 13.0 for k in range(1, 13))
#: Orders n of the discrete turns tried about each axis (360° / n).
DISCRETE_ORDERS = (2, 3, 4, 5, 6, 8)
#: Second moments whose smallest is at least this share of the largest are "equal every way".
ISOTROPIC_MOMENTS = 0.98
#: Hull vertices (farthest from the centroid first) whose axes an isotropic surface tries.
HULL_VERTEX_AXES = 16
#: Principal axes closer than this to a box axis are that box axis, degrees.
_SAME_AXIS_DEG = 10.0
_AXIS_NAMES = "xyz"


@dataclass(frozen=True)
class SymmetryTolerance:
    """How far a transformed surface may lie from the surface: on average (ADD-S) and at
    most (sampled Hausdorff distance), metres."""

    mean_m: float = 0.0008
    max_m: float = 0.010

    def __post_init__(self) -> None:
        if not (self.mean_m > 0 and self.max_m >= self.mean_m and math.isfinite(self.max_m)):
            raise ValueError(f"symmetry tolerance needs 0 < mean <= max (finite), got {self}")

    def text(self) -> str:
        return f"mean <= {self.mean_m * 1000:g} mm, max <= {self.max_m * 1000:g} mm"


@dataclass(frozen=True)
class FoundSymmetry:
    """One symmetry found about one axis.

    Attributes:
        axis: (3,) unit axis, mesh frame. center: (3,) a point of the axis, metres.
        order: n of an n-fold turn (2: a 180° flip), 0 for a continuous symmetry.
        mean_m, max_m: the worst mean and largest surface distance over its tested turns, m.
    """

    axis: np.ndarray
    center: np.ndarray
    order: int
    mean_m: float
    max_m: float

    def text(self) -> str:
        """``continuous about z (mean 0.2 mm, max 6.8 mm)``, ``flip about x (...)``, ``6-fold ...``."""
        kind = "continuous" if self.order == 0 else "flip" if self.order == 2 else f"{self.order}-fold turn"
        return f"{kind} about {axis_name(self.axis)} (mean {self.mean_m * 1000:.1f} mm, max {self.max_m * 1000:.1f} mm)"


@dataclass
class DetectedSymmetries:
    """What :func:`detect_symmetries` found.

    Attributes:
        discrete: (D, 4, 4) model-frame transforms, metres, identity NOT included (BOP's
            ``symmetries_discrete``; with a continuous axis only those it does not hold).
        continuous: [(axis (3,), offset (3,) metres)] (BOP's ``symmetries_continuous``).
        found: the symmetries found about the candidate axes (what :meth:`text` reports).
        tolerance: the tolerance used. seconds: time taken. source: the mesh (for reports).
        extra_discrete: discrete transforms beyond the turns ``found`` lists (products of
            them, such as a square section's diagonal flips).
        axes_tried: the candidate axes, in words ("the box axes x, y, z; 4 through the
            convex hull's vertices").
    """

    discrete: np.ndarray
    continuous: list[tuple[np.ndarray, np.ndarray]]
    found: list[FoundSymmetry]
    tolerance: SymmetryTolerance
    seconds: float = 0.0
    source: str = "<mesh>"
    extra_discrete: int = 0
    axes_tried: str = "the box axes x, y, z"

    @property
    def any(self) -> bool:
        return bool(len(self.discrete) or self.continuous)

    def text(self) -> str:
        """One line: ``continuous about z (...), flip about x (...)`` or ``none``."""
        if not self.found:
            return f"none ({self.tolerance.text()})"
        more = f", {self.extra_discrete} more discrete from combining them" if self.extra_discrete else ""
        return ", ".join(f.text() for f in self.found) + more

    def entry(self, units: str = "mm") -> dict[str, Any]:
        """The BOP ``models_info`` fields, lengths in ``units`` ("m", "cm", "mm")."""
        scale = 1.0 / UNIT_SCALE[units]
        out: dict[str, Any] = {}
        if len(self.discrete):
            mats = np.array(self.discrete, dtype=np.float64)
            mats[:, :3, 3] *= scale
            out["symmetries_discrete"] = [[round(float(v), 9) for v in m.reshape(-1)] for m in mats]
        if self.continuous:
            out["symmetries_continuous"] = [
                {"axis": [round(float(v), 9) for v in a], "offset": [round(float(v) * scale, 9) for v in o]}
                for a, o in self.continuous]
        return out

    def declaration(self, units: str = "mm") -> SymmetryDeclaration:
        """The found symmetries as a declaration (lengths in ``units``), as a file would give them."""
        return SymmetryDeclaration(self.entry(units), units,
                                   f"detected from {self.source} ({self.tolerance.text()})")


def axis_name(axis: np.ndarray) -> str:
    """``x``, ``-y`` for a mesh axis, else ``(0.71, 0.71, 0.00)``."""
    a = np.asarray(axis, dtype=np.float64)
    k = int(np.argmax(np.abs(a)))
    if abs(a[k]) > math.cos(math.radians(_SAME_AXIS_DEG)):
        return ("-" if a[k] < 0 else "") + _AXIS_NAMES[k]
    return "(" + ", ".join(f"{v:.2f}" for v in a) + ")"


def _rotation_about(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    return Rotation.from_rotvec(np.radians(angle_deg) * np.asarray(axis, dtype=np.float64)).as_matrix()


def _transform(R: np.ndarray, center: np.ndarray) -> np.ndarray:
    """(4, 4): rotation ``R`` about the point ``center``: ``x' = R (x - c) + c``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = center - R @ center
    return T


class _Surface:
    """A mesh's surface samples and the distance of any point to the surface (metres)."""

    def __init__(self, mesh: Any, seed: int):
        self.triangles = np.asarray(mesh.triangles, dtype=np.float64)
        dense, faces = trimesh.sample.sample_surface(mesh, DENSE_POINTS, seed=seed)
        self.faces = np.asarray(faces)
        self.tree = cKDTree(np.asarray(dense, dtype=np.float64))
        self.points = np.asarray(trimesh.sample.sample_surface(mesh, SAMPLE_POINTS, seed=seed + 1)[0],
                                 dtype=np.float64)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """(N,) distance of each of (N, 3) points to the surface: the nearest of the faces of
        its nearest dense samples (exact point-to-triangle; an upper bound of the distance)."""
        near, idx = self.tree.query(x, k=NEAREST_FACES)
        faces = self.faces[idx].reshape(-1)
        pts = np.repeat(x, NEAREST_FACES, axis=0)
        closest = trimesh.triangles.closest_point(self.triangles[faces], pts)
        d = np.linalg.norm(closest - pts, axis=1).reshape(len(x), NEAREST_FACES).min(axis=1)
        return np.minimum(d, near[:, 0])

    def error(self, T: np.ndarray, tol: SymmetryTolerance) -> tuple[float, float] | None:
        """(mean, max) surface distance of ``T`` both ways, metres; None as soon as one way
        exceeds ``tol``."""
        worst_mean = worst_max = 0.0
        for M in (T, np.linalg.inv(T)):
            d = self.distance(self.points @ M[:3, :3].T + M[:3, 3])
            mean, most = float(d.mean()), float(d.max())
            if mean > tol.mean_m or most > tol.max_m:
                return None
            worst_mean, worst_max = max(worst_mean, mean), max(worst_max, most)
        return worst_mean, worst_max


def _surface_moments(surface: _Surface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centroid (3,), second moments (3,) ascending, principal axes (3, 3) as columns) of the
    surface's area, metres."""
    tri = surface.triangles  # exact area moments: E[x] = s / 3, E[x x^T] = (sum v v^T + s s^T) / 12
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    weight = area / area.sum()
    s = tri.sum(axis=1)
    centroid = weight @ s / 3.0
    second = np.einsum("f,fvi,fvj->ij", weight, tri, tri) / 12.0 + np.einsum("f,fi,fj->ij", weight, s, s) / 12.0
    moments, vecs = np.linalg.eigh(second - np.outer(centroid, centroid))
    return centroid, moments, vecs


def _principal_axes(surface: _Surface) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(unit axis, centre)]: the principal axes of the surface (its area's second moments)
    through its centroid that differ from every box axis (a mesh modelled tilted in its frame)."""
    centroid, _, vecs = _surface_moments(surface)
    out = []
    for v in vecs.T:
        if np.max(np.abs(v)) < math.cos(math.radians(_SAME_AXIS_DEG)):
            out.append((v if v[np.argmax(np.abs(v))] > 0 else -v, centroid))
    return out


def _hull_vertex_axes(mesh: Any, surface: _Surface, tried: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(unit axis, centroid)]: for a surface whose second moments are equal every way, the
    axes from its centroid through the convex hull's vertices (the farthest
    :data:`HULL_VERTEX_AXES` first; one per line, none near an axis in ``tried``); else []."""
    centroid, moments, _ = _surface_moments(surface)
    if moments[0] < ISOTROPIC_MOMENTS * moments[-1]:
        return []
    hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64) - centroid
    far = np.argsort(-np.linalg.norm(hull, axis=1))
    same = math.cos(math.radians(_SAME_AXIS_DEG))
    out: list[tuple[np.ndarray, np.ndarray]] = []
    for v in hull[far[:HULL_VERTEX_AXES]]:
        length = np.linalg.norm(v)
        if length == 0:
            continue
        axis = v / length
        if any(abs(float(axis @ t)) > same for t in tried + [a for a, _ in out]):
            continue
        out.append((axis, centroid))
    return out


def _same_rotation(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.allclose(a[:3, :3], b[:3, :3], atol=1e-4))


def _closure(generators: list[np.ndarray], limit: int = 48) -> list[np.ndarray] | None:
    """The transforms generated by ``generators`` (products of any two, repeated), identity
    first; None beyond ``limit`` (48: the cube's full group)."""
    group = [np.eye(4)]
    frontier = list(generators)
    while frontier:
        new = []
        for T in frontier:
            if not any(_same_rotation(T, G) for G in group):
                group.append(T)
                new.append(T)
                if len(group) > limit:
                    return None
        frontier = [A @ B for A in new for B in group] + [B @ A for A in new for B in group]
    return group


def _turns_about(T: np.ndarray, axis: np.ndarray) -> bool:
    """True when ``T``'s rotation leaves ``axis`` in place (a turn about it, or the identity)."""
    return bool(np.allclose(T[:3, :3] @ axis, axis, atol=1e-4))


def detect_symmetries(mesh: Any, tolerance: SymmetryTolerance | None = None, seed: int = 0,
                      source: str = "<mesh>") -> DetectedSymmetries:
    """The geometric symmetries of a mesh within ``tolerance`` (module docstring).

    Args:
        mesh: ``trimesh.Trimesh`` in metres (with faces).
        tolerance: default :class:`SymmetryTolerance` (0.8 mm mean, 10 mm max).
        seed: seed of the surface samples (same seed, same answer).
        source: the mesh's name in reports.

    Returns:
        :class:`DetectedSymmetries` (model-frame transforms in metres).
    """
    start = time.perf_counter()
    tol = tolerance or SymmetryTolerance()
    if len(getattr(mesh, "faces", ())) == 0:
        raise ValueError(f"{source}: a point cloud has no surface to test symmetries on")
    surface = _Surface(mesh, seed)
    _, box_center = mesh_cuboid(mesh)
    continuous: list[FoundSymmetry] = []
    turns: list[FoundSymmetry] = []
    generators: list[np.ndarray] = []
    for axis in np.eye(3):
        _axis_symmetries(axis, box_center, surface, tol, continuous, turns, generators)
    tried = ["the box axes x, y, z"]
    axes = list(np.eye(3))
    if not continuous and not turns:
        principal = _principal_axes(surface)
        tried += [f"{len(principal)} principal axes"] if principal else []
        for axis, center in principal:
            axes.append(axis)
            _axis_symmetries(axis, center, surface, tol, continuous, turns, generators)
    if not continuous:
        through_hull = _hull_vertex_axes(mesh, surface, axes)
        tried += [f"{len(through_hull)} through the convex hull's vertices"] if through_hull else []
        for axis, center in through_hull:
            _axis_symmetries(axis, center, surface, tol, continuous, turns, generators)
    group = _closure(generators)
    if group is None:  # the turns found do not close into a finite group within tolerance
        group = [np.eye(4)] + generators
    group = [T for T in group[1:] if any(_same_rotation(T, g) for g in generators)
             or surface.error(T, tol) is not None]
    # a continuous axis already holds its own turns; of the turns that flip it, one is enough
    discrete, flips_kept = [], set()
    for T in group:
        if any(_turns_about(T, c.axis) for c in continuous):
            continue
        flipped = tuple(i for i, c in enumerate(continuous) if np.allclose(T[:3, :3] @ c.axis, -c.axis, atol=1e-4))
        if flipped:
            if flipped in flips_kept:
                continue
            flips_kept.add(flipped)
        discrete.append(T)
    # a continuous axis's flips are one flip turned about it: report the first
    turns = [t for i, t in enumerate(turns)
             if not any(abs(float(t.axis @ c.axis)) < 1e-3 and any(abs(float(u.axis @ c.axis)) < 1e-3
                                                                   for u in turns[:i]) for c in continuous)]
    listed = sum(t.order - 1 for t in turns)
    found = continuous + turns
    extra = max(0, len(discrete) - listed) if not continuous else 0
    return DetectedSymmetries(np.array(discrete, dtype=np.float64).reshape(-1, 4, 4),
                              [(c.axis.copy(), c.center.copy()) for c in continuous], found, tol,
                              time.perf_counter() - start, source, extra, "; ".join(tried))


def _worst_error(transforms: list[np.ndarray], surface: _Surface,
                 tol: SymmetryTolerance) -> tuple[float, float] | None:
    """The worst (mean, max) surface distance over ``transforms``; None when one fails."""
    worst_mean = worst_max = 0.0
    for T in transforms:
        err = surface.error(T, tol)
        if err is None:
            return None
        worst_mean, worst_max = max(worst_mean, err[0]), max(worst_max, err[1])
    return worst_mean, worst_max


def _axis_symmetries(axis: np.ndarray, center: np.ndarray, surface: _Surface, tol: SymmetryTolerance,
                     continuous: list[FoundSymmetry], turns: list[FoundSymmetry],
                     generators: list[np.ndarray]) -> None:
    """Test one axis: continuous, else the discrete orders; appends what holds to
    ``continuous`` / ``turns`` and the turns (each order's every power) to ``generators``."""
    if any(abs(float(axis @ c.axis)) > math.cos(math.radians(_SAME_AXIS_DEG)) for c in continuous):
        return
    worst = _worst_error([_transform(_rotation_about(axis, a), center) for a in CONTINUOUS_ANGLES_DEG], surface, tol)
    if worst is not None:
        continuous.append(FoundSymmetry(axis, center, 0, *worst))
        return
    passed: list[tuple[int, tuple[float, float]]] = []
    failed: list[int] = []
    for n in DISCRETE_ORDERS:
        if any(n % m == 0 for m in failed):  # an n-fold turn holds the m-fold ones
            continue
        powers = [_transform(_rotation_about(axis, 360.0 * k / n), center) for k in range(1, n)]
        worst = _worst_error(powers, surface, tol)
        if worst is None:
            failed.append(n)
            continue
        generators.extend(powers)
        passed.append((n, worst))
    if passed:
        turns.append(FoundSymmetry(axis, center, math.lcm(*(n for n, _ in passed)),
                                   max(w[0] for _, w in passed), max(w[1] for _, w in passed)))


_CACHE: dict[tuple[str, str, SymmetryTolerance | None], Any] = {}


def _file_key(path: Path) -> str:
    """The SHA-256 of a file's bytes ("" when it cannot be read: then nothing is cached)."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return ""


def detect_mesh_file_symmetries(path: str | os.PathLike, units: str | None = None,
                                tolerance: SymmetryTolerance | None = None) -> DetectedSymmetries:
    """:func:`detect_symmetries` of a mesh file (``io.meshes.load_mesh``, ``units`` as there),
    cached in this process by the file's SHA-256, unit and tolerance.

    Raises:
        InputFileError: an unreadable mesh. ValueError: a file without faces.
    """
    path = Path(path)
    tol = tolerance or SymmetryTolerance()
    key = (_file_key(path), units or DEFAULT_UNITS.get(path.suffix.lower(), ""), tol)
    if key[0] and key in _CACHE:
        return _CACHE[key]
    found = detect_symmetries(load_mesh(path, units=units), tol, source=str(path))
    if key[0]:
        _CACHE[key] = found
    return found


def mesh_file_size(path: str | os.PathLike, units: str | None = None) -> np.ndarray:
    """(3,) extents of a mesh file's axis-aligned box, metres (cached as above)."""
    path = Path(path)
    key = (_file_key(path), units or DEFAULT_UNITS.get(path.suffix.lower(), ""), None)
    if key[0] and key in _CACHE:
        return _CACHE[key]
    size = mesh_cuboid(load_mesh(path, units=units))[0]
    if key[0]:
        _CACHE[key] = size
    return size
