"""The turns of a trained model's poses by the texture (``appearance.trained_turns``): a model
that places the demo box's long axis right but turns it 60° about it gets the true pose back;
off by default, not with ICP, and an object it cannot turn is named in a warning."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from _targets_backend import TargetsBackend, demo_box_frame
from scipy.spatial.transform import Rotation

from dope_hope.demo_object import DEMO_SIZE_M
from dope_hope.geometry import project_points, rotation_error_deg
from dope_hope.inference.appearance import AppearanceSettings
from dope_hope.inference.detection import Detection
from dope_hope.inference.predictor import DopePredictor
from dope_hope.inference.turns import TrainedTurns, turn_detection
from dope_hope.io.dope_json import read_dope_json
from dope_hope.io.images import read_depth_m, read_rgb
from dope_hope.io.meshes import load_mesh
from dope_hope.symmetry.cuboid import corner_permutation

TURN = Rotation.from_euler("y", 60.0, degrees=True).as_matrix()  # about the demo box's long axis (y)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 160x120 frame of the demo box: (frame folder, mesh path, GT R, GT t)."""
    return demo_box_frame(tmp_path_factory.mktemp("turns"))


def trained_model(scene, R):
    """A 'trained model' of the box whose maps place it at (R, the true t)."""
    frame_dir, _, _, t = scene
    frame = read_dope_json(frame_dir / "000000.json")
    return TargetsBackend("DemoBox", DEMO_SIZE_M, [(R, t)], frame.K, (frame.height, frame.width))


def run(scene, R_model, mesh=None, mesh_units=None, **options):
    """(predictor, detections) of the 'trained model' at R_model on the frame, with -LS."""
    frame_dir, demo, _, _ = scene
    frame = read_dope_json(frame_dir / "000000.json")
    p = DopePredictor(trained_model(scene, R_model), mesh=mesh or demo, mesh_units=mesh_units, options=options)
    try:
        return p, p.predict(read_rgb(frame_dir / "000000.png"), frame.K,
                            depth=read_depth_m(frame_dir / "000000.depth.png"))
    finally:
        p.close()


def test_a_pose_turned_about_the_long_axis_is_turned_back(scene):
    frame_dir, _, R_gt, t_gt = scene
    K = read_dope_json(frame_dir / "000000.json").K
    p, (det,) = run(scene, R_gt @ TURN, appearance={"trained_turns": True})
    assert rotation_error_deg(det.R, R_gt) < 1.0
    assert np.linalg.norm(det.t - t_gt) < 0.01  # turned about the box centre, after -LS
    assert det.ls_applied and 0 < det.appearance_score <= 1
    assert det.texture_turn_deg == pytest.approx(300.0)  # -60° about y, the turn that undoes the model's
    rec = det.to_json("000000.png")
    assert rec["texture_turn_deg"] == 300.0 and rec["appearance_score"] == round(det.appearance_score, 4)
    assert "pose_ambiguity" not in rec
    np.testing.assert_allclose(det.projected_2d, project_points(p.objects[0].cuboid_mesh, K, det.R, det.t))


@pytest.mark.parametrize("refine_deg, error_deg", [(8.0, 0.0), (0.0, 8.0)])
def test_the_refinement_takes_out_a_small_tilt(scene, refine_deg, error_deg):
    """A model 60° off about the long axis and tilted 8° across it: the turn takes out the 60°,
    the refinement (``trained_refine_deg``) the tilt; without it the tilt stays."""
    _, _, R_gt, _ = scene
    tilt = Rotation.from_euler("x", 8.0, degrees=True).as_matrix()
    _, (det,) = run(scene, R_gt @ tilt @ TURN, appearance={"trained_turns": True, "trained_refine_deg": refine_deg})
    assert rotation_error_deg(det.R, R_gt) == pytest.approx(error_deg, abs=1.0)


def test_off_by_default_and_with_icp(scene):
    _, _, R_gt, _ = scene
    _, (det,) = run(scene, R_gt @ TURN)
    assert rotation_error_deg(det.R, R_gt) == pytest.approx(60.0, abs=1.0)  # the network's pose, as it was
    assert np.isnan(det.appearance_score) and "texture_turn_deg" not in det.to_json("000000.png")
    with pytest.warns(UserWarning, match="trained_turns does not run with ICP"):
        p, (det,) = run(scene, R_gt @ TURN, appearance={"trained_turns": True}, icp=True)
    assert p.trained_turns() is None  # the depth fit places the turn
    assert np.isnan(det.appearance_score)


def test_an_object_it_cannot_turn_is_named(scene, tmp_path):
    """A mesh without texture: no check, and a warning naming the object and why; a textured
    box with no long axis: no axis to turn about."""
    _, demo, R_gt, _ = scene
    bare = tmp_path / "DemoBox.ply"
    trimesh.load(demo, force="mesh", process=False).copy(include_visual=False).export(bare)
    with pytest.warns(UserWarning, match=r"no turns for DemoBox \(its mesh's surface is none\)"):
        _, (det,) = run(scene, R_gt @ TURN, mesh=bare, mesh_units="cm", appearance={"trained_turns": True})
    assert rotation_error_deg(det.R, R_gt) == pytest.approx(60.0, abs=1.0)
    squat = load_mesh(demo, units="cm")
    squat.apply_scale([1.0, 0.7, 1.0])  # 12.3 x 11.7 x 4.0 cm: no side 1.3x both others
    obj = SimpleNamespace(class_name="Squat", mesh=squat, cuboid_size_m=np.ptp(squat.vertices, axis=0),
                          cuboid_center_m=np.zeros(3))
    turns = TrainedTurns([obj], AppearanceSettings(), features=lambda images: images)
    assert turns.checks == {} and turns.skipped == {"Squat": "its box has no long axis"}


def test_turn_detection_relabels_the_keypoints():
    kp = np.arange(18, dtype=float).reshape(9, 2)
    det = Detection(class_name="X", score=1.0, R=np.eye(3), t=np.zeros(3), keypoints_2d=kp.copy(),
                    keypoint_scores=np.arange(9.0), inliers=np.arange(9) % 2 == 0,
                    projected_2d=np.zeros((9, 2)), reprojection_error_px=0.0, cuboid_size_m=np.ones(3))
    S = Rotation.from_euler("y", 180.0, degrees=True).as_matrix()
    turn_detection(det, S, S, np.ones(3))
    perm = corner_permutation(np.rint(S))
    np.testing.assert_array_equal(det.keypoints_2d, kp[perm])
    np.testing.assert_array_equal(det.keypoint_scores, np.arange(9.0)[perm])
    np.testing.assert_allclose(det.R, S)
    np.testing.assert_allclose(det.t, np.ones(3))
    assert perm[8] == 8 and sorted(perm) == list(range(9)) and list(perm) != list(range(9))


def test_the_refinement_step_is_checked():
    from dope_hope.errors import ConfigError

    assert AppearanceSettings.from_mapping({"trained_refine_deg": 0}).trained_refine_deg == 0.0
    with pytest.raises(ConfigError, match=r"appearance.trained_refine_deg must be 0 \(no refinement\) or a step"):
        AppearanceSettings.from_mapping({"trained_refine_deg": 50})
    with pytest.raises(ConfigError, match="trained_refine_deg"):
        AppearanceSettings.from_mapping({"trained_refine_deg": -1})
