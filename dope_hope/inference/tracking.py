"""Tracks of detected objects across the frames of a stream: ids, smoothed poses, coasting.

:class:`PoseTracker` takes each frame's detections (:meth:`DopePredictor.predict` /
:func:`predict_many`) and returns :class:`TrackedObject` s:

* **Association**, per class: each track's pose is predicted for the frame
  (:class:`~dope_hope.inference.pose_filter.PoseFilter`) and matched one-to-one to the
  detections by :func:`scipy.optimize.linear_sum_assignment` on the cost
  ``|t_det - t_pred| / gate_m + (1 - IoU of their 2D boxes) + rotation_weight * angle / 180``
  (angle after the symmetries); a pair is allowed when the translations are within ``gate_m``.
  A detection farther than ``gate_m`` still matches a confirmed track when it lies on the
  track's ray: moved along its own ray to the predicted depth it is within ``gate_m``
  (``reseed_depth``; a depth line search fooled by an occluder in front, say); the filter then
  takes its translation at that depth, refined against the depth image within
  ``coast_search`` (the frame's own estimate is still reported as ``t_detected``).
  An unmatched detection starts a track; while that track is tentative its detection is not
  published when its 2D box overlaps the predicted box of a confirmed track published in
  this frame (detected or coasted) by ``min_iou`` or more
  (the same object seen at a wrong depth, e.g. a line search fooled by an occluder); should it
  be a real object, it is published once confirmed.
* **Tracks**: a track is *confirmed* after ``confirm_hits`` detections; a tentative track
  ends at its first miss, a confirmed one after ``max_misses`` frames in a row without one.
  ``track_id`` counts up per class from 1 and is never reused.
* **Smoothed poses**: every detection corrects its track's filter; the published pose is the
  filter's (symmetry-aware, constant velocity: no lag on steady motion).
* **Coasting**: a confirmed track without a detection publishes its predicted pose, marked
  ``tracked="coasted"``, for at most ``max_coast`` frames; with a depth image the prediction
  is refined like a detection: the depth line search ("-LS") within ``coast_search`` and, when
  the predictor runs ICP, ICP.

Settings: the ``tracking`` section of the inference options (``dope_hope/configs/infer.yaml``),
checked by :class:`TrackingSettings`.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from dope_hope.errors import ConfigError
from dope_hope.geometry import NUM_KEYPOINTS, matrix_to_quaternion_xyzw, project_points, projected_bbox
from dope_hope.inference.detection import Detection, box_iou
from dope_hope.inference.pose_filter import PoseFilter, closest_equivalent
from dope_hope.inference.tracking_settings import TrackingSettings
from dope_hope.io.predictions import prediction_record
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.line_search import depth_line_search

if TYPE_CHECKING:
    from dope_hope.inference.predictor import DopePredictor

#: Values of ``TrackedObject.tracked``.
TRACKED_STATES = ("detected", "coasted")
#: Step of the sampled continuous symmetries (cylinders) used for the pose distance, degrees.
SYMMETRY_STEP_DEG = 5.0


@dataclass
class TrackedObject:
    """One published object of one frame.

    class_name, track_id (per class, from 1), tracked ("detected" | "coasted"), confirmed
    (the track had ``confirm_hits`` detections). score: the detection's, or for a coasted
    object its track's last detection score. R (3, 3), t (3,) metres: the published (tracked)
    pose. detection: the frame's own :class:`Detection` (None when coasted).
    projected_2d (9, 2) / bbox_2d (4,) or None: the published pose's cuboid keypoints and 2D
    box, px. ls_applied / ls_reason: the depth line search on a coasted pose (the detection's
    own otherwise). cuboid_size_m, cuboid_center_m: the model's box.
    """

    class_name: str
    track_id: int
    tracked: str
    confirmed: bool
    score: float
    R: np.ndarray
    t: np.ndarray
    detection: Detection | None
    cuboid_size_m: np.ndarray
    cuboid_center_m: np.ndarray
    projected_2d: np.ndarray | None = None
    bbox_2d: np.ndarray | None = None
    ls_applied: bool = False
    ls_reason: str = "no depth image"

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        return matrix_to_quaternion_xyzw(self.R)

    def to_json(self, image: str | None = None, **extra: Any) -> dict[str, Any]:
        """A predictions record (:mod:`dope_hope.io.predictions`): ``R`` / ``t`` /
        ``quaternion_xyzw`` the published pose, ``R_detected`` / ``t_detected`` the frame's own
        estimate (null when coasted), ``track_id``, ``tracked``; the detection's other fields
        (keypoints, -LS, ...) when detected."""
        box = None if self.bbox_2d is None else [round(float(v), 2) for v in self.bbox_2d]
        pose = {"R": np.asarray(self.R, dtype=np.float64).tolist(), "t": [float(v) for v in self.t],
                "quaternion_xyzw": [float(v) for v in self.quaternion_xyzw], "bbox_2d": box}
        if self.detection is not None:
            rec = self.detection.to_json(image, **extra)
            rec.update(pose, R_detected=rec["R"], t_detected=rec["t"])  # the kwargs hold the detection's
        else:
            rec = prediction_record("" if image is None else image, self.class_name, self.score, self.R, self.t,
                                    ls_applied=self.ls_applied, ls_reason=self.ls_reason,
                                    cuboid_size_m=[float(v) for v in self.cuboid_size_m], **extra)
            rec.update(pose, R_detected=None, t_detected=None)
            if image is None:
                del rec["image"]
        rec.update(track_id=int(self.track_id), tracked=self.tracked)
        return rec


@dataclass
class _Track:
    track_id: int
    filter: PoseFilter
    score: float
    hits: int = 1
    misses: int = 0
    last_frame: int = 0
    R_pred: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_pred: np.ndarray = field(default_factory=lambda: np.zeros(3))
    box_pred: np.ndarray | None = None


def class_symmetry_transforms(class_name: str, mesh_path: Any = None, units: str | None = None) -> np.ndarray:
    """(S, 4, 4) model-frame symmetries of an object, metres, identity first, in the one
    resolution order (:func:`dope_hope.symmetry.resolve.resolve_symmetries`: declarations beside
    its mesh file, the demo box's own, the HOPE category), else the identity only. Continuous
    symmetries are sampled every :data:`SYMMETRY_STEP_DEG`."""
    from dope_hope.symmetry.resolve import resolve_symmetries  # noqa: PLC0415 (meshes (trimesh) only for a class's declared symmetries)
    from dope_hope.symmetry.transforms import category_symmetries, declaration_transforms  # noqa: PLC0415 (meshes (trimesh) only for a class's declared symmetries)

    path = mesh_path if mesh_path is not None and not hasattr(mesh_path, "vertices") else None
    found = resolve_symmetries(class_name, path, units=units)
    if found.declaration is not None:
        return declaration_transforms(found.declaration, SYMMETRY_STEP_DEG)
    if found.category is not None:
        return category_symmetries(found.category, SYMMETRY_STEP_DEG)
    return np.eye(4)[None]


def recorded_symmetry_transforms(fields: Any) -> np.ndarray:
    """(S, 4, 4) model-frame symmetries, metres, of the BOP fields (mm) a model records for an
    object (``ObjectInfo.symmetries``); continuous ones every :data:`SYMMETRY_STEP_DEG`."""
    from dope_hope.io.symmetries import SymmetryDeclaration  # noqa: PLC0415 (meshes (trimesh) only for a recorded declaration)
    from dope_hope.symmetry.transforms import declaration_transforms  # noqa: PLC0415 (meshes (trimesh) only for a recorded declaration)

    return declaration_transforms(SymmetryDeclaration(dict(fields), "mm", "the model's object list"),
                                  SYMMETRY_STEP_DEG)


class PoseTracker:
    """Tracks of the detections of one or more predictors' objects (module docstring).

    Args:
        predictors: the :class:`DopePredictor` (or several) whose detections are tracked; they
            give each class's box, surface points and depth-refinement options.
        settings: :class:`TrackingSettings`, a mapping of overrides, or None for the
            predictors' own (``predictor.options.tracking``).
        symmetries: class name -> (S, 4, 4) model-frame symmetries (metres); default those
            the model records for the class (:func:`recorded_symmetry_transforms`), else
            :func:`class_symmetry_transforms` of the class.

    Use: ``tracked = tracker.update(detections, K, depth, frame=index)`` once per frame.
    """

    def __init__(self, predictors: DopePredictor | Sequence[DopePredictor],
                 settings: TrackingSettings | Mapping[str, Any] | None = None,
                 symmetries: Mapping[str, np.ndarray] | None = None):
        predictors = list(predictors) if isinstance(predictors, Sequence) else [predictors]
        self.predictors = {c: p for p in predictors for c in p.class_names}
        self.geometry = {o.class_name: o for p in predictors for o in p.objects}
        if settings is None:
            settings = getattr(predictors[0].options, "tracking", None) if predictors else None
        self.settings = settings if isinstance(settings, TrackingSettings) else TrackingSettings.from_mapping(settings)
        given = dict(symmetries or {})
        for c, geometry in self.geometry.items():  # else those the model records (its checkpoint's)
            recorded = getattr(geometry, "symmetries", None)
            if given.get(c) is None and recorded is not None:
                given[c] = recorded_symmetry_transforms(recorded)
        self.symmetries = {c: np.asarray(given[c] if given.get(c) is not None else class_symmetry_transforms(c),
                                         dtype=np.float64).reshape(-1, 4, 4) for c in self.predictors}
        self.tracks: dict[str, list[_Track]] = {c: [] for c in self.predictors}
        self._next_id = {c: 1 for c in self.predictors}
        self._frame = -1

    def update(self, detections: Sequence[Detection], K: np.ndarray, depth: DepthImage | np.ndarray | None = None,
               frame: int | None = None, image_hw: tuple[int, int] | None = None) -> list[TrackedObject]:
        """One frame: associate, filter, coast (module docstring).

        Args:
            detections: the frame's detections (mesh-frame poses, original-image px).
            K: (3, 3) intrinsics of the frame. depth: its depth, for coasting: a
                :class:`DepthImage`, or (H, W) metres (float) / millimetres (integers).
            frame: the frame's index in the stream (default: the previous one + 1); a gap
                (dropped frames) is predicted over. image_hw: (H, W) of the frame, to clip the
                2D boxes as the detections' are (default: the depth's).

        Returns:
            The published objects, detected ones first (by decreasing score), then coasted.
        """
        frame = self._frame + 1 if frame is None else int(frame)
        if depth is not None and not isinstance(depth, DepthImage):
            depth = DepthImage.from_raw(depth, K, 0.001, 1.0, image_hw)
        if image_hw is None and depth is not None:
            image_hw = depth.hw
        out: list[TrackedObject] = []
        coasted: list[TrackedObject] = []
        for class_name, dets in self._by_class(detections).items():
            tracks = self.tracks[class_name]
            started: list[_Track] = []
            for tr in tracks:
                tr.R_pred, tr.t_pred = tr.filter.predict(max(1, frame - tr.last_frame))
                tr.box_pred = projected_bbox(self.geometry[class_name].bbox_points, K, tr.R_pred, tr.t_pred,
                                             image_hw)
                tr.last_frame = frame
            pairs = self._associate(class_name, tracks, dets)
            matched = {ti for ti, _, _ in pairs}
            for ti, di, reseed in pairs:
                out.append(self._correct(class_name, tracks[ti], dets[di], K, depth, image_hw, reseed))
            taken = {di for _, di, _ in pairs}
            confirmed_boxes = [t.box_pred for t in tracks  # confirmed tracks published this frame
                               if t.hits >= self.settings.confirm_hits and t.misses < self.settings.max_coast]
            for di, det in enumerate(dets):
                if di not in taken:
                    obj = self._start(class_name, det, frame, K, image_hw, started)
                    if not any(box_iou(b, det.bbox_2d) >= self.settings.min_iou for b in confirmed_boxes):
                        out.append(obj)
            kept = []
            for ti, tr in enumerate(tracks):
                if ti in matched:
                    kept.append(tr)
                    continue
                tr.misses += 1
                if tr.hits < self.settings.confirm_hits or tr.misses > self.settings.max_misses:
                    continue  # tentative tracks end at their first miss
                kept.append(tr)
                if tr.misses <= self.settings.max_coast:
                    coasted.append(self._coast(class_name, tr, K, depth, image_hw))
            self.tracks[class_name] = kept + started
        self._frame = frame
        out.sort(key=lambda o: -o.score)
        return out + coasted

    # ------------------------------------------------------------------ steps
    def _by_class(self, detections: Sequence[Detection]) -> dict[str, list[Detection]]:
        by: dict[str, list[Detection]] = {c: [] for c in self.predictors}
        for d in detections:
            if d.class_name not in by:
                raise ConfigError(f"detection of {d.class_name!r}: the tracker has no predictor of that class "
                                  f"(known: {', '.join(sorted(by))})")
            by[d.class_name].append(d)
        return by

    def _associate(self, class_name: str, tracks: list[_Track], dets: list[Detection]
                   ) -> list[tuple[int, int, bool]]:
        """(track index, detection index, depth reseeded) of least total cost among the allowed
        pairs; a pair matched only on the track's ray (module docstring) costs 1 more."""
        if not tracks or not dets:
            return []
        s = self.settings
        big = 1e6
        C = np.full((len(tracks), len(dets)), big)
        reseed = np.zeros(C.shape, dtype=bool)
        for i, tr in enumerate(tracks):
            for j, d in enumerate(dets):
                t = np.asarray(d.t, dtype=np.float64)
                dist = float(np.linalg.norm(t - tr.t_pred))
                if dist > s.gate_m:  # on its track's ray at the predicted depth?
                    if not s.reseed_depth or tr.hits < s.confirm_hits or t[2] <= 0:
                        continue
                    dist = float(np.linalg.norm(t * (tr.t_pred[2] / t[2]) - tr.t_pred))
                    if dist > s.gate_m:
                        continue
                    reseed[i, j] = True
                iou = box_iou(tr.box_pred, d.bbox_2d)
                angle = closest_equivalent(np.asarray(d.R), t, tr.R_pred, self.symmetries[class_name])[2]
                C[i, j] = dist / s.gate_m + (1.0 - iou) + s.rotation_weight * angle / 180.0 + float(reseed[i, j])
        rows, cols = linear_sum_assignment(C)
        return [(int(r), int(c), bool(reseed[r, c])) for r, c in zip(rows, cols) if C[r, c] < big]

    def _new_filter(self, class_name: str, det: Detection) -> PoseFilter:
        return PoseFilter(det.R, det.t, self.symmetries[class_name], self.settings)

    def _start(self, class_name: str, det: Detection, frame: int, K: np.ndarray, image_hw,
               started: list[_Track]) -> TrackedObject:
        tr = _Track(self._next_id[class_name], self._new_filter(class_name, det), float(det.score), last_frame=frame)
        self._next_id[class_name] += 1
        started.append(tr)
        return self._published(class_name, tr, det, tr.filter.R, tr.filter.t, K, image_hw)

    def _correct(self, class_name: str, tr: _Track, det: Detection, K: np.ndarray, depth: DepthImage | None,
                 image_hw, reseed: bool) -> TrackedObject:
        t = np.asarray(det.t, dtype=np.float64)
        if reseed:  # the detection's direction at the track's depth, refined against the depth
            t = t * (tr.t_pred[2] / t[2])
            if depth is not None:
                p = self.predictors[class_name]
                res = depth_line_search(det.R, t, self.geometry[class_name].model_points, depth,
                                        replace(p.options.line_search, search=self.settings.coast_search))
                t = res.t if res.applied else t
        R, t = tr.filter.update(det.R, t, self._noise_scale(det))
        tr.hits, tr.misses, tr.score = tr.hits + 1, 0, float(det.score)
        return self._published(class_name, tr, det, R, t, K, image_hw)

    def _noise_scale(self, det: Detection) -> float:
        """How much noisier than usual a detection counts (TrackingSettings.reprojection_px)."""
        ref, e = self.settings.reprojection_px, float(det.reprojection_error_px)
        if ref <= 0 or not math.isfinite(e) or e <= ref:
            return 1.0
        return (e / ref) ** self.settings.reprojection_power

    def _published(self, class_name: str, tr: _Track, det: Detection | None, R: np.ndarray, t: np.ndarray,
                   K: np.ndarray, image_hw, ls: tuple[bool, str] | None = None) -> TrackedObject:
        p = self.geometry[class_name]
        applied, reason = ls if ls is not None else (det.ls_applied, det.ls_reason)
        return TrackedObject(
            class_name=class_name, track_id=tr.track_id, tracked="detected" if det is not None else "coasted",
            confirmed=tr.hits >= self.settings.confirm_hits,
            score=float(det.score) if det is not None else tr.score, R=R, t=t, detection=det,
            cuboid_size_m=p.cuboid_size_m.copy(), cuboid_center_m=p.cuboid_center_m.copy(),
            projected_2d=project_points(p.cuboid_mesh, K, R, t),
            bbox_2d=projected_bbox(p.bbox_points, K, R, t, image_hw), ls_applied=applied, ls_reason=reason)

    def _coast(self, class_name: str, tr: _Track, K: np.ndarray, depth: DepthImage | None,
               image_hw) -> TrackedObject:
        """The predicted pose of a confirmed track without a detection, refined against the depth."""
        R, t = tr.R_pred, tr.t_pred
        ls = (False, "no depth image")
        if depth is not None and self.settings.coast_refine:
            p = self.predictors[class_name]
            settings = replace(p.options.line_search, search=self.settings.coast_search)
            res = depth_line_search(R, t, self.geometry[class_name].model_points, depth, settings)
            ls = (bool(res.applied), f"coasted: {res.reason}")
            if res.applied:
                t = res.t
                if p.options.icp is True or (p.options.icp == "auto" and class_name in p.icp_objects):
                    probe = Detection(class_name, tr.score, R, t, np.full((NUM_KEYPOINTS, 2), np.nan),
                                      np.zeros(NUM_KEYPOINTS), np.zeros(NUM_KEYPOINTS, bool),
                                      np.zeros((NUM_KEYPOINTS, 2)), float("nan"), self.geometry[class_name].cuboid_size_m,
                                      ls_applied=True)
                    refined = p.refine_icp(probe, depth)
                    R, t = refined.R, refined.t
        return self._published(class_name, tr, None, R, t, K, image_hw, ls=ls)
