"""ObjectGeometry: one object of a predictor's model: its channel group, its cuboid (mesh frame
and the frame PnP runs in), its optional mesh and the surface points the depth steps use.

A predictor holds one per object it reports (:class:`dope_hope.inference.predictor.DopePredictor`);
each object's detections use its own cuboid, mesh and symmetries.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.catalog import get_object
from dope_hope.errors import ConfigError, UnknownObjectError
from dope_hope.geometry import CUBOID_CORNER_SIGNS, LEGACY_TO_MESH, NUM_KEYPOINTS, cuboid_keypoints
from dope_hope.model.info import ObjectInfo


@dataclass(frozen=True)
class MeshFromFile:
    """A mesh already read from its file: ``mesh`` (``trimesh.Trimesh``, metres), ``path`` and
    the ``units`` it was read in. A predictor that needs the box before it is built (a new
    object's, :class:`~dope_hope.inference.mesh_start.MeshStartPredictor`) hands its mesh so:
    the object keeps the file (its symmetry declarations sit beside it) without reading it twice."""

    mesh: Any
    path: Path
    units: str | None


class ObjectGeometry:
    """One object of a model, as the predictor uses it.

    Args:
        info: the model's :class:`~dope_hope.model.info.ObjectInfo` (class, cuboid, symmetries).
        group: its channel group k (belief [9k, 9k + 9), affinity [16k, 16k + 16)).
        legacy: the model's keypoints are in the legacy frame (official HOPE weights).
        mesh: optional mesh file, loaded ``trimesh.Trimesh`` (metres) or :class:`MeshFromFile`: its box replaces the
            model's cuboid (refused when it differs by more than 25 %) and its surface feeds
            the depth steps.
        mesh_units: units of a mesh file ("m", "cm", "mm"; default by suffix; a
            :class:`MeshFromFile` brings its own).
        ls_points, icp_points: surface points sampled for the line search / ICP (the
            inference options' ``ls_points`` / ``icp_points``).

    Attributes: class_name, group, symmetries (BOP fields, mm, or None), mesh, mesh_file and
    mesh_units (the file it was read from and the unit given for it; None for a loaded mesh),
    cuboid_size_m / cuboid_center_m (mesh frame, m), cuboid_mesh ((9, 3) mesh-frame keypoints,
    current order), cuboid_pnp (the keypoints PnP fits: legacy frame and order for a legacy model),
    pnp_axes (None, or the (3, 3) rotation ``A`` of :meth:`set_pnp_frame`: ``p_pnp = A p_mesh``) and
    pnp_order ((9,) int: mesh-order keypoints are ``keypoints_pnp[pnp_order]``), min_score (the
    pose-score threshold its detections must reach: ``info.min_score``, or None until the
    predictor sets the one it resolves).
    """

    def __init__(self, info: ObjectInfo, group: int, legacy: bool, mesh: Any,
                 mesh_units: str | None, ls_points: int, icp_points: int):
        self.class_name = str(info.class_name)
        self.group = int(group)
        self.symmetries = info.symmetries
        self.min_score: float | None = info.min_score
        self.ls_points, self.icp_points = int(ls_points), int(icp_points)
        self.mesh = None
        if isinstance(mesh, MeshFromFile):
            self.mesh_file, self.mesh_units, mesh = Path(mesh.path), mesh.units, mesh.mesh
        else:
            self.mesh_file = Path(mesh) if isinstance(mesh, (str, os.PathLike)) else None
            self.mesh_units = mesh_units if self.mesh_file is not None else None
        size = np.asarray(info.size_m, dtype=np.float64).reshape(3)
        center = np.zeros(3)
        if mesh is not None:
            self.mesh, size, center = self._load_mesh(mesh, mesh_units, size)
        self.cuboid_size_m = size
        self.cuboid_center_m = center
        self.cuboid_mesh = cuboid_keypoints(size, center)
        if legacy:
            # The same box in the legacy frame (p_legacy = L^T p_mesh), listed in the legacy
            # order: corner k at CUBOID_CORNER_SIGNS[k] * legacy extents / 2.
            size_leg = np.abs(LEGACY_TO_MESH).T @ size
            self.cuboid_pnp = cuboid_keypoints(size_leg, LEGACY_TO_MESH.T @ center)
        else:
            self.cuboid_pnp = self.cuboid_mesh
        self.pnp_axes: np.ndarray | None = None
        self.pnp_order = np.arange(NUM_KEYPOINTS)
        self._model_points: np.ndarray | None = None
        self._bbox_points: np.ndarray | None = None
        self._icp_model: tuple[np.ndarray, np.ndarray] | None = None

    def set_pnp_frame(self, axes: np.ndarray) -> None:
        """Fit PnP in another frame of the same box: ``p_pnp = axes @ p_mesh`` with ``axes`` a
        (3, 3) signed permutation of determinant 1 (a network that learned the object's up
        axis as its y axis: :mod:`dope_hope.inference.mesh_start`). The predictor turns the
        pose back (``R_mesh = R_pnp @ axes``) and lists the keypoints in the mesh frame's order.
        Not for a legacy-frame model."""
        A = np.asarray(axes, dtype=np.float64)
        if A.shape != (3, 3) or not np.allclose(np.abs(A).sum(axis=0), 1) or not np.allclose(np.abs(A).sum(axis=1), 1) \
                or not np.isclose(np.linalg.det(A), 1.0) or not np.allclose(np.abs(A), np.abs(A).round()):
            raise ConfigError(f"{self.class_name}: the PnP frame must be a signed axis permutation of determinant 1")
        self.cuboid_pnp = cuboid_keypoints(np.abs(A) @ self.cuboid_size_m, A @ self.cuboid_center_m)
        signs = CUBOID_CORNER_SIGNS @ A.T  # mesh corner j's signs in the PnP frame
        order = [int(np.flatnonzero(np.all(CUBOID_CORNER_SIGNS == m, axis=1))[0]) for m in signs]
        self.pnp_axes, self.pnp_order = A, np.array(order + [NUM_KEYPOINTS - 1])

    def channels(self, belief: np.ndarray, affinity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """This object's (9, h, w) belief and (16, h, w) affinity out of a model's maps."""
        k = self.group
        return belief[9 * k:9 * k + 9], affinity[16 * k:16 * k + 16]

    def _load_mesh(self, mesh: Any, units: str | None, model_size: np.ndarray):
        from dope_hope.io.meshes import check_mesh_box, load_mesh, mesh_cuboid  # noqa: PLC0415 (meshes (trimesh) only for an object given a mesh)

        source = "<mesh>"
        if isinstance(mesh, (str, os.PathLike)):
            source = str(mesh)
            mesh = load_mesh(mesh, units=units)
        size, center = mesh_cuboid(mesh)
        check_mesh_box(size, model_size, source, self.class_name, "the model's cuboid",
                       units=mesh.metadata.get("source_units"))
        return mesh, size, center

    def surface(self):
        """The mesh, else the cuboid's surface (for a non-box object the box's front face lies
        in front of the real surface: pass the mesh for non-box objects), metres."""
        if self.mesh is not None:
            return self.mesh
        import trimesh  # noqa: PLC0415 (trimesh only for an object given a mesh)

        box = trimesh.creation.box(extents=self.cuboid_size_m)
        box.apply_translation(self.cuboid_center_m)
        return box

    def has_icp_surface(self) -> bool:
        """Whether ICP has a surface to fit (:meth:`check_icp_surface` passes)."""
        try:
            self.check_icp_surface()
        except ConfigError:
            return False
        return True

    def check_icp_surface(self) -> None:
        """Without a mesh ICP fits the cuboid's surface to the depth: right for a box only."""
        if self.mesh is not None:
            return

        try:
            category = get_object(self.class_name).category
        except UnknownObjectError:
            category = "object outside the HOPE catalog"
        if category != "cuboid":
            raise ConfigError(f"ICP for {self.class_name} ({category}) needs its mesh (mesh= / --mesh): "
                              "without one it would fit the cuboid's surface, which is right for boxes only")

    @property
    def model_points(self) -> np.ndarray:
        """(ls_points, 3) mesh-frame surface points for the line search, metres (cached)."""
        if self._model_points is None:
            from dope_hope.io.meshes import sample_surface_points  # noqa: PLC0415 (meshes (trimesh) only for an object given a mesh)

            self._model_points = sample_surface_points(self.surface(), self.ls_points, seed=0)
        return self._model_points

    @property
    def bbox_points(self) -> np.ndarray:
        """(N, 3) mesh-frame points whose projection bounds the object, metres: the mesh's
        convex hull vertices, else the cuboid's 8 corners (cached)."""
        if self._bbox_points is None:
            if self.mesh is not None:
                self._bbox_points = np.asarray(self.mesh.convex_hull.vertices, dtype=np.float64)
            else:
                self._bbox_points = self.cuboid_mesh[:NUM_KEYPOINTS - 1].copy()
        return self._bbox_points

    @property
    def icp_model(self) -> tuple[np.ndarray, np.ndarray]:
        """((icp_points, 3) mesh-frame surface points, metres; their (icp_points, 3) unit
        normals) for ICP (cached)."""
        if self._icp_model is None:
            from dope_hope.io.meshes import sample_surface_points  # noqa: PLC0415 (meshes (trimesh) only for an object given a mesh)

            self.check_icp_surface()
            self._icp_model = sample_surface_points(self.surface(), self.icp_points, seed=0,
                                                    oversample=10, return_normals=True)
        return self._icp_model
