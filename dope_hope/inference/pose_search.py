"""The multi-hypothesis pose search: the pose of a cuboid from several candidate peaks per
keypoint (:func:`solve_pnp_candidates`), and of all centroids of an image
(:func:`solve_pnp_instances`).

:func:`solve_pnp_candidates` tries the least-squares pose through each type's first
candidate, then minimal sets of candidate corner peaks per centroid, and keeps the pose that
explains most candidates; its best hypothesis then goes through
:func:`dope_hope.inference.pnp.solve_pnp` (one-set PnP, its checks and its score).
:func:`solve_pnp_instances` runs it for every centroid of an image: the first step for all at
once, the search only where that step does not decide, without the peaks that accepted poses
already hold (a peak belongs to one object).
"""
from __future__ import annotations

import functools
import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from dope_hope.config import SectionSettings, at_least, positive_float
from dope_hope.geometry import CENTROID_INDEX, NUM_KEYPOINTS
from dope_hope.inference.hypothesis_scoring import (
    FIRST_CHECK,
    HypothesisScorer,
    MinimalSetBlock,
    assignment_consensus,
)
from dope_hope.inference.pnp import PnpSettings, PoseEstimate, pose_may_reach, solve_pnp, solve_pnp_many

#: :func:`solve_pnp_candidates`' budget, in AP3P minimal sets: the most it takes by default;
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
#: Minimal sets taken between two later checks of its stopping rules.
_HYPOTHESIS_CHUNK = 16


def _chunk_ends(n: int) -> list[int]:
    """How many of n minimal sets :func:`solve_pnp_candidates` has taken at each check of its
    stopping rules: ``FIRST_CHECK``, then every ``_HYPOTHESIS_CHUNK``, then n."""
    return sorted({min(FIRST_CHECK, n), *range(_HYPOTHESIS_CHUNK, n, _HYPOTHESIS_CHUNK), n})


@dataclass(frozen=True)
class HypothesisSettings(SectionSettings):
    """The multi-hypothesis search's settings (``hypotheses:`` in
    ``dope_hope/configs/infer.yaml``; :func:`solve_pnp_candidates`).

    hypothesis_threshold_px: a candidate supports a hypothesis within this distance, px.
    max_hypotheses: most AP3P minimal sets taken.
    """

    SECTION = "hypotheses"
    RULES = {"hypothesis_threshold_px": positive_float, "max_hypotheses": at_least(1)}

    hypothesis_threshold_px: float = DEFAULT_HYPOTHESIS_PX
    max_hypotheses: int = DEFAULT_MAX_HYPOTHESES


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


def solve_pnp_candidates(
    keypoint_ids: np.ndarray,
    points: np.ndarray,
    scores: np.ndarray,
    cuboid_points: np.ndarray,
    K: np.ndarray,
    settings: HypothesisSettings = HypothesisSettings(),
    pnp_settings: PnpSettings = PnpSettings(),
    min_score: float = 0.0,
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
    2. otherwise AP3P poses (:func:`dope_hope.inference.p3p.ap3p_poses`) from the centroid
       plus three corner candidates of distinct types (minimal sets), best-ranked first
       (candidates are listed best first per type), type triples of equal rank in a covering
       order (:func:`_covering_order`: any one, two, three wrong first choices are avoided by
       the 2nd, 4th, 10th set), taken after 4 and then every ``_HYPOTHESIS_CHUNK`` sets
       (:func:`_chunk_ends`), at most ``max_hypotheses``. After the first four (one
       ``cv2.solvePnP`` each: clean maps end there), the sets are solved and scored in blocks,
       each up to the search's earliest possible stop (``_STALL_AFTER`` sets after the last
       better hypothesis), one numpy call per block, with the result of taking one chunk at a
       time. Whenever a hypothesis beats the best so far and explains more than four types
       (not all), the least-squares pose through the candidates it explains is scored too
       (the local optimization of LO-RANSAC: noisy peaks put a minimal set's pose a few pixels
       off the far corners).

    The search ends as soon as a hypothesis explains every keypoint type present, or all but
    one and at least ``_ENOUGH_TYPES`` (a type whose candidates are all another object's
    peaks cannot be explained by any pose), or when ``_STALL_AFTER`` minimal sets in a row
    brought no better hypothesis (clutter: none ever fits its centroid). The search draws
    nothing at random, nor does its fallback below. The best hypothesis picks, per
    type, the candidate nearest its projection (or the type's strongest candidate where none
    is within the threshold: it counts as an outlier unless within the final threshold), and
    that assignment goes through :func:`solve_pnp` with the hypothesis as its consensus
    (``initial_pose``: the search is the RANSAC) and every one of its checks (refinement,
    inlier ratio, mean error). Where that consensus fails them, the types within
    ``reprojection_threshold_px`` of the best hypothesis go through it alone, the others
    missing (a type whose candidates are all another object's peaks or noise would otherwise
    fail every pose by the inlier ratio: on the Ketchup and six-object benchmarks' maps, a
    centroid and four to six corners the hypothesis explains, and no pose), and the whole
    assignment from the consensus of every four of its keypoints
    (:func:`~dope_hope.inference.hypothesis_scoring.assignment_consensus`, exhaustive where
    OpenCV's RANSAC samples); the higher-scoring of the two is kept. Nothing goes through
    :func:`solve_pnp` when fewer than its ``min_points`` types lie within
    ``reprojection_threshold_px`` of the best hypothesis. OpenCV's RANSAC does not fit the
    search itself: it counts every inlying correspondence, so several candidates
    of one type near a wrong pose outvote the right one.

    Args:
        keypoint_ids: (n,) int keypoint index of each candidate (0..7 corners, 8 the centroid),
            best candidate of each type first.
        points: (n, 2) candidate positions, image px.
        scores: (n,) candidate confidences (peak heights).
        cuboid_points: (9, 3) model-frame cuboid keypoints, metres.
        K: (3, 3) intrinsics of the image the points are in (no distortion).
        settings: :class:`HypothesisSettings` (``hypothesis_threshold_px``, ``max_hypotheses``).
        pnp_settings: :class:`PnpSettings` of the final :func:`solve_pnp`.
        min_score: no search, and no final :func:`solve_pnp`, where no pose of the candidates
            (or of the assignment the search ends with) can score this much: the mean of the
            best keypoint types' clipped confidences over the fewest keypoints its score can
            be divided by (:func:`dope_hope.inference.pnp.least_score_divisor`: the inliers an
            accepted pose needs), as the predictor's ``min_score`` would drop it. 0: every
            pose.

    Returns:
        :class:`PoseEstimate` (``keypoints``: the chosen candidate per type), or None: no
        centroid, fewer keypoint types than :func:`solve_pnp`'s ``min_points`` (no minimal
        set is solved then), no pose can reach ``min_score``, or the chosen assignment fails
        :func:`solve_pnp`.
    """
    step1 = _first_choices([(keypoint_ids, points, scores)], cuboid_points, K, settings, pnp_settings)[0]
    if step1 is None or step1[0]:
        return None if step1 is None else step1[1]
    prep = _Candidates.of(keypoint_ids, points, scores, cuboid_points, K, pnp_settings)
    return _search(prep, step1[2], settings, pnp_settings, min_score)



def solve_pnp_instances(
    candidates: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    cuboid_points: np.ndarray,
    K: np.ndarray,
    settings: HypothesisSettings = HypothesisSettings(),
    pnp_settings: PnpSettings = PnpSettings(),
    min_score: float = 0.0,
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
        cuboid_points, K, settings, pnp_settings, min_score: as in :func:`solve_pnp_candidates`
            (a centroid searched without peaks an accepted pose holds gets the bound of those left).

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
        found[i] = _search(prep, first_pose, settings, pnp_settings, min_score)
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
        ests = solve_pnp_many(kp, kp_scores, cuboid, K, (Rs[decided], ts[decided]), pnp_settings)
        for c, est in zip(decided.tolist(), ests):
            out[c] = (True, est, (Rs[c], ts[c]))
    return out


def _search(c: _Candidates, first_pose: tuple[np.ndarray, np.ndarray] | None, settings: HypothesisSettings,
            pnp_settings: PnpSettings, min_score: float = 0.0) -> PoseEstimate | None:
    """Step 2 of :func:`solve_pnp_candidates` (and its final :func:`solve_pnp`), after step 1's
    ``first_pose`` (scored first; None: the solver failed); nothing where no pose of these
    candidates, or of the assignment the search ends with, can score ``min_score``."""
    ids, pts, sc, cuboid, K, types, order, starts = c.ids, c.pts, c.sc, c.cuboid, c.K, c.types, c.order, c.starts
    if min_score > 0:
        # Types present whichever candidate each ends with: every candidate scored above the
        # keypoint threshold (solve_pnp treats the others as missing).
        u_ids, u_sc = ids[c.usable], sc[c.usable]
        n_present = len(c.types) - len(np.unique(u_ids[u_sc <= pnp_settings.min_score]))
        if not pose_may_reach(u_ids, u_sc, pnp_settings, min_score, n_present):
            return None
    hypothesis_threshold_px = settings.hypothesis_threshold_px
    anchor = c.first[-1]                                       # the centroid (type 8, last)
    groups = np.split(order, starts[1:])
    scorer = HypothesisScorer(ids, pts, np.clip(sc, 0.0, 1.0), groups, anchor, cuboid, K,
                               float(hypothesis_threshold_px))

    def refit() -> None:
        """While the best improves, also score the least-squares pose through the candidates it
        explains (when more than its own four): noisy peaks put a minimal set's pose a few
        pixels off the far corners, the fit through all of them is not."""
        for _ in range(3):
            if not scorer.improved or not 4 < scorer.best_explained.size < len(groups):
                break
            scorer.improved = False
            fit = _least_squares_pose(cuboid[ids[scorer.best_explained]], pts[scorer.best_explained], K)
            if fit[0] is not None:
                scorer.add(fit[0][None], fit[1][None])

    def take(block: MinimalSetBlock, lo: int, hi: int) -> None:
        """Consider the hypotheses of minimal sets lo..hi-1 (solved and scored in ``block``)."""
        block.take(scorer, lo, hi)
        refit()

    if first_pose is not None:
        scorer.add(first_pose[0][None], np.asarray(first_pose[1])[None])
        refit()
    n_types = len(types)
    enough = n_types if n_types - 1 < _ENOUGH_TYPES else n_types - 1
    if scorer.most_explained < enough:                                         # step 2
        sets = _minimal_sets(groups[:-1], settings.max_hypotheses)
        quads = np.concatenate([sets, np.full((len(sets), 1), anchor)], axis=1)  # 3 corners + centroid
        objs, imgs = cuboid[ids[quads]], pts[quads]                             # (S, 4, 3), (S, 4, 2)
        ends = _chunk_ends(len(quads))
        start = last_better = 0
        block = MinimalSetBlock.empty()
        for end in ends:
            if end > block.end:  # the first check's sets, then every set up to the earliest stop
                stop = end if start == 0 else next(e for e in ends if e >= end and (
                    e - last_better >= _STALL_AFTER or e == ends[-1]))
                block = MinimalSetBlock.solve(objs, imgs, K, start, stop, scorer)
            best_before = scorer.best_total
            take(block, start, end)
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
    kp_near, scores_near = kp.copy(), kp_scores.copy()   # the types within the final threshold alone
    for k, g, j in zip(types, groups, best_nearest):
        if best_err[j] <= pnp_settings.reprojection_threshold_px:
            kp_near[k], scores_near[k] = pts[j], sc[j]
        if best_err[j] > hypothesis_threshold_px:
            j = g[np.argmax(sc[g])]
        kp[k], kp_scores[k] = pts[j], sc[j]
    present = np.flatnonzero(np.isfinite(kp).all(axis=1) & (kp_scores > pnp_settings.min_score))
    full = pose_may_reach(present, kp_scores[present], pnp_settings, min_score, present.size)
    est = solve_pnp(kp, kp_scores, cuboid, K, pnp_settings, initial_pose=scorer.best_pose) if full else None
    consensus = est is not None
    near = np.isfinite(kp_near).all(axis=1)
    if est is None and not near[types].all():
        # The types the best hypothesis explains, alone: a type whose candidates are all
        # another object's peaks or noise fails every pose by the inlier ratio otherwise.
        present = np.flatnonzero(near & (scores_near > pnp_settings.min_score))
        if pose_may_reach(present, scores_near[present], pnp_settings, min_score, present.size):
            est = solve_pnp(kp_near, scores_near, cuboid, K, pnp_settings, initial_pose=scorer.best_pose)
    if full and not consensus:
        # A minimal set's pose is a few pixels off on noisy peaks: where its consensus does not
        # hold up, the consensus of every minimal set of the assignment may still find one that
        # does (the higher score of the two is kept).
        start = assignment_consensus(kp, np.isfinite(kp).all(axis=1) & (kp_scores > pnp_settings.min_score),
                                     cuboid, K, pnp_settings.reprojection_threshold_px)
        alt = None if start is None else solve_pnp(kp, kp_scores, cuboid, K, pnp_settings, initial_pose=start)
        est = alt if alt is not None and (est is None or alt.score > est.score) else est
    return est
