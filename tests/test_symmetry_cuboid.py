"""The rotations that map a cuboid onto itself, their corner permutations and their names."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.symmetry.cuboid import corner_permutation, cuboid_rotations, describe_rotation


def test_group_sizes_follow_the_box_shape():
    assert len(cuboid_rotations([0.06, 0.15, 0.04])) == 4    # three different extents
    assert len(cuboid_rotations([0.05, 0.12, 0.05])) == 8    # square section about y
    assert len(cuboid_rotations([0.07, 0.07, 0.07])) == 24   # a cube
    assert np.array_equal(cuboid_rotations([0.06, 0.15, 0.04])[0], np.eye(3))
    names = sorted(describe_rotation(S) for S in cuboid_rotations([0.06, 0.15, 0.04])[1:])
    assert names == ["180° about x", "180° about y", "180° about z"]
    square = {describe_rotation(S) for S in cuboid_rotations([0.05, 0.12, 0.05])}
    assert {"90° about y", "90° about -y"} <= square


def test_corner_permutation_relabels_the_projected_keypoints():
    size, K = np.array([0.05, 0.12, 0.05]), np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    R = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_matrix()
    t = np.array([0.02, -0.01, 0.6])
    box = cuboid_keypoints(size)
    uv = project_points(box, K, R, t)
    for S in cuboid_rotations(size):
        np.testing.assert_allclose(project_points(box, K, R @ S, t), uv[corner_permutation(S)], atol=1e-9)
