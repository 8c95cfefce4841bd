"""pose search: the pose of a cuboid from several candidate peaks per keypoint (multi-hypothesis
PnP), and of all centroids of an image."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_inference_pnp import CUBOID, K640, _check_all_found, _exact_keypoints

from dope_hope.errors import ConfigError
from dope_hope.geometry import (
    project_points,
    rotation_error_deg,
)
from dope_hope.inference.hypothesis_scoring import MinimalSetBlock
from dope_hope.inference.pnp import solve_pnp
from dope_hope.inference.pose_search import HypothesisSettings, solve_pnp_candidates, solve_pnp_instances


def _confused_candidates(seed=0):
    """Exact keypoints of one pose as candidates, plus, for corner maps 0, 1 and 2, a second
    and stronger peak on the box's corners 2, 3 and 0: a net unsure which corner is which."""
    R, t, kp = _exact_keypoints(seed)
    ids = list(range(9)) + [0, 1, 2]
    pts = np.vstack([kp, kp[[2, 3, 0]]])
    scores = np.r_[np.full(9, 0.5), 0.9, 0.9, 0.9]
    return R, t, np.array(ids), pts, scores


def test_candidates_find_the_pose_that_the_strongest_peaks_hide():
    R, t, ids, pts, scores = _confused_candidates()
    # Strongest peak per type: three corners on the wrong corner, no pose.
    strongest = pts[[9, 10, 11, 3, 4, 5, 6, 7, 8]]
    assert solve_pnp(strongest, scores[[9, 10, 11, 3, 4, 5, 6, 7, 8]], CUBOID, K640) is None
    p = solve_pnp_candidates(ids, pts, scores, CUBOID, K640)
    assert p is not None
    assert rotation_error_deg(p.R, R) < 0.01 and np.linalg.norm(p.t - t) < 1e-4
    np.testing.assert_allclose(p.keypoints, pts[:9])        # the assignment: each corner's own peak
    np.testing.assert_allclose(p.keypoint_scores, scores[:9])
    assert p.inliers.all() and p.score == pytest.approx(0.5)
    # Order of the candidates does not matter.
    perm = np.random.default_rng(1).permutation(len(ids))
    q = solve_pnp_candidates(ids[perm], pts[perm], scores[perm], CUBOID, K640)
    assert q is not None and rotation_error_deg(q.R, R) < 0.01


def _count_solves(monkeypatch) -> list[int]:
    """The pose search's hypotheses, as it takes them: ``cv2.SOLVEPNP_SQPNP`` per least-squares
    solve, ``cv2.SOLVEPNP_AP3P`` per minimal set considered (sets are solved in blocks that may
    end past the last one considered)."""
    import cv2

    import dope_hope.inference.pose_search as pose_mod

    calls: list[int] = []
    solve_pnp_cv, take = cv2.solvePnP, MinimalSetBlock.take

    def counting_pnp(*a, **kw):
        if kw.get("flags") != cv2.SOLVEPNP_AP3P:  # minimal sets are counted as taken
            calls.append(kw.get("flags"))
        return solve_pnp_cv(*a, **kw)

    def counting_take(block, scorer, lo, hi):
        calls.extend([cv2.SOLVEPNP_AP3P] * (hi - lo))
        return take(block, scorer, lo, hi)

    monkeypatch.setattr(pose_mod.cv2, "solvePnP", counting_pnp)
    monkeypatch.setattr(MinimalSetBlock, "take", counting_take)
    return calls


def test_the_search_takes_no_more_hypotheses_than_the_candidates_need(monkeypatch):
    import cv2

    import dope_hope.inference.pose_search as pose_mod

    calls = _count_solves(monkeypatch)  # least-squares solves and AP3P minimal sets
    # Consistent first candidates: the least-squares pose through them is the only hypothesis.
    R, t, kp = _exact_keypoints(4)
    assert solve_pnp_candidates(np.arange(9), kp, np.ones(9), CUBOID, K640) is not None
    assert calls == [cv2.SOLVEPNP_SQPNP]
    # Three types listed wrong-first: the minimal sets' covering order reaches three right
    # corners within the first check (4 sets).
    R, t, ids, pts, scores = _confused_candidates(3)
    order = np.r_[8, 9, 10, 11, np.arange(8)]  # centroid, then each type's wrong peak first
    calls.clear()
    p = solve_pnp_candidates(ids[order], pts[order], scores[order], CUBOID, K640)
    assert p is not None and rotation_error_deg(p.R, R) < 0.01 and p.inliers.all()
    np.testing.assert_allclose(p.keypoints, pts[:9])
    assert calls == [cv2.SOLVEPNP_SQPNP] + [cv2.SOLVEPNP_AP3P] * 4
    # A type whose only candidate is another object's peak: all types but that one explained
    # is enough, the search ends at the first minimal set that avoids it.
    R, t, kp = _exact_keypoints(6)
    kp[5] += [90.0, 70.0]
    calls.clear()
    p = solve_pnp_candidates(np.r_[8, np.arange(8)], kp[np.r_[8, np.arange(8)]], np.ones(9), CUBOID, K640)
    assert p is not None and rotation_error_deg(p.R, R) < 0.01
    assert not p.inliers[5] and p.inliers.sum() == 8
    assert calls[0] == cv2.SOLVEPNP_SQPNP and calls.count(cv2.SOLVEPNP_AP3P) <= 4
    # Clutter (three random peaks per corner type): no minimal set fits its own centroid, given
    # up after _STALL_AFTER sets without a better hypothesis.
    rng = np.random.default_rng(2)
    clutter_ids = np.r_[8, np.repeat(np.arange(8), 3)]
    clutter = np.vstack([[320.0, 240.0], rng.uniform(220, 420, (24, 2))])
    calls.clear()
    assert solve_pnp_candidates(clutter_ids, clutter, np.ones(25), CUBOID, K640) is None
    assert len(calls) == 1 + pose_mod._STALL_AFTER < pose_mod.DEFAULT_MAX_HYPOTHESES
    # Three corners and the centroid of one pose among the clutter: the first set fits, nothing
    # explains more than its own four; given up _STALL_AFTER sets after the last better one.
    R, t, kp = _exact_keypoints(7)
    partial = clutter.copy()
    partial[0], partial[[1, 4, 7]] = kp[8], kp[[0, 1, 2]]
    calls.clear()
    assert solve_pnp_candidates(clutter_ids, partial, np.ones(25), CUBOID, K640) is None
    assert 1 + pose_mod._STALL_AFTER < len(calls) <= 1 + pose_mod._STALL_AFTER + 2 * pose_mod._HYPOTHESIS_CHUNK
    calls.clear()
    assert solve_pnp_candidates(clutter_ids, partial, np.ones(25), CUBOID, K640,
                                HypothesisSettings(max_hypotheses=10)) is None
    assert len(calls) == 1 + 10
    with pytest.raises(ConfigError, match="max_hypotheses"):
        solve_pnp_candidates(ids, pts, scores, CUBOID, K640, HypothesisSettings(max_hypotheses=0))



def _cluttered_box(seed: int, corners: int, noise_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box's centroid and its first ``corners`` corners (noisy) among three random peaks per
    corner type, each type's peaks in random order: (25,) ids, (25, 2) px, (25,) scores."""
    rng = np.random.default_rng(seed)
    ids = np.r_[8, np.repeat(np.arange(8), 3)]
    pts = np.vstack([[320.0, 240.0], rng.uniform(220, 420, (24, 2))])
    scores = rng.uniform(0.3, 1.0, 25)
    kp = _exact_keypoints(seed)[2] + rng.normal(scale=noise_px, size=(9, 2))
    pts[0] = kp[8]
    for k in range(corners):
        pts[1 + 3 * k + rng.integers(3)] = kp[k]
    return ids, pts, scores


def test_minimal_sets_are_solved_in_blocks_up_to_the_earliest_stop_as_one_chunk_at_a_time_would(monkeypatch):
    """The search solves its minimal sets in blocks that end where it may stop next (the stall
    rule): each set once, none past the last considered unless a hypothesis explaining enough
    types ends the search within a block; the estimates equal those of solving each chunk on
    its own."""
    import dope_hope.inference.pose_search as pose_mod

    solve = MinimalSetBlock.solve.__func__
    blocks: list[tuple[int, int]] = []

    def recording(cls, objs, imgs, K, first, end, scorer):
        blocks.append((first, end))
        return solve(cls, objs, imgs, K, first, end, scorer)

    def chunk_by_chunk(cls, objs, imgs, K, first, end, scorer):
        end = min(e for e in pose_mod._chunk_ends(len(objs)) if e > first)
        blocks.append((first, end))
        return solve(cls, objs, imgs, K, first, end, scorer)

    cases = [_cluttered_box(seed, corners, noise) for seed in range(4) for corners in (3, 5, 8) for noise in (0.5, 2.5)]
    results = {}
    for name, how in (("blocks", recording), ("chunks", chunk_by_chunk)):
        monkeypatch.setattr(MinimalSetBlock, "solve", classmethod(how))
        results[name] = []
        for case in cases:
            blocks.clear()
            results[name].append((solve_pnp_candidates(*case, CUBOID, K640), list(blocks)))
    for (est, solved), (est_chunks, chunks) in zip(results["blocks"], results["chunks"]):
        assert [b for b, _ in solved] == [0] + [e for _, e in solved[:-1]]     # each set once
        assert solved[-1][1] >= chunks[-1][1]                                   # no fewer considered
        assert len(solved) < len(chunks) or len(chunks) == 1
        assert (est is None) == (est_chunks is None)
        if est is not None:
            np.testing.assert_array_equal(est.R, est_chunks.R)
            np.testing.assert_array_equal(est.keypoints, est_chunks.keypoints)
            assert est.score == est_chunks.score
    assert sum(est is not None for est, _ in results["blocks"]) >= 4
    assert sum(len(solved) > 1 for _, solved in results["blocks"]) >= 8   # searches past the first block


def test_instances_give_each_peak_to_one_object_and_drop_a_noise_centroid_before_any_minimal_set(monkeypatch):
    """solve_pnp_instances: box A, decided by step 1, holds its inlier peaks; a noise
    centroid beside it whose candidates are A's corners (they passed its angle test) and two
    noise peaks has too few types left and costs no minimal set; box B, listed wrong-first on
    three types, is still searched and found; a second centroid peak on A gives no second
    estimate."""
    import cv2

    calls = _count_solves(monkeypatch)
    RA, tA = Rotation.random(random_state=4).as_matrix(), np.array([-0.12, 0.0, 0.7])
    RB, tB = Rotation.random(random_state=5).as_matrix(), np.array([0.12, 0.02, 0.7])
    a, b = project_points(CUBOID, K640, RA, tA), project_points(CUBOID, K640, RB, tB)
    box_a = (np.arange(9), a, np.ones(9))
    noise = (np.r_[8, np.arange(8), 0, 1], np.vstack([a[8] + [25.0, 15.0], a[:8], a[8] + [[-30.0, 5.0], [10.0, -35.0]]]),
             np.r_[0.2, np.ones(8), 0.3, 0.3])
    box_b = (np.r_[8, 0, 1, 2, np.arange(8)], np.vstack([b[8], b[[2, 3, 0]], b[:8]]), np.r_[0.5, 0.9, 0.9, 0.9, np.full(8, 0.5)])
    twin_a = (np.arange(9), np.vstack([a[:8], a[8] + [1.0, 0.5]]), np.r_[np.ones(8), 0.9])
    found = solve_pnp_instances([box_a, noise, box_b, twin_a], CUBOID, K640)
    assert len(found) == 2
    _check_all_found(found, [RA, RB], [tA, tB], rot_deg=0.1, trans_m=1e-3)
    np.testing.assert_allclose(found[0].keypoints, a)  # A's own centroid peak, not its twin's
    assert calls.count(cv2.SOLVEPNP_AP3P) == 4  # box B's search only

def test_the_types_the_best_hypothesis_explains_give_the_pose_where_foreign_peaks_fail_the_inlier_ratio():
    """Three corner types whose only candidates are another object's peaks: the whole
    assignment has 6 inliers of 9 keypoints (under the 0.75 ratio) and fails, RANSAC too; the
    six types the best hypothesis explains give the pose, with the other three missing."""
    R, t, kp = _exact_keypoints(11)
    pts = kp.copy()
    pts[[1, 4, 6]] += [[95.0, -60.0], [-80.0, 70.0], [70.0, 85.0]]     # foreign peaks
    scores = np.full(9, 0.8)
    assert solve_pnp(pts, scores, CUBOID, K640) is None                 # RANSAC on all nine
    est = solve_pnp_candidates(np.arange(9), pts, scores, CUBOID, K640)
    assert est is not None and rotation_error_deg(est.R, R) < 0.01 and np.linalg.norm(est.t - t) < 1e-4
    assert est.inliers.tolist() == [True, False, True, True, False, True, False, True, True]
    assert np.isnan(est.keypoints[[1, 4, 6]]).all() and est.score == pytest.approx(6 * 0.8 / 9)
    # min_score above what any pose of these keypoints can score (0.8, all in view): no pose.
    assert solve_pnp_candidates(np.arange(9), pts, scores, CUBOID, K640, min_score=0.7) is not None
    assert solve_pnp_candidates(np.arange(9), pts, scores, CUBOID, K640, min_score=0.85) is None


def test_candidates_without_a_pose_or_a_centroid_give_none():
    rng = np.random.default_rng(0)
    ids = np.r_[np.repeat(np.arange(8), 2), 8]
    for _ in range(20):  # two random peaks per corner type around a centroid: nothing rigid
        pts = np.vstack([rng.uniform(220, 420, (16, 2)), [[320.0, 240.0]]])
        assert solve_pnp_candidates(ids, pts, np.ones(17), CUBOID, K640) is None
    R, t, ids, pts, scores = _confused_candidates()
    no_centroid = ids != 8
    assert solve_pnp_candidates(ids[no_centroid], pts[no_centroid], scores[no_centroid], CUBOID, K640) is None
    two_types = np.isin(ids, [0, 1, 8])
    assert solve_pnp_candidates(ids[two_types], pts[two_types], scores[two_types], CUBOID, K640) is None
    with pytest.raises(ValueError, match="length"):
        solve_pnp_candidates(ids, pts[:-1], scores, CUBOID, K640)
    with pytest.raises(ValueError, match="0..8"):
        solve_pnp_candidates(ids + 1, pts, scores, CUBOID, K640)


def test_min_score_skips_only_searches_whose_poses_could_not_reach_it(monkeypatch):
    """With min_score, a centroid whose candidates (or the assignment its search ends with) can
    give no pose of that score - its clipped confidences over the fewest inliers an accepted
    pose needs - is not searched (or not solved): every estimate whose best in-view score
    reaches min_score is still found, the same; the others may be dropped, and some are."""
    searched = []
    search = MinimalSetBlock.solve.__func__
    monkeypatch.setattr(MinimalSetBlock, "solve", classmethod(
        lambda cls, *a: searched.append(a[4] - a[3]) or search(cls, *a)))
    min_score, kept, dropped, unsearched = 0.6, 0, 0, 0
    for seed in range(12):
        for corners in (6, 8):
            ids, pts, scores = _cluttered_box(seed, corners, 1.0)
            scores = np.clip(scores - 0.15 * (seed % 3), 0.05, 1.0)
            searched.clear()
            every = solve_pnp_candidates(ids, pts, scores, CUBOID, K640)
            sets_every = sum(searched)
            searched.clear()
            some = solve_pnp_candidates(ids, pts, scores, CUBOID, K640, min_score=min_score)
            if every is None:
                assert some is None
                continue
            inliers = every.inliers
            best_in_view = np.clip(every.keypoint_scores[inliers], 0, 1).sum() / max(5, inliers.sum())
            if best_in_view >= min_score:
                assert some is not None and some.score == every.score
                np.testing.assert_array_equal(some.R, every.R)
                kept += 1
            elif some is None:  # (or a pose below min_score, which the predictor drops)
                dropped += 1
                assert sum(searched) <= sets_every
                unsearched += sets_every > 0 and not searched
    assert kept >= 3 and dropped >= 3 and unsearched >= 1
