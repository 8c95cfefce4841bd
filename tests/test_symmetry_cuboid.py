"""The rotations that map a cuboid onto itself, their corner permutations and their names."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.geometry import cuboid_keypoints, project_points
from dope_hope.symmetry.cuboid import corner_permutation, cuboid_rotations, describe_rotation, long_axis


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


def test_long_axis_is_the_one_much_longer_than_both_others():
    assert long_axis(np.array([0.065, 0.149, 0.043])) == 1  # the Ketchup bottle: y
    assert long_axis(np.array([0.05, 0.05, 0.08])) == 2  # a can: z
    assert long_axis(np.array([0.1227, 0.1672, 0.0402])) == 1  # the demo box: 1.36x
    assert long_axis(np.array([0.06, 0.05, 0.06])) is None  # a loaf: no axis stands out
    assert long_axis(np.array([0.10, 0.12, 0.04])) is None  # 1.2x: not long enough
    assert long_axis(np.array([0.10, 0.12, 0.04]), factor=1.1) == 1
