"""The consensus of every minimal set of one keypoint assignment (the pose search's fallback
where its own consensus fails): it must find the pose most keypoints support, outliers and
all, the same way every time, and refuse what cannot give a pose."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.geometry import cuboid_keypoints, project_points, rotation_error_deg
from dope_hope.inference.hypothesis_scoring import assignment_consensus

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
CUBOID = cuboid_keypoints(np.array([0.06, 0.15, 0.04]))
R_TRUE = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_matrix()
T_TRUE = np.array([0.05, -0.02, 0.6])


def _keypoints(rng, noise_px: float, outliers: tuple[int, ...]) -> np.ndarray:
    kp = project_points(CUBOID, K, R_TRUE, T_TRUE) + rng.normal(0.0, noise_px, (9, 2))
    for k in outliers:
        kp[k] += rng.choice([-1.0, 1.0], 2) * rng.uniform(30.0, 60.0, 2)   # another object's peak
    return kp


def test_the_pose_most_keypoints_support_outliers_and_all():
    rng = np.random.default_rng(0)
    for trial in range(20):
        outliers = tuple(rng.choice(9, size=trial % 3, replace=False).tolist())
        kp = _keypoints(rng, 1.0, outliers)
        R, t = assignment_consensus(kp, np.ones(9, bool), CUBOID, K, 8.0)
        assert rotation_error_deg(R, R_TRUE) < 5.0 and np.linalg.norm(t - T_TRUE) < 0.03, (trial, outliers)
        err = np.linalg.norm(project_points(CUBOID, K, R, t) - kp, axis=1)
        inliers = set(np.flatnonzero(err <= 8.0).tolist())
        assert inliers == set(range(9)) - set(outliers), (trial, outliers)


def test_missing_keypoints_are_left_out_and_the_answer_is_always_the_same():
    rng = np.random.default_rng(1)
    kp = _keypoints(rng, 1.0, (4,))
    kp[[2, 6]] = np.nan
    present = np.isfinite(kp).all(axis=1)
    first = assignment_consensus(kp, present, CUBOID, K, 8.0)
    again = assignment_consensus(kp.copy(), present.copy(), CUBOID, K, 8.0)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    assert rotation_error_deg(first[0], R_TRUE) < 5.0


def test_fewer_than_four_keypoints_give_no_pose():
    kp = project_points(CUBOID, K, R_TRUE, T_TRUE)
    present = np.zeros(9, bool)
    present[[0, 3, 8]] = True
    assert assignment_consensus(kp, present, CUBOID, K, 8.0) is None
