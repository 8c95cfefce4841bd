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
   by the current pose, takes its nearest model point (a
   :class:`~dope_hope.refine.nearest.NearestPointGrid` of the model, built once per model: a
   lookup of a few tens of nanoseconds where ``scipy.spatial.cKDTree`` takes about 2 us, and
   ICP makes some 140,000 of them a detection); pairs farther apart than the iteration's
   threshold (``thresholds_m``, shrinking from 3 cm to 5 mm) are dropped, which trims
   background, occluders in front and the other side of the object alike. Only the scene's
   visible surface is matched, so no visibility test of the model is needed.
3. **Update**: the linearised point-to-plane problem (residual ``(x - m) . n`` along the
   model normal ``n``) is a 6x6 least-squares solve for a small rotation ``w`` and a shift
   ``v``; its minimum-norm solution (the pseudo-inverse of the 6x6 normal equations, every
   start's at once) is the step, so a direction the surface does not constrain (the roll of
   a round bottle) is left where the keypoints put it. Hand-written
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
   the input's (beyond ``fit_tie``), it moved less than ``max_translation_m`` (and turned
   less than ``max_rotation_deg``, by default no bound) and it keeps to the object's own
   depth support; otherwise the input pose is returned with the reason (bad depth never
   changes a pose, as for the line search).
6. **Own depth support** (:func:`depth_support`): the fit only counts the scene points, so it
   cannot see a pose that grew or slid onto something else: a box hidden behind a board,
   moved to the board's depth, projects twice as large and fits the board as well as the
   box would. A pose's own support is the share of its visible model points, leaving out
   those an occluder hides, that the depth confirms (within ``fit_threshold_m``) inside the
   image region of the input pose (its silhouette, dilated by ``mask_dilate`` as for the
   scene points). The refined pose needs at least ``min_own_support``. The region is the
   input's (after -LS), not the keypoints' pose before the line search: a keypoints' pose at
   the wrong distance has a silhouette of the wrong size, and with it as the region the
   30-minute Ketchup model's recall at 2 cm with -LS + ICP fell from 60.5 to 50.3 % on the
   e2e bench's held-out frames
   (bench/RESULTS.md, "Post-processing vs the official decoder"); a start that the line
   search would move onto an occluder is the line search's own check (``DopePredictor``'s
   second search). Where the pose is right the share is the part of its surface the sensor
   measured (0.6-0.9 on the demo scenes); a pose that snapped to a distractor claims surface
   outside the region, or where the sensor saw nothing or saw through it (0.13 on the demo
   scene that showed it).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.config import (
    SectionSettings,
    at_least,
    each,
    fraction,
    nonnegative_float,
    one_of,
    or_none,
    positive_float,
)
from dope_hope.errors import ConfigError
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.line_search import auto_splat_px, visible_points
from dope_hope.refine.nearest import ExactNearest, NearestLookup, nearest_point_grid

#: Extra ICP starts: the input turned by +-90 and 180 deg about the model's x, y and z axes.
TURN_STARTS: tuple[np.ndarray, ...] = tuple(
    Rotation.from_euler(axis, deg, degrees=True).as_matrix() for axis in "xyz" for deg in (90, -90, 180))
#: (32, 2) the unit circle's rim: a silhouette's dilation by a disk (:func:`silhouette_mask`).
_RIM = np.stack([np.cos(np.arange(32) * np.pi / 16), np.sin(np.arange(32) * np.pi / 16)], axis=1)
#: Correspondence distance per iteration, metres (coarse to fine).
DEFAULT_THRESHOLDS_M: tuple[float, ...] = (0.03, 0.03, 0.02, 0.02, 0.015, 0.015, 0.01, 0.01,
                                           0.0075, 0.0075, 0.005, 0.005, 0.005, 0.005)


def _rotation_list(value: Any, name: str) -> tuple[tuple[tuple[float, ...], ...], ...]:
    """The rule of a list (maybe empty) of (3, 3) matrices of finite numbers; nested tuples."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
        raise ConfigError(f"{name} must be a list of 3x3 matrices, got {value!r}")
    out = []
    for m in value:
        try:
            a = np.asarray(m, dtype=np.float64)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape != (3, 3) or not np.isfinite(a).all():
            raise ConfigError(f"{name} must be a list of 3x3 matrices of finite numbers, got an entry {m!r}")
        out.append(tuple(tuple(row) for row in a.tolist()))
    return tuple(out)


@dataclass(frozen=True)
class IcpSettings(SectionSettings):
    """ICP's settings (``icp_refine:`` in ``dope_hope/configs/infer.yaml``; the steps of the
    module docstring).

    thresholds_m: correspondence distance of each iteration, metres (step 2). mask_dilate:
    silhouette dilation, fraction of its bounding-box size (steps 1, 6). max_scene_points:
    most depth pixels used. min_points: fewest scene points and pairs. fit_threshold_m:
    point-to-surface distance beyond which a scene point counts 0 in the fit (step 5), metres;
    also the depth agreement of a supported point (step 6). max_translation_m,
    max_rotation_deg: largest change accepted, metres and degrees (180 deg bounds nothing: lite
    models' rotations are often 60-100 deg off about the long axis). start_rotations: (3, 3)
    model-frame rotations S (kept as nested tuples); ICP also starts from ``R @ S``; () for the
    input pose only (step 4; default :data:`TURN_STARTS`). fit_tie: runs whose fits differ by at most this are
    equal; the one whose rotation is nearest the input's wins among them. coarse_points,
    coarse_iterations, finalists: step 4's coarse phase (``coarse_points`` None: every start
    runs every iteration on all points). min_own_support: least own depth support of a pose
    (step 6), in [0, 1]. nearest: how a scene point finds its model point (step 2): "grid" (a
    :class:`~dope_hope.refine.nearest.NearestPointGrid`) or "exact" (``scipy``'s cKDTree,
    2.8-3.0x slower a detection: the baseline).
    """

    SECTION = "icp_refine"
    RULES = {"thresholds_m": each(positive_float), "mask_dilate": nonnegative_float,
             "max_scene_points": at_least(1), "min_points": at_least(1), "fit_threshold_m": positive_float,
             "max_translation_m": nonnegative_float, "max_rotation_deg": nonnegative_float,
             "start_rotations": _rotation_list, "fit_tie": nonnegative_float,
             "coarse_points": or_none(at_least(0)), "coarse_iterations": at_least(0), "finalists": at_least(0),
             "min_own_support": fraction, "nearest": one_of("grid", "exact")}

    thresholds_m: tuple[float, ...] = DEFAULT_THRESHOLDS_M
    mask_dilate: float = 0.15
    max_scene_points: int = 3000
    min_points: int = 50
    fit_threshold_m: float = 0.01
    max_translation_m: float = 0.05
    max_rotation_deg: float = 180.0
    start_rotations: tuple = TURN_STARTS
    fit_tie: float = 0.005
    coarse_points: int | None = 750
    coarse_iterations: int = 6
    finalists: int = 3
    min_own_support: float = 0.3
    nearest: str = "grid"


@dataclass
class IcpResult:
    """Outcome of :func:`icp_refine`.

    R: (3, 3), t: (3,) metres: the refined pose (the input pose when not applied).
    applied: whether the pose changed. reason: "ok" or why not.
    fit_before / fit_after: soft fraction of the scene points on the model surface (1 = all
        exactly on it; see step 5) under the input / refined pose (NaN when not evaluated).
    own_support: the refined pose's own depth support (step 6; NaN when not evaluated).
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
    own_support: float = float("nan")


def silhouette_mask(points_c: np.ndarray, K: np.ndarray, hw: tuple[int, int], dilate: float) -> np.ndarray:
    """(H, W) bool: the convex hull of projected points, dilated by ``dilate`` times its larger
    bounding-box side (all False when fewer than three points project).

    Args:
        points_c: (N, 3) camera-frame points, metres (those at z <= 0 are ignored).
        K: (3, 3). hw: (H, W) of the image. dilate: see above.
    """
    H, W = hw
    uvw = points_c[points_c[:, 2] > 1e-6] @ K.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    # far off-image points only widen the hull; clipping keeps the int32 cast exact
    uv = np.clip(uv[np.isfinite(uv).all(axis=1)], -4.0 * max(H, W), 5.0 * max(H, W))
    mask = np.zeros((H, W), np.uint8)
    if len(uv) < 3:
        return mask.astype(bool)
    hull = cv2.convexHull(np.round(uv).astype(np.float32).reshape(-1, 1, 2)).reshape(-1, 2)
    r = int(round(dilate * float(max(np.ptp(uv[:, 0]), np.ptp(uv[:, 1])))))
    if r > 0:  # a convex polygon dilated by a disk: the hull of its corners moved around the disk's rim
        hull = cv2.convexHull((hull[:, None, :] + r * _RIM[None]).reshape(-1, 1, 2).astype(np.float32)).reshape(-1, 2)
    cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    return mask.astype(bool)


def points_in_region(region: np.ndarray, D: np.ndarray, K: np.ndarray, max_points: int) -> np.ndarray:
    """(M, 3) camera-frame points, metres, of the valid depth pixels of ``region`` ((H, W) bool)
    in depth D ((H, W) metres, NaN invalid; K (3, 3)), thinned evenly to at most ``max_points``."""
    v, u = np.nonzero(region & np.isfinite(D))
    if len(u) > max_points:
        keep = np.linspace(0, len(u) - 1, max_points).round().astype(np.int64)
        u, v = u[keep], v[keep]
    z = D[v, u]
    return np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)


def depth_support(R: np.ndarray, t: np.ndarray, model_points: np.ndarray, depth: DepthImage,
                  region: np.ndarray, tolerance_m: float) -> float:
    """A pose's own depth support (step 6 of the module docstring): the share of its visible,
    unoccluded model points that the depth confirms inside the detected region.

    A visible model point is confirmed where the depth at its pixel is within
    ``tolerance_m`` of its own depth, occluded where the depth lies farther than that in
    front of it (an occluder says nothing against the pose); a point with no depth or with
    depth behind it (the sensor sees through where the surface would be) counts against it.

    Args:
        R: (3, 3), t: (3,) metres: the pose. model_points: (N, 3) surface points, metres.
        depth: the depth image with its K. region: (H, W) bool, the detected region.
        tolerance_m: depth agreement of a confirmed point, metres.

    Returns:
        The share in [0, 1]; NaN when no visible point is unoccluded.
    """
    D, K = depth.metres, depth.K
    X = np.asarray(model_points, np.float64) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64)
    X = X[visible_points(X, K, D.shape, auto_splat_px(model_points, K, float(t[2])))]
    uvw = X @ K.T
    u = np.rint(uvw[:, 0] / uvw[:, 2]).astype(np.int64)
    v = np.rint(uvw[:, 1] / uvw[:, 2]).astype(np.int64)  # visible points project into the image
    r = D[v, u] - X[:, 2]  # NaN: no depth
    with np.errstate(invalid="ignore"):
        confirmed, occluded = np.abs(r) <= tolerance_m, r < -tolerance_m
    n = int((~occluded).sum())
    return float((confirmed & region[v, u]).sum() / n) if n else float("nan")


def own_depth_support(R: np.ndarray, t: np.ndarray, model_points: np.ndarray, depth: DepthImage,
                      settings: IcpSettings) -> float:
    """The own depth support (step 6) of a pose (R (3, 3), t (3,) metres) in its own detected
    region: its silhouette dilated by ``settings.mask_dilate``, confirmed within
    ``settings.fit_threshold_m``. ``model_points``: (N, 3) surface points, metres. A share in
    [0, 1] (NaN: no visible point unoccluded); at ``settings.min_own_support`` or more the depth
    confirms the object where the pose puts it (:func:`support_problem`)."""
    P = np.asarray(model_points, dtype=np.float64).reshape(-1, 3)
    region = silhouette_mask(P @ np.asarray(R, np.float64).T + np.asarray(t, np.float64).reshape(3), depth.K,
                             depth.hw, settings.mask_dilate)
    return depth_support(R, t, P, depth, region, settings.fit_threshold_m)


def _fits(grid: NearestLookup, PN: np.ndarray, x: np.ndarray, threshold_m: float) -> np.ndarray:
    """Soft inlier fractions of model-frame scene points ``x`` (B, n, 3) under B poses: per pose
    the mean of ``1 - (r / tau)^2`` over its n points, ``r`` the point-to-plane distance to the
    nearest model point (``grid``; ``PN`` (M, 6) the model's points and normals) when that point
    is within ``tau = threshold_m`` (else 0); 1 = every point on the surface. (B,); NaN where n
    is 0."""
    if not x.shape[1]:
        return np.full(len(x), np.nan)
    diff, normals, near = _pairs(grid, PN, x, threshold_m)
    r = np.sum(diff * normals, axis=-1)
    return np.where(near, np.clip(1.0 - (r / threshold_m) ** 2, 0.0, 1.0), 0.0).sum(axis=1) / x.shape[1]


def _pairs(grid: NearestLookup, PN: np.ndarray, x: np.ndarray, threshold_m: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 for model-frame scene points ``x`` (B, n, 3): (x minus its nearest model point
    (B, n, 3), that point's normal (B, n, 3), whether the pair is within ``threshold_m`` (B, n)
    bool); ``PN`` (M, 6) the model's points and normals, ``grid`` its lookup."""
    idx = grid.nearest(x)
    mn = PN[idx]
    diff = x - mn[..., :3]
    return diff, mn[..., 3:], (idx >= 0) & (np.sum(diff * diff, axis=-1) <= threshold_m ** 2)


def _in_model_frame(S: np.ndarray, Rs: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """(n, 3) camera-frame scene points under B poses (Rs (B, 3, 3), ts (B, 3)) -> (B, n, 3)
    model-frame points ``(S - t) @ R``."""
    return np.matmul(S[None] - ts[:, None, :], Rs)


def _iterate(S: np.ndarray, PN: np.ndarray, grid: NearestLookup, Rs: np.ndarray, ts: np.ndarray,
             thresholds_m: Sequence[float], min_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Point-to-plane ICP from B starts at once (Rs (B, 3, 3), ts (B, 3); ``PN`` (M, 6) the
    model's points and normals), an iteration of all of them per threshold: (Rs, ts, rmse_m
    (B,), problems) with ``problems[b]`` "" for a start that kept the object, else why it
    stopped (its pose then meaningless). Each start's step is the minimum-norm solution of its
    6x6 normal equations (the pseudo-inverse: the least-squares step of the module docstring, a
    direction the surface does not constrain left alone)."""
    Rs, ts = np.array(Rs, dtype=np.float64), np.array(ts, dtype=np.float64)
    rmse = np.full(len(Rs), np.nan)
    problems = [""] * len(Rs)
    live = np.arange(len(Rs))
    for th in thresholds_m:
        x = _in_model_frame(S, Rs[live], ts[live])  # (b, n, 3)
        diff, n, pair = _pairs(grid, PN, x, th)
        count = pair.sum(axis=1)
        for b, c in zip(live, count):
            if c < min_points:
                problems[b] = f"ICP lost the object ({int(c)} pairs within {th * 100:.1f} cm)"
        keep = count >= min_points
        live, x, n, diff, pair, count = live[keep], x[keep], n[keep], diff[keep], pair[keep], count[keep]
        if not len(live):
            break
        w = pair.astype(np.float64)
        r = np.sum(diff * n, axis=-1) * w
        A = np.concatenate([np.cross(x, n), n], axis=2) * w[..., None]  # (b, n, 6)
        At = A.transpose(0, 2, 1)
        step = -np.matmul(np.linalg.pinv(np.matmul(At, A), rcond=1e-12, hermitian=True),
                          np.matmul(At, r[..., None]))  # (b, 6, 1)
        rmse[live] = np.sqrt(np.sum((r + np.matmul(A, step)[..., 0]) ** 2, axis=1) / count)
        step = step[..., 0]
        # x' = dR x + v in the model frame  <=>  R' = R dR^T, t' = t - R' v
        Rs[live] = Rs[live] @ Rotation.from_rotvec(step[:, :3]).as_matrix().transpose(0, 2, 1)
        ts[live] = ts[live] - np.einsum("bij,bj->bi", Rs[live], step[:, 3:])
    return Rs, ts, rmse, problems


@dataclass
class _Search:
    """What every ICP run of one call shares: scene points, model, its grid and the settings."""

    S: np.ndarray
    PN: np.ndarray
    grid: NearestLookup
    thresholds_m: Sequence[float]
    min_points: int
    fit_threshold_m: float

    def fits(self, S: np.ndarray, Rs: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """(B,) fits of scene points S (n, 3) under B poses."""
        return _fits(self.grid, self.PN, _in_model_frame(S, Rs, ts), self.fit_threshold_m)

    def coarse(self, Rs: np.ndarray, ts: np.ndarray, coarse_points: int, iterations: int, finalists: int
               ) -> tuple[np.ndarray, np.ndarray, str]:
        """Step 4's coarse phase: every start (Rs (B, 3, 3), ts (B, 3); the plain one first), the
        first ``iterations`` on a thinned scene; the plain start and the ``finalists``
        best-fitting others go on. Returns (their Rs, ts; the first problem met)."""
        sub = self.S[np.linspace(0, len(self.S) - 1, coarse_points).round().astype(np.int64)]
        sub_min = max(10, round(self.min_points * len(sub) / len(self.S)))
        Rc, tc, _, problems = _iterate(sub, self.PN, self.grid, Rs, ts, self.thresholds_m[:iterations], sub_min)
        ok = np.array([not p for p in problems])
        fits = np.full(len(Rs), -np.inf)
        fits[ok] = self.fits(sub, Rc[ok], tc[ok])
        others = [i for i in np.argsort(-fits[1:], kind="stable") + 1 if ok[i]][:finalists]
        chosen = ([0] if ok[0] else []) + others
        return Rc[chosen], tc[chosen], next((p for p in problems if p), "")

    def runs(self, Rs: np.ndarray, ts: np.ndarray, coarse_points: int | None, coarse_iterations: int,
             finalists: int) -> tuple[list, str]:
        """Step 4: ICP from every start (Rs (B, 3, 3), ts (B, 3); the coarse phase first when it
        applies): ([(fit, R, t, rmse_m)] of the runs that kept the object, the first problem met)."""
        fine, coarse_problem = self.thresholds_m, ""
        if len(Rs) > 1 and coarse_points and len(self.S) > coarse_points and len(fine) > coarse_iterations:
            Rs, ts, coarse_problem = self.coarse(Rs, ts, coarse_points, coarse_iterations, finalists)
            fine = fine[coarse_iterations:]
        if not len(Rs):
            return [], coarse_problem
        Rf, tf, rmse, problems = _iterate(self.S, self.PN, self.grid, Rs, ts, fine, self.min_points)
        ok = [i for i, p in enumerate(problems) if not p]
        fits = self.fits(self.S, Rf[ok], tf[ok]) if ok else []
        runs = [(float(f), Rf[i], tf[i], float(rmse[i])) for f, i in zip(fits, ok)]
        return runs, coarse_problem or next((p for p in problems if p), "")


def _model_arrays(model_points, model_normals) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points and normals as float64; ValueError for a programming mistake."""
    P = np.asarray(model_points, dtype=np.float64).reshape(-1, 3)
    N = np.asarray(model_normals, dtype=np.float64).reshape(-1, 3)
    if len(P) != len(N):
        raise ValueError(f"{len(P)} model points but {len(N)} normals")
    return P, N


def _refusal(moved_m: float, turned_deg: float, fit_after: float, fit_before: float, own_support: float,
             settings: IcpSettings) -> str:
    """Why the refined pose is refused (step 5), or "" when it is kept."""
    if moved_m > settings.max_translation_m:
        return f"ICP moved the object {moved_m * 100:.1f} cm > {settings.max_translation_m * 100:.1f} cm"
    if turned_deg > settings.max_rotation_deg:
        return f"ICP turned the object {turned_deg:.0f} deg > {settings.max_rotation_deg:.0f} deg"
    if fit_after < fit_before - settings.fit_tie:
        return f"ICP fits the depth worse (fit {fit_after:.3f} < {fit_before:.3f})"
    return support_problem("ICP", own_support, settings.min_own_support)


def _nearest_best_run(runs: list, R0: np.ndarray, fit_tie: float) -> tuple:
    """Step 4's winner among runs [(fit, R, t, rmse_m)]: of those within ``fit_tie`` of the best
    fit, the one whose rotation is nearest the input rotation ``R0``."""
    top = max(r[0] for r in runs)
    return min((r for r in runs if r[0] >= top - fit_tie),
               key=lambda r: Rotation.from_matrix(r[1] @ R0.T).magnitude())


def support_problem(what: str, own_support: float, min_own_support: float) -> str:
    """Why a pose is refused by step 6 (``what`` names who moved it), or "" when it is kept."""
    if own_support >= min_own_support:
        return ""
    share = "none of its surface is unoccluded" if np.isnan(own_support) else \
        f"the depth confirms {100 * own_support:.0f} % of its surface there < {100 * min_own_support:.0f} %"
    return f"{what} left the object's own depth support (detected region: {share})"


def icp_refine(
    R: np.ndarray,
    t: np.ndarray,
    model_points: np.ndarray,
    model_normals: np.ndarray,
    depth: DepthImage,
    settings: IcpSettings = IcpSettings(),
) -> IcpResult:
    """Refine a pose by point-to-plane ICP against a depth image (steps of the module docstring).

    Args:
        R: (3, 3), t: (3,) metres: the pose to refine (``x_c = R x + t``), best after -LS.
        model_points, model_normals: (N, 3) surface points, metres (a few thousand), and their
            unit normals (sign irrelevant).
        depth: the depth image in metres with its K (:class:`~dope_hope.refine.depth.DepthImage`).
        settings: :class:`IcpSettings` (iterations, starts, acceptance).

    Returns:
        :class:`IcpResult`; the input pose with a reason when not applied.
    """
    s = settings
    R0 = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t0 = np.asarray(t, dtype=np.float64).reshape(3)

    def refuse(reason: str, **kw) -> IcpResult:
        return IcpResult(R=R0.copy(), t=t0.copy(), applied=False, reason=reason, **kw)

    P, N = _model_arrays(model_points, model_normals)
    if problem := depth.problem_for(t0):
        return refuse(problem)
    P_cam = P @ R0.T + t0  # (N, 3) the model in the camera frame under the input pose
    region = silhouette_mask(P_cam, depth.K, depth.hw, s.mask_dilate)
    S = points_in_region(region, depth.metres, depth.K, s.max_scene_points)
    if len(S) < s.min_points:
        return refuse(f"too few depth pixels under the object ({len(S)} < {s.min_points})", n_points=len(S))
    reach_m = max((*s.thresholds_m, s.fit_threshold_m))
    grid = nearest_point_grid(P, reach_m) if s.nearest == "grid" else ExactNearest(P, reach_m)
    search = _Search(S, np.concatenate([P, N], axis=1), grid, list(s.thresholds_m), s.min_points, s.fit_threshold_m)
    fit_before = float(search.fits(S, R0[None], t0[None])[0])
    Rs = np.stack([R0 @ np.asarray(r, float).reshape(3, 3) for r in [np.eye(3), *s.start_rotations]])
    runs, problem = search.runs(Rs, np.repeat(t0[None], len(Rs), axis=0), s.coarse_points, s.coarse_iterations,
                                s.finalists)
    if not runs:
        return refuse(problem, fit_before=fit_before, n_points=len(S))
    fit_after, Rc, tc, rmse = _nearest_best_run(runs, R0, s.fit_tie)
    own_support = depth_support(Rc, tc, P, depth, region, s.fit_threshold_m)
    kw = dict(fit_before=fit_before, fit_after=fit_after, rmse_m=rmse, n_points=len(S), own_support=own_support)
    turned_deg = float(np.degrees(Rotation.from_matrix(Rc @ R0.T).magnitude()))
    if reason := _refusal(float(np.linalg.norm(tc - t0)), turned_deg, fit_after, fit_before, own_support, s):
        return refuse(reason, **kw)
    return IcpResult(R=Rc, t=tc, applied=True, reason="ok", **kw)
