"""Turning a detection's pose about its object, and the turns of a trained model's poses by
the texture.

:func:`turn_detection` replaces a detection's pose by a rotation ``R S`` of it about the
cuboid centre and keeps its keypoints in the corner order of the new pose.

:class:`TrainedTurns` (``appearance.trained_turns``, off by default): a trained model places
a can's or bottle's axis well and the turn about it less well (the 30-minute Ketchup model of
``bench/e2e_accuracy.py``: of its held-out poses within 10 cm but not 2 cm of a bottle, most
are off by 45-90° about the bottle's axis). For each detection of an object whose mesh is
textured and whose box has a long axis (:func:`~dope_hope.symmetry.cuboid.long_axis`: the
axis of a can, a bottle, a tall box), the appearance check
(:class:`~dope_hope.inference.appearance.AppearanceCheck`) compares the pose and its turns of
``appearance.spin_step_deg`` about that axis, upright only (the network tells up from down),
and the one whose render the network's first layers find most like the image replaces it;
then that pose tilted and turned by ``appearance.trained_refine_deg`` (8°) either way about
each mesh axis is compared once more the same way (the 30° turns leave up to 15° about the
axis, and the network's tilt a few degrees: on the two 30-minute Ketchup models, 51.7 / 49.0 %
within 2 cm with -LS against 50.0 / 48.0 % without this step).
It runs before -LS (which then places the pose kept: a pose 60° off about the axis puts the
depth's surface elsewhere and -LS would move it along the ray for it); with ICP it does not
run (the depth fit places the turn). Its cost: one render per pose, 12 turns at 30° steps and
6 refinements, ~0.17 s a detection on 2 cores (Mesa llvmpipe, a 15,000-face mesh).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.inference.appearance import AppearanceCheck, AppearanceSettings, surface_appearance
from dope_hope.inference.detection import Detection
from dope_hope.inference.object_geometry import ObjectGeometry
from dope_hope.symmetry.cuboid import corner_permutation, long_axis, nearest_cube_rotation


def turn_detection(det: Detection, S: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
    """In place: ``det`` takes the pose (R (3, 3), t (3,) m) = its pose turned by the mesh-frame
    rotation ``S`` (3, 3) about its cuboid centre; its keypoints, their scores and inliers
    follow in the corner order of the nearest quarter turn of ``S`` (corner k of ``R S``
    projects where corner perm[k] of the old pose does). ``projected_2d`` and ``bbox_2d`` are
    the caller's."""
    perm = corner_permutation(nearest_cube_rotation(S))
    det.keypoints_2d, det.keypoint_scores, det.inliers = det.keypoints_2d[perm], det.keypoint_scores[perm], det.inliers[perm]
    det.R, det.t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)


class TrainedTurns:
    """The turns of a trained model's poses about each object's long axis (module docstring).

    Args:
        objects: the predictor's objects; those with a textured mesh and a long axis get a
            check (the others' poses stay as they are: :attr:`skipped` says why).
        settings: the ``appearance`` section (``spin_step_deg``, ``crop_px``, ...).
        features: the network's first layers, (N, H, W, 3) uint8 -> (N, C, h, w)
            (:meth:`~dope_hope.inference.backends.TorchBackend.texture_features`).

    Attributes: checks ({class name: AppearanceCheck}), axes ({class name: (3,) its long
    axis, mesh frame}), refinements ((R, 3, 3) the identity, then the small rotations about
    each mesh axis of ``trained_refine_deg`` either way; the identity alone for 0), skipped
    ({class name: reason}).
    """

    def __init__(self, objects: Sequence[ObjectGeometry], settings: AppearanceSettings,
                 features: Callable[[np.ndarray], np.ndarray]):
        self.checks: dict[str, AppearanceCheck] = {}
        self.axes: dict[str, np.ndarray] = {}
        step = np.radians(settings.trained_refine_deg)
        small = [Rotation.from_rotvec(sign * step * axis).as_matrix() for axis in np.eye(3) for sign in (-1.0, 1.0)]
        self.refinements = np.stack([np.eye(3)] + (small if step > 0 else []))
        self.skipped: dict[str, str] = {}
        for obj in objects:
            axis = long_axis(obj.cuboid_size_m)
            surface = surface_appearance(obj.mesh) if obj.mesh is not None else "none"
            if surface != "textured":
                self.skipped[obj.class_name] = "no textured mesh" if obj.mesh is None else f"its mesh's surface is {surface}"
            elif axis is None:
                self.skipped[obj.class_name] = "its box has no long axis"
            else:
                up = self.axes[obj.class_name] = np.eye(3)[axis]
                self.checks[obj.class_name] = AppearanceCheck(
                    obj.mesh, np.eye(3)[None], obj.cuboid_center_m, settings, up=up, surface=surface,
                    features=features, upside_down=False)

    def turn(self, det: Detection, rgb: np.ndarray, K: np.ndarray) -> None:
        """In place: ``det`` turned to the pose its render finds most like the (H, W, 3) uint8
        image with intrinsics K (3, 3), where its object has a check; ``texture_turn_deg``
        (the turn applied about the long axis, 0 for none) and ``appearance_score`` (the colour
        score's best) set. ``projected_2d`` and ``bbox_2d`` are the caller's."""
        check = self.checks.get(det.class_name)
        if check is None:
            return
        res = check.compare(rgb, K, det.R, det.t)
        det.appearance_score = res.score
        S = check.rotations[res.best]
        det.texture_turn_deg = float(np.degrees(Rotation.from_matrix(S).as_rotvec() @ self.axes[det.class_name])) % 360.0
        if res.best != 0:
            turn_detection(det, S, res.R, res.t)
        if len(self.refinements) > 1:
            fine = check.compare(rgb, K, det.R, det.t, rotations=self.refinements)
            if fine.best != 0:
                turn_detection(det, self.refinements[fine.best], fine.R, fine.t)

    def close(self) -> None:
        """Free the checks' GL contexts."""
        for check in self.checks.values():
            check.close()
        self.checks.clear()
