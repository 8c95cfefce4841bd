"""Depth ICP (dope_hope.refine.icp): exact box depth in, the pose that made it out; bad depth refused;
a pose's own depth support counted in its detected region (a pose moved onto a distractor has little)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from box_depth import render_box_depth
from scipy.spatial.transform import Rotation

from dope_hope.errors import ConfigError
from dope_hope.geometry import intrinsics_matrix, rotation_error_deg
from dope_hope.io.meshes import sample_surface_points
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.icp import IcpSettings, depth_support, icp_refine, points_in_region, silhouette_mask

K = intrinsics_matrix(600.0, 600.0, 319.5, 239.5)
HW = (480, 640)
BOX = np.array([0.065, 0.15, 0.045])  # a bottle-sized box: three distinct extents
R_GT = Rotation.from_euler("xyz", [30, -40, 15], degrees=True).as_matrix()
T_GT = np.array([0.05, -0.03, 0.70])
POINTS, NORMALS = sample_surface_points(trimesh.creation.box(extents=BOX), 2000, oversample=10,
                                        return_normals=True)


def depth_mm(R=R_GT, t=T_GT):
    return np.round(render_box_depth(BOX, R, t, K, HW) * 1000).astype(np.uint16)


def perturbed(deg: float, axis, shift_m):
    dR = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()
    return R_GT @ dR, T_GT + np.asarray(shift_m)


@pytest.mark.parametrize("deg, axis, shift", [
    (12.0, [1, 2, 0], [0.008, -0.006, 0.010]),
    (30.0, [0, 1, 0], [0.0, 0.0, 0.0]),      # a turn about the long axis: what lite nets get wrong
    (0.0, [1, 0, 0], [0.0, 0.0, 0.0]),        # already exact: stays exact
])
def test_icp_recovers_the_pose_that_made_the_depth(deg, axis, shift):
    R0, t0 = perturbed(deg, axis, shift)
    res = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K, depth_scale_m=0.001, image_hw=HW))
    assert res.applied and res.reason == "ok"
    assert rotation_error_deg(res.R, R_GT) < 1.0
    assert np.linalg.norm(res.t - T_GT) < 0.002
    assert res.fit_after >= 0.95 and res.fit_after >= res.fit_before - 0.005  # fit_tie
    assert res.rmse_m < 0.002  # millimetre depth quantisation


def test_icp_ignores_an_occluder_in_front():
    depth = depth_mm().astype(np.float64) * 0.001
    occluder = np.zeros(HW, bool)
    occluder[:, :330] = True  # a wall 15 cm in front of the object's left part
    depth[occluder & (depth > 0)] = T_GT[2] - 0.15
    R0, t0 = perturbed(10.0, [1, 0, 1], [0.006, 0.004, -0.005])
    res = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth, K, image_hw=HW))
    assert res.applied
    assert rotation_error_deg(res.R, R_GT) < 1.5 and np.linalg.norm(res.t - T_GT) < 0.003


@pytest.mark.parametrize("depth, hw, reason", [
    (None, HW, "no depth image"),
    (np.zeros(HW, np.uint16), HW, "no valid pixel"),
    (np.full((240, 320), 700, np.uint16), HW, "depth is 320x240"),
    (np.full(HW, 1500, np.uint16), HW, "ICP lost the object"),  # a far wall, no object
])
def test_bad_or_foreign_depth_never_changes_the_pose(depth, hw, reason):
    R0, t0 = perturbed(5.0, [0, 0, 1], [0.002, 0.0, 0.0])
    res = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth, K, image_hw=hw))
    assert not res.applied and reason in res.reason
    np.testing.assert_array_equal(res.R, R0)
    np.testing.assert_array_equal(res.t, t0)


def test_object_outside_the_depth_is_refused():
    R0, t0 = R_GT, np.array([2.0, 0.0, 0.7])  # projects far right of the image
    res = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K))
    assert not res.applied and "too few depth pixels" in res.reason


def test_a_move_beyond_the_bounds_is_refused():
    R0, t0 = perturbed(0.0, [1, 0, 0], [0.015, 0.0, 0.0])
    res = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K), IcpSettings(max_translation_m=0.005))
    assert not res.applied and "moved the object" in res.reason
    np.testing.assert_array_equal(res.t, t0)
    R0, _ = perturbed(30.0, [0, 1, 0], [0, 0, 0])
    res = icp_refine(R0, T_GT, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K), IcpSettings(max_rotation_deg=10.0))
    assert not res.applied and "turned the object" in res.reason


def test_scene_points_are_the_depth_under_the_dilated_silhouette():
    D = depth_mm() * 0.001
    D[D == 0] = np.nan
    region = silhouette_mask(POINTS @ R_GT.T + T_GT, K, D.shape, dilate=0.0)
    S = points_in_region(region, D, K, max_points=100000)
    assert len(S) > 1000
    # back-projection: every point lies on the box surface (within the mm rounding)
    local = (S - T_GT) @ R_GT
    outside = np.abs(local) - BOX / 2
    assert np.all(outside.max(axis=1) < 0.002) and np.all(np.abs(outside).min(axis=1) < 0.002)
    assert len(points_in_region(region, D, K, max_points=500)) == 500


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="normals"):
        icp_refine(R_GT, T_GT, POINTS, NORMALS[:10], DepthImage.from_raw(depth_mm(), K))
    with pytest.raises(ConfigError, match="thresholds_m"):
        icp_refine(R_GT, T_GT, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K), IcpSettings(thresholds_m=()))


def test_turned_starts_recover_a_quarter_turn_the_plain_start_cannot():
    R0, t0 = perturbed(80.0, [0, 1, 0], [0.004, 0.0, 0.0])  # 80 deg about the long axis
    one = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K), IcpSettings(start_rotations=()))
    assert not one.applied or rotation_error_deg(one.R, R_GT) > 10
    for coarse_points in (750, None):  # the default coarse phase, and every start on every point
        res = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K),
                         IcpSettings(coarse_points=coarse_points))
        assert res.applied and rotation_error_deg(res.R, R_GT) < 1.0 and np.linalg.norm(res.t - T_GT) < 0.002


def test_a_geometric_symmetry_is_left_to_the_keypoints():
    # The box turned 180 deg about its y axis fits the depth exactly as well: the run nearest
    # the input rotation wins, so the refined pose stays on the input's side.
    R0, t0 = perturbed(180.0, [0, 1, 0], [0.0, 0.0, 0.0])
    R0 = R0 @ Rotation.from_euler("x", 8, degrees=True).as_matrix()
    res = icp_refine(R0, t0, POINTS, NORMALS, DepthImage.from_raw(depth_mm(), K))
    assert res.applied
    flipped = R_GT @ Rotation.from_euler("y", 180, degrees=True).as_matrix()
    assert rotation_error_deg(res.R, flipped) < 1.0


def board_depth(board_z: float = 0.38) -> DepthImage:
    """The box of ``depth_mm`` behind a board at ``board_z`` m that hides all but its right
    edge and reaches far up and left; no depth elsewhere (a photo background)."""
    D = depth_mm().astype(np.float64) * 0.001
    v, u = np.nonzero(D)
    board = np.zeros(HW, bool)
    board[: v.max() + 15, : int(u.max() - 0.2 * np.ptp(u))] = True
    D[board] = board_z
    return DepthImage.from_raw(D, K, image_hw=HW)


def test_own_depth_support_counts_confirmed_surface_inside_the_detected_region():
    exact = DepthImage.from_raw(depth_mm(), K)
    region = silhouette_mask(POINTS @ R_GT.T + T_GT, K, HW, 0.15)
    assert depth_support(R_GT, T_GT, POINTS, exact, region, 0.01) > 0.95
    # an occluder says nothing against the pose: the surface it leaves is still confirmed
    hidden = board_depth()
    assert depth_support(R_GT, T_GT, POINTS, hidden, region, 0.01) > 0.95
    # the box at the board's depth: a surface twice as large, mostly off the region or on no depth
    assert depth_support(R_GT, T_GT * 0.38 / T_GT[2], POINTS, hidden, region, 0.01) < 0.3
    # outside the detected region nothing counts
    assert depth_support(R_GT, T_GT, POINTS, exact, np.zeros(HW, bool), 0.01) == 0.0
