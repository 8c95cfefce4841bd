"""One detection of one object: class, score, mesh-frame pose, keypoints, refinement record.

:meth:`Detection.to_json` writes one record of the predictions JSON-lines format
(:mod:`dope_hope.io.predictions`) that ``dope-hope evaluate`` reads.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dope_hope.geometry import (
    matrix_to_quaternion_xyzw,
)
from dope_hope.io.predictions import prediction_record


# ----------------------------------------------------------------------------- detections
@dataclass
class Detection:
    """One detected object, mesh-frame pose (``x_c = R x + t``).

    class_name: the model's object. score: pose score in [0, 1] (:func:`pose.solve_pnp`).
    R: (3, 3). t: (3,) metres (after the line search when applied).
    keypoints_2d: (9, 2) detected cuboid keypoints, original-image px, current keypoint order
        (geometry.CUBOID_CORNER_SIGNS, then the centre); NaN where not found.
    keypoint_scores: (9,) belief at each keypoint (0 where missing), same order.
    inliers: (9,) bool, keypoints consistent with the pose, same order.
    projected_2d: (9, 2) the cuboid keypoints projected under (R, t), original-image px.
    reprojection_error_px: mean inlier reprojection error, original-image px.
    cuboid_size_m, cuboid_center_m: the mesh-frame box used, metres.
    bbox_2d: (4,) [u_min, v_min, u_max, v_max] 2D box of the object under (R, t), original
        px: the projected mesh (its convex hull's vertices) or, without a mesh, the projected
        cuboid, clipped to the image like the BOP toolkit's ``calc_2d_bbox``; None when it
        misses the image (:func:`dope_hope.geometry.projected_bbox`).
    ls_applied / ls_reason / ls_scale: outcome of the depth line search ("no depth image"
        when none was given).
    icp_applied / icp_reason / icp_fit: outcome of the depth ICP ("not requested" without
        ``icp=True``); icp_fit: soft fraction of the depth points under the object that lie on
        the model surface under the returned pose (1 = all; :func:`dope_hope.refine.icp.icp_refine`;
        NaN when not evaluated).
    pose_ambiguity: None for a detector of the object itself; for a detector of its cuboid
        (:mod:`dope_hope.inference.mesh_start`) the rotations ``S`` (names, mesh frame, about
        the box centre) for which the pose ``R S`` is as likely as ``R``: the cuboid's
        symmetries and turns about the up axis that the appearance check could not tell
        apart (empty: resolved).
    cuboid_symmetries: with pose_ambiguity, all the cuboid's symmetries (names).
    network_score / appearance_score: with pose_ambiguity, the pose score of the maps and
        the appearance check's (:mod:`dope_hope.inference.appearance`); ``score`` is their
        geometric mean. network_score also holds a depth-confirmed pose's own keypoint score.
    depth_confirmed: the pose scored under the object's threshold and the depth confirmed it
        (:mod:`dope_hope.inference.depth_confirm`); ``score`` is then that threshold.
    texture_turn_deg: where ``appearance.trained_turns`` ran (:mod:`dope_hope.inference.turns`),
        the turn about the object's long axis it applied, degrees in [0, 360) (0: the network's
        pose kept), with ``appearance_score`` (its colour score); NaN where it did not run.
    """

    class_name: str
    score: float
    R: np.ndarray
    t: np.ndarray
    keypoints_2d: np.ndarray
    keypoint_scores: np.ndarray
    inliers: np.ndarray
    projected_2d: np.ndarray
    reprojection_error_px: float
    cuboid_size_m: np.ndarray
    cuboid_center_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bbox_2d: np.ndarray | None = None
    ls_applied: bool = False
    ls_reason: str = "no depth image"
    ls_scale: float = 1.0
    icp_applied: bool = False
    icp_reason: str = "not requested"
    icp_fit: float = float("nan")
    pose_ambiguity: tuple[str, ...] | None = None
    cuboid_symmetries: tuple[str, ...] = ()
    network_score: float = float("nan")
    appearance_score: float = float("nan")
    texture_turn_deg: float = float("nan")
    depth_confirmed: bool = False

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """(4,) scalar-last quaternion of R (w >= 0)."""
        return matrix_to_quaternion_xyzw(self.R)

    def to_json(self, image: str | None = None, **extra: Any) -> dict[str, Any]:
        """One record of the predictions JSON-lines format (:mod:`dope_hope.io.predictions`,
        read by :mod:`dope_hope.evaluation`): ``image``, ``class``, ``score``, ``R`` (3x3 rows),
        ``t`` (m), ``ls_applied``, plus ``quaternion_xyzw``, ``ls_reason``, ``ls_scale``,
        ``keypoints_2d`` (9 x [u, v] original px, null where missing), ``keypoint_scores``,
        ``reprojection_error_px``, ``cuboid_size_m``, ``bbox_2d`` ([u_min, v_min, u_max, v_max]
        original px, null when the box misses the image) and, with ICP requested, ``icp_applied``,
        ``icp_reason`` and ``icp_fit``, and for a detector of a cuboid ``pose_ambiguity``,
        ``cuboid_symmetries``, ``network_score`` and ``appearance_score``, and where a trained
        model's pose was turned by its texture ``texture_turn_deg`` and ``appearance_score``,
        and for a pose the depth confirmed ``depth_confirmed`` and ``network_score``, which the
        evaluation ignores.

        ``image`` names the frame (omitted when None: then pass ``scene_id``/``im_id``);
        ``extra`` adds keys (e.g. ``time``, ``scene_id``). The result is strict JSON (no NaN).
        """
        kp = [[None if not math.isfinite(v) else round(float(v), 3) for v in row]
              for row in np.asarray(self.keypoints_2d, dtype=np.float64)]
        rec = prediction_record(
            "" if image is None else image, self.class_name, self.score, self.R, self.t,
            ls_applied=self.ls_applied,
            quaternion_xyzw=[float(v) for v in self.quaternion_xyzw],
            ls_reason=self.ls_reason, ls_scale=float(self.ls_scale), keypoints_2d=kp,
            keypoint_scores=[round(float(v), 4) for v in self.keypoint_scores],
            reprojection_error_px=round(float(self.reprojection_error_px), 4),
            cuboid_size_m=[float(v) for v in self.cuboid_size_m],
            bbox_2d=None if self.bbox_2d is None else [round(float(v), 2) for v in self.bbox_2d], **extra)
        if self.icp_reason != "not requested":
            rec.update(icp_applied=self.icp_applied, icp_reason=self.icp_reason,
                       icp_fit=None if not math.isfinite(self.icp_fit) else round(float(self.icp_fit), 4))
        if self.pose_ambiguity is not None:
            rec.update(pose_ambiguity=list(self.pose_ambiguity), cuboid_symmetries=list(self.cuboid_symmetries),
                       network_score=round(float(self.network_score), 4),
                       appearance_score=round(float(self.appearance_score), 4))
        elif math.isfinite(self.texture_turn_deg):
            rec.update(texture_turn_deg=round(float(self.texture_turn_deg), 2),
                       appearance_score=round(float(self.appearance_score), 4))
        if self.depth_confirmed:
            rec.update(depth_confirmed=True, network_score=round(float(self.network_score), 4))
        if image is None:
            del rec["image"]
        return rec


def box_iou(a: np.ndarray | None, b: np.ndarray | None) -> float:
    """Intersection over union of two [u_min, v_min, u_max, v_max] boxes (0 when one is None)."""
    if a is None or b is None:
        return 0.0
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0
