"""pose: PnP-RANSAC from (partial) decoded keypoints, and the depth line search (-LS)."""
from __future__ import annotations

import numpy as np
import pytest
from box_depth import box_surface_points, render_box_depth
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.errors import ConfigError
from dope_hope.geometry import (
    cuboid_keypoints,
    intrinsics_matrix,
    project_points,
    rotation_error_deg,
    scale_intrinsics,
)
from dope_hope.inference.pnp import (
    PnpSettings,
    PoseEstimate,
    least_score_divisor,
    min_inliers,
    score_in_view,
    solve_pnp,
)
from dope_hope.maps.decode import decode_maps
from dope_hope.maps.targets import make_targets
from dope_hope.refine.depth import HOPE_REALSENSE_DEPTH_CALIBRATION, DepthImage
from dope_hope.refine.line_search import (
    LineSearchSettings,
    auto_splat_px,
    depth_line_search,
    visible_points,
)
from dope_hope.synth.depth_noise import add_realsense_noise

K640 = intrinsics_matrix(615.0, 615.0, 319.5, 239.5)
K400 = scale_intrinsics(K640, 400 / 640, 300 / 480)  # the network's 400x300 input
HW400 = (300, 400)
CUBOID = cuboid_keypoints(get_object("Popcorn").size_array)  # 12.7 x 8.5 x 3.8 cm


def _poses(seed: int, n: int = 3):
    rng = np.random.default_rng(seed)
    Rs = Rotation.random(n, random_state=seed).as_matrix()
    xs = np.linspace(-0.16, 0.16, n)
    ts = [np.array([x, rng.uniform(-0.08, 0.08), rng.uniform(0.5, 1.0)]) for x in xs]
    return list(Rs), ts


def _check_all_found(poses: list[PoseEstimate], Rs, ts, rot_deg=1.0, trans_m=0.002):
    assert len(poses) == len(ts)
    matched = set()
    for p in poses:
        j = int(np.argmin([np.linalg.norm(p.t - t) for t in ts]))
        matched.add(j)
        assert rotation_error_deg(p.R, Rs[j]) < rot_deg
        assert np.linalg.norm(p.t - ts[j]) < trans_m
    assert matched == set(range(len(ts)))


@pytest.mark.parametrize("stride", [8, 1])
@pytest.mark.parametrize("seed", [0, 1])
def test_targets_decode_pnp_returns_every_instance(stride, seed):
    Rs, ts = _poses(seed)
    kp = np.stack([project_points(CUBOID, K400, R, t) for R, t in zip(Rs, ts)])
    belief, affinity = make_targets(kp, HW400, stride)
    instances = decode_maps(belief, affinity, stride)
    poses = [solve_pnp(i.keypoints, i.scores, CUBOID, K400) for i in instances]
    assert all(p is not None for p in poses)
    _check_all_found(poses, Rs, ts)
    for p in poses:
        assert p.inliers.all() and p.score == pytest.approx(1.0, abs=1e-3)
        assert p.reprojection_error_px < 0.05


@pytest.mark.parametrize("stride", [8, 1])
def test_three_corners_missing_per_instance_still_gives_every_pose(stride):
    Rs, ts = _poses(2)
    kp = np.stack([project_points(CUBOID, K400, R, t) for R, t in zip(Rs, ts)])
    rng = np.random.default_rng(3)
    for i in range(len(kp)):
        kp[i, rng.choice(8, 3, replace=False)] = np.nan
    belief, affinity = make_targets(kp, HW400, stride)
    instances = decode_maps(belief, affinity, stride)
    assert [int(i.present.sum()) for i in instances] == [6, 6, 6]
    poses = [solve_pnp(i.keypoints, i.scores, CUBOID, K400) for i in instances]
    assert all(p is not None for p in poses)
    _check_all_found(poses, Rs, ts)
    for p in poses:
        assert p.inliers.sum() == 6 and p.score == pytest.approx(6 / 9, abs=1e-3)


def _exact_keypoints(seed=0):
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.array([0.03, -0.02, 0.7])
    return R, t, project_points(CUBOID, K640, R, t)


def test_an_outlying_keypoint_is_rejected_and_lowers_the_score():
    R, t, kp = _exact_keypoints()
    kp[2] += [60.0, -40.0]
    p = solve_pnp(kp, np.full(9, 0.9), CUBOID, K640)
    assert p is not None
    assert p.inliers.tolist() == [True, True, False] + [True] * 6
    assert rotation_error_deg(p.R, R) < 0.01 and np.linalg.norm(p.t - t) < 1e-4
    assert p.score == pytest.approx(0.9 * 8 / 9)
    np.testing.assert_allclose(p.projected, project_points(CUBOID, K640, R, t), atol=1e-3)
    np.testing.assert_array_equal(p.keypoints, kp)


def test_a_cut_off_object_is_scored_by_the_keypoints_inside_the_image():
    """Keypoints beyond the border can have no peak: the in-view score divides by those the pose
    puts inside the image (at least min_points); all nine inside: the nine-keypoint score."""
    R, t, kp = _exact_keypoints()
    whole = solve_pnp(kp, np.full(9, 0.9), CUBOID, K640)
    assert score_in_view(whole, (480, 640)) == pytest.approx(whole.score) == pytest.approx(0.9)
    # the same object, shifted so that some keypoints fall beyond the right border
    shift = 640 - np.sort(kp[:, 0])[-3] + 1.0                   # 3 keypoints left outside
    cut = kp + [shift, 0.0]
    outside = cut[:, 0] > 639.5
    assert outside.sum() == 3
    found = np.where(outside[:, None], np.nan, cut)             # the network finds the other six
    p = solve_pnp(found, np.full(9, 0.9), CUBOID, K640)
    assert p is not None and p.score == pytest.approx(0.9 * 6 / 9)
    assert score_in_view(p, (480, 640)) == pytest.approx(0.9)
    assert score_in_view(p, (480, 640), min_points=7) == pytest.approx(0.9 * 6 / 7)
    # a keypoint inside the image but not found still counts against the pose
    found[np.flatnonzero(~outside)[0]] = np.nan
    q = solve_pnp(found, np.full(9, 0.9), CUBOID, K640)
    assert score_in_view(q, (480, 640)) == pytest.approx(0.9 * 5 / 6)


def test_min_points_is_honoured_down_to_four():
    R, t, kp = _exact_keypoints(1)
    kp[[0, 2, 5, 6, 7]] = np.nan  # 4 left (3 corners + centre)
    assert solve_pnp(kp, None, CUBOID, K640) is None  # default min_points = 5
    p = solve_pnp(kp, None, CUBOID, K640, PnpSettings(min_points=4))
    assert p is not None and rotation_error_deg(p.R, R) < 0.1 and np.linalg.norm(p.t - t) < 1e-3
    with pytest.raises(ConfigError, match="min_points must be >= 4"):
        solve_pnp(kp, None, CUBOID, K640, PnpSettings(min_points=3))
    # Low-confidence keypoints count as missing.
    R, t, kp = _exact_keypoints(2)
    scores = np.array([1, 1, 1, 1, 0, 0, 0, 0, 1.0])
    assert solve_pnp(kp, scores, CUBOID, K640) is not None
    assert solve_pnp(kp, scores, CUBOID, K640, PnpSettings(min_score=0.5, min_points=6)) is None


def test_inconsistent_keypoints_give_no_pose():
    rng = np.random.default_rng(0)
    for _ in range(20):
        kp = np.stack([rng.uniform(0, 640, 9), rng.uniform(0, 480, 9)], axis=1)
        assert solve_pnp(kp, np.ones(9), CUBOID, K640) is None


def test_a_pose_behind_the_camera_is_rejected(monkeypatch):
    """Points behind the camera project too (u = fx x / z + cx); such a pose must not pass."""
    import cv2

    import dope_hope.inference.pnp as pose_mod

    R = Rotation.random(random_state=4).as_matrix()
    t = np.array([0.02, 0.01, -0.7])
    kp = project_points(CUBOID, K640, R, t)
    rvec = cv2.Rodrigues(R)[0]
    monkeypatch.setattr(pose_mod.cv2, "solvePnPRansac",
                        lambda *a, **k: (True, rvec, t.reshape(3, 1), np.arange(9).reshape(-1, 1)))
    monkeypatch.setattr(pose_mod.cv2, "solvePnPRefineLM", lambda o, i, K, d, r, tv, **kw: (r, tv))
    assert solve_pnp(kp, np.ones(9), CUBOID, K640) is None
    t_front = np.array([0.02, 0.01, 0.7])  # the same stubbed solver in front: accepted
    kp = project_points(CUBOID, K640, R, t_front)
    monkeypatch.setattr(pose_mod.cv2, "solvePnPRansac",
                        lambda *a, **k: (True, rvec, t_front.reshape(3, 1), np.arange(9).reshape(-1, 1)))
    assert solve_pnp(kp, np.ones(9), CUBOID, K640) is not None


# ---------------------------------------------------------------------------------------
# Depth line search. Depth is ray-cast analytically (exact, no GL needed).

K320 = intrinsics_matrix(307.5, 307.5, 159.5, 119.5)
HW320 = (240, 320)
BOX = get_object("Cookies").size_array  # 12.3 x 16.7 x 4.0 cm


POINTS = box_surface_points(BOX)


def _ls_pose(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed + 10).as_matrix()
    t = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.06, 0.06), rng.uniform(0.5, 1.0)])
    return R, t


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("factor", [0.9, 1.1])
def test_line_search_pulls_a_translation_off_by_ten_percent_back(seed, factor):
    R, t = _ls_pose(seed)
    depth = render_box_depth(BOX, R, t, K320, HW320)
    res = depth_line_search(R, factor * t, POINTS, DepthImage.from_raw(depth, K320))
    assert res.applied and res.reason == "ok"
    assert np.linalg.norm(res.t - t) < 0.002
    assert res.scale == pytest.approx(1 / factor, abs=0.003)
    assert res.n_valid >= 50 and res.residual_m < 0.001


@pytest.mark.parametrize("seed", range(4))
def test_line_search_with_realsense_noise_is_within_five_mm(seed):
    R, t = _ls_pose(seed)
    depth = render_box_depth(BOX, R, t, K320, HW320)
    noisy = add_realsense_noise(depth, None, K320, np.random.default_rng(seed))
    for factor in (0.9, 1.1):
        res = depth_line_search(R, factor * t, POINTS, DepthImage.from_raw(noisy, K320))
        assert res.applied, res.reason
        assert np.linalg.norm(res.t - t) < 0.005


def test_line_search_survives_partial_occlusion():
    R, t = _ls_pose(1)
    depth = render_box_depth(BOX, R, t, K320, HW320)
    obj = depth > 0
    cols = np.nonzero(obj.any(axis=0))[0]
    cut = cols[0] + int(0.35 * (cols[-1] - cols[0]))  # an occluder over the left third
    occluded = depth.copy()
    occluded[:, :cut][obj[:, :cut]] = t[2] - 0.15
    res = depth_line_search(R, 1.08 * t, POINTS, DepthImage.from_raw(occluded, K320))
    assert res.applied and np.linalg.norm(res.t - t) < 0.003


def test_uint16_depth_scale_and_calibration_factor():
    R, t = _ls_pose(2)
    depth = render_box_depth(BOX, R, t, K320, HW320)
    # Tenth-of-millimetre units.
    d_u16 = np.round(depth / 0.0001).astype(np.uint16)
    res = depth_line_search(R, 1.1 * t, POINTS, DepthImage.from_raw(d_u16, K320, depth_scale_m=0.0001))
    assert res.applied and np.linalg.norm(res.t - t) < 0.002
    # A raw capture whose depth must be multiplied by a known factor (the HOPE authors' D415).
    raw_mm = np.round(depth / HOPE_REALSENSE_DEPTH_CALIBRATION * 1000).astype(np.uint16)
    uncal = depth_line_search(R, 1.1 * t, POINTS, DepthImage.from_raw(raw_mm, K320))
    cal = depth_line_search(R, 1.1 * t, POINTS, DepthImage.from_raw(raw_mm, K320, calibration=HOPE_REALSENSE_DEPTH_CALIBRATION))
    assert cal.applied and np.linalg.norm(cal.t - t) < 0.002
    assert np.linalg.norm(uncal.t - t) > 0.01  # 2 % scale error: ~1.5 cm at 0.75 m


@pytest.mark.parametrize(
    "make_depth,reason",
    [
        (lambda d: None, "no depth"),
        (lambda d: np.zeros_like(d), "no valid pixel"),
        (lambda d: np.full_like(d, np.nan), "no valid pixel"),
        (lambda d: d[::2, ::2], "K implies"),
        (lambda d: np.zeros((5,)), "2-D"),
        (lambda d: np.where(np.random.default_rng(0).random(d.shape) < 0.985, 0.0, d),
         "too few visible points"),
    ],
)
def test_bad_depth_leaves_the_pose_unchanged_with_a_reason(make_depth, reason):
    R, t = _ls_pose(0)
    depth = render_box_depth(BOX, R, t, K320, HW320)
    t_in = 1.1 * t
    res = depth_line_search(R, t_in, POINTS, DepthImage.from_raw(make_depth(depth), K320))
    assert not res.applied and reason in res.reason
    np.testing.assert_array_equal(res.t, t_in)
    assert res.scale == 1.0


def test_other_refusals():
    R, t = _ls_pose(0)
    depth = render_box_depth(BOX, R, t, K320, HW320)
    res = depth_line_search(R, 1.1 * t, POINTS, DepthImage.from_raw(depth, K320, image_hw=(480, 640)))
    assert not res.applied and "the image is 640x480" in res.reason
    # The object is nowhere near where the pose says: optimum far outside the search range.
    far = depth_line_search(R, 0.5 * t, POINTS, DepthImage.from_raw(depth, K320))
    assert not far.applied and ("bound" in far.reason or "residual" in far.reason)
    np.testing.assert_array_equal(far.t, 0.5 * t)
    behind = depth_line_search(R, -t, POINTS, DepthImage.from_raw(depth, K320))
    assert not behind.applied and "behind" in behind.reason
    # min_valid is configurable
    sparse = depth_line_search(R, 1.1 * t, POINTS, DepthImage.from_raw(depth, K320),
                               LineSearchSettings(min_valid=100000))
    assert not sparse.applied and "too few" in sparse.reason


@pytest.mark.parametrize("seed", range(6))
def test_visible_points_are_on_the_visible_surface(seed):
    R, t = _ls_pose(seed)
    Xc = POINTS @ R.T + t
    depth = render_box_depth(BOX, R, t, K320, HW320)
    uv = project_points(Xc, K320)
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    inside = (u >= 0) & (u < 320) & (v >= 0) & (v < 240)
    surface = np.full(len(Xc), np.nan)
    surface[inside] = depth[v[inside], u[inside]]
    surface[surface == 0] = np.nan  # silhouette-edge points rounding onto the background
    on_surface = np.abs(surface - Xc[:, 2]) < 0.004  # truly visible (within a pixel's slope)
    behind = Xc[:, 2] - surface > 0.01  # hidden by more than 1 cm

    splat = auto_splat_px(POINTS, K320, t[2])
    vis = visible_points(Xc, K320, HW320, splat)
    assert (vis & behind).sum() <= 0.05 * vis.sum()  # few harmful outliers
    assert (vis & on_surface).sum() >= 0.5 * on_surface.sum()  # most of the surface kept
    # With normals the back faces are culled: no harmful point at all.
    half = BOX / 2
    normals = np.where(np.isclose(np.abs(POINTS), half), np.sign(POINTS), 0.0) @ R.T
    vis_n = visible_points(Xc, K320, HW320, splat, normals_c=normals)
    assert (vis_n & behind).sum() == 0
    assert (vis_n & on_surface).sum() >= 0.7 * on_surface.sum()


def test_line_search_bracket_with_scales_without_depth_warns_nothing():
    """Scales whose points leave the valid depth cost inf; the bounded search inside a bracket
    that reaches them must neither warn (numpy's inf - inf) nor return such a scale."""
    import warnings

    from dope_hope.refine.line_search import _best_scale

    class Cost:
        def __call__(self, s: float) -> float:
            return np.inf if s > 1.02 else (s - 1.0) ** 2

        def costs(self, scales: np.ndarray) -> np.ndarray:
            return np.array([self(s) for s in scales])

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scale, at_bound = _best_scale(Cost(), (0.5, 1.5), 11)
    assert scale == pytest.approx(1.0, abs=1e-4) and not at_bound


@pytest.mark.parametrize("cost", ["median", "huber"])
def test_the_grid_costs_in_one_pass_equal_each_scale_on_its_own(cost):
    """The line search's grid (all scales in one array pass) costs what each scale's own
    residuals give: median |r|, or the mean Huber loss; inf where too few points have depth."""
    from dope_hope.refine.line_search import _ScaleCost

    R, t = _ls_pose(2)
    depth = render_box_depth(BOX, R, t, K320, HW320)
    depth[:, :150] = 0.0  # no depth on the left: some scales' points fall there
    D = DepthImage.from_raw(depth, K320).metres
    scales = np.linspace(0.4, 2.5, 41)
    counts = [_ScaleCost(POINTS @ R.T, t, K320, D, 1, cost, 0.01).residuals(s).size for s in scales]
    min_valid = int(np.median(counts))  # about half the scales have too few points with depth
    f = _ScaleCost(POINTS @ R.T, t, K320, D, min_valid=min_valid, cost=cost, huber_delta_m=0.01)
    expected = []
    for s in scales:
        a = np.abs(f.residuals(s))
        d = 0.01
        expected.append(np.inf if a.size < min_valid else np.median(a) if cost == "median"
                        else np.mean(np.where(a <= d, 0.5 * a * a, d * (a - 0.5 * d))))
    got = f.costs(scales)
    assert np.isinf(expected).any() and np.isfinite(expected).sum() > 10
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=0)
    assert f(scales[7]) == pytest.approx(expected[7], rel=1e-12)


def test_the_inliers_a_pose_needs_bound_the_divisor_of_its_score():
    settings = PnpSettings()
    assert [min_inliers(n, settings) for n in (0, 5, 6, 7, 8, 9)] == [5, 5, 5, 6, 6, 7]
    np.testing.assert_array_equal(min_inliers(np.array([4, 8, 9]), settings), [5, 6, 7])
    assert min_inliers(9, PnpSettings(min_points=4, min_inlier_ratio=0.5)) == 5
    assert least_score_divisor(settings) == 5 and least_score_divisor(settings, 9) == 7
    assert least_score_divisor(PnpSettings(score_in_view=False), 9) is None
    # Nine keypoints, seven inliers: the in-view score divides by at least 7 (no fewer
    # inliers are accepted), whatever the image.
    R, t, kp = _exact_keypoints(3)
    kp[[1, 6]] += [[40.0, -30.0], [-35.0, 25.0]]
    scores = np.linspace(0.2, 1.0, 9)
    est = solve_pnp(kp, scores, CUBOID, K640)
    assert est is not None and est.inliers.sum() == 7
    for hw in ((480, 640), (2, 2)):
        assert score_in_view(est, hw) <= np.sort(np.clip(scores, 0, 1))[::-1][:7].mean() + 1e-12
