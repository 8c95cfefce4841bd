"""Pose hypotheses of the multi-hypothesis pose search scored against a centroid's candidate
peaks (:class:`HypothesisScorer`), its minimal sets solved and scored a block at a time
(:class:`MinimalSetBlock`), and the consensus of every minimal set of one keypoint
assignment (:func:`assignment_consensus`); the search itself is
:func:`dope_hope.inference.pose_search.solve_pnp_candidates`.
"""
from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

from dope_hope.inference.p3p import ap3p_each, ap3p_poses

#: Minimal sets taken before the first check of the search's stopping rules (any single wrong
#: first choice is avoided by the second set; clean maps end there): solved one by one
#: (:func:`~dope_hope.inference.p3p.ap3p_each`), where a batch's fixed cost is that of ~14 sets.
FIRST_CHECK = 4


def front_projections(Rs: np.ndarray, ts: np.ndarray, points_t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, 2, n) image px of (3, n) model points ``points_t`` under H poses Rs (H, 3, 3), ts
    (H, 3); NaN where a point lies at or behind the camera (a pose there explains nothing)."""
    cam = Rs @ points_t + ts[:, :, None]                                      # (H, 3, n)
    img = K @ cam
    with np.errstate(divide="ignore", invalid="ignore"):
        return img[:, :2] / np.where(cam[:, 2] > 0, img[:, 2], np.nan)[:, None]


class HypothesisScorer:
    """Scores pose hypotheses against candidate peaks and keeps the best (see
    :func:`~dope_hope.inference.pose_search.solve_pnp_candidates`).

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

    def score(self, Rs: np.ndarray, ts: np.ndarray) -> "HypothesisScores":
        """Score hypotheses Rs (H, 3, 3), ts (H, 3) at once: (H, 3, 9) camera-frame cuboids ->
        per type the nearest candidate to the projection, explained within the threshold."""
        proj = front_projections(Rs, ts, self.cuboid_t, self.K)              # (H, 2, 9)
        d = proj[:, :, self.ids] - self.pts.T[None]                           # (H, 2, n)
        err = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)                            # (H, n)
        centre_ok = err[:, self.anchor] <= self.threshold                     # else it explains nothing
        err[~np.isfinite(err) | ~centre_ok[:, None]] = np.inf
        err = np.concatenate([err, np.full((len(err), 1), np.inf)], axis=1)  # column n: no candidate
        per_slot = err[:, self.slots]                                         # (H, T, w)
        nearest = self.slots[self.type_index, np.argmin(per_slot, axis=2)]   # (H, T)
        inside = per_slot.min(axis=2) <= self.threshold
        total = np.where(centre_ok, (inside * self.weight[nearest]).sum(axis=1), -np.inf)
        return HypothesisScores(total, inside.sum(axis=1), err, nearest, inside)

    def consider(self, scores: "HypothesisScores", Rs: np.ndarray, ts: np.ndarray, lo: int, hi: int) -> None:
        """Take hypotheses lo..hi-1 of ``scores`` (of Rs, ts): the best of them replaces the best
        so far when it explains more weight (the first of equals)."""
        if hi <= lo:
            return
        h = lo + int(np.argmax(scores.total[lo:hi]))
        if np.isfinite(scores.total[h]) and scores.total[h] > self.best_total:
            self.best_total, self.best_err, self.best_nearest = float(scores.total[h]), scores.err[h], scores.nearest[h]
            self.best_pose = (Rs[h], ts[h])
            self.best_explained = scores.nearest[h][scores.inside[h]]
            self.improved = True
        self.most_explained = max(self.most_explained, int(scores.explained[lo:hi].max()))

    def add(self, Rs: np.ndarray, ts: np.ndarray) -> None:
        """Score hypotheses Rs (H, 3, 3), ts (H, 3) and take them all."""
        self.consider(self.score(Rs, ts), Rs, ts, 0, len(Rs))


@dataclass(frozen=True)
class HypothesisScores:
    """H hypotheses scored by :meth:`HypothesisScorer.score`: total (H,) summed weight of the
    types they explain (-inf: the centroid's candidate is not within the threshold); explained
    (H,) types explained; err (H, n + 1) px from each candidate to its type's projection (inf
    where the centroid test fails; column n: no candidate); nearest (H, T) candidate per type;
    inside (H, T) within the threshold."""

    total: np.ndarray
    explained: np.ndarray
    err: np.ndarray
    nearest: np.ndarray
    inside: np.ndarray


@dataclass(frozen=True)
class MinimalSetBlock:
    """Minimal sets first..end-1 of a search, solved (:func:`ap3p_poses`) and scored at once:
    Rs (h, 3, 3), ts (h, 3) of the h that have a pose; offsets (end - first + 1,) the index
    among them of each set's hypothesis (sets without a pose have none); scores of the h."""

    first: int
    end: int
    Rs: np.ndarray
    ts: np.ndarray
    offsets: np.ndarray
    scores: HypothesisScores | None

    @classmethod
    def empty(cls) -> "MinimalSetBlock":
        return cls(0, 0, np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(1, dtype=int), None)

    @classmethod
    def solve(cls, objs: np.ndarray, imgs: np.ndarray, K: np.ndarray, first: int, end: int,
              scorer: HypothesisScorer) -> "MinimalSetBlock":
        """Sets first..end-1 of (S, 4, 3) model / (S, 4, 2) image quadruples (those of the first
        check one by one, :func:`~dope_hope.inference.p3p.ap3p_each`; a block never holds sets
        on both sides of it)."""
        solve = ap3p_each if end <= FIRST_CHECK else ap3p_poses
        Rs, ts, solved = solve(objs[first:end], imgs[first:end], K)
        return cls(first, end, Rs, ts, np.r_[0, np.cumsum(solved)], scorer.score(Rs, ts) if len(Rs) else None)

    def take(self, scorer: HypothesisScorer, lo: int, hi: int) -> None:
        """Let ``scorer`` consider the hypotheses of sets lo..hi-1 (within the block)."""
        if self.scores is not None:
            scorer.consider(self.scores, self.Rs, self.ts, int(self.offsets[lo - self.first]),
                            int(self.offsets[hi - self.first]))


@functools.lru_cache(maxsize=16)
def _four_point_sets(n: int) -> np.ndarray:
    """(C(n, 3), 4) int, read-only: every three of n points, each followed by the first point
    not among them (which chooses among the three's P3P solutions)."""
    triples = np.array(list(itertools.combinations(range(n), 3)), dtype=np.int64).reshape(-1, 3)
    fourth = np.array([min(set(range(n)) - set(t)) for t in triples.tolist()], dtype=np.int64)
    out = np.concatenate([triples, fourth[:, None]], axis=1)
    out.flags.writeable = False
    return out


def assignment_consensus(keypoints: np.ndarray, present: np.ndarray, cuboid: np.ndarray, K: np.ndarray,
                         threshold_px: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The pose of one keypoint assignment that most of its keypoints support: every three of
    the present keypoints (a fourth choosing among their P3P solutions) solved at once
    (:func:`ap3p_poses`), the pose with the most keypoints within ``threshold_px`` kept (ties:
    the least summed error of those). The exhaustive, deterministic counterpart of
    ``cv2.solvePnPRansac`` for the nine keypoints of a cuboid: at most 84 minimal sets, one
    batch (about 0.5 ms), where OpenCV's RANSAC draws up to its iteration count one solve at a
    time (about 2 ms at 200 when no consensus ends it early); hand-written because no library
    solves a batch of P3P problems (:mod:`dope_hope.inference.p3p`).

    Args:
        keypoints: (9, 2) image px (NaN where missing). present: (9,) bool, those used.
        cuboid: (9, 3) model keypoints, metres. K: (3, 3). threshold_px: inlier distance, px.

    Returns:
        (R (3, 3), t (3,)), or None with fewer than four present keypoints or no solution.
    """
    idx = np.flatnonzero(present)
    if len(idx) < 4:
        return None
    sets = idx[_four_point_sets(len(idx))]                                     # (S, 4)
    Rs, ts, _ = ap3p_poses(cuboid[sets], keypoints[sets], K)
    if not len(Rs):
        return None
    proj = front_projections(Rs, ts, cuboid[idx].T, K)                       # (h, 2, n)
    err = np.linalg.norm(proj - keypoints[idx].T[None], axis=1)               # (h, n)
    inside = err <= threshold_px
    total = np.where(inside, err, 0.0).sum(axis=1)
    best = int(np.lexsort((total, -inside.sum(axis=1)))[0])
    return Rs[best], ts[best]
