"""A new object posed with no training: the pretrained start as a detector of one mesh's cuboid.

The shipped start (``dope_hope/assets/pretrained_lite.pt``, docs/commands/train.md
"Pretraining") learned the cuboid keypoints of thousands of procedural boxes, cans and
bottles. :class:`MeshStartPredictor` runs it on a user's mesh with no training:

- **The cuboid** is the mesh's bounding box (metres; the mesh file's units as
  :func:`dope_hope.io.meshes.load_mesh` reads them), the class the mesh's name
  (:func:`dope_hope.io.models_dir.mesh_class_name`) unless given.
- **Axes.** The start learned the HOPE frame conventions: y is the vertical axis of cans and
  bottles. A mesh whose up axis is another declares it (``up_axis="z"``, ``--up-axis z``; any
  of x, y, z, -x, -y, -z): PnP then fits the same box turned so that this axis is y
  (:meth:`~dope_hope.inference.object_geometry.ObjectGeometry.set_pnp_frame`) and the pose
  comes back in the mesh frame. Nothing is guessed: a mesh whose longest extent lies on
  another axis than the declared one gets a warning (:func:`up_axis_warning`), and so does
  one far outside the sizes the start learned (:func:`size_warning`: a wrong unit, mostly).
- **Pose ambiguity.** The start was trained with category-canonical labels
  (``procedural.canonical_labels``, :mod:`dope_hope.symmetry.labels`): for a symmetric shape
  it reports one of the symmetric-equivalent poses, and for a shape it never saw as such it
  cannot tell apart the poses ``R S`` for the cuboid's own symmetries ``S``
  (:func:`dope_hope.symmetry.cuboid.cuboid_rotations`: 180° about x, y and z for a box of
  three different extents). Each detection lists them (``cuboid_symmetries``) and those the
  appearance left open (``pose_ambiguity``).
- **Appearance** (:mod:`dope_hope.inference.appearance`): a cuboid detector finds every
  object of that shape. Each candidate is compared with the textured mesh rendered at each
  equivalent pose and at each turn about the up axis (``appearance.spin_step_deg``, 30° by
  default: the start learned cans and bottles without a front, so it places the up axis of an
  object it never saw far better than the turn about it); the pose the start's own first
  layers find most like the image is kept (``appearance.texture_features``; which resolves
  the ambiguity when the texture is not symmetric), the score becomes the geometric mean of the
  network's and the appearance's, and candidates whose appearance scores under ``min_score``
  are dropped. A mesh of one colour is compared at the network's pose alone (its colour tells
  look-alikes, not poses); one with no texture and no colours gets no check, and a warning
  (``appearance.enabled: false`` turns the check off for any mesh). -LS runs after it, on
  the pose it kept; with ICP, -LS and ICP run before it, on the network's poses, and it
  compares their equivalent poses alone.
- **Several new objects** (:func:`dope_hope.inference.model_set.build_start_predictors`): one
  predictor each; the start's maps know no object, so :func:`predict_many` computes them once
  per image and working size for all of them (its cache, keyed by :attr:`start_id`).
- **Scales.** The start saw objects of its training crops' sizes; the network runs at each of
  the ``new_object`` section's ``scales`` times the model's working size
  (:class:`~dope_hope.inference.new_object_settings.NewObjectSettings`), the detections are
  pooled as a trained model's several sizes are (:func:`~dope_hope.inference.scales.pool_detections`:
  of two whose 2D boxes overlap by an IoU above ``multiscale.duplicate_iou``, the
  higher-scoring one is kept).
"""
from __future__ import annotations

import os
import warnings
from collections.abc import Collection, Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.assets import PRETRAINED_WEIGHTS
from dope_hope.catalog import HOPE_OBJECTS
from dope_hope.errors import ConfigError
from dope_hope.geometry import value_for_object
from dope_hope.inference.appearance import AppearanceCheck, AppearanceSettings, surface_appearance
from dope_hope.inference.backends import start_backend
from dope_hope.inference.detection import Detection
from dope_hope.inference.object_geometry import MeshFromFile
from dope_hope.inference.predictor import DopePredictor
from dope_hope.inference.scales import pool_detections
from dope_hope.inference.turns import turn_detection
from dope_hope.io.meshes import load_mesh, mesh_cuboid
from dope_hope.io.models_dir import mesh_class_name
from dope_hope.refine.depth import DepthImage
from dope_hope.symmetry.cuboid import cuboid_rotations, describe_rotation, long_axis

#: ``up_axis`` -> the rotation ``A`` (``p_start = A p_mesh``) that turns that axis into +y.
UP_AXES: dict[str, np.ndarray] = {
    "y": np.eye(3),
    "-y": np.diag([1.0, -1.0, -1.0]),
    "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "-z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "x": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    "-x": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}
#: A mesh whose largest side lies this many times beyond the HOPE objects' range of largest sides
#: (the sizes the start learned, before its training frames' 25 % jitter of each extent) gets a
#: warning: a wrong unit, or an object the start cannot find.
LEARNED_SIZE_FACTOR = 2.5


def up_axis_rotation(up_axis: str) -> np.ndarray:
    """(3, 3) ``A`` with ``p_start = A p_mesh``: the declared up axis becomes the start's y;
    ConfigError naming the accepted values for anything else."""
    if up_axis not in UP_AXES:
        raise ConfigError(f"up axis must be one of {', '.join(UP_AXES)}, got {up_axis!r}")
    return UP_AXES[up_axis].copy()


def up_axis_warning(size_m: np.ndarray, up_axis: str, source: str) -> str | None:
    """A warning when the mesh's long axis (:func:`~dope_hope.symmetry.cuboid.long_axis`) is
    another axis than the declared up axis, else None."""
    size = np.asarray(size_m, dtype=np.float64).reshape(3)
    k = long_axis(size)
    if k is None or k == "xyz".index(up_axis[-1]):
        return None
    cm = ", ".join(f"{a} {v * 100:.1f}" for a, v in zip("xyz", size))
    return (f"{source}: the mesh is longest along {'xyz'[k]} ({cm} cm) but its up axis is taken as {up_axis}; "
            f"if {'xyz'[k]} is its vertical axis (a can's or bottle's axis), declare it (--up-axis {'xyz'[k]})")


def size_warning(size_m: np.ndarray, source: str) -> str | None:
    """A warning when the mesh's largest side lies more than :data:`LEARNED_SIZE_FACTOR` times
    outside the largest sides of the HOPE objects (the start's training objects' sizes), else None."""
    largest = float(np.max(size_m))
    sides = [max(o.size) for o in HOPE_OBJECTS]
    lo, hi = min(sides), max(sides)
    if lo / LEARNED_SIZE_FACTOR <= largest <= hi * LEARNED_SIZE_FACTOR:
        return None
    return (f"{source}: the mesh's largest side is {largest * 100:.3g} cm, the start learned objects of "
            f"{lo * 100:.3g}-{hi * 100:.3g} cm: if the file is in another unit than it was read in, "
            "give it (--mesh-units); an object of that size the start is unlikely to find")


class MeshStartPredictor(DopePredictor):
    """The pretrained start as a detector of one mesh's cuboid (module docstring).

    Args:
        mesh: the object's mesh file (textured for the appearance check), or a loaded
            ``trimesh.Trimesh`` in metres with ``class_name``.
        class_name: the reported class (default: the mesh file's, ``mesh_class_name``).
        up_axis: the mesh axis that is the object's vertical axis: x, y (default), z, -x, -y, -z.
        mesh_units: units of the mesh file ("m", "cm", "mm"; default by suffix), or a mapping
            class name -> unit ("" for any other).
        start: the start's weights (default: the shipped ``pretrained_lite.pt``).
        appearance: :class:`~dope_hope.inference.appearance.AppearanceSettings`, or a mapping of
            its fields read over the options' ``appearance`` section (True: that section as it
            is); ``False`` turns the check off (every cuboid of this shape is reported).
        device, threads, options, **overrides: as :class:`DopePredictor` (``min_score``
            applies to the network's pose score; default 0: the appearance decides; the
            ``new_object`` section sets the working sizes, e.g. ``new_object={"scales": (1.0,)}``).

    Attributes beyond DopePredictor's: start (the weights' path), start_id (what tells one
    start's maps from another's: the file and the device), up_axis, symmetries ((S, 3, 3)
    the cuboid's rotations, mesh frame, identity first), symmetry_names, scales, appearance
    (the check or None), warnings (the warnings issued while building).
    """

    def __init__(self, mesh: Any, class_name: str | None = None, up_axis: str = "y",
                 mesh_units: str | Mapping[str, str] | None = None, start: str | os.PathLike | None = None,
                 appearance: AppearanceSettings | Mapping[str, Any] | bool = True,
                 device: str = "cpu", threads: int | None = None,
                 options: Mapping[str, Any] | None = None, **overrides: Any):
        mesh_file = units = None
        if isinstance(mesh, (str, os.PathLike)):
            name = class_name or mesh_class_name(mesh)
            mesh_file, units = Path(mesh), value_for_object(mesh_units, name)
            loaded, source = load_mesh(mesh_file, units=units), str(mesh)
        elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            if not class_name:
                raise ConfigError("class_name: name the object of a loaded mesh (a file names its own)")
            loaded, source, name = mesh, f"<{class_name} mesh>", class_name
        else:
            raise ConfigError(f"mesh: give the object's mesh file or a loaded trimesh.Trimesh, got {type(mesh).__name__}")
        A = up_axis_rotation(up_axis)
        size, center = mesh_cuboid(loaded)
        self.warnings: list[str] = []
        for message in (size_warning(size, source), up_axis_warning(size, up_axis, source)):
            if message is not None:
                self._warn(message)
        self.start = Path(start or PRETRAINED_WEIGHTS)
        backend = start_backend(self.start, name, size, device, threads)
        stat = self.start.stat()
        self.start_id = (str(self.start.resolve()), stat.st_size, stat.st_mtime_ns, device)
        given = {"min_score": 0.0, **dict(options or {}), **overrides}
        if isinstance(given.get("multiscale"), Mapping) and "scales" in given["multiscale"]:
            raise ConfigError("multiscale.scales sets a trained model's working sizes; a new object's are "
                              "new_object.scales")
        super().__init__(backend, mesh=loaded if mesh_file is None else MeshFromFile(loaded, mesh_file, units),
                         options=given)
        self.up_axis = up_axis
        self.scales = self.options.new_object.scales
        self.objects[0].set_pnp_frame(A)
        self.symmetries = cuboid_rotations(size)
        self.symmetry_names = tuple(describe_rotation(S) for S in self.symmetries[1:])
        self.appearance: AppearanceCheck | None = None
        settings = appearance if isinstance(appearance, AppearanceSettings) else self.options.appearance
        if isinstance(appearance, Mapping):
            settings = AppearanceSettings.from_mapping({**asdict(settings), **appearance})
        surface = surface_appearance(loaded) if appearance is not False and settings.enabled else None
        if surface is not None:
            if surface == "none":
                self._warn(f"{source}: the mesh has no texture and no colours, so the appearance check is off: every "
                           "cuboid of its shape is reported (look-alikes too), its pose known up to the cuboid's "
                           "symmetries; a textured mesh (OBJ with its MTL and image, or a PLY with colours) tells them "
                           "apart")
            else:
                up = A.T @ np.array([0.0, 1.0, 0.0])  # the start's y, in the mesh frame
                self.appearance = AppearanceCheck(loaded, self.symmetries, center, settings, up=up, surface=surface,
                                                  features=backend.texture_features)

    def _warn(self, message: str) -> None:
        """Keep ``message`` in :attr:`warnings` and issue it (a UserWarning)."""
        self.warnings.append(message)
        warnings.warn(message, UserWarning, stacklevel=3)

    def describe(self) -> str:
        """One line: what runs, and what the poses are known up to."""
        sym = ", ".join(self.symmetry_names) or "none"
        check = "no appearance check"
        if self.appearance is not None and self.appearance.surface == "uniform":
            check = "the mesh is one colour: the appearance check drops look-alikes of another colour and leaves them open"
        elif self.appearance is not None:
            step = self.appearance.settings.spin_step_deg
            turns = f" and turns of {step:g}° about the up axis" if step > 0 else ""
            check = f"the appearance check picks among them{turns} where the texture tells them apart"
        return (f"{self.class_name}: the pretrained start ({self.start}) as a detector of its "
                f"{' x '.join(f'{v * 100:.1f}' for v in self.cuboid_size_m)} cm cuboid, untrained on it, "
                f"up axis {self.up_axis}; poses known up to the cuboid's symmetries ({sym}); {check}")

    def detect_image(self, rgb: np.ndarray, K: np.ndarray, depth: DepthImage | None,
                     cache: dict[tuple, Any] | None = None, on_maps=None,
                     classes: Collection[str] | None = None) -> list[Detection]:
        """The detections of every scale (the network's maps of each kept in ``cache`` for the
        other new objects of the same start: :attr:`start_id`), checked against the
        appearance, duplicates merged, then the turns of those kept and -LS on ``depth``
        (module docstring); with ICP, -LS and ICP run first, on the network's poses, and the check compares their equivalent poses
        alone (the depth fit places the turn better than a small crop's texture: on the
        held-out Ketchup frames 38.8 % within 2 cm against 35.0 % with the turns first);
        ``on_maps`` sees the maps of the first scale."""
        if classes is not None and self.class_name not in classes:
            return []
        cache = {} if cache is None else cache
        icp_first = self.icp_runs(self.objects[0], depth)
        pooled: list[Detection] = []
        for i, (key, net_input) in enumerate(self.network_inputs(rgb, cache, self.scales)):
            maps_key = ("start maps", self.start_id, *key)  # the start's maps know no object: shared
            if maps_key not in cache:
                cache[maps_key] = self.infer_maps(net_input)
            belief, affinity, net_in = cache[maps_key]
            if on_maps is not None and i == 0:
                on_maps(self, belief, affinity, net_in)
            pooled += self.detections_from_maps(belief, affinity, net_in, K, depth if icp_first else None)
        checked = [self.check_appearance(d, rgb, K, turns=False) for d in pooled]
        kept = pool_detections([d for d in checked if d is not None], self.options.multiscale.duplicate_iou)
        if icp_first:
            return kept  # -LS and ICP ran on the network's poses, before the check
        turns = self.appearance is not None and len(self.appearance.rotations) > self.appearance.n_symmetries
        obj = self.objects[0]
        for det in kept:
            if turns:
                self.check_appearance(det, rgb, K)  # the turns, for the candidates kept
            self.depth_stages(obj, det, depth)
            if depth is not None:
                self.project_detection(obj, det, K, rgb.shape[:2])
        return kept

    def check_appearance(self, det: Detection, rgb: np.ndarray, K: np.ndarray, turns: bool = True) -> Detection | None:
        """``det`` with its best pose, scores and ambiguity (module docstring), or None when its
        appearance scores under the check's ``min_score``; ``turns``: also the turns about the
        up axis (:meth:`detect_image` compares the equivalent poses of every candidate, and
        the turns of those it keeps). A pose turned about the up axis keeps the network's
        keypoints in the corner order of the nearest quarter turn."""
        if np.isnan(det.network_score):
            det.network_score = det.score
        det.cuboid_symmetries = self.symmetry_names
        if self.appearance is None:
            det.pose_ambiguity = self.symmetry_names
            return det
        res = self.appearance.compare(rgb, K, det.R, det.t, turns=turns)
        if res.score < self.appearance.settings.min_score:
            return None
        rotations = self.appearance.rotations
        best = rotations[res.best]
        if self.appearance.surface == "uniform":  # one colour: the pose stays the network's, nothing resolved
            det.pose_ambiguity = self.symmetry_names
        else:
            det.pose_ambiguity = tuple(describe_rotation(best.T @ rotations[k]) for k in res.ambiguous)
        det.appearance_score = res.score
        det.score = float(np.sqrt(max(det.network_score, 0.0) * res.score))
        if res.best != 0:
            turn_detection(det, best, res.R, res.t)
            self.project_detection(self.objects[0], det, K, rgb.shape[:2])
        return det

    def close(self) -> None:
        """Free the appearance check's GL context."""
        super().close()
        if self.appearance is not None:
            self.appearance.close()
