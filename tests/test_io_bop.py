"""dope_hope.io.bop readers on BOP files synthesized here and the per-model sample infos."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from dope_hope.errors import InputFileError
from dope_hope.io.bop import (
    iter_bop_split,
    list_bop_scenes,
    read_models_info,
    read_scene_camera,
    read_scene_gt,
    read_scene_gt_info,
    read_scene_gt_stored,
    read_test_targets,
)
from dope_hope.io.meshes import load_mesh
from dope_hope.symmetry.transforms import symmetry_transforms

K0 = [1390.5, 0.0, 964.9, 0.0, 1386.9, 522.5, 0.0, 0.0, 1.0]
R_A = Rotation.from_euler("zyx", [30, 20, -50], degrees=True).as_matrix()


def _dump(path: Path, data) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


def _gt(R, t_mm, obj_id):
    return {"cam_R_m2c": np.asarray(R).ravel().tolist(), "cam_t_m2c": list(t_mm), "obj_id": obj_id}


def _info(vf, bbox_visib):
    return {"bbox_obj": [10, 20, 30, 40], "bbox_visib": bbox_visib, "px_count_all": 1200,
            "px_count_valid": 1100, "px_count_visib": 900, "visib_fract": vf}


@pytest.fixture
def split(tmp_path) -> Path:
    """hope-like split: scene 1 with 2 images (png + jpg), scene 3 without ground truth."""
    s1 = tmp_path / "val" / "000001"
    _dump(s1 / "scene_camera.json", {"0": {"cam_K": K0, "depth_scale": 0.1},
                                     "5": {"cam_K": K0, "depth_scale": 1.0}})
    _dump(s1 / "scene_gt.json", {"0": [_gt(R_A, [10.0, -20.0, 800.0], 11), _gt(np.eye(3), [0, 0, 1000], 13)],
                                 "5": [_gt(np.eye(3), [5.0, 5.0, 500.0], 1)]})
    _dump(s1 / "scene_gt_info.json", {"0": [_info(0.75, [100, 50, 20, 30]), _info(0.0, [-1, -1, 0, 0])],
                                      "5": [_info(1.0, [0, 0, 8, 6])]})
    (s1 / "rgb").mkdir()
    (s1 / "depth").mkdir()
    cv2.imwrite(str(s1 / "rgb" / "000000.png"), np.zeros((6, 8, 3), np.uint8))
    cv2.imwrite(str(s1 / "rgb" / "000005.jpg"), np.zeros((6, 8, 3), np.uint8))
    cv2.imwrite(str(s1 / "depth" / "000000.png"), np.full((6, 8), 7000, np.uint16))
    s3 = tmp_path / "val" / "000003"
    _dump(s3 / "scene_camera.json", {"2": {"cam_K": K0}})
    (tmp_path / "val" / "notes").mkdir()
    return tmp_path / "val"


def test_scene_files_values(split):
    cams = read_scene_camera(split / "000001" / "scene_camera.json")
    assert sorted(cams) == [0, 5]
    K, scale = cams[0]
    np.testing.assert_allclose(K, np.reshape(K0, (3, 3)))
    assert scale == pytest.approx(1e-4)  # 0.1 mm per unit, in metres
    assert cams[5][1] == pytest.approx(1e-3)
    assert read_scene_camera(split / "000003" / "scene_camera.json")[2][1] == pytest.approx(1e-3)

    gts = read_scene_gt(split / "000001" / "scene_gt.json")
    obj_id, R, t = gts[0][0]
    assert obj_id == 11
    np.testing.assert_allclose(R, R_A, atol=1e-12)
    np.testing.assert_allclose(t, [0.010, -0.020, 0.800])  # mm -> m
    assert [g[0] for g in gts[0]] == [11, 13]
    # as stored (for BOP19 scoring): millimetres, R exactly the file's numbers
    _, R_s, t_s = read_scene_gt_stored(split / "000001" / "scene_gt.json")[0][0]
    np.testing.assert_array_equal(R_s, np.reshape(np.asarray(R_A).ravel().tolist(), (3, 3)))
    np.testing.assert_array_equal(t_s, [10.0, -20.0, 800.0])

    infos = read_scene_gt_info(split / "000001" / "scene_gt_info.json")
    a = infos[0][0]
    assert a.visib_fract == 0.75
    assert (a.px_count_all, a.px_count_valid, a.px_count_visib) == (1200, 1100, 900)
    np.testing.assert_allclose(a.bbox_obj, [10, 20, 30, 40])
    np.testing.assert_allclose(a.bbox_visib_xyxy, [100, 50, 120, 80])


def test_iter_bop_split(split):
    assert list_bop_scenes(split) == [1, 3]
    frames = list(iter_bop_split(split))
    assert [(f.scene_id, f.im_id) for f in frames] == [(1, 0), (1, 5), (3, 2)]
    fr = frames[0].frame
    assert fr.image_path == split / "000001" / "rgb" / "000000.png"
    assert fr.depth_path == split / "000001" / "depth" / "000000.png"
    assert (fr.width, fr.height) == (8, 6)
    assert fr.depth_scale_m == pytest.approx(1e-4)
    assert [o.class_name for o in fr.objects] == ["Ketchup", "Mayo"]  # catalog ids 11, 13
    assert [o.instance_id for o in fr.objects] == [0, 1]
    assert fr.objects[0].visibility == 0.75
    np.testing.assert_allclose(fr.objects[0].bbox_xyxy, [100, 50, 120, 80])
    np.testing.assert_allclose(fr.objects[0].t, [0.010, -0.020, 0.800])
    R_s, t_s = fr.objects[0].stored_pose
    np.testing.assert_array_equal(t_s, [10.0, -20.0, 800.0])
    np.testing.assert_array_equal(R_s.ravel(), np.asarray(R_A).ravel().tolist())
    assert frames[1].frame.image_path.suffix == ".jpg"
    assert frames[1].frame.depth_path is None
    assert frames[1].frame.objects[0].class_name == "AlphabetSoup"
    assert frames[2].frame.objects == [] and frames[2].frame.image_path is None
    assert frames[0].annotation is fr and frames[0].image_path == fr.image_path
    only3 = list(iter_bop_split(split, scene_ids=[3], class_name=lambda i: f"o{i}"))
    assert [(f.scene_id, f.im_id) for f in only3] == [(3, 2)]


def test_test_targets(tmp_path):
    path = _dump(tmp_path / "test_targets_bop19.json", [
        {"im_id": 4, "inst_count": 1, "obj_id": 2, "scene_id": 1},
        {"im_id": 4, "inst_count": 2, "obj_id": 11, "scene_id": 1}])
    assert read_test_targets(path) == [(1, 4, 2, 1), (1, 4, 11, 2)]


def test_models_info_keyed_mm(tmp_path):
    flip_z = np.diag([-1.0, -1.0, 1.0, 1.0])
    flip_z[:3, 3] = [0.0, 0.0, 10.0]  # mm
    path = _dump(tmp_path / "models_info.json", {
        "1": {"diameter": 102.1, "min_x": -20.0, "min_y": -50.0, "min_z": -10.0,
              "size_x": 40.0, "size_y": 100.0, "size_z": 20.0,
              "symmetries_discrete": [flip_z.ravel().tolist()]},
        "2": {"diameter": 80.0, "symmetries_continuous": [{"axis": [0, 2, 0], "offset": [0, 0, 5]}]},
        "3": {"diameter": 50.0}})
    info = read_models_info(path)
    assert sorted(info) == [1, 2, 3]
    assert info[1]["diameter_m"] == pytest.approx(0.1021)
    np.testing.assert_allclose(info[1]["size_m"], [0.04, 0.1, 0.02])
    np.testing.assert_allclose(info[1]["min_m"], [-0.02, -0.05, -0.01])
    assert info[1]["symmetries_discrete"].shape == (1, 4, 4)
    np.testing.assert_allclose(info[1]["symmetries_discrete"][0][:3, 3], [0, 0, 0.01])
    (axis, offset), = info[2]["symmetries_continuous"]
    np.testing.assert_allclose(axis, [0, 1, 0])
    np.testing.assert_allclose(offset, [0, 0, 0.005])
    assert info[3]["symmetries_discrete"].shape == (0, 4, 4)
    # transforms: identity first; discrete x continuous products; offsets respected
    T = symmetry_transforms(info[2], step_deg=90)
    assert T.shape == (4, 4, 4)
    np.testing.assert_allclose(T[0], np.eye(4))
    p = np.array([0.01, 0.0, 0.005])  # 1 cm from the axis, at the offset
    q = T[2, :3, :3] @ p + T[2, :3, 3]  # 180° about y through (0, 0, 5 mm)
    np.testing.assert_allclose(q, [-0.01, 0.0, 0.005], atol=1e-12)
    assert symmetry_transforms(info[1]).shape == (2, 4, 4)
    assert symmetry_transforms(info[3]).shape == (1, 4, 4)


def _hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    return max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max())


def _apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


@pytest.mark.parametrize("name, step, tol", [("cylinder", 360 / 32, 1e-5), ("hex_screw", 1.0, 1e-3)])
def test_symmetric_models_infos_map_mesh_onto_itself(shared_data, name, step, tol):
    """The per-model BOP-style infos (not keyed by obj_id) of the DOPE sample meshes (metres):
    every symmetry puts the mesh's vertices back on its surface (the hex screw's round thread
    is faceted with a section count that 60° does not divide, hence its looser bound)."""
    folder = shared_data / "symmetric_models" / name
    info = read_models_info(folder / "model_info.json", units="m")
    assert list(info) == [0]
    info = info[0]
    assert "align_axes" in info
    mesh = load_mesh(folder / "textured.obj", units="m")
    verts = np.unique(mesh.vertices, axis=0)
    transforms = symmetry_transforms(info, step_deg=step)
    assert len(transforms) == (64 if name == "cylinder" else 6)

    def off_surface(T: np.ndarray) -> float:
        return trimesh.proximity.closest_point_naive(mesh, _apply(T, verts))[1].max()

    assert max(off_surface(T) for T in transforms) < tol
    # rotations that are not symmetries move vertices off the surface
    not_symmetries = [([1, 0, 0], 90)] + ([([0, 0, 1], 30)] if name == "hex_screw" else [])
    for axis, angle in not_symmetries:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(np.radians(angle) * np.array(axis, float)).as_matrix()
        assert off_surface(T) > 5 * tol


def _write_info(tmp_path: Path, info: dict) -> dict:
    return read_models_info(_dump(tmp_path / "models_info.json", {"1": info}))[1]


def test_generated_cylinder_and_box_symmetries(tmp_path):
    """Cylinder along y (continuous about y + the top-bottom flip) and box (3 flips) in mm."""
    cyl = trimesh.creation.cylinder(radius=30.0, height=100.0, sections=24)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # z -> y
    assert np.argmax(cyl.extents) == 1
    flip_x = np.diag([1.0, -1.0, -1.0, 1.0])
    info = _write_info(tmp_path, {"diameter": 116.6, "symmetries_discrete": [flip_x.ravel().tolist()],
                                  "symmetries_continuous": [{"axis": [0, 1, 0], "offset": [0, 0, 0]}]})
    verts = np.unique(cyl.vertices, axis=0) * 0.001
    transforms = symmetry_transforms(info, step_deg=15.0)
    assert len(transforms) == 48
    assert max(_hausdorff(_apply(T, verts), verts) for T in transforms) < 1e-12

    box = trimesh.creation.box(extents=[40.0, 100.0, 20.0])
    flips = [np.diag(d + [1.0]).ravel().tolist() for d in ([1.0, -1, -1], [-1.0, 1, -1], [-1.0, -1, 1])]
    info = _write_info(tmp_path, {"diameter": 109.5, "symmetries_discrete": flips})
    pts = trimesh.sample.sample_surface(box, 2000, seed=0)[0] * 0.001
    transforms = symmetry_transforms(info)
    assert len(transforms) == 4
    for T in transforms:
        # the box's surface maps onto itself: transformed samples stay on the surface
        q = np.abs(_apply(T, pts))
        on_face = np.isclose(q, [0.02, 0.05, 0.01], atol=1e-12).any(axis=1)
        assert on_face.all() and (q <= [0.02 + 1e-12, 0.05 + 1e-12, 0.01 + 1e-12]).all()
        assert _hausdorff(_apply(T, box.vertices * 0.001), box.vertices * 0.001) < 1e-12


@pytest.mark.parametrize("reader, data, message", [
    (read_scene_camera, {"0": {"cam_K": [1, 2, 3]}}, "0.cam_K: expected shape (9,), got (3,)"),
    (read_scene_camera, {"x": {"cam_K": K0}}, "x: expected an integer image id as key"),
    (read_scene_camera, {"0": {}}, "0.cam_K: missing field"),
    (read_scene_gt, {"0": [{"cam_R_m2c": [1] * 9, "cam_t_m2c": [0, 0, 1], "obj_id": 1}]},
     "0[0].cam_R_m2c: not a rotation matrix"),
    (read_scene_gt, {"0": [{"cam_R_m2c": np.eye(3).ravel().tolist(), "obj_id": 1}]},
     "0[0].cam_t_m2c: missing field"),
    (read_scene_gt, {"0": {"obj_id": 1}}, "0: expected a list"),
    (read_scene_gt_info, {"0": [{"visib_fract": 2.0}]}, "0[0].visib_fract: expected a fraction"),
    (read_models_info, {"1": {"symmetries_discrete": [[1, 0, 0]]}},
     "1.symmetries_discrete[0]: expected shape (16,), got (3,)"),
    (read_models_info, {"1": {"symmetries_continuous": [{"offset": [0, 0, 0]}]}},
     "1.symmetries_continuous[0].axis: missing field"),
    (read_models_info, {"diameter": "big"}, "diameter: expected a finite number"),
    (read_test_targets, [{"im_id": 1, "obj_id": 2, "scene_id": 3}], "[0].inst_count: missing field"),
    (read_test_targets, {"a": 1}, "top level: expected a list"),
])
def test_malformed_inputs_name_file_and_field(tmp_path, reader, data, message):
    path = _dump(tmp_path / "file.json", data)
    with pytest.raises(InputFileError) as err:
        reader(path)
    assert str(err.value).startswith(f"{path}: ")
    assert message in str(err.value)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(InputFileError, match="scene_gt file not found"):
        read_scene_gt(tmp_path / "scene_gt.json")
    (tmp_path / "scene_camera.json").write_text("{")
    with pytest.raises(InputFileError, match="malformed JSON"):
        read_scene_camera(tmp_path / "scene_camera.json")
    with pytest.raises(InputFileError, match="split folder not found"):
        list(iter_bop_split(tmp_path / "nope"))
