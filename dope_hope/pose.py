"""Poses from 2D cuboid keypoints (PnP-RANSAC) and the depth line search ("-LS").

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

**Depth line search** (:func:`depth_line_search`, the HOPE paper's "-LS"). Monocular poses
are most uncertain along the viewing ray; with a depth image the translation is rescaled,
``t' = s t``, keeping R. The model points (a dense surface sampling, metres) are
projected under the initial pose and z-buffered on the image grid (the nearest point per
pixel, ``np.minimum.at``, then a minimum filter about as wide as the point spacing so that
the far side does not show through the gaps between front points); points within a small,
slope-aware margin of the nearest surface are *visible* (:func:`visible_points`; with
``model_normals`` back faces are culled first); visibility is decided once, under the
initial pose. For each candidate ``s`` the visible points are moved *exactly*,
``x_c = R x + s t`` - their depth is ``(R x)_z + s t_z``, not ``s`` times the old depth, and
they project to slightly different pixels, so the projection is recomputed for every
candidate (the "ray model", which scales the whole camera-frame object by ``s``, would keep
pixels fixed but change the object's size). The observed depth ``D`` is sampled bilinearly
(nearest pixel where a neighbour is invalid) and the cost is the median of ``|D - z|``
(``cost="median"``, robust to < 50 % occlusion) or the mean Huber loss (``cost="huber"``).
The search is bounded (``search``): a coarse grid, then ``scipy.optimize.minimize_scalar``
(bounded Brent) between the grid neighbours of the best node.

Bad depth never changes the pose: ``applied=False`` with a ``reason`` when the depth is
missing, not 2-D, of another size than the image (``image_hw``) or than ``K`` implies
(``2 c + 1`` more than 25 % away from the depth's width or height),
without valid pixels, when too few visible points have valid depth (``min_valid``), when the
optimum sits on the search bound or its residual exceeds ``max_residual_m``.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import minimum_filter
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree
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

#: Depth scale factor of the HOPE RealSense frames (their depth was rescaled by this).
HOPE_REALSENSE_DEPTH_CALIBRATION = 0.98042517


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


# ----------------------------------------------------------------------------------------
# Depth line search


@dataclass
class LineSearchResult:
    """Outcome of :func:`depth_line_search`.

    t: (3,) translation, metres (the input t when not applied).
    applied: whether t was changed. reason: "ok" or why not.
    scale: s with ``t = s * t_in`` (1.0 when not applied).
    residual_m: median |D - z| of the visible points at the optimum, metres (NaN when not
        evaluated).
    n_valid: visible model points with valid depth at the optimum.
    """

    t: np.ndarray
    applied: bool
    reason: str
    scale: float = 1.0
    residual_m: float = float("nan")
    n_valid: int = 0


def _depth_to_metres(depth, depth_scale_m: float, calibration: float) -> np.ndarray:
    d = np.asarray(depth)
    if np.issubdtype(d.dtype, np.integer):
        m = d.astype(np.float64) * depth_scale_m
    else:
        m = d.astype(np.float64)
    m = m * calibration
    m[~np.isfinite(m) | (m <= 0)] = np.nan
    return m


def depth_in_metres(depth, K: np.ndarray, t: np.ndarray, depth_scale_m: float = 0.001,
                    calibration: float = 1.0, image_hw: tuple[int, int] | None = None,
                    ) -> tuple[np.ndarray | None, str]:
    """Check a depth image against the pose and K; convert it to metres.

    Args:
        depth: (H, W) integer depth in units of ``depth_scale_m``, or float metres (or None).
        K: (3, 3). t: (3,) metres, the pose's translation. image_hw: (H, W) the depth must have.

    Returns:
        ((H, W) float metres with NaN where invalid, "") or (None, the one-line problem): no
        depth, not 2-D, another size than the image or than K implies, the pose behind the
        camera, no valid pixel.
    """
    if depth is None:
        return None, "no depth image"
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2 or d.size == 0:
        return None, f"depth must be a 2-D image, got shape {d.shape}"
    H, W = d.shape
    if image_hw is not None and (H, W) != tuple(image_hw):
        return None, f"depth is {W}x{H}, the image is {image_hw[1]}x{image_hw[0]}"
    # K's principal point sits near the image centre: a depth image of another resolution
    # (e.g. half size with a full-size K) puts it far off (2cx+1 vs W by > 25 %).
    implied_w, implied_h = 2 * K[0, 2] + 1, 2 * K[1, 2] + 1
    if not (0.75 < implied_w / W < 1.33 and 0.75 < implied_h / H < 1.33):
        return None, (f"depth is {W}x{H} but K implies about {implied_w:.0f}x{implied_h:.0f} "
                      "(principal point far from the depth image centre)")
    if t[2] <= 0:
        return None, "pose is behind the camera (t_z <= 0)"
    D = _depth_to_metres(d, depth_scale_m, calibration)
    if not np.isfinite(D).any():
        return None, "depth has no valid pixel (all zero / NaN)"
    return D, ""


def visible_points(
    points_c: np.ndarray, K: np.ndarray, hw: tuple[int, int], splat_px: int = 2,
    margin_m: float = 0.005, max_slope: float = 2.0, normals_c: np.ndarray | None = None,
) -> np.ndarray:
    """Which camera-frame points are visible (front-most in their pixel neighbourhood).

    The nearest point per pixel is z-buffered (``np.minimum.at``), then the buffer is
    min-filtered over ``(2*splat_px+1)^2`` pixels so that the far side cannot show through
    the gaps between sampled front points. A point is visible if its depth is within
    ``margin_m + splat_px * (z / fx) * max_slope`` of that local minimum: the second term is
    the depth change of a surface inclined up to ``atan(max_slope)`` (63 deg) across the
    filter window, so inclined front faces are mostly not hidden by their own nearer parts
    (faces steeper than that can lose points: harmless, they only drop out of the fit).
    Given normals, back-facing points are dropped first, so none of the far side leaks in.

    Args:
        points_c: (N, 3) camera-frame points, metres.
        K: (3, 3). hw: (H, W) of the image.
        splat_px: filter radius, pixels; should be about the point spacing in pixels.
        margin_m: depth tolerance, metres. max_slope: see above.
        normals_c: optional (N, 3) camera-frame outward normals.

    Returns:
        (N,) bool; points behind the camera or outside the image are not visible.
    """
    H, W = hw
    z = points_c[:, 2]
    vis = np.zeros(len(points_c), dtype=bool)
    front = z > 1e-6
    if normals_c is not None:
        front &= np.einsum("ij,ij->i", np.asarray(normals_c, dtype=np.float64), points_c) < 0
    if not front.any():
        return vis
    uvw = points_c[front] @ K.T
    u = np.rint(uvw[:, 0] / uvw[:, 2]).astype(np.int64)
    v = np.rint(uvw[:, 1] / uvw[:, 2]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    if not inside.any():
        return vis
    fi = np.flatnonzero(front)[inside]
    u, v, zf = u[inside], v[inside], z[fi]
    # Crop to the points' bounding box (plus the splat) to keep the filter cheap.
    u0, v0 = max(u.min() - splat_px, 0), max(v.min() - splat_px, 0)
    u1, v1 = min(u.max() + splat_px, W - 1), min(v.max() + splat_px, H - 1)
    hh, ww = v1 - v0 + 1, u1 - u0 + 1
    pix = (v - v0) * ww + (u - u0)
    zbuf = np.full(hh * ww, np.inf)
    np.minimum.at(zbuf, pix, zf)  # nearest point per pixel
    zbuf = zbuf.reshape(hh, ww)
    if splat_px > 0:
        zbuf = minimum_filter(zbuf, size=2 * splat_px + 1, mode="nearest")
    tol = margin_m + splat_px * zf / K[0, 0] * max_slope
    vis[fi] = zf <= zbuf.ravel()[pix] + tol
    return vis


def auto_splat_px(model_points: np.ndarray, K: np.ndarray, depth_m: float) -> int:
    """Half the typical spacing of the model points in pixels at ``depth_m``, in [1, 6].

    The spacing is the median nearest-neighbour distance (scipy cKDTree, on at most 1000
    query points); a (2r+1)-wide window then covers the gaps between front points.
    """
    P = np.asarray(model_points, dtype=np.float64)
    if len(P) < 2:
        return 1
    query = P[:: max(1, len(P) // 1000)]
    d, _ = cKDTree(P).query(query, k=2)
    spacing_px = float(np.median(d[:, 1])) * float(K[0, 0]) / max(depth_m, 1e-6)
    return int(np.clip(np.ceil(spacing_px / 2.0), 1, 6))


def _sample_depth(D: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear depth at (u, v); nearest pixel where a neighbour is invalid; NaN outside."""
    H, W = D.shape
    out = np.full(u.shape, np.nan)
    ok = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    if not ok.any():
        return out
    uu, vv = u[ok], v[ok]
    x0 = np.clip(np.floor(uu).astype(np.int64), 0, W - 2 if W > 1 else 0)
    y0 = np.clip(np.floor(vv).astype(np.int64), 0, H - 2 if H > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = uu - x0, vv - y0
    d00, d01, d10, d11 = D[y0, x0], D[y0, x1], D[y1, x0], D[y1, x1]
    bil = (d00 * (1 - fx) + d01 * fx) * (1 - fy) + (d10 * (1 - fx) + d11 * fx) * fy
    near = D[np.rint(vv).astype(np.int64), np.rint(uu).astype(np.int64)]
    out[ok] = np.where(np.isfinite(bil), bil, near)
    return out


def depth_line_search(
    R: np.ndarray,
    t: np.ndarray,
    model_points: np.ndarray,
    depth,
    K: np.ndarray,
    depth_scale_m: float = 0.001,
    calibration: float = 1.0,
    search: tuple[float, float] = (0.8, 1.25),
    min_valid: int = 50,
    cost: str = "median",
    huber_delta_m: float = 0.01,
    visibility_margin_m: float = 0.005,
    splat_px: int | None = None,
    grid_steps: int = 41,
    max_residual_m: float | None = 0.02,
    image_hw: tuple[int, int] | None = None,
    model_normals: np.ndarray | None = None,
) -> LineSearchResult:
    """Rescale the translation along its ray to agree with a depth image (HOPE "-LS").

    Args:
        R: (3, 3), t: (3,) metres: the pose to refine (``x_c = R x + t``).
        model_points: (N, 3) model surface points, metres (a few thousand is plenty).
        depth: (H, W) depth image: integer (e.g. uint16) in units of ``depth_scale_m``, or
            float metres; 0 / NaN / inf = invalid.
        K: (3, 3) intrinsics of the depth image (registered to the colour camera).
        depth_scale_m: metres per integer depth unit (0.001 for uint16 millimetres).
        calibration: multiplies the depth in metres (the HOPE RealSense frames need
            :data:`HOPE_REALSENSE_DEPTH_CALIBRATION`).
        search: (lo, hi) bounds of the scale s.
        min_valid: minimum visible points with valid depth.
        cost: "median" (median |D - z|) or "huber" (mean Huber loss, ``huber_delta_m``).
        visibility_margin_m, splat_px: visibility test (see :func:`visible_points`);
            ``splat_px=None`` picks half the model points' spacing in pixels
            (:func:`auto_splat_px`).
        grid_steps: coarse grid size over ``search``.
        max_residual_m: refuse the result when the robust residual exceeds it (None = off).
        image_hw: (H, W) the depth must have, when known.
        model_normals: optional (N, 3) outward normals of the model points (back-face culling).

    Returns:
        :class:`LineSearchResult`; ``t`` unchanged with a reason when not applied.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    K = np.asarray(K, dtype=np.float64)

    def refuse(reason: str, **kw) -> LineSearchResult:
        return LineSearchResult(t=t.copy(), applied=False, reason=reason, **kw)

    if cost not in ("median", "huber"):
        raise ValueError(f"cost must be 'median' or 'huber', got {cost!r}")
    D, problem = depth_in_metres(depth, K, t, depth_scale_m, calibration, image_hw)
    if problem:
        return refuse(problem)

    P = np.asarray(model_points, dtype=np.float64).reshape(-1, 3)
    A = P @ R.T  # camera-frame points without translation
    if splat_px is None:
        splat_px = auto_splat_px(P, K, float(t[2]))
    normals_c = None if model_normals is None else np.asarray(model_normals, float).reshape(-1, 3) @ R.T
    vis = visible_points(A + t, K, D.shape, splat_px, visibility_margin_m, normals_c=normals_c)
    if not vis.any():
        return refuse("object does not project into the depth image")
    A = A[vis]

    def residuals(s: float) -> np.ndarray:
        X = A + s * t
        uvw = X @ K.T
        z = uvw[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            r = _sample_depth(D, uvw[:, 0] / z, uvw[:, 1] / z) - z
        return r[np.isfinite(r)]

    def objective(s: float) -> float:
        r = residuals(s)
        if r.size < min_valid:
            return np.inf
        a = np.abs(r)
        if cost == "median":
            return float(np.median(a))
        quad = a <= huber_delta_m
        return float(np.mean(np.where(quad, 0.5 * a * a, huber_delta_m * (a - 0.5 * huber_delta_m))))

    n0 = residuals(1.0).size
    if n0 < min_valid:
        return refuse(f"too few visible points with valid depth ({n0} < {min_valid})", n_valid=n0)

    lo, hi = float(search[0]), float(search[1])
    grid = np.linspace(lo, hi, max(int(grid_steps), 3))
    costs = np.array([objective(s) for s in grid])
    if not np.isfinite(costs).any():
        return refuse("no valid depth along the search range", n_valid=n0)
    i = int(np.argmin(costs))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    res = minimize_scalar(objective, bounds=(a, b), method="bounded", options={"xatol": 1e-6})
    s_best, c_best = (float(res.x), float(res.fun)) if res.fun <= costs[i] else (grid[i], costs[i])
    n_valid = int(residuals(s_best).size)
    residual = float(np.median(np.abs(residuals(s_best))))
    step = grid[1] - grid[0]
    at_lo = i == 0 and s_best <= lo + 0.5 * step
    at_hi = i == len(grid) - 1 and s_best >= hi - 0.5 * step
    if at_lo or at_hi:
        return refuse(f"optimum at the search bound (s = {s_best:.3f})",
                      residual_m=residual, n_valid=n_valid)
    if max_residual_m is not None and residual > max_residual_m:
        return refuse(f"depth residual {residual * 1000:.1f} mm > {max_residual_m * 1000:.1f} mm",
                      residual_m=residual, n_valid=n_valid)
    return LineSearchResult(t=s_best * t, applied=True, reason="ok", scale=s_best,
                            residual_m=residual, n_valid=n_valid)
