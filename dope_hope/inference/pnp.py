"""Poses from 2D cuboid keypoints: PnP-RANSAC and the multi-hypothesis pose search.

**PnP** (:func:`solve_pnp`). The official DOPE drops an object as soon as one of its nine
keypoints is missing; we use whatever keypoints were found, down to ``min_points`` (>= 4):

1. ``cv2.solvePnPRansac`` on the present keypoints (OpenCV's kernel is EPnP on 5-point
   samples, or P3P + a 4th point to pick among P3P's up to four solutions when only 4 points
   exist; the consensus set is then solved with SQPnP, which also handles a planar set such as
   one face of the box). Plain P3P/AP3P on 3 points is never used: with 3 points the pose is
   ambiguous (up to four exact solutions) and nothing can choose between them. Given a
   consensus pose (``initial_pose``, from :func:`solve_pnp_candidates`' search), the
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

The multi-hypothesis search (:func:`solve_pnp_candidates`) tries the least-squares pose through
each type's first candidate, then minimal sets of candidate corner peaks per centroid, and
keeps the pose that explains most candidates. :func:`solve_pnp_instances` runs it for every
centroid of an image: the first step for all at once, the search only where that step does not
decide, without the peaks that accepted poses already hold (a peak belongs to one object).
"""
from __future__ import annotations

import functools
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from dope_hope.config import (
    SectionSettings,
    at_least,
    finite_float,
    fraction,
    nonnegative_float,
    positive_float,
)
from dope_hope.errors import ConfigError
from dope_hope.geometry import CENTROID_INDEX, NUM_KEYPOINTS

#: :func:`solve_pnp` defaults, also what :func:`solve_pnp_candidates` checks its best
#: hypothesis against before calling it.
DEFAULT_MIN_POINTS = 5
DEFAULT_REPROJECTION_PX = 8.0
#: :func:`solve_pnp_candidates`' budget, in AP3P minimal sets: the most it solves by default;
#: it stops when ``_STALL_AFTER`` sets in a row found no better hypothesis (clutter: none ever
#: fits; a noisy box's last improvement came by the 51st set, its first fit by the 33rd, on
#: the README video test's 320x240 frames, where stopping after 8 unfit or 32 unexplaining sets
#: lost two boxes); a hypothesis explaining all keypoint types present but one, and at least
#: ``_ENOUGH_TYPES``, ends the search.
DEFAULT_MAX_HYPOTHESES = 400
#: A candidate supports a pose hypothesis within this distance of its projection, px.
DEFAULT_HYPOTHESIS_PX = 5.0
_STALL_AFTER = 64
_ENOUGH_TYPES = 6
#: Minimal sets solved between two later checks of its stopping rules.
_HYPOTHESIS_CHUNK = 16


def _chunk_ends(n: int) -> list[int]:
    """How many of n minimal sets :func:`solve_pnp_candidates` has solved at each check of its
    stopping rules: 4 (any single wrong first choice is avoided by the second set), then every
    ``_HYPOTHESIS_CHUNK``, then n."""
    return sorted({min(4, n), *range(_HYPOTHESIS_CHUNK, n, _HYPOTHESIS_CHUNK), n})


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
    the final pose of :func:`solve_pnp_candidates`). Thresholds in pixels of the image the
    keypoints and ``K`` refer to.

    min_points: fewest present keypoints and inliers (>= 4: three points leave up to four
    poses). reprojection_threshold_px: RANSAC / final inlier threshold. max_mean_error_px:
    reject the pose when the mean inlier error is larger. min_score: a keypoint with score
    <= ``min_score`` is treated as missing. min_inlier_ratio: reject when fewer than this
    fraction of the present keypoints are inliers (5 of 9 random points can fit some pose;
    see the module docstring). ransac_iterations, ransac_confidence: OpenCV's RANSAC.
    """

    SECTION = "pnp"
    RULES = {"min_points": at_least(4), "reprojection_threshold_px": positive_float,
             "max_mean_error_px": nonnegative_float, "min_score": finite_float, "min_inlier_ratio": fraction,
             "ransac_iterations": at_least(1), "ransac_confidence": _open_fraction}

    min_points: int = DEFAULT_MIN_POINTS
    reprojection_threshold_px: float = DEFAULT_REPROJECTION_PX
    max_mean_error_px: float = 4.0
    min_score: float = 0.0
    min_inlier_ratio: float = 0.75
    ransac_iterations: int = 200
    ransac_confidence: float = 0.999


@dataclass(frozen=True)
class HypothesisSettings(SectionSettings):
    """The multi-hypothesis search's settings (``hypotheses:`` in
    ``dope_hope/configs/infer.yaml``; :func:`solve_pnp_candidates`).

    hypothesis_threshold_px: a candidate supports a hypothesis within this distance, px.
    max_hypotheses: most AP3P minimal sets solved.
    """

    SECTION = "hypotheses"
    RULES = {"hypothesis_threshold_px": positive_float, "max_hypotheses": at_least(1)}

    hypothesis_threshold_px: float = DEFAULT_HYPOTHESIS_PX
    max_hypotheses: int = DEFAULT_MAX_HYPOTHESES

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
            :func:`solve_pnp_candidates`): it replaces RANSAC; the present keypoints within
            ``settings.reprojection_threshold_px`` of it are the inliers refined, every check
            follows.

    Returns:
        :class:`PoseEstimate`, or None when the keypoints do not support a pose.
    """
    poses = None if initial_pose is None else ([initial_pose[0]], [initial_pose[1]])
    return _solve_pnp_many(
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
    """:func:`_solve_pnp_many`'s inputs, checked: kp (B, 9, 2) px, sc (B, 9) scores, present
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


def _solve_pnp_many(keypoints: np.ndarray, scores: np.ndarray | None, cuboid_points: np.ndarray, K: np.ndarray,
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
    ok = ((n_in >= settings.min_points) & (n_in >= settings.min_inlier_ratio * sets.n_present[which])
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


def _covering_order(n_types: int) -> np.ndarray:
    """(C(n, 3), 3) int: every three of ``n_types`` corner types, in a covering order: each
    next triple avoids as many as possible of the sets of up to three types (wrong first
    choices) that no earlier triple avoids (greedy; ties: lexicographic). With 8 types, any
    one wrong type is avoided by the 2nd triple at the latest, any two by the 4th, any three
    by the 10th (lexicographic order: 22nd, 37th, 47th)."""
    combos = np.array(list(itertools.combinations(range(n_types), 3)), dtype=np.int64).reshape(-1, 3)
    bits = (1 << combos).sum(axis=1)
    wrong = [sum(1 << k for k in w) for r in range(4) for w in itertools.combinations(range(n_types), r)]
    avoids = (bits[:, None] & np.array(wrong)[None]) == 0                    # (C, W)
    open_ = np.ones(len(wrong), dtype=bool)
    left = np.ones(len(combos), dtype=bool)
    order = []
    for _ in range(len(combos)):
        gain = np.where(left, (avoids & open_).sum(axis=1), -1)
        i = int(np.argmax(gain))
        order.append(i)
        left[i] = False
        open_ &= ~avoids[i]
    return combos[order]


@functools.lru_cache(maxsize=32)
def _minimal_set_table(n_types: int, n_ranks: int) -> np.ndarray:
    """(S, 6) int, read-only: (slot a, b, c, rank a, b, c) for every three of ``n_types``
    corner types and every rank below ``n_ranks`` within each, ordered by the rank sum (ties:
    type triples in :func:`_covering_order`, then ranks lexicographically)."""
    combos = _covering_order(n_types)
    ranks = np.indices((n_ranks,) * 3).reshape(3, -1).T
    table = np.concatenate([np.repeat(combos, len(ranks), axis=0), np.tile(ranks, (len(combos), 1))], axis=1)
    table = table[np.argsort(table[:, 3:].sum(axis=1), kind="stable")]
    table.flags.writeable = False
    return table


def _minimal_sets(by_type: list[np.ndarray], max_sets: int) -> np.ndarray:
    """(S, 3) int: candidate indices of three corners of distinct types, the most promising
    first: ordered by the sum of the candidates' ranks within their type (each ``by_type``
    list is best first), so the first set is made of every type's first choice. At most
    ``max_sets`` sets (read from a table built once per type and rank count)."""
    counts = np.array([len(m) for m in by_type])
    table = _minimal_set_table(len(by_type), int(counts.max()))
    rows = table[np.flatnonzero(np.all(table[:, 3:] < counts[table[:, :3]], axis=1))[:max_sets]]
    padded = np.zeros((len(by_type), counts.max()), dtype=np.int64)
    for i, members in enumerate(by_type):
        padded[i, : len(members)] = members
    return padded[rows[:, :3], rows[:, 3:]]


def _least_squares_pose(obj: np.ndarray, img: np.ndarray, K: np.ndarray,
                        ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``cv2.SOLVEPNP_SQPNP`` through (n, 3) model / (n, 2) image points (no distortion) as
    (R (3, 3), t (3,)), or (None, None) when it fails."""
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, np.ascontiguousarray(img), K, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None, None
    if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        return None, None
    return cv2.Rodrigues(rvec)[0], tvec.ravel()


def _ap3p_poses(objs: np.ndarray, imgs: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.SOLVEPNP_AP3P`` on each of (H, 4, 3) model / (H, 4, 2) image point quadruples (no
    distortion): ((h, 3, 3) R, (h, 3) t) of the h that succeed."""
    Rs, ts = [], []
    for obj, img in zip(objs, imgs):
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_AP3P)
        except cv2.error:
            continue
        if ok and np.isfinite(rvec).all() and np.isfinite(tvec).all():
            Rs.append(cv2.Rodrigues(rvec)[0])
            ts.append(tvec.ravel())
    return np.array(Rs).reshape(-1, 3, 3), np.array(ts).reshape(-1, 3)


def solve_pnp_candidates(
    keypoint_ids: np.ndarray,
    points: np.ndarray,
    scores: np.ndarray,
    cuboid_points: np.ndarray,
    K: np.ndarray,
    settings: HypothesisSettings = HypothesisSettings(),
    pnp_settings: PnpSettings = PnpSettings(),
) -> PoseEstimate | None:
    """Pose of one cuboid from several candidate peaks per keypoint (multi-hypothesis PnP).

    A trained network often puts a second, sometimes stronger, peak of corner map k on
    another corner of the same box; taking one peak per type then leaves too few consistent
    keypoints for :func:`solve_pnp`. Here every candidate may be used. Pose hypotheses are
    scored by the summed confidence (clipped to [0, 1]) of the keypoint types whose nearest
    candidate lies within ``hypothesis_threshold_px`` of the projection - one candidate per
    type, so duplicates cannot inflate a score - and kept only when they project the centroid
    within that distance of its peak (the candidates were gathered for that centroid):

    1. the least-squares pose (``cv2.SOLVEPNP_SQPNP``) through every type's first candidate.
       On clean maps it is the answer: when each first candidate lies within the threshold
       and is the nearest of its type, they go to :func:`solve_pnp` without further search;
    2. otherwise ``cv2.SOLVEPNP_AP3P`` poses from the centroid plus three corner candidates of
       distinct types (minimal sets), best-ranked first (candidates are listed best first per
       type), type triples of equal rank in a covering order (:func:`_covering_order`: any
       one, two, three wrong first choices are avoided by the 2nd, 4th, 10th set), checked
       after 4 and then every ``_HYPOTHESIS_CHUNK`` sets (:func:`_chunk_ends`), at most
       ``max_hypotheses``. Whenever a hypothesis beats the best so far and explains more
       than four types (not all), the least-squares pose through the candidates it explains
       is scored too (the local optimization of LO-RANSAC: noisy peaks put a minimal set's
       pose a few pixels off the far corners).

    The search ends as soon as a hypothesis explains every keypoint type present, or all but
    one and at least ``_ENOUGH_TYPES`` (a type whose candidates are all another object's
    peaks cannot be explained by any pose), or when ``_STALL_AFTER`` minimal sets in a row
    brought no better hypothesis (clutter: none ever fits its centroid). The search draws
    nothing at random (only the RANSAC fallback below does). The best hypothesis picks, per
    type, the candidate nearest its projection (or the type's strongest candidate where none
    is within the threshold: it counts as an outlier unless within the final threshold), and
    that assignment goes through :func:`solve_pnp` with the hypothesis as its consensus
    (``initial_pose``: the search is the RANSAC) and every one of its checks (refinement,
    inlier ratio, mean error), then, where that consensus fails them, with RANSAC; it is
    skipped when fewer than its ``min_points`` types lie within its
    ``reprojection_threshold_px`` of the best hypothesis. OpenCV's RANSAC does not fit the search itself: it counts every inlying
    correspondence, so several candidates of one type near a wrong pose outvote the right one.

    Args:
        keypoint_ids: (n,) int keypoint index of each candidate (0..7 corners, 8 the centroid),
            best candidate of each type first.
        points: (n, 2) candidate positions, image px.
        scores: (n,) candidate confidences (peak heights).
        cuboid_points: (9, 3) model-frame cuboid keypoints, metres.
        K: (3, 3) intrinsics of the image the points are in (no distortion).
        settings: :class:`HypothesisSettings` (``hypothesis_threshold_px``, ``max_hypotheses``).
        pnp_settings: :class:`PnpSettings` of the final :func:`solve_pnp`.

    Returns:
        :class:`PoseEstimate` (``keypoints``: the chosen candidate per type), or None: no
        centroid, fewer keypoint types than :func:`solve_pnp`'s ``min_points`` (no minimal
        set is solved then), or the chosen assignment fails :func:`solve_pnp`.
    """
    step1 = _first_choices([(keypoint_ids, points, scores)], cuboid_points, K, settings, pnp_settings)[0]
    if step1 is None or step1[0]:
        return None if step1 is None else step1[1]
    prep = _Candidates.of(keypoint_ids, points, scores, cuboid_points, K, pnp_settings)
    return _search(prep, step1[2], settings, pnp_settings)



def solve_pnp_instances(
    candidates: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    cuboid_points: np.ndarray,
    K: np.ndarray,
    settings: HypothesisSettings = HypothesisSettings(),
    pnp_settings: PnpSettings = PnpSettings(),
) -> list[PoseEstimate]:
    """Poses of the objects of one image: :func:`solve_pnp_candidates` per centroid, a peak
    belonging to one object only.

    1. Every centroid's step 1 (the least-squares pose through each type's first candidate):
       a centroid whose first candidates it explains is decided there (clean maps: all). A
       centroid whose first candidates are, on all but fewer than ``min_points`` types, a
       centroid's listed before it goes straight to 2.
    2. The other centroids in the given order (strongest first), each searched without the
       peaks (same type, same position) that an accepted pose holds as inliers: a noise
       blob next to boxes passes the angle test with their corners; without those it lacks
       the ``min_points`` types any pose needs and is dropped before any minimal set.
    3. Two estimates explaining one object (at least half of one's inliers are the other's
       inlier peaks): the higher-scoring is kept.

    Args:
        candidates: per centroid (keypoint_ids (n,), points (n, 2) px, scores (n,)) as
            :func:`solve_pnp_candidates` takes them.
        cuboid_points, K, settings, pnp_settings: as in :func:`solve_pnp_candidates`.

    Returns:
        The estimates kept, highest score first.
    """
    found: list[PoseEstimate | None] = [None] * len(candidates)
    pending = []
    for i, step1 in enumerate(_first_choices(candidates, cuboid_points, K, settings, pnp_settings)):
        if step1 is not None:                                                         # 1
            decided, found[i], first_pose = step1
            if not decided:
                pending.append((i, _Candidates.of(*candidates[i], cuboid_points, K, pnp_settings), first_pose))
    taken = [_inlier_peaks([e for e in found if e is not None])] if pending else []   # (k, 3) type, u, v
    for i, prep, first_pose in pending:                                               # 2
        peaks = np.concatenate(taken) if taken else np.zeros((0, 3))
        mine = np.concatenate([prep.ids[:, None], prep.pts], axis=1)
        free = ~np.any(np.all(mine[:, None] == peaks[None], axis=2), axis=1)
        if not free.all() or first_pose is None:  # (None: left to this step, or no solution)
            if not free.all():
                prep = _Candidates.of(prep.ids[free], prep.pts[free], prep.sc[free], prep.cuboid, prep.K,
                                      pnp_settings)
                if prep is None:
                    continue
            first_pose = _least_squares_pose(prep.cuboid[prep.types], prep.pts[prep.first], prep.K)
            first_pose = None if first_pose[0] is None else first_pose
        found[i] = _search(prep, first_pose, settings, pnp_settings)
        if found[i] is not None:
            taken.append(_inlier_peaks([found[i]]))
    found = sorted((e for e in found if e is not None), key=lambda e: -e.score)       # 3
    if len(found) < 2:
        return found
    inliers = np.stack([e.inliers for e in found])                                   # (E, 9)
    keypoints = np.stack([e.keypoints for e in found])                               # (E, 9, 2)
    same = inliers[:, None] & inliers[None] & np.all(np.abs(keypoints[:, None] - keypoints[None]) < 1e-6, axis=3)
    covers = (2 * same.sum(axis=2) >= inliers.sum(axis=1)[:, None]).tolist()         # [i][j]: j holds half of i
    kept: list[int] = []
    for i in range(len(found)):
        if not any(covers[i][j] for j in kept):
            kept.append(i)
    return [found[i] for i in kept]


def _inlier_peaks(ests: list[PoseEstimate]) -> np.ndarray:
    """(k, 3) keypoint type, u, v (px) of each inlier of the estimates."""
    if not ests:
        return np.zeros((0, 3))
    which, kind = np.nonzero(np.stack([e.inliers for e in ests]))
    return np.concatenate([kind[:, None], np.stack([e.keypoints for e in ests])[which, kind]], axis=1)


@dataclass
class _Candidates:
    """One centroid's checked candidates, grouped by type (see :func:`solve_pnp_candidates`).

    ids (n,) int, pts (n, 2) px, sc (n,): the input; cuboid (9, 3) metres; K (3, 3);
    usable: (u,) indices of the finite candidates; counts (9,) usable candidates per type;
    types: (T,) keypoint types present (the centroid, 8, last); order: usable candidates
    grouped by type, each group best first; starts (T,) where each group begins in order;
    first (T,) each type's first candidate.
    """

    ids: np.ndarray
    pts: np.ndarray
    sc: np.ndarray
    cuboid: np.ndarray
    K: np.ndarray
    usable: np.ndarray
    counts: np.ndarray
    types: np.ndarray
    order: np.ndarray
    starts: np.ndarray
    first: np.ndarray

    @classmethod
    def of(cls, keypoint_ids, points, scores, cuboid_points, K, pnp_settings: PnpSettings) -> "_Candidates | None":
        """Checked inputs, or None when no pose can pass :func:`solve_pnp`
        (:func:`_pose_possible`)."""
        ids, pts, sc, _ = _checked([(keypoint_ids, points, scores)])
        usable = np.flatnonzero(np.isfinite(pts).all(axis=1) & np.isfinite(sc))
        counts = np.bincount(ids[usable], minlength=NUM_KEYPOINTS)
        if not _pose_possible(counts, pnp_settings.min_points):
            return None
        types = np.flatnonzero(counts)
        # Candidate indices per type present, each best first (the input order).
        order = usable[np.argsort(ids[usable], kind="stable")]
        starts = np.cumsum(counts[types]) - counts[types]
        return cls(ids, pts, sc, np.asarray(cuboid_points, dtype=np.float64).reshape(NUM_KEYPOINTS, 3),
                   np.asarray(K, dtype=np.float64), usable, counts, types, order, starts, order[starts])


def _checked(candidates: Sequence[tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centroids' candidates (keypoint_ids, points, scores) as one table: (n,) int ids,
    (n, 2) float px, (n,) float scores, (n,) int centroid of each row; ValueError when a
    centroid's lengths differ or an id is not a keypoint index."""
    ids = [np.asarray(c[0], dtype=int).ravel() for c in candidates]
    pts = [np.asarray(c[1], dtype=np.float64).reshape(-1, 2) for c in candidates]
    sc = [np.asarray(c[2], dtype=np.float64).ravel() for c in candidates]
    sizes = [len(a) for a in ids]
    for a, b, c in zip(sizes, pts, sc):
        if not a == len(b) == len(c):
            raise ValueError(f"keypoint_ids, points and scores differ in length: {a}, {len(b)}, {len(c)}")
    owner = np.repeat(np.arange(len(candidates)), sizes)
    ids, pts, sc = np.concatenate(ids), np.concatenate(pts), np.concatenate(sc)
    if len(ids) and (ids.min() < 0 or ids.max() >= NUM_KEYPOINTS):
        raise ValueError(f"keypoint ids must be in 0..{NUM_KEYPOINTS - 1}, got {sorted(set(ids.tolist()))}")
    return ids, pts, sc, owner


def _pose_possible(counts: np.ndarray, min_points: int) -> np.ndarray:
    """(...,) bool from (..., 9) usable candidates per keypoint type: a centroid is present and
    at least :func:`solve_pnp`'s ``min_points`` types (one keypoint per type reaches it)."""
    return (counts[..., CENTROID_INDEX] > 0) & (np.count_nonzero(counts, axis=-1) >= min_points)


def _first_choices(candidates: Sequence[tuple], cuboid_points: np.ndarray, K: np.ndarray,
                   settings: HypothesisSettings, pnp_settings: PnpSettings) -> list[tuple | None]:
    """Step 1 of :func:`solve_pnp_candidates` for every centroid of one image at once: the
    least-squares pose through each type's first candidate (one solve per centroid, the
    candidates of all projected and checked together). Per centroid None (no pose possible:
    :func:`_pose_possible`), else (decided, estimate, pose): decided when each first
    candidate lies within ``hypothesis_threshold_px`` of that pose and is the nearest of its type (the
    estimate is then :func:`solve_pnp`'s answer, maybe None, for all decided at once); pose:
    (R, t), or None where the solver failed."""
    m = len(candidates)
    out: list[tuple | None] = [None] * m
    if m == 0:
        return out
    ids, pts, sc, owner = _checked(candidates)
    cuboid = np.asarray(cuboid_points, dtype=np.float64).reshape(NUM_KEYPOINTS, 3)
    K = np.asarray(K, dtype=np.float64)
    usable = np.flatnonzero(np.isfinite(pts).all(axis=1) & np.isfinite(sc))
    order = usable[np.lexsort((usable, ids[usable], owner[usable]))]   # by centroid, type, input order
    key = owner[order] * NUM_KEYPOINTS + ids[order]
    min_points = pnp_settings.min_points
    possible = _pose_possible(np.bincount(key, minlength=m * NUM_KEYPOINTS).reshape(m, NUM_KEYPOINTS), min_points)
    if not possible.any():
        return out
    new_type = np.r_[True, key[1:] != key[:-1]]
    group_start = np.flatnonzero(new_type)
    first = order[group_start]                             # each centroid's first candidate per type
    first_at = group_start[np.cumsum(new_type) - 1]        # per position in order: its type's first
    bounds = np.searchsorted(owner[first], np.arange(m + 1))
    # A centroid whose first candidates are, on all but fewer than min_points types, those of
    # a centroid listed before it (stronger) is left to step 2 (a noise blob beside a box, or
    # the box's second centroid peak): where that centroid's pose holds them, they are gone.
    peak = np.stack([ids[first], pts[first, 0], pts[first, 1]], axis=1)
    by_peak = np.lexsort((owner[first], peak[:, 2], peak[:, 1], peak[:, 0]))
    shared = np.zeros(len(first), dtype=bool)
    shared[by_peak[1:]] = np.all(peak[by_peak[1:]] == peak[by_peak[:-1]], axis=1)
    own = np.bincount(owner[first[~shared]], minlength=m)
    Rs, ts = np.zeros((m, 3, 3)), np.zeros((m, 3))
    solved = np.zeros(m, dtype=bool)
    for c in np.flatnonzero(possible):
        if own[c] < min_points:
            out[c] = (False, None, None)
            continue
        f = first[bounds[c]: bounds[c + 1]]
        R, t = _least_squares_pose(cuboid[ids[f]], pts[f], K)
        out[c] = (False, None, None if R is None else (R, t))
        if R is not None:
            Rs[c], ts[c], solved[c] = R, t, True
    pos = np.flatnonzero(solved[owner[order]])
    rows = order[pos]
    uvw = (np.einsum("nij,nj->ni", Rs[owner[rows]], cuboid[ids[rows]]) + ts[owner[rows]]) @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        d = uvw[:, :2] / uvw[:, 2:] - pts[rows]
    err = np.full(len(order), np.inf)
    err[pos] = np.where(uvw[:, 2] > 0, d[:, 0] ** 2 + d[:, 1] ** 2, np.inf)                # squared, px^2
    ref = err[first_at[pos]]
    bad = ~(ref <= settings.hypothesis_threshold_px ** 2) | (err[pos] < ref)
    decided = np.flatnonzero(solved & (np.bincount(owner[rows[bad]], minlength=m) == 0))
    if decided.size:
        slot = np.full(m, -1)
        slot[decided] = np.arange(decided.size)
        f = first[slot[owner[first]] >= 0]
        kp = np.full((decided.size, NUM_KEYPOINTS, 2), np.nan)
        kp_scores = np.zeros((decided.size, NUM_KEYPOINTS))
        kp[slot[owner[f]], ids[f]] = pts[f]
        kp_scores[slot[owner[f]], ids[f]] = sc[f]
        ests = _solve_pnp_many(kp, kp_scores, cuboid, K, (Rs[decided], ts[decided]), pnp_settings)
        for c, est in zip(decided.tolist(), ests):
            out[c] = (True, est, (Rs[c], ts[c]))
    return out


def _search(c: _Candidates, first_pose: tuple[np.ndarray, np.ndarray] | None, settings: HypothesisSettings,
            pnp_settings: PnpSettings) -> PoseEstimate | None:
    """Step 2 of :func:`solve_pnp_candidates` (and its final :func:`solve_pnp`), after step 1's
    ``first_pose`` (scored first; None: the solver failed)."""
    ids, pts, sc, cuboid, K, types, order, starts = c.ids, c.pts, c.sc, c.cuboid, c.K, c.types, c.order, c.starts
    hypothesis_threshold_px = settings.hypothesis_threshold_px
    anchor = c.first[-1]                                       # the centroid (type 8, last)
    groups = np.split(order, starts[1:])
    scorer = _HypothesisScorer(ids, pts, np.clip(sc, 0.0, 1.0), groups, anchor, cuboid, K,
                               float(hypothesis_threshold_px))

    def add(Rs, ts) -> None:
        """Score hypotheses; while the best improves, also the least-squares pose through the
        candidates it explains (when more than its own four): noisy peaks put a minimal
        set's pose a few pixels off the far corners, the fit through all of them is not."""
        scorer.add(Rs, ts)
        for _ in range(3):
            if not scorer.improved or not 4 < scorer.best_explained.size < len(groups):
                break
            scorer.improved = False
            fit = _least_squares_pose(cuboid[ids[scorer.best_explained]], pts[scorer.best_explained], K)
            if fit[0] is not None:
                scorer.add([fit[0]], [fit[1]])

    if first_pose is not None:
        add([first_pose[0]], [first_pose[1]])
    n_types = len(types)
    enough = n_types if n_types - 1 < _ENOUGH_TYPES else n_types - 1
    if scorer.most_explained < enough:                                         # step 2
        sets = _minimal_sets(groups[:-1], settings.max_hypotheses)
        quads = np.concatenate([sets, np.full((len(sets), 1), anchor)], axis=1)  # 3 corners + centroid
        objs, imgs = cuboid[ids[quads]], np.ascontiguousarray(pts[quads])       # (S, 4, 3), (S, 4, 2)
        start = last_better = 0
        for end in _chunk_ends(len(quads)):
            best_before = scorer.best_total
            add(*_ap3p_poses(objs[start:end], imgs[start:end], K))
            start, last_better = end, end if scorer.best_total > best_before else last_better
            if scorer.most_explained >= enough:
                break  # every type present explained, or all but a foreign one
            if end - last_better >= _STALL_AFTER:
                break  # no better hypothesis for a while: clutter, or the best there is
    if scorer.best_err is None:
        return None
    best_err, best_nearest = scorer.best_err, scorer.best_nearest
    if np.count_nonzero(best_err[best_nearest] <= pnp_settings.reprojection_threshold_px) < pnp_settings.min_points:
        return None  # fewer than min_points keypoints near the best pose
    kp = np.full((NUM_KEYPOINTS, 2), np.nan)
    kp_scores = np.zeros(NUM_KEYPOINTS)
    for k, g, j in zip(types, groups, best_nearest):
        if best_err[j] > hypothesis_threshold_px:
            j = g[np.argmax(sc[g])]
        kp[k], kp_scores[k] = pts[j], sc[j]
    est = solve_pnp(kp, kp_scores, cuboid, K, pnp_settings, initial_pose=scorer.best_pose)
    # A minimal set's pose is a few pixels off on noisy peaks: where its consensus does not
    # hold up, RANSAC on the assignment may still find one that does.
    return est if est is not None else solve_pnp(kp, kp_scores, cuboid, K, pnp_settings)


class _HypothesisScorer:
    """Scores pose hypotheses against candidate peaks and keeps the best (see
    :func:`solve_pnp_candidates`).

    ids (n,), pts (n, 2) image px, weight (n,) in [0, 1]: the candidates; groups: per keypoint
    type present, its candidate indices (best first); anchor: the centroid candidate;
    cuboid (9, 3) metres; K (3, 3); threshold_px: a candidate supports a hypothesis within it.
    """

    def __init__(self, ids: np.ndarray, pts: np.ndarray, weight: np.ndarray, groups: list[np.ndarray],
                 anchor: int, cuboid: np.ndarray, K: np.ndarray, threshold_px: float):
        n = len(ids)
        self.ids, self.pts, self.anchor, self.cuboid_t, self.K, self.threshold = ids, pts, anchor, cuboid.T, K, threshold_px
        width = max(len(g) for g in groups)
        self.slots = np.full((len(groups), width), n)          # (T, w) candidate index, n = none
        for i, g in enumerate(groups):
            self.slots[i, : len(g)] = g
        self.type_index = np.arange(len(groups))
        self.weight = np.append(weight, 0.0)
        self.most_explained = 0
        self.best_total = -1.0
        self.improved = False                        # set when a hypothesis beats the best
        self.best_explained = np.zeros(0, dtype=int)  # candidates the best explains, one per type
        self.best_pose: tuple[np.ndarray, np.ndarray] | None = None   # (R, t) of the best hypothesis
        self.best_err: np.ndarray | None = None      # (n + 1,) errors under the best hypothesis
        self.best_nearest: np.ndarray | None = None  # (T,) its nearest candidate per type

    def add(self, Rs, ts) -> None:
        """Score hypotheses, Rs (H, 3, 3) and ts (H, 3) (arrays or lists), at once: (H, 3, 9)
        camera-frame cuboids -> per type the nearest candidate to the projection, explained
        within the threshold."""
        if len(Rs) == 0:
            return
        cam = np.asarray(Rs) @ self.cuboid_t + np.asarray(ts)[:, :, None]   # (H, 3, 9)
        img = self.K @ cam
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = img[:, :2] / np.where(cam[:, 2] > 0, img[:, 2], np.nan)[:, None]   # (H, 2, 9)
        d = proj[:, :, self.ids] - self.pts.T[None]                           # (H, 2, n)
        err = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)                            # (H, n)
        centre_ok = err[:, self.anchor] <= self.threshold
        if not centre_ok.any():
            return  # none fits its centroid: it explains nothing
        err[~np.isfinite(err) | ~centre_ok[:, None]] = np.inf
        err = np.concatenate([err, np.full((len(err), 1), np.inf)], axis=1)  # column n: no candidate
        per_slot = err[:, self.slots]                                         # (H, T, w)
        pick = np.argmin(per_slot, axis=2)                                    # (H, T)
        nearest = self.slots[self.type_index, pick]
        inside = per_slot.min(axis=2) <= self.threshold
        total = (inside * self.weight[nearest]).sum(axis=1)
        valid = centre_ok
        h = int(np.argmax(np.where(valid, total, -np.inf)))
        if valid[h] and total[h] > self.best_total:
            self.best_total, self.best_err, self.best_nearest = float(total[h]), err[h], nearest[h]
            self.best_pose = (Rs[h], np.asarray(ts[h]))
            self.best_explained = nearest[h][inside[h]]
            self.improved = True
        self.most_explained = max(self.most_explained, int(inside.sum(axis=1).max()))
