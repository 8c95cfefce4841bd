"""Many P3P problems at once (dope_hope.inference.p3p.ap3p_poses), against OpenCV's AP3P."""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from test_inference_pnp import CUBOID, K640

from dope_hope.geometry import project_points
from dope_hope.inference.p3p import ap3p_poses


def _minimal_sets(n: int, noise_px: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """n sets of three cuboid corners and the centroid seen from random poses 0.4-1.2 m away,
    their image points with Gaussian noise: objs (n, 4, 3), imgs (n, 4, 2), R (n, 3, 3), t (n, 3)."""
    rng = np.random.default_rng(seed)
    Rs = Rotation.random(n, random_state=seed).as_matrix()
    ts = np.column_stack([rng.uniform(-0.2, 0.2, n), rng.uniform(-0.15, 0.15, n), rng.uniform(0.4, 1.2, n)])
    corners = np.array([rng.choice(8, 3, replace=False) for _ in range(n)])
    objs = CUBOID[np.column_stack([corners, np.full(n, 8)])]
    imgs = np.stack([project_points(o, K640, R, t) for o, R, t in zip(objs, Rs, ts)])
    return objs, imgs + rng.normal(scale=noise_px, size=imgs.shape), Rs, ts


def _squared_error_px(R: np.ndarray, t: np.ndarray, obj: np.ndarray, img: np.ndarray) -> float:
    return float(((project_points(obj, K640, R, t) - img) ** 2).sum())


def test_exact_minimal_sets_give_their_poses():
    objs, imgs, Rs, ts = _minimal_sets(300, 0.0, seed=0)
    R, t, solved = ap3p_poses(objs, imgs, K640)
    assert solved.all() and R.shape == (300, 3, 3) and t.shape == (300, 3)
    np.testing.assert_allclose(R, Rs, atol=1e-8)
    np.testing.assert_allclose(t, ts, atol=1e-9)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_noisy_sets_give_opencvs_pose_or_one_that_fits_the_four_points_better():
    """Per set the pose of ``cv2.solvePnP(..., SOLVEPNP_AP3P)``, or, where OpenCV's AP3P misses a
    real root of the quartic, another exact solution of the three points whose fourth point
    lies nearer its image point."""
    objs, imgs, _, _ = _minimal_sets(1000, 2.0, seed=1)
    objs[-1, :, 0] = 0.0       # the last set: its three corners and centroid on a line: no pose
    objs[-1, :, 1] = [0.0, 0.02, 0.04, 0.01]
    objs[-1, :, 2] = [0.0, 0.01, 0.02, 0.005]
    R, t, solved = ap3p_poses(objs, imgs, K640)
    same = better = 0
    for k, i in enumerate(np.flatnonzero(solved)):
        ok, rvec, tvec = cv2.solvePnP(objs[i], imgs[i], K640, None, flags=cv2.SOLVEPNP_AP3P)
        assert ok
        R_cv = cv2.Rodrigues(rvec)[0]
        if np.abs(R[k] - R_cv).max() < 1e-9 and np.abs(t[k] - tvec.ravel()).max() < 1e-9:
            same += 1
            continue
        assert _squared_error_px(R[k], t[k], objs[i], imgs[i]) < _squared_error_px(R_cv, tvec.ravel(), objs[i], imgs[i])
        assert _squared_error_px(R[k], t[k], objs[i, :3], imgs[i, :3]) < 1e-12   # exact on its three points
        assert (objs[i] @ R[k].T + t[k])[:, 2].min() > 0                           # in front of the camera
        better += 1
    assert not solved[-1] and solved[:-1].all()
    assert same >= 900 and same + better == 999


def test_degenerate_and_empty_batches():
    objs, imgs, _, _ = _minimal_sets(3, 0.0, seed=2)
    imgs[1, 1] = imgs[1, 0]        # two image points on one pixel
    objs[2, 2] = objs[2, 0]        # two model points in one place
    R, t, solved = ap3p_poses(objs, imgs, K640)
    assert solved.tolist() == [True, False, False] and R.shape == (1, 3, 3) and t.shape == (1, 3)
    R, t, solved = ap3p_poses(np.zeros((0, 4, 3)), np.zeros((0, 4, 2)), K640)
    assert R.shape == (0, 3, 3) and t.shape == (0, 3) and solved.shape == (0,)
