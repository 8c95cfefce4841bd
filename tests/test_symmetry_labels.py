"""symmetry.labels: one corner order per view of a symmetric object."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.errors import ConfigError
from dope_hope.geometry import cuboid_keypoints, intrinsics_matrix, project_points
from dope_hope.symmetry.labels import (
    camera_direction,
    canonical_keypoints,
    canonical_permutation,
    corner_permutations,
)
from dope_hope.symmetry.resolve import label_symmetries
from dope_hope.symmetry.transforms import category_symmetries

K = intrinsics_matrix(615.0, 615.0, 319.5, 239.5)


@pytest.mark.parametrize("category, size, count", [
    ("bottle", get_object("Ketchup").size_array, 2),
    ("cuboid", get_object("Cookies").size_array, 4),
    ("cylinder", np.array([0.06, 0.07, 0.06]), 8),   # square cross-section: 90° steps too
    ("cylinder", np.array([0.06, 0.07, 0.065]), 4),  # not square: only the 180° turns
])
def test_only_symmetries_that_permute_the_corners_are_kept(category, size, count):
    rots, perms = corner_permutations(size, category_symmetries(category, step_deg=90.0))
    assert len(perms) == count and np.array_equal(perms[0], np.arange(9))
    cub = cuboid_keypoints(size)
    for S, perm in zip(rots, perms):
        np.testing.assert_allclose(cub @ S.T, cub[perm], atol=1e-12)
        assert perm[8] == 8  # the centroid stays


@pytest.mark.parametrize("category, name", [("bottle", "Ketchup"), ("cuboid", "Cookies")])
def test_symmetric_poses_get_the_same_labels(category, name):
    """Poses R and R S look alike; their relabelled keypoints must be equal (the network
    is never asked to tell them apart), and each label set is a pose's true projection."""
    size = get_object(name).size_array
    rots, perms = corner_permutations(size, category_symmetries(category))
    cub = cuboid_keypoints(size)
    rng = np.random.default_rng(0)
    for R in Rotation.random(50, random_state=1).as_matrix():
        t = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.1, 0.1), rng.uniform(0.4, 1.0)])
        labels = []
        for S in rots:
            RS = R @ S
            kp = project_points(cub, K, RS, t)[None]
            labels.append(canonical_keypoints(kp, camera_direction(RS, t)[None], rots, perms)[0])
        for other in labels[1:]:
            np.testing.assert_allclose(other, labels[0], atol=1e-9)
        assert any(np.allclose(labels[0], project_points(cub, K, R @ S, t), atol=1e-9) for S in rots)


def test_views_without_a_pose_keep_their_order():
    rots, perms = corner_permutations(get_object("Ketchup").size_array, category_symmetries("bottle"))
    assert np.isnan(camera_direction(np.eye(3), np.zeros(3))).all()
    assert canonical_permutation(np.full(3, np.nan), rots, perms).tolist() == list(range(9))


def test_symmetry_setting():
    assert label_symmetries("none", "Ketchup") is None
    assert label_symmetries(None, "Ketchup") is None
    T, source = label_symmetries("auto", "ketchup")
    assert source == "bottle category"
    np.testing.assert_allclose(T, category_symmetries("bottle"))
    T, source = label_symmetries("auto", "DemoBox")
    assert source == "declared in dope_hope.demo_object"
    np.testing.assert_allclose(T, category_symmetries("cuboid"), atol=1e-12)
    assert label_symmetries("cylinder", "MyCan")[1] == "cylinder category"
    with pytest.raises(ConfigError, match="not a HOPE object"):
        label_symmetries("auto", "MyCan")
    with pytest.raises(ConfigError, match="targets.symmetry"):
        label_symmetries("sphere", "Ketchup")
