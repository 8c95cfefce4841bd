"""dope_hope.geometry: keypoint order, projection, PnP round trip, rotations, legacy frame."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dope_hope.geometry import (
    CENTROID_INDEX,
    CUBOID_CORNER_SIGNS,
    CUBOID_EDGES,
    LEGACY_TO_CURRENT_INDEX,
    LEGACY_TO_MESH,
    NUM_KEYPOINTS,
    cuboid_keypoints,
    intrinsics_matrix,
    legacy_keypoints_to_current,
    legacy_rotation_to_mesh,
    legacy_size_to_mesh,
    matrix_to_quaternion_xyzw,
    mesh_rotation_to_legacy,
    nearest_rotation,
    project_points,
    quaternion_xyzw_to_matrix,
    rotation_error_deg,
    scale_intrinsics,
    transform_points,
)

KETCHUP_LEGACY_M = np.array([14.8608, 4.3368, 6.4514]) / 100.0
K = intrinsics_matrix(615.0, 612.0, 321.5, 239.25)

quaternions = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-2)


def test_corner_order_is_the_documented_table():
    # ARCHITECTURE.md: + − + | − − + | − + + | + + + | + − − | − − − | − + − | + + −
    table = "+-+ --+ -++ +++ +-- --- -+- ++-".split()
    signs = np.array([[1 if c == "+" else -1 for c in s] for s in table])
    np.testing.assert_array_equal(CUBOID_CORNER_SIGNS, signs)
    kp = cuboid_keypoints([0.06, 0.15, 0.04], center=[0.01, 0.0, -0.02])
    assert kp.shape == (NUM_KEYPOINTS, 3) and CENTROID_INDEX == 8
    np.testing.assert_allclose(kp[0], [0.04, -0.075, 0.0])
    np.testing.assert_allclose(kp[6], [-0.02, 0.075, -0.04])
    np.testing.assert_allclose(kp[8], [0.01, 0.0, -0.02])
    np.testing.assert_allclose(kp[:8].mean(0), kp[8])


def test_edges_join_corners_differing_in_one_axis():
    assert len(set(map(frozenset, CUBOID_EDGES))) == 12
    for a, b in CUBOID_EDGES:
        assert np.sum(CUBOID_CORNER_SIGNS[a] != CUBOID_CORNER_SIGNS[b]) == 1


def test_project_points_pinhole_and_pose():
    uv = project_points(np.array([[0.0, 0.0, 2.0], [0.2, -0.1, 1.0]]), K)
    np.testing.assert_allclose(uv, [[321.5, 239.25], [321.5 + 123.0, 239.25 - 61.2]])
    R = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    uv2 = project_points(np.array([[-1.0, 0.0, 0.0]]), K, R, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(uv2, [[321.5, 239.25]])  # lands on (0, 0, 2)
    with np.errstate(all="ignore"):
        assert not np.isfinite(project_points(np.array([[0.1, 0.0, 0.0]]), K)).all()


def test_cuboid_projection_solvepnp_round_trip():
    rng = np.random.default_rng(7)
    kp = cuboid_keypoints([0.0645, 0.1486, 0.0434])
    for _ in range(10):
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        t = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), rng.uniform(0.4, 1.2)])
        uv = project_points(kp, K, R, t)
        ok, rvec, tvec = cv2.solvePnP(kp, uv, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
        assert ok
        assert rotation_error_deg(cv2.Rodrigues(rvec)[0], R) < 1e-4
        np.testing.assert_allclose(tvec.ravel(), t, atol=1e-6)
        np.testing.assert_allclose(transform_points(kp, R, t)[:, 2], (kp @ R.T + t)[:, 2])


@settings(max_examples=60, deadline=None)
@given(q=quaternions)
def test_quaternion_round_trip(q):
    q = np.array(q) / np.linalg.norm(q)
    R = quaternion_xyzw_to_matrix(q)
    q2 = matrix_to_quaternion_xyzw(R)
    assert q2[3] >= 0
    assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-9
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(q2), R, atol=1e-12)


def test_quaternion_is_scalar_last():
    R = quaternion_xyzw_to_matrix([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])  # 90° about z
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(sx=st.floats(0.1, 4.0), sy=st.floats(0.1, 4.0),
       p=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.2, 3.0)))
def test_scale_intrinsics_matches_resized_pixel_coordinates(sx, sy, p):
    """u' = sx (u + 0.5) - 0.5: pixel edges, not centres, scale with the image."""
    uv = project_points(np.array([p]), K)[0]
    uv2 = project_points(np.array([p]), scale_intrinsics(K, sx, sy))[0]
    np.testing.assert_allclose(uv2, [sx * (uv[0] + 0.5) - 0.5, sy * (uv[1] + 0.5) - 0.5], atol=1e-9)
    np.testing.assert_allclose(scale_intrinsics(scale_intrinsics(K, sx, sy), 1 / sx, 1 / sy), K,
                               atol=1e-9)


def test_scale_intrinsics_halving_maps_pixel_grid():
    # a 640-wide image halved: the centre of the leftmost 2 pixels (u = 0.5) becomes u' = 0
    K2 = scale_intrinsics(intrinsics_matrix(500, 500, 0.5, 0.5), 0.5, 0.5)
    np.testing.assert_allclose(K2[:2, 2], [0.0, 0.0])
    np.testing.assert_allclose(np.diag(K2)[:2], [250.0, 250.0])


def test_rotation_error_and_nearest_rotation():
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    R2 = R @ Rotation.from_rotvec([0, 0, np.radians(7)]).as_matrix()
    assert rotation_error_deg(R, R2) == pytest.approx(7.0)
    np.testing.assert_allclose(nearest_rotation(0.01 * R), R, atol=1e-12)  # drops scale
    noisy = R + np.random.default_rng(0).normal(scale=1e-3, size=(3, 3))
    Rn = nearest_rotation(noisy)
    np.testing.assert_allclose(Rn @ Rn.T, np.eye(3), atol=1e-12)
    assert rotation_error_deg(Rn, R) < 0.2
    assert np.linalg.det(nearest_rotation(np.diag([1.0, 1.0, -1.0]))) == pytest.approx(1.0)


def test_legacy_frame_ketchup_sizes_and_rotation():
    assert np.linalg.det(LEGACY_TO_MESH) == pytest.approx(1.0)
    np.testing.assert_allclose(legacy_size_to_mesh(KETCHUP_LEGACY_M),
                               [0.064514, 0.148608, 0.043368])
    R = Rotation.random(random_state=3).as_matrix()
    np.testing.assert_allclose(mesh_rotation_to_legacy(legacy_rotation_to_mesh(R)), R, atol=1e-12)


def test_legacy_keypoints_coincide_with_mesh_keypoints_as_a_set():
    """R_mesh = R_legacy L^T: the legacy box in the legacy pose is the mesh box in the mesh pose."""
    size_mesh = legacy_size_to_mesh(KETCHUP_LEGACY_M)
    kp_legacy = cuboid_keypoints(KETCHUP_LEGACY_M)
    kp_mesh = cuboid_keypoints(size_mesh)
    rng = np.random.default_rng(11)
    for _ in range(5):
        R_legacy = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        t = rng.normal(size=3) + [0, 0, 2]
        a = transform_points(kp_legacy, R_legacy, t)
        b = transform_points(kp_mesh, legacy_rotation_to_mesh(R_legacy), t)
        dist = np.linalg.norm(a[:, None] - b[None], axis=-1)
        match = dist.argmin(axis=1)
        assert dist.min(axis=1).max() < 1e-12  # every legacy point is a mesh point...
        assert sorted(match) == list(range(9))  # ...one-to-one
        np.testing.assert_array_equal(match, LEGACY_TO_CURRENT_INDEX)
        # and the reorder helper turns the legacy projection into the current one
        np.testing.assert_allclose(legacy_keypoints_to_current(project_points(a, K)),
                                   project_points(b, K), atol=1e-9)


def test_legacy_keypoints_to_current_batches():
    kp = np.arange(2 * 9 * 2, dtype=float).reshape(2, 9, 2)
    out = legacy_keypoints_to_current(kp)
    np.testing.assert_array_equal(out[:, LEGACY_TO_CURRENT_INDEX], kp)
    np.testing.assert_array_equal(out[:, 8], kp[:, 8])


def test_projected_bbox_clips_like_bop_calc_2d_bbox():
    from dope_hope.geometry import intrinsics_matrix, projected_bbox

    K = intrinsics_matrix(100.0, 100.0, 50.0, 40.0)
    pts = np.array([[-0.1, -0.05, 0.0], [0.1, 0.05, 0.0], [0.0, 0.0, 0.1]])
    box = projected_bbox(pts, K, np.eye(3), np.array([0.0, 0.0, 1.0]), (80, 100))
    np.testing.assert_allclose(box, [40.0, 35.0, 60.0, 45.0])  # z = 1 m for the extremes
    # half outside on the left: clipped to pixel 0 as the BOP toolkit does ([0, W-1] x [0, H-1])
    box = projected_bbox(pts, K, np.eye(3), np.array([-0.5, 0.0, 1.0]), (80, 100))
    np.testing.assert_allclose(box, [0.0, 35.0, 10.0, 45.0])
    assert projected_bbox(pts, K, np.eye(3), np.array([-2.0, 0.0, 1.0]), (80, 100)) is None  # misses
    assert projected_bbox(pts, K, np.eye(3), np.array([0.0, 0.0, -0.05]), (80, 100)) is None  # behind
    np.testing.assert_allclose(projected_bbox(pts, K, np.eye(3), np.array([-0.5, 0.0, 1.0]), None),
                               [-10.0, 35.0, 10.0, 45.0])


def test_fit_cuboid_recovers_the_box_that_views_imply_and_not_from_one_view():
    from dope_hope.geometry import fit_cuboid

    size, center = np.array([0.05, 0.05, 0.08]), np.array([0.004, -0.002, 0.01])
    K = intrinsics_matrix(500.0, 500.0, 319.5, 239.5)
    views = []
    for seed in range(3):
        R = Rotation.random(random_state=seed).as_matrix()
        t = np.array([0.02 * seed, -0.01, 0.5])
        views.append((project_points(cuboid_keypoints(size, center), K, R, t), K, R, t))
    fitted_size, fitted_center, rms = fit_cuboid(views)
    np.testing.assert_allclose(fitted_size, size, atol=1e-9)
    np.testing.assert_allclose(fitted_center, center, atol=1e-9)
    assert rms < 1e-6
    # one view: a box twice the size twice as far projects the same, so nothing is implied
    assert fit_cuboid(views[:1]) is None and fit_cuboid([]) is None
    # poses in another frame than the keypoints': the one box fits badly, which rms says
    R0 = views[0][2] @ Rotation.from_euler("z", 90, degrees=True).as_matrix()
    assert fit_cuboid([views[0][:2] + (R0, views[0][3])] + views[1:])[2] > 2.0


def test_inside_image_takes_the_border_pixels_and_refuses_nan():
    """Pixel centres at integers: [-0.5, W - 0.5] x [-0.5, H - 0.5] is the image, borders in."""
    from dope_hope.geometry import inside_image

    uv = np.array([[-0.5, -0.5], [639.5, 479.5], [-0.51, 10.0], [10.0, 479.51], [np.nan, 5.0], [320.0, 240.0]])
    assert inside_image(uv, (480, 640)).tolist() == [True, True, False, False, False, True]
