"""A new object posed with no training: the pretrained start as a detector of a mesh's cuboid.

The start's maps are replaced by perfect ones (``TargetsBackend``: the keypoints a network
that learned the start's frame would find) where a test checks poses; the shipped start
itself runs where a test checks that the path runs. CLI and Python alike.
"""
from __future__ import annotations

import functools
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from _targets_backend import TargetsBackend

from dope_hope import cli
from dope_hope.demo_object import DEMO_SIZE_M, demo_object_mesh, write_demo_object
from dope_hope.errors import ConfigError
from dope_hope.geometry import cuboid_keypoints, project_points, rotation_error_deg
from dope_hope.inference.mesh_start import UP_AXES, MeshStartPredictor, size_warning, up_axis_rotation
from dope_hope.inference.object_geometry import ObjectGeometry
from dope_hope.inference.pnp import PnpSettings, solve_pnp
from dope_hope.model.info import ObjectInfo

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 160x120 synthetic frame of the demo box saved as MyBox.obj (not the demo model's
    object): (folder with 000000.png/.json/.depth.png, mesh path, GT R, GT t)."""
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.synth.generate import SynthJob
    from dope_hope.synth.to_disk import generate_dataset

    root = tmp_path_factory.mktemp("start")
    demo = write_demo_object(root / "mesh")
    mesh = demo.with_name("MyBox.obj")
    shutil.copy(demo, mesh)
    cfg = {"target": {"count": [1, 1], "truncation_prob": 0.0, "distance_m": [0.45, 0.55]},
           "distractors": {"count": [0, 0], "occluder_prob": 0.0}}
    generate_dataset(root / "data", SynthJob(demo, size=(160, 120), config=cfg), 1, progress=False)
    (gt,) = read_dope_json(root / "data" / "000000.json").objects
    return root / "data", mesh, gt.R, gt.t


@functools.cache
def shipped_start_features():
    """The shipped start's first layers (what the appearance check chooses the pose by)."""
    from dope_hope.assets import PRETRAINED_WEIGHTS
    from dope_hope.inference.backends import start_backend

    return start_backend(PRETRAINED_WEIGHTS, "Box", np.asarray(DEMO_SIZE_M)).texture_features


def perfect_start(monkeypatch, frame_dir: Path, R_start: np.ndarray, t: np.ndarray, size_start) -> None:
    """The start's maps become the perfect ones of one object at (R_start, t) in its frame;
    its first layers stay the shipped start's."""
    from dope_hope.io.dope_json import read_dope_json

    frame = read_dope_json(frame_dir / "000000.json")
    features = shipped_start_features()

    def fake(start, class_name, size_m, device="cpu", threads=None):
        b = TargetsBackend(class_name, np.abs(size_start), [(R_start, t)], frame.K, (frame.height, frame.width))
        b.info = SimpleNamespace(objects=(ObjectInfo(class_name, tuple(size_m)),), min_score=None)  # mesh frame
        b.texture_features = features
        return b

    monkeypatch.setattr("dope_hope.inference.mesh_start.start_backend", fake)


def test_up_axis_rotations_turn_the_axis_into_y():
    from dope_hope.commands.argtypes import UP_AXIS_NAMES

    assert sorted(UP_AXES) == sorted(UP_AXIS_NAMES)  # what --up-axis accepts is what the library knows
    for name, A in UP_AXES.items():
        axis = np.zeros(3)
        axis["xyz".index(name[-1])] = -1.0 if name.startswith("-") else 1.0
        np.testing.assert_allclose(A @ axis, [0, 1, 0])
        assert np.isclose(np.linalg.det(A), 1.0)
    with pytest.raises(ConfigError, match="up axis must be one of"):
        up_axis_rotation("w")


def test_a_mesh_far_from_the_learned_sizes_gets_a_warning():
    """A 15 cm bottle in millimetres read as centimetres is 1.5 m: the start learned objects
    of 6.8-25 cm (the HOPE objects'); a size near them passes."""
    line = size_warning(np.array([0.06, 1.5, 0.04]), "bottle.obj")
    assert line.startswith("bottle.obj: the mesh's largest side is 150 cm") and "--mesh-units" in line
    assert "0.6 cm" in size_warning(np.array([0.006, 0.004, 0.002]), "tiny.obj")
    assert size_warning(np.array([0.06, 0.15, 0.04]), "bottle.obj") is None
    assert size_warning(np.array([0.045, 0.04, 0.04]), "lemon.obj") is None  # the grocery lemon


def test_pnp_frame_round_trip():
    size, K = np.array([0.05, 0.04, 0.16]), np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [30, -20, 60], degrees=True).as_matrix()
    t = np.array([0.03, -0.02, 0.7])
    obj = ObjectGeometry(ObjectInfo("Tube", tuple(size)), 0, False, None, None, 100, 100)
    A = up_axis_rotation("z")
    obj.set_pnp_frame(A)
    np.testing.assert_allclose(np.ptp(obj.cuboid_pnp, axis=0), [0.05, 0.16, 0.04])  # z up is the start's y
    uv_net = project_points(obj.cuboid_pnp, K, R @ A.T, t)  # what the start sees
    est = solve_pnp(uv_net, np.ones(9), obj.cuboid_pnp, K, PnpSettings())
    np.testing.assert_allclose(est.R @ A, R, atol=1e-6)
    np.testing.assert_allclose(uv_net[obj.pnp_order], project_points(obj.cuboid_mesh, K, R, t), atol=1e-6)


def test_a_z_up_mesh_comes_back_in_its_own_frame_with_its_ambiguity(scene, monkeypatch):
    """The demo box turned so that its vertical axis is z, declared --up-axis z: the start
    sees the box as it learned it (y up); the pose returns in the z-up frame, the texture
    picks the true one of the four equivalent poses."""
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_depth_m, read_rgb

    frame_dir, _, R_gt, t_gt = scene
    A = up_axis_rotation("z")
    mesh_z = demo_object_mesh()
    T = np.eye(4)
    T[:3, :3] = A.T  # p_z = A^T p_demo: the box's vertical y becomes z
    mesh_z.apply_transform(T)
    frame = read_dope_json(frame_dir / "000000.json")
    flip = np.diag([-1.0, 1.0, -1.0])  # the start reports an equivalent pose, 180° about y
    perfect_start(monkeypatch, frame_dir, R_gt @ flip, t_gt, DEMO_SIZE_M)
    p = MeshStartPredictor(mesh_z, class_name="ZBox", up_axis="z")
    try:
        dets = p.predict(read_rgb(frame_dir / "000000.png"), frame.K,
                         depth=read_depth_m(frame_dir / "000000.depth.png"))
    finally:
        p.close()
    (det,) = dets
    R_gt_z = R_gt @ A  # the GT pose in the z-up frame
    assert rotation_error_deg(det.R, R_gt_z) < 1.0
    assert np.linalg.norm(det.t - t_gt) < 0.01
    kp = project_points(cuboid_keypoints(np.ptp(mesh_z.vertices, axis=0)), frame.K, R_gt_z, t_gt)
    assert np.abs(det.keypoints_2d - kp).max() < 1.0  # in the z-up mesh's corner order
    rec = det.to_json("000000.png")
    assert sorted(rec["cuboid_symmetries"]) == ["180° about x", "180° about y", "180° about z"]
    assert rec["pose_ambiguity"] == []  # the demo box's faces differ: the texture resolved it
    assert 0 < rec["appearance_score"] <= 1 and rec["network_score"] > 0
    assert rec["score"] == pytest.approx(np.sqrt(rec["appearance_score"] * rec["network_score"]), abs=1e-3)


@pytest.mark.parametrize("step, turned_back", [(30.0, True), (0.0, False)])
def test_the_appearance_turns_a_pose_about_the_up_axis(scene, monkeypatch, step, turned_back):
    """The start placing the box's up axis right but turned 60° about it (as it places a
    bottle it never saw): the turns of ``appearance.spin_step_deg`` find the true pose before
    -LS; without them (0) the pose stays turned."""
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_depth_m, read_rgb

    frame_dir, mesh, R_gt, t_gt = scene
    turn = np.array([[0.5, 0.0, np.sqrt(0.75)], [0.0, 1.0, 0.0], [-np.sqrt(0.75), 0.0, 0.5]])  # 60° about y
    perfect_start(monkeypatch, frame_dir, R_gt @ turn, t_gt, DEMO_SIZE_M)
    frame = read_dope_json(frame_dir / "000000.json")
    p = MeshStartPredictor(mesh, options={"appearance": {"spin_step_deg": step}})
    try:
        assert ("turns of 30° about the up axis" in p.describe()) is turned_back
        dets = p.predict(read_rgb(frame_dir / "000000.png"), frame.K, depth=read_depth_m(frame_dir / "000000.depth.png"))
    finally:
        p.close()
    (det,) = dets
    assert (rotation_error_deg(det.R, R_gt) < 1.0) is turned_back
    assert rotation_error_deg(det.R, R_gt) == pytest.approx(0.0 if turned_back else 60.0, abs=1.0)
    assert det.ls_applied and (np.linalg.norm(det.t - t_gt) < 0.01 or not turned_back)  # -LS on the pose kept
    np.testing.assert_allclose(det.projected_2d, project_points(p.objects[0].cuboid_mesh, frame.K, det.R, det.t))


def test_with_icp_the_depth_stages_run_first_and_no_turn_is_compared(scene, monkeypatch):
    """With ICP the depth places the turn: -LS and ICP run on the network's pose, and the
    check compares the cuboid's equivalent poses alone (no turn left open or taken)."""
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_depth_m, read_rgb

    frame_dir, mesh, R_gt, t_gt = scene
    perfect_start(monkeypatch, frame_dir, R_gt, t_gt, DEMO_SIZE_M)
    frame = read_dope_json(frame_dir / "000000.json")
    p = MeshStartPredictor(mesh, icp=True, appearance={"ambiguity_margin": 1.0})  # every pose compared left open
    try:
        (det,) = p.predict(read_rgb(frame_dir / "000000.png"), frame.K,
                           depth=read_depth_m(frame_dir / "000000.depth.png"))
    finally:
        p.close()
    assert det.ls_applied and det.icp_reason not in ("not requested", "no depth image")
    assert sorted(det.pose_ambiguity) == ["180° about x", "180° about y", "180° about z"]  # no "30° about y"
    assert rotation_error_deg(det.R, R_gt) < 1.0


def test_a_mesh_without_texture_or_of_one_colour_keeps_the_networks_pose(scene, monkeypatch):
    """No texture and no colours: no check (a warning says so), every cuboid reported. One
    colour: the check compares the network's pose alone (colour tells look-alikes, not
    poses) and resolves nothing. ``appearance.enabled: false`` turns it off for any mesh."""
    import trimesh

    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_rgb

    frame_dir, mesh, R_gt, t_gt = scene
    perfect_start(monkeypatch, frame_dir, R_gt, t_gt, DEMO_SIZE_M)
    rgb, K = read_rgb(frame_dir / "000000.png"), read_dope_json(frame_dir / "000000.json").K
    plain = trimesh.creation.box(extents=DEMO_SIZE_M)
    one_colour = plain.copy()
    one_colour.visual.vertex_colors = [200, 40, 30, 255]
    with pytest.warns(UserWarning, match="no texture and no colours, so the appearance check is off"):
        bare = MeshStartPredictor(plain, class_name="Plain")
    coloured = MeshStartPredictor(one_colour, class_name="Red", appearance={"min_score": 0.0})
    off = MeshStartPredictor(mesh, options={"appearance": {"enabled": False}})
    try:
        assert bare.appearance is None and off.appearance is None and "no appearance check" in bare.describe()
        assert coloured.appearance.surface == "uniform" and "one colour" in coloured.describe()
        for p in (bare, coloured, off):
            (det,) = p.predict(rgb, K)
            assert rotation_error_deg(det.R, R_gt) < 1.0, p.class_name  # the network's pose, unturned
            assert sorted(det.pose_ambiguity) == ["180° about x", "180° about y", "180° about z"]
            assert np.isfinite(det.appearance_score) == (p is coloured)
    finally:
        for p in (bare, coloured, off):
            p.close()


def test_the_working_sizes_are_the_new_object_section(scene, monkeypatch):
    """``new_object.scales`` sets the sizes the start runs at (Python and --set alike): one
    size, one forward pass; ``multiscale.scales`` (a trained model's) is refused there."""
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_rgb

    frame_dir, mesh, R_gt, t_gt = scene
    perfect_start(monkeypatch, frame_dir, R_gt, t_gt, DEMO_SIZE_M)
    calls = []
    real = MeshStartPredictor.infer_maps
    monkeypatch.setattr(MeshStartPredictor, "infer_maps", lambda self, x: calls.append(x) or real(self, x))
    p = MeshStartPredictor(mesh, new_object={"scales": [1.0]}, multiscale={"duplicate_iou": 0.3})
    try:
        assert p.scales == (1.0,) and p.options.multiscale.duplicate_iou == 0.3
        (det,) = p.predict(read_rgb(frame_dir / "000000.png"), read_dope_json(frame_dir / "000000.json").K)
    finally:
        p.close()
    assert len(calls) == 1 and rotation_error_deg(det.R, R_gt) < 1.0
    with pytest.raises(ConfigError, match="new_object.scales must be a non-empty list"):
        MeshStartPredictor(mesh, new_object={"scales": []})
    with pytest.raises(ConfigError, match="multiscale.scales sets a trained model's working sizes"):
        MeshStartPredictor(mesh, multiscale={"scales": [1.0, 0.5]})


def test_shipped_start_runs_in_python(scene):
    frame_dir, mesh, _, _ = scene
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_rgb

    p = MeshStartPredictor(mesh, appearance={"min_score": 0.0}, threads=1)
    try:
        assert p.class_name == "MyBox" and len(p.symmetries) == 4
        assert p.objects[0].mesh_file == Path(mesh)  # --track reads its symmetries from this file
        assert "untrained" in p.describe() and "180° about y" in p.describe()
        dets = p.predict(read_rgb(frame_dir / "000000.png"), read_dope_json(frame_dir / "000000.json").K)
    finally:
        p.close()
    for d in dets:
        assert d.class_name == "MyBox" and d.pose_ambiguity is not None and np.isfinite(d.appearance_score)


def run_cli(argv, capsys):
    try:
        code = cli.main(["infer", *map(str, argv)])
    except SystemExit as exc:  # argparse's refusals
        code = exc.code
    out, err = capsys.readouterr()
    return code, [json.loads(line) for line in out.splitlines() if line.strip()], err


def one_line_error(code, err):
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("dope-hope infer: error:"), err
    return lines[0]


def test_cli_mesh_without_weights_runs_the_start(scene, tmp_path, monkeypatch, capsys):
    frame_dir, mesh, R_gt, t_gt = scene
    perfect_start(monkeypatch, frame_dir, R_gt, t_gt, DEMO_SIZE_M)
    out = tmp_path / "o"
    code, records, err = run_cli([frame_dir / "000000.png", "--mesh", mesh, "--depth", "auto", "--out", out], capsys)
    assert code == 0, err
    assert "MyBox: the pretrained start" in err and "poses known up to the cuboid's symmetries" in err
    (rec,) = records
    assert rec["class"] == "MyBox" and rec["pose_ambiguity"] == [] and len(rec["cuboid_symmetries"]) == 3
    assert rotation_error_deg(np.array(rec["R"]), R_gt) < 1.0 and rec["ls_applied"] is True
    saved = [json.loads(line) for line in (out / "predictions.jsonl").read_text().splitlines()]
    assert saved[0]["pose_ambiguity"] == []


def test_cli_shipped_start_and_its_warning(scene, tmp_path, capsys):
    frame_dir, mesh, _, _ = scene
    import trimesh

    lying = tmp_path / "Lying" / "textured.obj"  # longest along z, up axis left at y
    lying.parent.mkdir()
    trimesh.creation.box(extents=[4.0, 5.0, 16.0]).export(lying)
    code, _, err = run_cli([frame_dir / "000000.png", "--mesh", lying, "--out", tmp_path / "o",
                            "--no-overlay", "--threads", "1"], capsys)
    assert code == 0, err
    assert "warning:" in err and "longest along z" in err and "--up-axis z" in err
    assert "no texture and no colours, so the appearance check is off" in err  # a bare box: nothing to compare
    assert "Lying: the pretrained start" in err


def test_several_new_objects_share_one_network_pass(scene, monkeypatch, tmp_path, capsys):
    """--mesh A --mesh NAME=B without --weights: one predictor per new object, each with its
    own up axis (--up-axis NAME=AXIS) and class; the start's maps are computed once per image
    and working size for all of them (predict_many's shared cache)."""
    import trimesh

    from dope_hope.inference.model_set import build_start_predictors
    from dope_hope.inference.predictor import predict_many
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_rgb

    frame_dir, mesh, R_gt, t_gt = scene
    perfect_start(monkeypatch, frame_dir, R_gt, t_gt, DEMO_SIZE_M)
    lying = tmp_path / "Tube.obj"
    trimesh.creation.box(extents=[4.0, 5.0, 16.0]).export(lying)
    calls = []
    real = MeshStartPredictor.infer_maps
    monkeypatch.setattr(MeshStartPredictor, "infer_maps", lambda self, x: calls.append(self.class_name) or real(self, x))
    with pytest.warns(UserWarning, match="no texture"):
        ps = build_start_predictors({"MyBox": mesh, "Tube": lying}, up_axes={"Tube": "z"}, mesh_units="cm")
    try:
        assert [(p.class_name, p.up_axis) for p in ps] == [("MyBox", "y"), ("Tube", "z")]
        frame = read_dope_json(frame_dir / "000000.json")
        dets = predict_many(ps, read_rgb(frame_dir / "000000.png"), frame.K)
    finally:
        for p in ps:
            p.close()
    assert calls == ["MyBox"] * len(ps[0].scales)  # the second object reuses the first one's maps
    assert {d.class_name for d in dets} >= {"MyBox"}
    with pytest.raises(ConfigError, match="--up-axis Milk=z: Milk is not an object of this run"):
        build_start_predictors({"MyBox": mesh}, up_axes={"Milk": "z"})
    with pytest.raises(ConfigError, match="--classes Milk: Milk is not an object of this run"):
        build_start_predictors({"MyBox": mesh}, classes=["Milk"])
    with pytest.warns(UserWarning, match="no texture"):
        (tube,) = build_start_predictors({"MyBox": mesh, "Tube": lying}, classes=["tube"], mesh_units="cm",
                                         up_axes="z")
    assert tube.class_name == "Tube"
    tube.close()

    code, records, err = run_cli([frame_dir / "000000.png", "--mesh", mesh, "--mesh", f"Tube={lying}",
                                  "--up-axis", "Tube=z", "--mesh-units", "cm", "--out", tmp_path / "o", "--no-overlay"],
                                 capsys)
    assert code == 0, err
    assert "MyBox: the pretrained start" in err and "Tube: the pretrained start" in err and "up axis z" in err
    assert any(r["class"] == "MyBox" for r in records)
    folder = tmp_path / "meshes"  # one models folder: each mesh in it a new object, --classes keeps some
    folder.mkdir()
    shutil.copy(mesh, folder / "MyBox.obj")
    shutil.copy(lying, folder / "Tube.obj")
    code, records, err = run_cli([frame_dir / "000000.png", "--mesh", folder, "--mesh-units", "cm", "--classes", "MyBox",
                                  "--out", tmp_path / "o2", "--no-overlay"], capsys)
    assert code == 0, err
    assert "MyBox: the pretrained start" in err and "Tube:" not in err and {r["class"] for r in records} == {"MyBox"}


def test_cli_refuses_bad_input_with_one_line(scene, tmp_path, capsys):
    frame_dir, mesh, _, _ = scene
    img = frame_dir / "000000.png"
    line = one_line_error(*run_cli([img, "--mesh", mesh, "--up-axis", "w"], capsys)[::2])
    assert "--up-axis w: must be one of x, y, z, -x, -y, -z" in line
    line = one_line_error(*run_cli([img, "--mesh", mesh, "--up-axis", "Other=z"], capsys)[::2])
    assert "--up-axis Other=z: Other is not an object of this run (objects: MyBox)" in line
    line = one_line_error(*run_cli([img, "--mesh", mesh, "--mesh", f"mybox={mesh}"], capsys)[::2])
    assert "is MyBox too" in line and "--mesh NAME=PATH" in line
    line = one_line_error(*run_cli([img, "--mesh", f"={mesh}"], capsys)[::2])
    assert "name the object before '='" in line
    line = one_line_error(*run_cli([img, "--mesh", mesh, "--weights", "w.pt", "--up-axis", "z"], capsys)[::2])
    assert "--up-axis" in line and "no --weights" in line
    line = one_line_error(*run_cli([img, "--start", "s.pt"], capsys)[::2])
    assert "--start" in line and "--mesh FILE" in line
    line = one_line_error(*run_cli([img, "--mesh", mesh, "--set", "appearance.spin_step_deg=400"], capsys)[::2])
    assert "appearance.spin_step_deg" in line and "(0, 180]" in line
    line = one_line_error(*run_cli([img, "--mesh", mesh, "--set", "appearance.enabled=1"], capsys)[::2])
    assert "appearance.enabled must be true or false" in line
    line = one_line_error(*run_cli([img, "--mesh", mesh, "--set", "new_object.scales=[1.0,0]"], capsys)[::2])
    assert "new_object.scales" in line and "> 0" in line
    line = one_line_error(*run_cli([img, "--mesh", tmp_path / "missing.obj", "--out", tmp_path / "o"], capsys)[::2])
    assert "missing.obj" in line
    with pytest.raises(ConfigError, match="class_name"):
        MeshStartPredictor(demo_object_mesh())
