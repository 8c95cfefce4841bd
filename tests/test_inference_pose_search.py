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


def test_the_search_solves_no_more_hypotheses_than_the_candidates_need(monkeypatch):
    import cv2

    import dope_hope.inference.pose_search as pose_mod

    calls = []  # AP3P minimal-set hypotheses
    real = cv2.solvePnP

    def counting(*a, **kw):
        calls.append(kw.get("flags"))
        return real(*a, **kw)

    monkeypatch.setattr(pose_mod.cv2, "solvePnP", counting)
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



def test_instances_give_each_peak_to_one_object_and_drop_a_noise_centroid_before_any_minimal_set(monkeypatch):
    """solve_pnp_instances: box A, decided by step 1, holds its inlier peaks; a noise
    centroid beside it whose candidates are A's corners (they passed its angle test) and two
    noise peaks has too few types left and costs no minimal set; box B, listed wrong-first on
    three types, is still searched and found; a second centroid peak on A gives no second
    estimate."""
    import cv2

    import dope_hope.inference.pose_search as pose_mod

    calls = []
    real = cv2.solvePnP

    def counting(*a, **kw):
        calls.append(kw.get("flags"))
        return real(*a, **kw)

    monkeypatch.setattr(pose_mod.cv2, "solvePnP", counting)
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
