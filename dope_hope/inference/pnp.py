"""Poses from 2D cuboid keypoints: PnP-RANSAC on one keypoint set (:func:`solve_pnp`).

The official DOPE drops an object as soon as one of its nine keypoints is missing; we use
whatever keypoints were found, down to ``min_points`` (>= 4):

1. ``cv2.solvePnPRansac`` on the present keypoints (OpenCV's kernel is EPnP on 5-point
   samples, or P3P + a 4th point to pick among P3P's up to four solutions when only 4 points
   exist; the consensus set is then solved with SQPnP, which also handles a planar set such as
   one face of the box). Plain P3P/AP3P on 3 points is never used: with 3 points the pose is
   ambiguous (up to four exact solutions) and nothing can choose between them. Given a
   consensus pose (``initial_pose``, from the pose search of
   :mod:`dope_hope.inference.pose_search`), the
   keypoints within the threshold of it are the inliers instead.
2. ``cv2.solvePnPRefineLM`` (Levenberg-Marquardt on the reprojection error, until a step no
   longer changes the pose) on the inliers; inliers are recomputed under the refined pose.
3. Rejections (return ``None``, never a made-up pose): fewer than ``min_points`` present
   keypoints or inliers; inliers fewer than ``min_inlier_ratio`` (0.75) of the present
   keypoints; the model origin or the cuboid centre at ``z <= 0`` (behind the camera); mean
   inlier reprojection error above ``max_mean_error_px``. The ratio test matters: with
   five points RANSAC has only four redundant constraints: on 50-px maps of uniform noise
   (every cell a candidate) it fitted a pose to 1 in 27 decoded candidate instances without
   the ratio test, 1 in 2000 with it.

Score: ``score = sum(clip(scores[inliers], 0, 1)) / 9`` - the mean keypoint confidence of the
inliers times the inlier fraction of *all nine* keypoints, so missing and outlying keypoints
both lower it. All thresholds are in pixels of the image the keypoints and ``K`` refer to.
:func:`score_in_view` divides by the keypoints the pose puts inside the image instead (at
least ``min_points``): a keypoint beyond the image border can have no peak, so a cut-off
object is not scored as if its corners were missing (the predictor's default,
``pnp.score_in_view``).

Several candidate peaks per keypoint (the multi-hypothesis pose search, which ends in
:func:`solve_pnp`) are :mod:`dope_hope.inference.pose_search`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from dope_hope.config import (
    SectionSettings,
    at_least,
    boolean,
    finite_float,
    fraction,
    nonnegative_float,
    positive_float,
)
from dope_hope.errors import ConfigError
from dope_hope.geometry import CENTROID_INDEX, NUM_KEYPOINTS, inside_image
from dope_hope.maps.decode import keypoint_score_bound, may_reach

#: :func:`solve_pnp` defaults, also what the pose search checks its best
#: hypothesis against before calling it.
DEFAULT_MIN_POINTS = 5
DEFAULT_REPROJECTION_PX = 8.0


#: :func:`solve_pnp`'s Levenberg-Marquardt stops when a step changes the pose by less than
#: FLT_EPSILON (relative). OpenCV's default adds a 20-iteration count, and OpenCV 5 then runs
#: ~10 iterations where one or two reach the same pose (same result in 300 random cases, from
#: noisy keypoints and bad starts; ~4x faster).
_LM_CRITERIA = (cv2.TERM_CRITERIA_EPS, 0, float(np.finfo(np.float32).eps))


def _open_fraction(value: Any, name: str) -> float:
    """The rule of a number strictly between 0 and 1 (OpenCV's RANSAC confidence)."""
    v = finite_float(value, name)
    if not 0 < v < 1:
        raise ConfigError(f"{name} must be in (0, 1), got {value!r}")
    return v


@dataclass(frozen=True)
class PnpSettings(SectionSettings):
    """:func:`solve_pnp`'s settings (``pnp:`` in ``dope_hope/configs/infer.yaml``; also those of
    the final pose of :func:`dope_hope.inference.pose_search.solve_pnp_candidates`). Thresholds in pixels of the image the
    keypoints and ``K`` refer to.

    min_points: fewest present keypoints and inliers (>= 4: three points leave up to four
    poses). reprojection_threshold_px: RANSAC / final inlier threshold. max_mean_error_px:
    reject the pose when the mean inlier error is larger. min_score: a keypoint with score
    <= ``min_score`` is treated as missing. min_inlier_ratio: reject when fewer than this
    fraction of the present keypoints are inliers (5 of 9 random points can fit some pose;
    see the module docstring). ransac_iterations, ransac_confidence: OpenCV's RANSAC.
    score_in_view: the predictor scores a pose by the keypoints it puts inside the image
    (:func:`score_in_view`); false: by all nine, as :func:`solve_pnp` does.
    """

    SECTION = "pnp"
    RULES = {"min_points": at_least(4), "reprojection_threshold_px": positive_float,
             "max_mean_error_px": nonnegative_float, "min_score": finite_float, "min_inlier_ratio": fraction,
             "ransac_iterations": at_least(1), "ransac_confidence": _open_fraction, "score_in_view": boolean}

    min_points: int = DEFAULT_MIN_POINTS
    reprojection_threshold_px: float = DEFAULT_REPROJECTION_PX
    max_mean_error_px: float = 4.0
    min_score: float = 0.0
    min_inlier_ratio: float = 0.75
    ransac_iterations: int = 200
    ransac_confidence: float = 0.999
    score_in_view: bool = True


@dataclass
class PoseEstimate:
    """A 6-DoF pose from 2D keypoints.

    R: (3, 3) rotation, model -> camera. t: (3,) translation, metres (``x_c = R x + t``).
    score: float in [0, 1] (see the module docstring).
    inliers: (9,) bool, keypoints consistent with the pose.
    reprojection_error_px: mean reprojection error of the inliers, pixels.
    keypoints: (9, 2) the input keypoints, image px (NaN where missing).
    projected: (9, 2) the cuboid keypoints projected under the pose, image px.
    keypoint_scores: (9,) the input keypoint confidences (1 where none were given).
    """

    R: np.ndarray
    t: np.ndarray
    score: float
    inliers: np.ndarray
    reprojection_error_px: float
    keypoints: np.ndarray
    projected: np.ndarray | None = None
    keypoint_scores: np.ndarray | None = None


def solve_pnp(
    keypoints: np.ndarray,
    scores: np.ndarray | None,
    cuboid_points: np.ndarray,
    K: np.ndarray,
    settings: PnpSettings = PnpSettings(),
    dist_coeffs: np.ndarray | None = None,
    initial_pose: tuple[np.ndarray, np.ndarray] | None = None,
) -> PoseEstimate | None:
    """Pose of one cuboid from its (possibly partial) projected keypoints.

    Args:
        keypoints: (9, 2) image px; NaN rows are missing.
        scores: (9,) keypoint confidences in [0, 1] (None = all 1); a keypoint with score
            <= ``settings.min_score`` is treated as missing.
        cuboid_points: (9, 3) model-frame cuboid keypoints, metres.
        K: (3, 3) intrinsics of the image the keypoints are in.
        settings: :class:`PnpSettings` (thresholds, RANSAC, rejections).
        dist_coeffs: OpenCV distortion coefficients (None = none).
        initial_pose: (R (3, 3), t (3,)) a consensus pose found elsewhere (the search of
            :func:`~dope_hope.inference.pose_search.solve_pnp_candidates`): it replaces RANSAC; the present keypoints within
            ``settings.reprojection_threshold_px`` of it are the inliers refined, every check
            follows.

    Returns:
        :class:`PoseEstimate`, or None when the keypoints do not support a pose.
    """
    poses = None if initial_pose is None else ([initial_pose[0]], [initial_pose[1]])
    return solve_pnp_many(
        np.asarray(keypoints, dtype=np.float64).reshape(1, NUM_KEYPOINTS, 2),
        None if scores is None else np.asarray(scores, dtype=np.float64).reshape(1, NUM_KEYPOINTS),
        cuboid_points, K, poses, settings, dist_coeffs)[0]


def _project(obj: np.ndarray, Rs: np.ndarray, ts: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(B, n, 2) image px of (n, 3) model points under B poses (Rs (B, 3, 3), ts (B, 3));
    ``cv2.projectPoints`` per pose where ``dist`` has a non-zero coefficient."""
    if not dist.any():
        uvw = (obj @ Rs.transpose(0, 2, 1) + ts[:, None]) @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return uvw[..., :2] / uvw[..., 2:]
    return np.stack([cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
                     for R, t in zip(Rs, ts)]).reshape(len(Rs), len(obj), 2)


@dataclass
class _KeypointSets:
    """:func:`solve_pnp_many`'s inputs, checked: kp (B, 9, 2) px, sc (B, 9) scores, present
    (B, 9) bool (finite and scored above ``min_score``), n_present (B,), obj (9, 3) cuboid
    keypoints, metres, K (3, 3), dist (n,) distortion coefficients."""

    kp: np.ndarray
    sc: np.ndarray
    present: np.ndarray
    n_present: np.ndarray
    obj: np.ndarray
    K: np.ndarray
    dist: np.ndarray

    @classmethod
    def of(cls, keypoints, scores, cuboid_points, K, dist_coeffs, min_score: float) -> "_KeypointSets":
        kp = np.asarray(keypoints, dtype=np.float64).reshape(-1, NUM_KEYPOINTS, 2)
        B = len(kp)
        sc = np.ones((B, NUM_KEYPOINTS)) if scores is None else np.asarray(scores, dtype=np.float64).reshape(B, -1)
        present = np.all(np.isfinite(kp), axis=2) & np.isfinite(sc) & (sc > min_score)      # (B, 9)
        return cls(kp, sc, present, present.sum(axis=1),
                   np.asarray(cuboid_points, dtype=np.float64).reshape(NUM_KEYPOINTS, 3),
                   np.asarray(K, dtype=np.float64),
                   np.zeros(5) if dist_coeffs is None else np.asarray(dist_coeffs, dtype=np.float64))


def solve_pnp_many(keypoints: np.ndarray, scores: np.ndarray | None, cuboid_points: np.ndarray, K: np.ndarray,
                    initial_poses: tuple | None, settings: PnpSettings = PnpSettings(),
                    dist_coeffs: np.ndarray | None = None) -> list[PoseEstimate | None]:
    """:func:`solve_pnp` of B keypoint sets at once (its steps and checks; the projections
    and checks of all sets in one pass, the solvers per set): keypoints (B, 9, 2) px, scores
    (B, 9) or None, initial_poses None or (B rotations (3, 3), B translations (3,))."""
    sets = _KeypointSets.of(keypoints, scores, cuboid_points, K, dist_coeffs, settings.min_score)
    if initial_poses is None:
        starts = _ransac_starts(sets, settings)
    else:
        starts = _consensus_starts(sets, initial_poses, settings)
    return _accepted_poses(sets, _refined_starts(sets, starts, settings.min_points), settings)


def _ransac_starts(sets: _KeypointSets, settings: PnpSettings) -> list[tuple]:
    """Step 1 by RANSAC: (set, rvec, tvec, (9,) bool consensus) of each set with at least
    ``min_points`` present keypoints whose RANSAC succeeds."""
    starts = []
    for b in np.flatnonzero(sets.n_present >= settings.min_points):
        idx = np.flatnonzero(sets.present[b])
        try:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                sets.obj[idx], sets.kp[b, idx], sets.K, sets.dist,
                iterationsCount=settings.ransac_iterations,
                reprojectionError=settings.reprojection_threshold_px,
                confidence=settings.ransac_confidence,
                flags=cv2.SOLVEPNP_SQPNP,
            )
        except cv2.error:
            continue
        if ok and inl is not None:
            consensus = np.zeros(NUM_KEYPOINTS, dtype=bool)
            consensus[idx[inl.ravel()]] = True
            starts.append((b, rvec, tvec, consensus))
    return starts


def _consensus_starts(sets: _KeypointSets, initial_poses: tuple, settings: PnpSettings) -> list[tuple]:
    """Step 1 from given poses: (set, rvec, tvec, (9,) bool consensus: the present keypoints
    within the threshold of the pose) of each set with at least ``min_points`` present."""
    B = len(sets.kp)
    Rs = np.asarray(initial_poses[0], dtype=np.float64).reshape(B, 3, 3)
    ts = np.asarray(initial_poses[1], dtype=np.float64).reshape(B, 3)
    d = _project(sets.obj, Rs, ts, sets.K, sets.dist) - sets.kp
    with np.errstate(invalid="ignore"):
        consensus = sets.present & (np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2) <= settings.reprojection_threshold_px)
    return [(b, cv2.Rodrigues(Rs[b])[0], ts[b].reshape(3, 1), consensus[b])
            for b in np.flatnonzero(sets.n_present >= settings.min_points)]


def _refined_starts(sets: _KeypointSets, starts: list[tuple], min_points: int) -> list[tuple]:
    """Step 2: Levenberg-Marquardt on each start's consensus of at least ``min_points``
    keypoints: [(set, R (3, 3), t (3,))]."""
    refined = []
    for b, rvec, tvec, consensus in starts:
        if consensus.sum() < min_points:
            continue
        try:
            rvec, tvec = cv2.solvePnPRefineLM(sets.obj[consensus], np.ascontiguousarray(sets.kp[b, consensus]),
                                              sets.K, sets.dist, rvec, tvec, criteria=_LM_CRITERIA)
        except cv2.error:
            continue
        refined.append((b, cv2.Rodrigues(rvec)[0], tvec.reshape(3)))
    return refined


def _accepted_poses(sets: _KeypointSets, refined: list[tuple], settings: PnpSettings) -> list[PoseEstimate | None]:
    """Step 3 on the refined poses, all at once: inliers under each pose, the rejections,
    the score; per set its :class:`PoseEstimate` or None."""
    out: list[PoseEstimate | None] = [None] * len(sets.kp)
    if not refined:
        return out
    which = np.array([b for b, _, _ in refined])
    Rs = np.stack([R for _, R, _ in refined])
    ts = np.stack([t for _, _, t in refined])
    projected = _project(sets.obj, Rs, ts, sets.K, sets.dist)                           # (B', 9, 2)
    d = projected - sets.kp[which]
    with np.errstate(invalid="ignore"):
        err = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
        inliers = sets.present[which] & (err <= settings.reprojection_threshold_px)
    n_in = inliers.sum(axis=1)
    centre_z = (Rs @ sets.obj[CENTROID_INDEX] + ts)[:, 2]
    mean_err = np.where(inliers, err, 0.0).sum(axis=1) / np.maximum(n_in, 1)
    ok = ((n_in >= min_inliers(sets.n_present[which], settings))
          & (ts[:, 2] > 0) & (centre_z > 0) & (mean_err <= settings.max_mean_error_px))
    scores_out = np.where(inliers, np.clip(sets.sc[which], 0.0, 1.0), 0.0).sum(axis=1) / NUM_KEYPOINTS
    for j in np.flatnonzero(ok):
        b = which[j]
        out[b] = PoseEstimate(
            R=Rs[j], t=ts[j].copy(), score=float(scores_out[j]), inliers=inliers[j],
            reprojection_error_px=float(mean_err[j]), keypoints=sets.kp[b].copy(), projected=projected[j],
            keypoint_scores=sets.sc[b].copy(),
        )
    return out


def min_inliers(n_present: int | np.ndarray, settings: PnpSettings) -> int | np.ndarray:
    """The fewest inliers :func:`solve_pnp` accepts among ``n_present`` present keypoints (an
    int or an int array): ``min_points``, and ``min_inlier_ratio`` of those present."""
    if np.ndim(n_present) == 0:
        return max(settings.min_points, math.ceil(settings.min_inlier_ratio * int(n_present)))
    return np.maximum(settings.min_points, np.ceil(settings.min_inlier_ratio * np.asarray(n_present))).astype(int)


def least_score_divisor(settings: PnpSettings, n_present: int = 0) -> int | None:
    """The fewest keypoints the score of a pose :func:`solve_pnp` accepts is divided by, where at
    least ``n_present`` keypoints are present (0: any number): with ``score_in_view`` the inliers
    it needs (:func:`min_inliers`: the in-view score divides by at least the inlier count);
    None without: all nine. :func:`dope_hope.maps.decode.keypoint_score_bound` with it bounds
    the score of any pose from given peaks."""
    return min_inliers(n_present, settings) if settings.score_in_view else None


def pose_may_reach(keypoint_ids: np.ndarray, heights: np.ndarray, settings: PnpSettings, min_score: float,
                   n_present: int = 0) -> bool:
    """Whether a pose :func:`solve_pnp` accepts from keypoints of these types ((n,) int) and
    confidences ((n,)), at least ``n_present`` of them present (0: any number), may score
    ``min_score`` (:func:`dope_hope.maps.decode.keypoint_score_bound` over
    :func:`least_score_divisor`); always where ``min_score`` <= 0, with nothing computed."""
    if min_score <= 0:
        return True
    return may_reach(keypoint_score_bound(keypoint_ids, heights, least_score_divisor(settings, n_present)), min_score)


def score_in_view(estimate: PoseEstimate, image_hw: tuple[int, int], min_points: int = DEFAULT_MIN_POINTS) -> float:
    """The pose score over the keypoints the pose puts inside the image: the inliers' clipped
    confidences summed, divided by the number of ``estimate.projected`` keypoints inside the
    (H, W) ``image_hw`` (pixel centres at integers: [-0.5, W - 0.5] x [-0.5, H - 0.5]), or by
    ``min_points`` or the inlier count where larger. Equals ``estimate.score`` when all nine
    lie inside; never above the mean of the ``min_points`` best keypoint confidences
    (:func:`dope_hope.maps.decode.keypoint_score_bound` with ``min_points``)."""
    inside = int(inside_image(estimate.projected, image_hw).sum())
    inliers = np.asarray(estimate.inliers, dtype=bool)
    scores = np.ones(NUM_KEYPOINTS) if estimate.keypoint_scores is None else np.asarray(estimate.keypoint_scores)
    total = float(np.clip(scores[inliers], 0.0, 1.0).sum())
    return total / max(min_points, inside, int(inliers.sum()))
