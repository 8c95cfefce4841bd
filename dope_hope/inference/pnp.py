"""Poses from 2D cuboid keypoints: PnP-RANSAC and the multi-hypothesis pose search.

**PnP** (:func:`solve_pnp`). The official DOPE drops an object as soon as one of its nine
keypoints is missing; we use whatever keypoints were found, down to ``min_points`` (>= 4):

1. ``cv2.solvePnPRansac`` on the present keypoints (OpenCV's kernel is EPnP on 5-point
   samples, or P3P + a 4th point to pick among P3P's up to four solutions when only 4 points
   exist; the consensus set is then solved with SQPnP, which also handles a planar set such as
   one face of the box). Plain P3P/AP3P on 3 points is never used: with 3 points the pose is
   ambiguous (up to four exact solutions) and nothing can choose between them.
2. ``cv2.solvePnPRefineLM`` (Levenberg-Marquardt on the reprojection error) on the inliers;
   inliers are recomputed under the refined pose.
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

The multi-hypothesis search (:func:`solve_pnp_candidates`) tries minimal sets of candidate
corner peaks per centroid and keeps the pose that explains most candidates.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.geometry import CENTROID_INDEX, NUM_KEYPOINTS

#: :func:`solve_pnp` defaults, also what :func:`solve_pnp_candidates` checks its best
#: hypothesis against before calling it.
DEFAULT_MIN_POINTS = 5


DEFAULT_REPROJECTION_PX = 8.0


#: Pose hypotheses solved between two checks of :func:`solve_pnp_candidates`' early stop.
_HYPOTHESIS_CHUNK = 16


#: :func:`solve_pnp_candidates` gives up after this many hypotheses when none explained more
#: than its own four keypoints.
_GIVE_UP_AFTER = 128


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


def _reprojection_errors(obj: np.ndarray, img: np.ndarray, rvec, tvec, K, dist) -> np.ndarray:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)


def solve_pnp(
    keypoints: np.ndarray,
    scores: np.ndarray | None,
    cuboid_points: np.ndarray,
    K: np.ndarray,
    min_points: int = DEFAULT_MIN_POINTS,
    reprojection_threshold_px: float = DEFAULT_REPROJECTION_PX,
    max_mean_error_px: float = 4.0,
    dist_coeffs: np.ndarray | None = None,
    min_score: float = 0.0,
    min_inlier_ratio: float = 0.75,
    ransac_iterations: int = 200,
    ransac_confidence: float = 0.999,
) -> PoseEstimate | None:
    """Pose of one cuboid from its (possibly partial) projected keypoints.

    Args:
        keypoints: (9, 2) image px; NaN rows are missing.
        scores: (9,) keypoint confidences in [0, 1] (None = all 1); a keypoint with score
            <= ``min_score`` is treated as missing.
        cuboid_points: (9, 3) model-frame cuboid keypoints, metres.
        K: (3, 3) intrinsics of the image the keypoints are in.
        min_points: minimum number of present keypoints and of inliers (>= 4).
        reprojection_threshold_px: RANSAC / final inlier threshold, pixels.
        max_mean_error_px: reject the pose when the mean inlier error is larger, pixels.
        dist_coeffs: OpenCV distortion coefficients (None = none).
        min_inlier_ratio: reject when fewer than this fraction of the present keypoints
            are inliers (5 of 9 random points can fit some pose; see the module docstring).
        min_score, ransac_iterations, ransac_confidence: as named.

    Returns:
        :class:`PoseEstimate`, or None when the keypoints do not support a pose.
    """
    if min_points < 4:
        raise ValueError("min_points must be >= 4: three points leave up to four poses")
    kp = np.asarray(keypoints, dtype=np.float64).reshape(NUM_KEYPOINTS, 2)
    sc = np.ones(NUM_KEYPOINTS) if scores is None else np.asarray(scores, dtype=np.float64)
    obj_all = np.asarray(cuboid_points, dtype=np.float64).reshape(NUM_KEYPOINTS, 3)
    K = np.asarray(K, dtype=np.float64)
    dist = np.zeros(5) if dist_coeffs is None else np.asarray(dist_coeffs, dtype=np.float64)
    present = np.all(np.isfinite(kp), axis=1) & np.isfinite(sc) & (sc > min_score)
    idx = np.flatnonzero(present)
    if idx.size < min_points:
        return None
    obj, img = obj_all[idx], kp[idx]
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, K, dist,
            iterationsCount=ransac_iterations,
            reprojectionError=float(reprojection_threshold_px),
            confidence=ransac_confidence,
            flags=cv2.SOLVEPNP_SQPNP,
        )
    except cv2.error:
        return None
    if not ok or inl is None or len(inl) < min_points:
        return None
    inl = inl.ravel()
    try:
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, dist, rvec, tvec)
    except cv2.error:
        return None
    err = _reprojection_errors(obj, img, rvec, tvec, K, dist)
    inlier_local = err <= reprojection_threshold_px
    if inlier_local.sum() < min_points or inlier_local.sum() < min_inlier_ratio * idx.size:
        return None
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.reshape(3)
    centre_z = (R @ obj_all[CENTROID_INDEX] + t)[2]
    if t[2] <= 0 or centre_z <= 0:
        return None
    mean_err = float(err[inlier_local].mean())
    if mean_err > max_mean_error_px:
        return None
    inliers = np.zeros(NUM_KEYPOINTS, dtype=bool)
    inliers[idx[inlier_local]] = True
    score = float(np.clip(sc[inliers], 0.0, 1.0).sum() / NUM_KEYPOINTS)
    proj, _ = cv2.projectPoints(obj_all, rvec, tvec, K, dist)
    return PoseEstimate(
        R=R, t=t.copy(), score=score, inliers=inliers, reprojection_error_px=mean_err,
        keypoints=kp.copy(), projected=proj.reshape(-1, 2), keypoint_scores=sc.copy(),
    )


def _minimal_sets(by_type: list[np.ndarray], max_sets: int) -> np.ndarray:
    """(S, 3) int: candidate indices of three corners of distinct types, the most promising
    first: ordered by the sum of the candidates' ranks within their type (each ``by_type``
    list is best first), so the first set is made of every type's first choice. At most
    ``max_sets`` sets."""
    sets, rank_sums = [], []
    for g in itertools.combinations(range(len(by_type)), 3):
        members = [by_type[i] for i in g]
        ranks = np.indices([len(m) for m in members]).reshape(3, -1).T        # (n, 3)
        sets.append(np.stack([members[i][ranks[:, i]] for i in range(3)], axis=1))
        rank_sums.append(ranks.sum(axis=1))
    order = np.argsort(np.concatenate(rank_sums), kind="stable")[:max_sets]
    return np.concatenate(sets)[order]


def solve_pnp_candidates(
    keypoint_ids: np.ndarray,
    points: np.ndarray,
    scores: np.ndarray,
    cuboid_points: np.ndarray,
    K: np.ndarray,
    hypothesis_threshold_px: float = 5.0,
    max_hypotheses: int = 400,
    **pnp_options,
) -> PoseEstimate | None:
    """Pose of one cuboid from several candidate peaks per keypoint (multi-hypothesis PnP).

    A trained network often puts a second, sometimes stronger, peak of corner map k on
    another corner of the same box; taking one peak per type then leaves too few consistent
    keypoints for :func:`solve_pnp`. Here every candidate may be used: each pose hypothesis
    is solved (``cv2.SOLVEPNP_AP3P``) from the centroid plus three corner candidates of
    distinct types, kept only when it projects the centroid within
    ``hypothesis_threshold_px`` of its peak (the candidates were gathered for that centroid),
    and scored by the summed confidence (clipped to [0, 1]) of the keypoint types whose
    nearest candidate lies within ``hypothesis_threshold_px`` of the projection - one
    candidate per type, so duplicates cannot inflate a score. Sets are tried best-ranked
    first (candidates are listed best first per type: the first set is every type's first
    choice), at most ``max_hypotheses`` of them, and the search stops as soon as a hypothesis
    explains every keypoint type present, so a clean instance costs one chunk of solves; it
    gives up after ``_GIVE_UP_AFTER`` when no hypothesis explains more than its own four
    points (clutter, not a cuboid), and skips the final :func:`solve_pnp` when fewer than its
    ``min_points`` types lie within its ``reprojection_threshold_px`` of the best hypothesis.
    The order is fixed, so the result is reproducible. The best hypothesis picks, per type,
    the candidate nearest its projection (or the type's strongest candidate where none is
    within the threshold: it counts as an outlier unless within the final RANSAC threshold),
    and that assignment goes through :func:`solve_pnp` with every one of its checks (RANSAC, refinement, inlier ratio, mean
    error). OpenCV's RANSAC does not fit: it counts every inlying correspondence, so several
    candidates of one type near a wrong pose outvote the right one.

    Args:
        keypoint_ids: (n,) int keypoint index of each candidate (0..7 corners, 8 the centroid),
            best candidate of each type first.
        points: (n, 2) candidate positions, image px.
        scores: (n,) candidate confidences (peak heights).
        cuboid_points: (9, 3) model-frame cuboid keypoints, metres.
        K: (3, 3) intrinsics of the image the points are in (no distortion).
        hypothesis_threshold_px: a candidate supports a hypothesis within this distance, px.
        max_hypotheses: most minimal sets solved.
        **pnp_options: keyword arguments of :func:`solve_pnp` for the final pose.

    Returns:
        :class:`PoseEstimate` (``keypoints``: the chosen candidate per type), or None: no
        centroid, fewer than three corner types, or the chosen assignment fails
        :func:`solve_pnp`.
    """
    ids = np.asarray(keypoint_ids, dtype=int).ravel()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    sc = np.asarray(scores, dtype=np.float64).ravel()
    if not (len(ids) == len(pts) == len(sc)):
        raise ValueError(f"keypoint_ids, points and scores differ in length: {len(ids)}, {len(pts)}, {len(sc)}")
    if np.any((ids < 0) | (ids >= NUM_KEYPOINTS)):
        raise ValueError(f"keypoint ids must be in 0..{NUM_KEYPOINTS - 1}, got {sorted(set(ids.tolist()))}")
    if max_hypotheses < 1:
        raise ValueError(f"max_hypotheses must be >= 1, got {max_hypotheses}")
    cuboid = np.asarray(cuboid_points, dtype=np.float64).reshape(NUM_KEYPOINTS, 3)
    K = np.asarray(K, dtype=np.float64)
    usable = np.all(np.isfinite(pts), axis=1) & np.isfinite(sc)
    by_type = {k: np.flatnonzero(usable & (ids == k)) for k in range(NUM_KEYPOINTS)}
    by_type = {k: v for k, v in by_type.items() if v.size}
    corner_types = [k for k in by_type if k != CENTROID_INDEX]
    if CENTROID_INDEX not in by_type or len(corner_types) < 3:
        return None
    anchor = by_type[CENTROID_INDEX][0]
    sets = _minimal_sets([by_type[k] for k in corner_types], int(max_hypotheses))
    weight = np.clip(sc, 0.0, 1.0)
    quads = np.concatenate([sets, np.full((len(sets), 1), anchor)], axis=1)   # (S, 4): 3 corners + centroid
    objs, imgs = cuboid[ids[quads]], np.ascontiguousarray(pts[quads])

    min_points = int(pnp_options.get("min_points", DEFAULT_MIN_POINTS))
    best_score, best_nearest, best_err, most_explained = -1.0, None, None, 0
    for start in range(0, len(sets), _HYPOTHESIS_CHUNK):
        rvecs, tvecs = [], []
        for q in range(start, min(start + _HYPOTHESIS_CHUNK, len(sets))):
            try:
                ok, rvec, tvec = cv2.solvePnP(objs[q], imgs[q], K, None, flags=cv2.SOLVEPNP_AP3P)
            except cv2.error:
                continue
            if ok and np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
                rvecs.append(rvec.ravel())
                tvecs.append(tvec.ravel())
        if not rvecs:
            continue
        # Score the chunk at once: (H, 9, 3) camera-frame cuboids -> (H, 9, 2) projections.
        cam = np.einsum("hij,kj->hki", Rotation.from_rotvec(np.asarray(rvecs)).as_matrix(), cuboid)
        cam += np.asarray(tvecs)[:, None, :]
        z = cam[..., 2]
        proj = (cam @ K.T)[..., :2] / np.where(z > 0, z, np.nan)[..., None]
        err = np.linalg.norm(proj[:, ids] - pts[None], axis=2)               # (H, n)
        err = np.where(usable[None] & np.isfinite(err), err, np.inf)
        centre_err = np.linalg.norm(proj[:, CENTROID_INDEX] - pts[anchor], axis=1)
        err[~(centre_err <= hypothesis_threshold_px) | (z[:, CENTROID_INDEX] <= 0)] = np.inf
        total = np.zeros(len(err))
        explained = np.zeros(len(err), dtype=int)
        nearest = {}
        for k, cols in by_type.items():
            j = cols[np.argmin(err[:, cols], axis=1)]                         # (H,) nearest candidate
            inside = err[np.arange(len(err)), j] <= hypothesis_threshold_px
            nearest[k] = j
            total += np.where(inside, weight[j], 0.0)
            explained += inside
        h = int(np.argmax(total))
        if np.isfinite(err[h]).any() and total[h] > best_score:
            best_score, best_err = total[h], err[h]
            best_nearest = {k: int(j[h]) for k, j in nearest.items()}
        most_explained = max(most_explained, int(explained.max()))
        if most_explained == len(by_type):
            break  # a hypothesis explains every type present: none can explain more
        if start + _HYPOTHESIS_CHUNK >= _GIVE_UP_AFTER and most_explained <= quads.shape[1]:
            break  # nothing beyond its own minimal set: peaks of no rigid cuboid (clutter)
    if best_nearest is None:
        return None
    final_px = float(pnp_options.get("reprojection_threshold_px", DEFAULT_REPROJECTION_PX))
    if sum(best_err[j] <= final_px for j in best_nearest.values()) < min_points:
        return None  # fewer than min_points keypoints near the best pose: spare solve_pnp's RANSAC
    kp = np.full((NUM_KEYPOINTS, 2), np.nan)
    kp_scores = np.zeros(NUM_KEYPOINTS)
    for k, j in best_nearest.items():
        if best_err[j] > hypothesis_threshold_px:
            j = int(by_type[k][np.argmax(sc[by_type[k]])])
        kp[k], kp_scores[k] = pts[j], sc[j]
    return solve_pnp(kp, kp_scores, cuboid, K, **pnp_options)
