"""DopePredictor: images of any layout -> mesh-frame poses, for mesh and legacy (official) models.

The whole chain (resize, pad, K scaling, decode, PnP, legacy frame conversion, keypoints back
to the original image, depth line search) runs against ``TargetsBackend``, which renders
perfect maps of known poses, so detections must equal the poses. Real networks (a tiny lite
checkpoint, a fake official DOPE-DR-50 import) check the torch backend and the metadata.
"""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
from _targets_backend import TargetsBackend
from box_depth import render_box_depth
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.config import load_config
from dope_hope.errors import CameraError, ConfigError, InputFileError, ModelFileError
from dope_hope.geometry import (
    cuboid_keypoints,
    intrinsics_matrix,
    mesh_rotation_to_legacy,
    project_points,
    rotation_error_deg,
    scale_intrinsics,
)
from dope_hope.inference.backends import MapBackend, TorchBackend
from dope_hope.inference.predictor import NO_ICP_SURFACE, DopePredictor, predict_many
from dope_hope.model import build_model
from dope_hope.model.checkpoint import (
    import_official,
    make_object_info,
    save_checkpoint,
)
from dope_hope.preprocess import DEFAULT_HEIGHT, to_rgb8
from dope_hope.refine.depth import DepthImage

torch.set_num_threads(1)

K640 = intrinsics_matrix(600.0, 600.0, 319.5, 239.5)
OBJ = get_object("Cookies")  # a box: the cuboid surface is the object's surface
POSES = [
    (Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix(), np.array([0.08, -0.02, 0.60])),
    (Rotation.from_euler("xyz", [-15, -120, 5], degrees=True).as_matrix(), np.array([-0.14, 0.04, 0.75])),
]
LITE = {"model": {"arch": "lite", "head": 50, "stages": 2,
                  "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "input": {"size": [64, 64]}}


def white(hw):
    return np.full((*hw, 3), 255, np.uint8)


def backend(poses=POSES, K=K640, hw=(480, 640), **kw):
    return TargetsBackend(OBJ.name, OBJ.size_array, poses, K, hw, **kw)


def match(dets, poses, rot_deg=0.05, t_m=5e-4):
    """Each GT pose has exactly one detection within the tolerances."""
    assert len(dets) == len(poses)
    for R, t in poses:
        errs = [(rotation_error_deg(d.R, R), np.linalg.norm(d.t - t)) for d in dets]
        assert sum(r < rot_deg and e < t_m for r, e in errs) == 1, errs


def test_mesh_frame_chain_returns_the_rendered_poses():
    p = DopePredictor(backend(), height=400)
    dets = p.predict(white((480, 640)), K640)
    match(dets, POSES)
    for d in dets:
        R, t = min(POSES, key=lambda pose: np.linalg.norm(pose[1] - d.t))
        gt_uv = project_points(cuboid_keypoints(OBJ.size_array), K640, R, t)
        # keypoints are reported in ORIGINAL-image pixels and the current order
        assert np.abs(d.keypoints_2d - gt_uv).max() < 0.01
        assert np.abs(d.projected_2d - gt_uv).max() < 0.01
        assert d.inliers.all() and 0.9 < d.score <= 1.0
        assert d.reprojection_error_px < 0.01
        assert d.class_name == "Cookies" and not d.ls_applied and d.ls_reason == "no depth image"
        q = d.quaternion_xyzw
        assert q[3] >= 0 and rotation_error_deg(Rotation.from_quat(q).as_matrix(), d.R) < 1e-6
    assert dets[0].score >= dets[1].score


def test_legacy_frame_model_returns_mesh_frame_poses():
    legacy_poses = [(mesh_rotation_to_legacy(R), t) for R, t in POSES]
    # The legacy frame is a real rotation away: skipping the conversion would be caught.
    assert rotation_error_deg(legacy_poses[0][0], POSES[0][0]) > 90
    p = DopePredictor(backend(poses=legacy_poses, frame="legacy"), height=400)
    assert p.legacy
    dets = p.predict(white((480, 640)), K640)
    match(dets, POSES)
    for d in dets:
        R, t = min(POSES, key=lambda pose: np.linalg.norm(pose[1] - d.t))
        gt_uv = project_points(cuboid_keypoints(OBJ.size_array), K640, R, t)
        assert np.abs(d.keypoints_2d - gt_uv).max() < 0.01  # reordered into the current order
        np.testing.assert_allclose(d.cuboid_size_m, OBJ.size_array)


def test_fake_official_checkpoint_metadata_and_frame_conversion(tmp_path):
    official = build_model(load_config("dope_dr_50")).state_dict()
    pth = tmp_path / "Cookies.pth"
    torch.save({f"module.{k}": v for k, v in official.items()}, pth)
    del official
    import_official(pth, "Cookies", out_path=tmp_path / "cookies_official.pt")
    p = DopePredictor(tmp_path / "cookies_official.pt")
    real = p.backend
    assert isinstance(real, TorchBackend) and isinstance(real, MapBackend)
    assert (real.frame, real.keypoint_order, real.stride) == ("legacy", "dope-legacy", 8)
    assert real.mean == pytest.approx((0.485, 0.456, 0.406))
    assert real.std == pytest.approx((0.229, 0.224, 0.225))
    np.testing.assert_allclose(real.size_m, OBJ.size_array)
    # official weights run at DOPE's height 400, whatever the recorded 400x400 input size
    assert p.working_size((480, 640)) == ((400, 533), (400, 536))
    p.options = replace(p.options, height=64)  # the real network's last stage, on a small input (CPU time)
    belief, affinity, net_in = p.infer_maps(white((64, 80)) // 2)
    assert belief.shape == (9, 8, 10) and affinity.shape == (16, 8, 10)
    assert net_in.batch.shape == (1, 3, 64, 80)

    # Same metadata, maps of known legacy-frame poses: the output must be mesh-frame poses.
    mocked = backend(poses=[(mesh_rotation_to_legacy(R), t) for R, t in POSES], frame="legacy")
    mocked.mean, mocked.std, mocked.input_hw = real.mean, real.std, real.input_hw
    mocked.size_m = real.size_m
    dets = DopePredictor(mocked).predict(white((480, 640)), K640)
    match(dets, POSES)


def test_resize_keeps_K_consistent():
    """640x480 with K and 1280x960 with the scaled K: the same scene, the same poses."""
    small = DopePredictor(backend(), height=400).predict(white((480, 640)), K640)
    K_big = scale_intrinsics(K640, 2.0, 2.0)
    big_backend = backend(K=K_big, hw=(960, 1280))
    big = DopePredictor(big_backend, height=400).predict(white((960, 1280)), K_big)
    assert big_backend.calls[-1] == {"padded": (400, 536), "resized": (400, 533)}
    assert len(small) == len(big) == 2
    for a, b in zip(small, big):
        assert rotation_error_deg(a.R, b.R) < 0.05
        assert np.linalg.norm(a.t - b.t) < 2e-4
        np.testing.assert_allclose(b.keypoints_2d, 2 * (a.keypoints_2d + 0.5) - 0.5, atol=0.05)


@pytest.mark.parametrize("hw,height", [((333, 500), 400), ((481, 641), 203), ((480, 640), 120)])
def test_odd_sizes_are_padded_and_still_exact(hw, height):
    K = intrinsics_matrix(560.0, 570.0, hw[1] / 2 + 3.2, hw[0] / 2 - 4.1)
    poses = [(POSES[0][0], np.array([0.03, -0.01, 0.9 * 640 / hw[1] + 0.3]))]
    b = backend(poses=poses, K=K, hw=hw)
    dets = DopePredictor(b, height=height).predict(white(hw), K)
    Hp, Wp = b.calls[-1]["padded"]
    assert Hp % 8 == 0 and Wp % 8 == 0 and b.calls[-1]["resized"][0] == height
    match(dets, poses)


def test_working_size_rules():
    lite_like = backend(input_hw=(200, 200))
    p = DopePredictor(lite_like)  # height None: fit inside the training input, as training did
    assert p.working_size((480, 640)) == ((150, 200), (152, 200))
    assert DopePredictor(lite_like, height=240).working_size((480, 640)) == ((240, 320), (240, 320))
    assert DopePredictor(backend()).working_size((480, 640))[0] == (DEFAULT_HEIGHT, 533)
    fixed = backend()
    fixed.fixed_input_hw = (96, 96)
    assert DopePredictor(fixed).working_size((480, 640)) == ((72, 96), (96, 96))
    with pytest.raises(ConfigError, match="height"):
        DopePredictor(backend(), height=5)


def test_image_layouts_and_warnings():
    rgb = np.random.default_rng(0).integers(0, 256, (6, 7, 3), dtype=np.uint8)
    gray = rgb[:, :, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # lossless conversions stay silent
        np.testing.assert_array_equal(to_rgb8(gray), np.repeat(gray[:, :, None], 3, 2))
        np.testing.assert_array_equal(to_rgb8(gray[:, :, None]), to_rgb8(gray))
        opaque = np.dstack([rgb, np.full(gray.shape, 255, np.uint8)])
        np.testing.assert_array_equal(to_rgb8(opaque), rgb)
        np.testing.assert_array_equal(to_rgb8(rgb / 255.0), rgb)
    rgba = np.dstack([rgb, np.full(gray.shape, 255, np.uint8)])
    rgba[0, 0, 3] = 0
    with pytest.warns(UserWarning, match="alpha channel dropped"):
        np.testing.assert_array_equal(to_rgb8(rgba), rgb)
    with pytest.warns(UserWarning, match="16-bit"):
        np.testing.assert_array_equal(to_rgb8(rgb.astype(np.uint16) * 257), rgb)
    for bad in (np.zeros((4, 4, 5), np.uint8), np.zeros((4, 4, 3), np.int32), np.full((4, 4), 2.0)):
        with pytest.raises(ValueError):
            to_rgb8(bad)


def test_every_layout_gives_the_same_detections():
    p = DopePredictor(backend(), height=400)
    ref = p.predict(white((480, 640)), K640)
    gray = np.full((480, 640), 255, np.uint8)
    rgba = np.dstack([white((480, 640)), np.full((480, 640), 255, np.uint8)])
    rgba[:10, :10, 3] = 0
    with pytest.warns(UserWarning, match="16-bit"):
        d16 = p.predict(np.full((480, 640, 3), 65535, np.uint16), K640)
    with pytest.warns(UserWarning, match="alpha"):
        d_rgba = p.predict(rgba, K640)
    for dets in (p.predict(gray, K640), d16, d_rgba):
        assert len(dets) == len(ref)
        for a, b in zip(ref, dets):
            np.testing.assert_allclose(a.t, b.t)
            np.testing.assert_allclose(a.R, b.R)


@pytest.mark.parametrize("frame", ["mesh", "legacy"])
def test_mesh_box_and_off_centre_origin(tmp_path, frame):
    """With mesh=, the cuboid is the mesh's box (size AND centre) and t is the mesh origin's."""
    import trimesh

    center = np.array([0.01, -0.02, 0.005])
    mesh = trimesh.creation.box(extents=OBJ.size_array)
    mesh.apply_translation(center)
    if frame == "legacy":
        b = backend(poses=[(mesh_rotation_to_legacy(R), t) for R, t in POSES], frame="legacy",
                    center=center)
    else:
        b = backend(center=center)
    p = DopePredictor(b, height=400, mesh=mesh)
    np.testing.assert_allclose(p.cuboid_center_m, center, atol=1e-12)
    match(p.predict(white((480, 640)), K640), POSES)
    # Ignoring the offset would move t by R @ center (about 2 cm): the test would notice.
    assert min(np.linalg.norm(R @ center) for R, _ in POSES) > 0.015
    mesh_cm = mesh.copy()
    mesh_cm.apply_scale(100.0)  # a mesh in the wrong units is refused, not used
    path = tmp_path / "cookies_cm_as_m.obj"
    mesh_cm.export(path)
    with pytest.raises(InputFileError, match="too large for an object .*likely in cm: give its unit as cm"):
        DopePredictor(backend(), mesh=path, mesh_units="m")
    mesh_mm = mesh.copy()
    mesh_mm.apply_scale(1000.0)  # millimetres read as centimetres: 1.7 m, a plausible size, yet not the model's
    mesh_mm.export(path)
    with pytest.raises(ConfigError, match=r"does not match the model's cuboid .*likely in mm, not cm"):
        DopePredictor(backend(), mesh=path, mesh_units="cm")
    with pytest.raises(ConfigError, match="wrong object or wrong mesh units"):
        DopePredictor(backend(), mesh=trimesh.creation.box(extents=OBJ.size_array * [1, 2, 1]))


def test_depth_line_search_fixes_the_distance():
    R, t = POSES[0]
    depth_m = render_box_depth(OBJ.size_array, R, t, K640, (480, 640))
    depth_mm = np.round(depth_m * 1000).astype(np.uint16)
    # The "network" sees the object 8 % too far (a monocular scale error): PnP says 1.08 t.
    p = DopePredictor(backend(poses=[(R, 1.08 * t)]), height=400)
    (mono,) = p.predict(white((480, 640)), K640)
    assert abs(np.linalg.norm(mono.t) / np.linalg.norm(t) - 1.08) < 0.003
    (ls,) = p.predict(white((480, 640)), K640, depth=depth_mm, depth_scale_m=0.001)
    assert ls.ls_applied and ls.ls_reason == "ok"
    assert ls.ls_scale == pytest.approx(1 / 1.08, abs=0.003)
    assert np.linalg.norm(ls.t - t) < 0.003
    np.testing.assert_allclose(ls.R, mono.R)
    # projected_2d follows the refined pose
    np.testing.assert_allclose(ls.projected_2d, project_points(cuboid_keypoints(OBJ.size_array), K640, R, ls.t))
    (bad,) = p.predict(white((480, 640)), K640, depth=depth_mm[::2, ::2])
    assert not bad.ls_applied and "depth is 320x240" in bad.ls_reason
    np.testing.assert_allclose(bad.t, mono.t)


def test_icp_corrects_the_rotation_the_keypoints_got_wrong():
    R, t = POSES[0]
    depth_mm = np.round(render_box_depth(OBJ.size_array, R, t, K640, (480, 640)) * 1000).astype(np.uint16)
    # The "network" turns the box 25 deg about its own long axis and puts it 6 % too far.
    R_net = R @ Rotation.from_euler("y", 25, degrees=True).as_matrix()
    p = DopePredictor(backend(poses=[(R_net, 1.06 * t)]), height=400, icp=True)
    (ls_only,) = DopePredictor(backend(poses=[(R_net, 1.06 * t)]), height=400).predict(
        white((480, 640)), K640, depth=depth_mm)
    assert ls_only.ls_applied and rotation_error_deg(ls_only.R, R) > 20
    assert "icp_applied" not in ls_only.to_json("a.png")
    (det,) = p.predict(white((480, 640)), K640, depth=depth_mm)
    assert det.ls_applied and det.icp_applied and det.icp_reason == "ok" and det.icp_fit > 0.9
    assert rotation_error_deg(det.R, R) < 1.0 and np.linalg.norm(det.t - t) < 0.003
    np.testing.assert_allclose(det.projected_2d, project_points(cuboid_keypoints(OBJ.size_array), K640, det.R, det.t))
    rec = det.to_json("a.png")
    assert rec["icp_applied"] is True and rec["icp_reason"] == "ok"
    (mono,) = p.predict(white((480, 640)), K640)
    assert not mono.icp_applied and mono.icp_reason == "no depth image"
    # refine_icp: the same step on a -LS detection, as a copy (the -LS pose is kept)
    ls_R, ls_t = ls_only.R.copy(), ls_only.t.copy()
    copy = p.refine_icp(ls_only, DepthImage.from_raw(depth_mm, K640))
    np.testing.assert_allclose(copy.R, det.R, atol=1e-9)
    np.testing.assert_allclose(copy.t, det.t, atol=1e-9)
    np.testing.assert_allclose(copy.projected_2d, det.projected_2d, atol=1e-6)
    assert copy.icp_applied and not ls_only.icp_applied
    np.testing.assert_array_equal(ls_only.R, ls_R)
    np.testing.assert_array_equal(ls_only.t, ls_t)


def test_icp_without_a_mesh_is_refused_for_non_boxes():
    b = TargetsBackend("Ketchup", get_object("Ketchup").size_array, POSES[:1], K640, (480, 640))
    with pytest.raises(ConfigError, match="ICP for Ketchup \\(bottle\\) needs its mesh"):
        DopePredictor(b, icp=True)
    DopePredictor(b)  # -LS alone keeps the cuboid fallback
    DopePredictor(backend(), icp=True)  # Cookies is a box: its cuboid is its surface


def test_icp_auto_runs_where_there_is_depth_and_a_surface():
    """icp="auto" (the accurate preset's): a box's detection with depth gets ICP as with
    icp=True; without depth, -LS and ICP neither; a bottle without its mesh has no surface to
    fit: -LS alone, and no refusal at construction."""
    R, t = POSES[0]
    depth_mm = np.round(render_box_depth(OBJ.size_array, R, t, K640, (480, 640)) * 1000).astype(np.uint16)
    R_net = R @ Rotation.from_euler("y", 25, degrees=True).as_matrix()
    (on,) = DopePredictor(backend(poses=[(R_net, 1.06 * t)]), height=400, icp=True).predict(
        white((480, 640)), K640, depth=depth_mm)
    auto = DopePredictor(backend(poses=[(R_net, 1.06 * t)]), height=400, icp="auto")
    (det,) = auto.predict(white((480, 640)), K640, depth=depth_mm)
    assert det.icp_applied and rotation_error_deg(det.R, R) < 1.0
    np.testing.assert_allclose(det.R, on.R, atol=1e-12)
    (mono,) = auto.predict(white((480, 640)), K640)
    assert not mono.icp_applied and mono.icp_reason == "no depth image"
    b = TargetsBackend("Ketchup", get_object("Ketchup").size_array, POSES[:1], K640, (480, 640))
    bottle = DopePredictor(b, icp="auto")
    assert bottle.icp_objects == set() and auto.icp_objects == {OBJ.name}
    (ls,) = bottle.predict(white((480, 640)), K640, depth=depth_mm)
    assert ls.icp_reason == NO_ICP_SURFACE and not bottle.icp_runs(bottle.objects[0], DepthImage.from_raw(depth_mm, K640))


def test_line_search_widens_where_its_optimum_lies_beyond_its_range():
    R, t = POSES[0]
    depth_mm = np.round(render_box_depth(OBJ.size_array, R, t, K640, (480, 640)) * 1000).astype(np.uint16)
    far = (R, 1.5 * t)  # beyond the line search's 0.8-1.25 range
    narrow = DopePredictor(backend(poses=[far]), height=400, line_search={"wide_search": None})
    (refused,) = narrow.predict(white((480, 640)), K640, depth=depth_mm)
    assert not refused.ls_applied and "search bound" in refused.ls_reason
    (ls,) = DopePredictor(backend(poses=[far]), height=400).predict(white((480, 640)), K640, depth=depth_mm)
    assert ls.ls_applied and ls.ls_reason == "ok (search 0.5-2)" and abs(ls.ls_scale - 1 / 1.5) < 0.01
    assert np.linalg.norm(ls.t - t) < 0.005
    (det,) = DopePredictor(backend(poses=[far]), height=400, icp=True).predict(
        white((480, 640)), K640, depth=depth_mm)
    assert det.ls_applied and det.icp_applied
    assert np.linalg.norm(det.t - t) < 0.003 and rotation_error_deg(det.R, R) < 1.0


def test_icp_stage_keeps_a_hidden_box_off_the_board_in_front():
    """The keypoints are right, but a board 28 cm in front hides all of the box except its right
    edge (no depth elsewhere, as behind the demo's photo backgrounds). -LS refuses (optimum at
    its bound); its wider search finds the board (s ~ 0.55) and ICP would fit the box to it,
    twice as large as the keypoints show it: the object's own depth support
    (dope_hope.refine.icp, step 6) keeps the box where the keypoints put it, with and without ICP."""
    R, t = POSES[0]
    box = render_box_depth(OBJ.size_array, R, t, K640, (480, 640))
    v, u = np.nonzero(box)
    depth = box.copy()
    depth[: v.max() + 15, : int(u.max() - 0.2 * np.ptp(u))] = 0.32
    assert 0.1 < ((depth == box) & (box > 0)).sum() / (box > 0).sum() < 0.3  # the box ~20 % visible
    depth_mm = np.round(depth * 1000).astype(np.uint16)
    for icp in (False, True):
        (det,) = DopePredictor(backend(poses=[(R, t)]), height=400, icp=icp).predict(
            white((480, 640)), K640, depth=depth_mm)
        assert not det.ls_applied and "search bound" in det.ls_reason and "own depth support" in det.ls_reason
        assert np.linalg.norm(det.t - t) < 0.003 and rotation_error_deg(det.R, R) < 1.0

def test_predict_many_runs_each_model_once_and_merges():
    a = backend(poses=POSES[:1])
    b = TargetsBackend("Ketchup", get_object("Ketchup").size_array,
                       [(POSES[1][0], POSES[1][1])], K640, (480, 640))
    dets = predict_many([DopePredictor(a, height=400), DopePredictor(b, height=400)],
                        white((480, 640)), K640)
    assert sorted(d.class_name for d in dets) == ["Cookies", "Ketchup"]
    assert [d.score for d in dets] == sorted((d.score for d in dets), reverse=True)
    assert len(a.calls) == len(b.calls) == 1


def test_bad_intrinsics_are_a_camera_error():
    p = DopePredictor(backend(), height=400)
    for K in (np.eye(2), intrinsics_matrix(-600, 600, 320, 240), np.full((3, 3), np.nan)):
        with pytest.raises(CameraError):
            p.predict(white((48, 64)), K)


def test_tiny_torch_checkpoint_runs_end_to_end(tmp_path):
    path = tmp_path / "lite.pt"
    save_checkpoint(path, build_model(LITE), LITE, make_object_info("Ketchup"))
    p = DopePredictor(path, backend="auto")
    assert isinstance(p.backend, TorchBackend) and p.backend.input_hw == (64, 64)
    img = np.random.default_rng(1).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    belief, affinity, net_in = p.infer_maps(img)
    assert net_in.resized_hw == (48, 64) and belief.shape == (9, 6, 8) and affinity.shape == (16, 6, 8)
    # the maps are the network's LAST stage
    with torch.inference_mode():
        last = p.backend.model(torch.from_numpy(net_in.batch))[-1]
    np.testing.assert_allclose(belief, last[0][0].numpy(), atol=1e-6)
    dets = p.predict(img, scale_intrinsics(K640, 0.2, 0.2))
    assert all(d.class_name == "Ketchup" and np.isfinite(d.t).all() for d in dets)


def test_bad_weights_files(tmp_path):
    with pytest.raises(ModelFileError, match="not found"):
        DopePredictor(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(ModelFileError, match="junk.pt"):
        DopePredictor(junk)
    # a checkpoint whose state dict belongs to another network
    other = tmp_path / "other.pt"
    save_checkpoint(other, build_model(LITE), LITE, make_object_info("Ketchup"))
    ckpt = torch.load(other, weights_only=True)
    ckpt["model"] = torch.nn.Linear(3, 2).state_dict()
    torch.save(ckpt, other)
    with pytest.raises(ModelFileError, match="another architecture"):
        DopePredictor(other)
    onnx_named = tmp_path / "model.onnx"
    onnx_named.write_bytes(b"not really")
    with pytest.raises(ModelFileError, match="ONNX"):
        DopePredictor(onnx_named, backend="torch")
    with pytest.raises(ConfigError, match="backend"):
        DopePredictor(junk, backend="tensorrt")


def test_auto_backend_runs_exported_onnx_like_torch(tmp_path):
    from dope_hope.export.to_onnx import ExportSettings, export_model
    from dope_hope.inference.onnx_backend import OnnxBackend
    from dope_hope.model.checkpoint import load_model

    path = tmp_path / "lite.pt"
    save_checkpoint(path, build_model(LITE), LITE, make_object_info("Ketchup"))
    model, ckpt = load_model(path)
    export_model(model, ckpt, tmp_path / "lite.onnx", ExportSettings(dynamic=True))
    torch_p = DopePredictor(path)
    onnx_p = DopePredictor(tmp_path / "lite.onnx", threads=1)  # auto: onnxruntime for .onnx
    assert isinstance(onnx_p.backend, OnnxBackend)
    assert onnx_p.backend.providers == ["CPUExecutionProvider"]
    img = np.random.default_rng(2).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    assert onnx_p.working_size(img.shape[:2]) == torch_p.working_size(img.shape[:2])
    b_t, a_t, _ = torch_p.infer_maps(img)
    b_o, a_o, _ = onnx_p.infer_maps(img)
    for onnx_maps, torch_maps in ((b_o, b_t), (a_o, a_t)):
        scale = np.abs(torch_maps).max()
        assert scale > 0 and np.abs(onnx_maps - torch_maps).max() < 1e-3 * scale


def test_partly_outside_object_and_strict_json(tmp_path):
    """Corners off the image are missing (NaN -> null in JSON); the pose still comes out, and its
    score counts only the keypoints the pose puts inside the image."""
    import json

    from dope_hope.io.predictions import read_predictions, write_predictions_jsonl

    R = POSES[0][0]
    t = np.array([0.25, 0.0, 0.6])  # the box crosses the right border
    uv = project_points(cuboid_keypoints(OBJ.size_array), K640, R, t)
    outside = uv[:, 0] > 639.5
    assert outside.sum() == 2 and uv[outside, 0].min() > 644  # beyond the padded map too
    (det,) = DopePredictor(backend(poses=[(R, t)]), height=400).predict(white((480, 640)), K640)
    assert np.isnan(det.keypoints_2d[outside]).all() and not det.inliers[outside].any()
    assert rotation_error_deg(det.R, R) < 0.05 and np.linalg.norm(det.t - t) < 5e-4
    # scored by the keypoints inside the image: all found; by all nine (pnp.score_in_view false): 7/9
    assert det.score == pytest.approx(1.0, abs=0.01)
    (nine,) = DopePredictor(backend(poses=[(R, t)]), height=400, pnp={"score_in_view": False}).predict(
        white((480, 640)), K640)
    assert nine.score == pytest.approx((~outside).sum() / 9, abs=0.01)
    rec = det.to_json("000001.png", time=0.5)
    json.dumps(rec, allow_nan=False)  # strict JSON
    assert all(rec["keypoints_2d"][k] == [None, None] for k in np.flatnonzero(outside))
    write_predictions_jsonl(tmp_path / "p.jsonl", [rec])
    (pred,), _ = read_predictions(tmp_path / "p.jsonl")
    assert pred.image == "000001.png" and pred.class_name == "Cookies" and pred.time == 0.5
    np.testing.assert_allclose(pred.R, det.R, atol=1e-9)
    np.testing.assert_allclose(pred.t, det.t)
    assert "image" not in det.to_json()


class _SpuriousCentroidBackend(TargetsBackend):
    """Perfect maps of one instance plus a spurious centroid between the true centroid and
    corner 0, and a weaker stray corner-0 peak whose field points at the true centroid."""

    def run(self, batch):
        from dope_hope.maps.targets import make_targets

        belief, affinity = super().run(batch)
        Hp, Wp = batch.shape[2:]
        sx = sy = self.calls[-1]["resized"][1] / self.image_hw[1]
        kp = self.network_keypoints(sx, sy)[0]
        c1, p1 = kp[8], kp[0]
        d = p1 - c1
        stray = np.full((1, 9, 2), np.nan)
        stray[0, 0], stray[0, 8] = c1 + 0.5 * np.array([-d[1], d[0]]), c1
        spurious = np.full((1, 9, 2), np.nan)
        spurious[0, 8] = c1 + 0.6 * d
        bs, as_ = make_targets(stray, (Hp, Wp), self.stride, self.sigma, self.radius)
        bc, _ = make_targets(spurious, (Hp, Wp), self.stride, self.sigma, self.radius)
        belief = belief.copy()
        belief[0, 0] = np.maximum(belief[0, 0], 0.6 * bs[0])
        belief[0, 8] = np.maximum(belief[0, 8], bc[8])
        affinity = affinity.copy()
        affinity[0, :2] += as_[:2]
        return belief, affinity


def _spurious(poses):
    return _SpuriousCentroidBackend(OBJ.name, OBJ.size_array, poses, K640, (480, 640), stride=4, sigma=1.0,
                                    radius=1.0)


def test_a_centroid_robbed_of_a_corner_by_a_spurious_one_still_gets_its_pose():
    """One-to-one grouping gives the true corner 0 to a spurious centroid; the candidate
    search lets both centroids use it, and the two explanations of one box give one detection."""
    poses = POSES[:1]
    strict = {"min_inlier_ratio": 1.0}  # one wrong corner out of nine fails the pose
    dets = DopePredictor(_spurious(poses), pnp=strict).predict(white((480, 640)), K640)
    match(dets, poses)
    # DOPE's grouping alone gives no pose.
    assert DopePredictor(_spurious(poses), pnp=strict, pose_search="groups").predict(
        white((480, 640)), K640) == []


class _ConfusedCornersBackend(TargetsBackend):
    """Perfect maps, except that belief maps 0, 1 and 2 also carry a stronger peak on the
    box's corners 2, 3 and 0, with fields pointing at the centroid (the lite nets' commonest
    error: which corner is which)."""

    def run(self, batch):
        from dope_hope.maps.targets import make_targets

        belief, affinity = super().run(batch)
        Hp, Wp = batch.shape[2:]
        s = self.calls[-1]["resized"][1] / self.image_hw[1]
        kp = self.network_keypoints(s, s)[0]
        wrong = np.full((1, 9, 2), np.nan)
        wrong[0, [0, 1, 2]], wrong[0, 8] = kp[[2, 3, 0]], kp[8]
        bw, aw = make_targets(wrong, (Hp, Wp), self.stride, self.sigma, self.radius)
        belief, affinity = belief.copy(), affinity.copy()
        belief[0, :3] = np.maximum(0.7 * belief[0, :3], bw[:3])
        ring = np.linalg.norm(aw[:6].reshape(3, 2, Hp // self.stride, Wp // self.stride), axis=1) > 0
        affinity[0, :6] = np.where(np.repeat(ring, 2, axis=0), aw[:6], affinity[0, :6])
        return belief, affinity


def test_a_second_peak_on_the_wrong_corner_does_not_cost_the_detection():
    poses = POSES[:1]
    backend_ = _ConfusedCornersBackend(OBJ.name, OBJ.size_array, poses, K640, (480, 640), stride=4,
                                       sigma=1.0, radius=1.0)
    dets = DopePredictor(backend_).predict(white((480, 640)), K640)
    match(dets, poses)
    assert dets[0].inliers.all()
    # Corner maps 0-2 peak hardest on the wrong corners: one corner per type fails.
    assert DopePredictor(backend_, pose_search="groups").predict(white((480, 640)), K640) == []
    with pytest.raises(ConfigError, match="pose_search"):
        DopePredictor(backend_, pose_search="ransac")


class _FadedBackend(TargetsBackend):
    """The perfect maps at ``gain`` times their height, plus seeded uniform noise on the belief
    (a weakly trained net: peaks of every height, some spurious)."""

    def __init__(self, *args, gain: float = 1.0, noise: float = 0.0, **kw):
        super().__init__(*args, **kw)
        self.gain, self.noise = gain, noise

    def run(self, batch):
        belief, affinity = super().run(batch)
        rng = np.random.default_rng(len(self.calls))
        return (self.gain * belief + self.noise * rng.random(belief.shape)).astype(np.float32), affinity


@pytest.mark.parametrize("pose_search", ["hypotheses", "groups"])
def test_skipping_objects_that_cannot_reach_min_score_changes_no_detection(pose_search):
    """An object's decoding is skipped when no pose of its maps can score min_score; the
    detections are those of min_score 0 that score at least min_score, at every threshold."""
    def backend(gain, noise=0.0):
        return _FadedBackend(OBJ.name, OBJ.size_array, POSES, K640, (480, 640), gain=gain, noise=noise)

    for gain, noise in ((1.0, 0.0), (0.6, 0.15), (0.35, 0.3)):
        everything = DopePredictor(backend(gain=gain, noise=noise), min_score=0.0, pose_search=pose_search)
        all_dets = everything.predict(white((480, 640)), K640)
        for min_score in (0.2, 0.3, 0.45, 0.6, 0.9):
            pred = DopePredictor(backend(gain=gain, noise=noise), min_score=min_score, pose_search=pose_search)
            kept = [(d.score, d.t.tolist()) for d in all_dets if d.score >= min_score]
            assert [(d.score, d.t.tolist()) for d in pred.predict(white((480, 640)), K640)] == kept


def test_maps_too_weak_for_min_score_are_not_decoded(monkeypatch):
    calls = []
    original = DopePredictor._poses
    monkeypatch.setattr(DopePredictor, "_poses", lambda self, *a: calls.append(1) or original(self, *a))
    def weak():  # peaks of 0.3 at most: no pose scores above 0.3
        return _FadedBackend(OBJ.name, OBJ.size_array, POSES, K640, (480, 640), gain=0.3)

    assert DopePredictor(weak(), min_score=0.5).predict(white((480, 640)), K640) == [] and calls == []
    assert DopePredictor(weak(), min_score=0.1).predict(white((480, 640)), K640) and calls


class _TwoStrengthsBackend(TargetsBackend):
    """The perfect maps of POSES, the second object's belief at 0.4 times its height (a weak
    instance beside a strong one in the same maps)."""

    def run(self, batch):
        strong = TargetsBackend(OBJ.name, OBJ.size_array, POSES[:1], K640, (480, 640)).run(batch)
        weak = TargetsBackend(OBJ.name, OBJ.size_array, POSES[1:], K640, (480, 640)).run(batch)
        self.calls.append(1)
        return np.maximum(strong[0], 0.4 * weak[0]), strong[1] + weak[1]


def test_a_centroid_whose_peaks_cannot_reach_min_score_is_not_searched(monkeypatch):
    """Within one object's maps, a centroid whose candidates allow no pose of min_score (the
    mean of its min_points best keypoint types) goes to no pose search; the detections are
    those of min_score 0 that reach it."""
    import dope_hope.inference.predictor as predictor_module

    searched = []
    real = predictor_module.solve_pnp_instances
    monkeypatch.setattr(predictor_module, "solve_pnp_instances",
                        lambda candidates, *a, **kw: searched.append(len(candidates)) or real(candidates, *a, **kw))
    backend_ = _TwoStrengthsBackend(OBJ.name, OBJ.size_array, POSES, K640, (480, 640))
    all_dets = DopePredictor(backend_, min_score=0.0).predict(white((480, 640)), K640)
    match(all_dets, POSES)
    assert searched == [2] and sorted(round(d.score, 1) for d in all_dets) == [0.4, 1.0]
    searched.clear()
    dets = DopePredictor(backend_, min_score=0.5).predict(white((480, 640)), K640)
    assert searched == [1]  # the weak centroid is dropped before the search
    assert [(d.score, d.t.tolist()) for d in dets] == [(d.score, d.t.tolist()) for d in all_dets if d.score >= 0.5]


@pytest.mark.parametrize("scales", [(1.0,), (1.0, 0.75)])
def test_a_pose_under_the_threshold_is_kept_where_the_depth_confirms_it(scales):
    """Faint maps (peaks at 0.3: every pose scores under the threshold 0.5): with
    ``depth_confirm`` and ICP, the pose the depth confirms is kept, scored at the threshold,
    flagged, its keypoint score in ``network_score``; without depth, with depth of something
    else, or without the rule, nothing is kept. One size or several (the late depth stages)."""
    R, t = POSES[0]
    depth_mm = np.round(render_box_depth(OBJ.size_array, R, t, K640, (480, 640)) * 1000).astype(np.uint16)
    elsewhere = np.round(render_box_depth(OBJ.size_array, R, t + [0.2, 0.0, 0.0], K640, (480, 640)) * 1000
                         ).astype(np.uint16)

    def predictor(**kw):
        faint = _FadedBackend(OBJ.name, OBJ.size_array, [POSES[0]], K640, (480, 640), gain=0.3)
        return DopePredictor(faint, height=400, min_score=0.5, icp=True, multiscale={"scales": list(scales)}, **kw)

    confirm = {"depth_confirm": {"min_score": 0.1}}
    (det,) = predictor(**confirm).predict(white((480, 640)), K640, depth=depth_mm)
    assert det.depth_confirmed and det.score == 0.5 and 0.1 <= det.network_score < 0.5
    assert det.icp_applied and det.icp_fit >= 0.95
    assert rotation_error_deg(det.R, R) < 1.0 and np.linalg.norm(det.t - t) < 0.003
    rec = det.to_json("a.png")
    assert rec["depth_confirmed"] is True and rec["network_score"] == pytest.approx(det.network_score, abs=1e-4)
    assert predictor(**confirm).predict(white((480, 640)), K640) == []  # no depth: the threshold alone
    assert predictor(**confirm).predict(white((480, 640)), K640, depth=elsewhere) == []
    assert predictor().predict(white((480, 640)), K640, depth=depth_mm) == []  # the rule off (the default)
    strong = DopePredictor(backend(poses=[POSES[0]]), height=400, min_score=0.5, icp=True, **confirm)
    (kept,) = strong.predict(white((480, 640)), K640, depth=depth_mm)
    assert not kept.depth_confirmed and kept.score > 0.9 and "depth_confirmed" not in kept.to_json("a.png")
