"""Depth ICP refinement ("-ICP"): align the model surface with the depth image, all six DoF.

The HOPE paper's "-LS" (:func:`dope_hope.refine.line_search.depth_line_search`) only rescales the
translation along its ray; the rotation stays what the keypoints gave. With a registered depth
image the whole pose can be refined: :func:`icp_refine` runs point-to-plane ICP between the
depth pixels under the object's projected silhouette and the model surface, and keeps the
result only when it fits the depth better than the input pose did.

1. **Scene points**: the model points are projected under the input pose; their convex hull,
   dilated by ``mask_dilate`` of its bounding-box size (so that the true object is covered
   when the input pose is somewhat off), selects depth pixels, back-projected to camera-frame
   points (metres) and thinned evenly to at most ``max_scene_points``.
2. **Correspondences** go from scene to model: each scene point, moved into the model frame
   by the current pose, takes its nearest model point (``scipy.spatial.cKDTree``, built
   once); pairs farther apart than the iteration's threshold (``thresholds_m``, shrinking
   from 3 cm to 5 mm) are dropped, which trims background, occluders in front and the other
   side of the object alike. Only the scene's visible surface is matched, so no visibility
   test of the model is needed.
3. **Update**: the linearised point-to-plane problem (residual ``(x - m) . n`` along the
   model normal ``n``) is a 6x6 least-squares solve for a small rotation ``w`` and a shift
   ``v``; ``numpy.linalg.lstsq`` takes the minimum-norm step, so a direction the surface does
   not constrain (the roll of a round bottle) is left where the keypoints put it. Hand-written
   because none of the project's libraries has point-to-plane ICP (OpenCV's
   ``ppf_match_3d`` ICP is in the contrib build only, Open3D is not a dependency), and the
   solve is a dozen lines.
4. **Several starts**: ICP converges only from a rotation a few tens of degrees off, and the
   keypoints of a briefly trained net often get the object turned by about 90 or 180 deg
   (the roll of a bottle about its axis, a box seen from the wrong side). ICP therefore also
   starts from the input turned by +-90 and 180 deg about each model axis
   (:data:`TURN_STARTS`, ten runs in all; each does its first, coarse iterations on a
   thinned scene, and the plain start and the three best-fitting others finish on all the
   points). The run whose pose fits the depth best wins; runs
   within ``fit_tie`` of the best count as equal and the one nearest the input rotation wins
   among them, so the depth never flips an object onto one of its own geometric
   symmetries (a box turned 180 deg fits its depth exactly as well) - there the keypoints,
   which see the texture, decide (what the starts and the coarse phase buy and cost:
   bench/RESULTS.md, ``bench/postprocess.py --only-icp``).
5. **Acceptance**: the fit is the soft fraction of scene points on the model surface (each
   point counts ``1 - (r / fit_threshold_m)^2``, ``r`` its point-to-plane distance, 0 beyond
   ``fit_threshold_m``: finer than a plain inlier count, which cannot tell a bottle's right
   roll from one a few degrees off). The refined pose is kept when its fit is not worse than
   the input's (beyond ``fit_tie``) and it moved
   less than ``max_translation_m`` (and turned less than ``max_rotation_deg``, by default no
   bound); otherwise the input pose is
   returned with the reason (bad depth never changes a pose, as for the line search).

Run it after the line search: ICP's correspondences need the object's depth within a few
centimetres, which the line search provides.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from dope_hope.refine.depth import DepthImage

#: Extra ICP starts: the input turned by +-90 and 180 deg about the model's x, y and z axes.
TURN_STARTS: tuple[np.ndarray, ...] = tuple(
    Rotation.from_euler(axis, deg, degrees=True).as_matrix() for axis in "xyz" for deg in (90, -90, 180))
#: Correspondence distance per iteration, metres (coarse to fine).
DEFAULT_THRESHOLDS_M: tuple[float, ...] = (0.03, 0.03, 0.02, 0.02, 0.015, 0.015, 0.01, 0.01,
                                           0.0075, 0.0075, 0.005, 0.005, 0.005, 0.005)


@dataclass
class IcpResult:
    """Outcome of :func:`icp_refine`.

    R: (3, 3), t: (3,) metres: the refined pose (the input pose when not applied).
    applied: whether the pose changed. reason: "ok" or why not.
    fit_before / fit_after: soft fraction of the scene points on the model surface (1 = all
        exactly on it; see step 5) under the input / refined pose (NaN when not evaluated).
    rmse_m: RMS point-to-plane residual of the last iteration's pairs, metres.
    n_points: scene points used.
    """

    R: np.ndarray
    t: np.ndarray
    applied: bool
    reason: str
    fit_before: float = float("nan")
    fit_after: float = float("nan")
    rmse_m: float = float("nan")
    n_points: int = 0


def scene_points_under(points_c: np.ndarray, D: np.ndarray, K: np.ndarray, dilate: float,
                       max_points: int) -> np.ndarray:
    """Back-projected depth pixels under the dilated silhouette of projected points.

    Args:
        points_c: (N, 3) camera-frame model points, metres (those at z <= 0 are ignored).
        D: (H, W) depth, metres, NaN = invalid. K: (3, 3).
        dilate: dilation as a fraction of the silhouette's larger bounding-box side.
        max_points: thin evenly to at most this many.

    Returns:
        (M, 3) camera-frame points, metres (M may be 0).
    """
    H, W = D.shape
    uvw = points_c[points_c[:, 2] > 1e-6] @ K.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    # far off-image points only widen the hull; clipping keeps the int32 cast exact
    uv = np.clip(uv[np.isfinite(uv).all(axis=1)], -4.0 * max(H, W), 5.0 * max(H, W))
    if len(uv) < 3:
        return np.empty((0, 3))
    hull = cv2.convexHull(np.round(uv).astype(np.int32).reshape(-1, 1, 2))
    mask = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    extent = float(max(np.ptp(uv[:, 0]), np.ptp(uv[:, 1])))
    r = int(round(dilate * extent))
    if r > 0:
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    v, u = np.nonzero(mask.astype(bool) & np.isfinite(D))
    if len(u) > max_points:
        keep = np.linspace(0, len(u) - 1, max_points).round().astype(np.int64)
        u, v = u[keep], v[keep]
    z = D[v, u]
    return np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)


def _fit(tree: cKDTree, normals: np.ndarray, x: np.ndarray, threshold_m: float) -> float:
    """Soft inlier fraction of model-frame scene points ``x``: the mean of ``1 - (r / tau)^2``
    over the points, ``r`` the point-to-plane distance to the nearest model point when that
    point is within ``tau = threshold_m`` (else 0); 1 = every point on the surface."""
    if not len(x):
        return float("nan")
    d, idx = tree.query(x, distance_upper_bound=threshold_m)
    near = np.isfinite(d)
    r = np.einsum("ij,ij->i", x[near] - tree.data[idx[near]], normals[idx[near]])
    return float(np.clip(1.0 - (r / threshold_m) ** 2, 0.0, 1.0).sum() / len(x))


def _iterate(S: np.ndarray, P: np.ndarray, N: np.ndarray, tree: cKDTree, R: np.ndarray, t: np.ndarray,
             thresholds_m: Sequence[float], min_points: int):
    """Point-to-plane ICP from (R, t): (R, t, rmse_m, "") or (None, None, nan, why it stopped)."""
    rmse = float("nan")
    for th in thresholds_m:
        x = (S - t) @ R  # scene points in the model frame
        d, idx = tree.query(x, distance_upper_bound=th)
        pair = np.isfinite(d)
        if pair.sum() < min_points:
            return None, None, rmse, f"ICP lost the object ({int(pair.sum())} pairs within {th * 100:.1f} cm)"
        x, m, n = x[pair], P[idx[pair]], N[idx[pair]]
        r = np.einsum("ij,ij->i", x - m, n)
        A = np.concatenate([np.cross(x, n), n], axis=1)
        step = np.linalg.lstsq(A, -r, rcond=1e-6)[0]
        rmse = float(np.sqrt(np.mean((r + A @ step) ** 2)))
        # x' = dR x + v in the model frame  <=>  R' = R dR^T, t' = t - R' v
        R = R @ Rotation.from_rotvec(step[:3]).as_matrix().T
        t = t - R @ step[3:]
    return R, t, rmse, ""


def icp_refine(
    R: np.ndarray,
    t: np.ndarray,
    model_points: np.ndarray,
    model_normals: np.ndarray,
    depth: DepthImage,
    thresholds_m: Sequence[float] = DEFAULT_THRESHOLDS_M,
    mask_dilate: float = 0.15,
    max_scene_points: int = 3000,
    min_points: int = 50,
    fit_threshold_m: float = 0.01,
    max_translation_m: float = 0.05,
    max_rotation_deg: float = 180.0,
    start_rotations: Sequence[np.ndarray] = TURN_STARTS,
    fit_tie: float = 0.005,
    coarse_points: int | None = 750,
    coarse_iterations: int = 6,
    finalists: int = 3,
) -> IcpResult:
    """Refine a pose by point-to-plane ICP against a depth image (see the module docstring).

    Args:
        R: (3, 3), t: (3,) metres: the pose to refine (``x_c = R x + t``), best after the
            line search.
        model_points: (N, 3) model surface points, metres (a few thousand).
        model_normals: (N, 3) their unit normals (sign irrelevant).
        depth: the depth image in metres with its K (:class:`~dope_hope.refine.depth.DepthImage`).
        thresholds_m: correspondence distance of each iteration, metres.
        mask_dilate: silhouette dilation, fraction of its bounding-box size.
        max_scene_points: depth pixels used at most.
        min_points: fewest scene points and pairs to go on with.
        fit_threshold_m: point-to-surface distance beyond which a scene point counts 0 in the
            fit (step 5).
        max_translation_m, max_rotation_deg: largest change accepted (the default 180 deg
            bounds nothing: lite models' rotations are often off by 60-100 deg about the long
            axis, which ICP corrects; the depth fit decides).
        start_rotations: (3, 3) model-frame rotations S; ICP also starts from ``R @ S`` (the
            object turned about its own origin), and the best-fitting run wins; () for the
            input pose only.
        fit_tie: runs whose fits differ by at most this are equal; the one whose rotation is
            nearest the input's wins among them.
        coarse_points, coarse_iterations, finalists: with several starts, each first runs
            ``coarse_iterations`` iterations on ``coarse_points`` evenly thinned scene points;
            the plain start and the ``finalists`` best-fitting others then finish on all
            points (None: every start runs every iteration on all points).

    Returns:
        :class:`IcpResult`; the input pose with a reason when not applied.
    """
    R0 = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t0 = np.asarray(t, dtype=np.float64).reshape(3)
    K = depth.K

    def refuse(reason: str, **kw) -> IcpResult:
        return IcpResult(R=R0.copy(), t=t0.copy(), applied=False, reason=reason, **kw)

    if not thresholds_m:
        raise ValueError("thresholds_m must name at least one iteration")
    P = np.asarray(model_points, dtype=np.float64).reshape(-1, 3)
    N = np.asarray(model_normals, dtype=np.float64).reshape(-1, 3)
    if len(P) != len(N):
        raise ValueError(f"{len(P)} model points but {len(N)} normals")
    problem = depth.problem_for(t0)
    D = depth.metres
    if problem:
        return refuse(problem)
    S = scene_points_under(P @ R0.T + t0, D, K, mask_dilate, max_scene_points)
    if len(S) < min_points:
        return refuse(f"too few depth pixels under the object ({len(S)} < {min_points})", n_points=len(S))
    tree = cKDTree(P)
    fit_before = _fit(tree, N, (S - t0) @ R0, fit_threshold_m)
    starts = [(R0 @ np.asarray(s, float).reshape(3, 3), t0) for s in [np.eye(3), *start_rotations]]
    first_problem = ""
    fine = list(thresholds_m)
    if len(starts) > 1 and coarse_points and len(S) > coarse_points and len(fine) > coarse_iterations:
        # Coarse phase: every start, the first iterations, a thinned scene; the plain start
        # and the best-fitting others go on.
        sub = S[np.linspace(0, len(S) - 1, coarse_points).round().astype(np.int64)]
        sub_min = max(10, round(min_points * len(sub) / len(S)))
        coarse = []
        for i, (Rs, ts) in enumerate(starts):
            Rc, tc, _, problem = _iterate(sub, P, N, tree, Rs, ts, fine[:coarse_iterations], sub_min)
            if problem:
                first_problem = first_problem or problem
                continue
            coarse.append((i == 0, _fit(tree, N, (sub - tc) @ Rc, fit_threshold_m), Rc, tc))
        plain = [c for c in coarse if c[0]]
        others = sorted((c for c in coarse if not c[0]), key=lambda c: -c[1])[:finalists]
        starts = [(c[2], c[3]) for c in plain + others]
        fine = fine[coarse_iterations:]
    runs = []
    for Rs, ts in starts:
        Rc, tc, rmse, problem = _iterate(S, P, N, tree, Rs, ts, fine, min_points)
        if problem:
            first_problem = first_problem or problem
            continue
        runs.append((_fit(tree, N, (S - tc) @ Rc, fit_threshold_m), Rc, tc, rmse))
    if not runs:
        return refuse(first_problem, fit_before=fit_before, n_points=len(S))
    top = max(r[0] for r in runs)
    fit_after, Rc, tc, rmse = min((r for r in runs if r[0] >= top - fit_tie),
                                  key=lambda r: Rotation.from_matrix(r[1] @ R0.T).magnitude())
    moved_m = float(np.linalg.norm(tc - t0))
    turned_deg = float(np.degrees(Rotation.from_matrix(Rc @ R0.T).magnitude()))
    kw = dict(fit_before=fit_before, fit_after=fit_after, rmse_m=rmse, n_points=len(S))
    if moved_m > max_translation_m:
        return refuse(f"ICP moved the object {moved_m * 100:.1f} cm > {max_translation_m * 100:.1f} cm", **kw)
    if turned_deg > max_rotation_deg:
        return refuse(f"ICP turned the object {turned_deg:.0f} deg > {max_rotation_deg:.0f} deg", **kw)
    if fit_after < fit_before - fit_tie:
        return refuse(f"ICP fits the depth worse (fit {fit_after:.3f} < {fit_before:.3f})", **kw)
    return IcpResult(R=Rc, t=tc, applied=True, reason="ok", **kw)
