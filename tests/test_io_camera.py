"""Camera intrinsics from camera files (every accepted form) and from sibling annotations."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dope_hope.annotation import FrameAnnotation
from dope_hope.errors import InputFileError
from dope_hope.geometry import intrinsics_matrix
from dope_hope.io.camera import find_image_camera, read_camera_file
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_depth_mm, write_rgb

K = intrinsics_matrix(615.0, 612.5, 320.25, 239.75)
INTR = {"fx": 615.0, "fy": 612.5, "cx": 320.25, "cy": 239.75}


@pytest.mark.parametrize("doc", [
    dict(INTR, width=640, height=480),
    {"K": K.tolist(), "width": 640, "height": 480},
    {"K": K.ravel().tolist()},
    {"cam_K": K.ravel().tolist(), "depth_scale": 1.0},
    {"camera_data": {"intrinsics": INTR, "width": 640, "height": 480}},
    {"intrinsics": INTR},
    {"camera": {"intrinsics": K.tolist(), "width": 640, "height": 480}},
    {"camera_settings": [{"intrinsic_settings": INTR,
                          "captured_image_size": {"width": 640, "height": 480}}]},
])
def test_camera_file_forms(tmp_path, doc):
    path = tmp_path / "K.json"
    path.write_text(json.dumps(doc))
    cam = read_camera_file(path)
    np.testing.assert_allclose(cam.K, K)
    if "width" in json.dumps(doc):
        assert (cam.width, cam.height) == (640, 480)
        with pytest.raises(InputFileError, match="640x480.*320x240"):
            cam.check_size("img.png", 320, 240)
    cam.check_size("img.png", 640, 480)


@pytest.mark.parametrize("doc,problem", [
    ({"fx": 1, "fy": 1, "cx": 0}, "no camera intrinsics"),
    ({"K": [[1, 0], [0, 1]]}, "3x3 matrix or 9 numbers"),
    ({"fx": -5, "fy": 5, "cx": 0, "cy": 0}, "fx, fy > 0"),
    ({"K": [1, 0, 0, 0, 1, 0, 0, 0, 2]}, "fx, fy > 0"),
    ({"fx": "a", "fy": 5, "cx": 0, "cy": 0}, "finite number"),
    ([1, 2, 3], "expected a JSON object"),
])
def test_bad_camera_files_name_the_problem(tmp_path, doc, problem):
    path = tmp_path / "K.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=problem) as info:
        read_camera_file(path)
    assert "K.json" in str(info.value)


def test_dope_sibling_with_depth(tmp_path):
    write_rgb(tmp_path / "000007.png", np.zeros((480, 640, 3), np.uint8))
    write_depth_mm(tmp_path / "000007.depth.png", np.ones((480, 640)))
    write_dope_json(tmp_path / "000007.json", FrameAnnotation(source=tmp_path / "000007.json", K=K,
                                                              width=640, height=480, objects=[]))
    cam = find_image_camera(tmp_path / "000007.png")
    np.testing.assert_allclose(cam.K, K)
    assert cam.depth_path == tmp_path / "000007.depth.png" and cam.depth_scale_m == 0.001
    assert (cam.width, cam.height) == (640, 480) and cam.source.name == "000007.json"


def test_hope_sibling(tmp_path):
    write_rgb(tmp_path / "0003_rgb.jpg", np.zeros((48, 64, 3), np.uint8))
    write_depth_mm(tmp_path / "0003_depth.png", np.ones((48, 64)))
    (tmp_path / "0003.json").write_text(json.dumps(
        {"camera": {"intrinsics": K.tolist(), "width": 64, "height": 48}, "objects": []}))
    cam = find_image_camera(tmp_path / "0003_rgb.jpg")
    np.testing.assert_allclose(cam.K, K)
    assert cam.depth_path == tmp_path / "0003_depth.png" and cam.source.name == "0003.json"


def test_bop_scene_camera_two_levels_up(tmp_path):
    scene = tmp_path / "val" / "000002"
    write_rgb(scene / "rgb" / "000005.png", np.zeros((48, 64, 3), np.uint8))
    write_depth_mm(scene / "depth" / "000005.png", np.ones((48, 64)))
    (scene / "scene_camera.json").write_text(json.dumps(
        {"5": {"cam_K": K.ravel().tolist(), "depth_scale": 0.1},
         "6": {"cam_K": (2 * K).ravel().tolist(), "depth_scale": 1.0}}))
    cam = find_image_camera(scene / "rgb" / "000005.png")
    np.testing.assert_allclose(cam.K, K)
    assert cam.depth_path == scene / "depth" / "000005.png"
    assert cam.depth_scale_m == pytest.approx(0.0001)
    write_rgb(scene / "rgb" / "000009.png", np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(InputFileError, match="no entry for image 9"):
        find_image_camera(scene / "rgb" / "000009.png")


def test_no_annotation_means_no_camera(tmp_path):
    write_rgb(tmp_path / "photo.png", np.zeros((8, 8, 3), np.uint8))
    assert find_image_camera(tmp_path / "photo.png") is None
    (tmp_path / "photo.json").write_text("{not json")
    with pytest.raises(InputFileError, match="photo.json"):
        find_image_camera(tmp_path / "photo.png")


# ----------------------------------------------------------------------------- ROS camera_info
P_RECT = np.array([[590.0, 0.0, 321.0, 0.0], [0.0, 596.0, 241.5, 0.0], [0.0, 0.0, 1.0, 0.0]])


def ost_yaml(D=(0.0, 0.0, 0.0, 0.0, 0.0), model="plumb_bob", P=P_RECT) -> str:
    """A camera_calibration ``ost.yaml`` (the file `cameracalibrator` saves)."""
    def block(rows, cols, data):
        return f"  rows: {rows}\n  cols: {cols}\n  data: [{', '.join(repr(float(v)) for v in np.ravel(data))}]\n"

    return ("image_width: 640\nimage_height: 480\ncamera_name: narrow_stereo\n"
            f"camera_matrix:\n{block(3, 3, K)}distortion_model: {model}\n"
            f"distortion_coefficients:\n{block(1, len(D), D)}"
            f"rectification_matrix:\n{block(3, 3, np.eye(3))}projection_matrix:\n{block(3, 4, P)}")


def test_ros_calibration_yaml_without_distortion_is_camera_matrix(tmp_path):
    path = tmp_path / "ost.yaml"
    path.write_text(ost_yaml())
    cam = read_camera_file(path)
    np.testing.assert_allclose(cam.K, K)  # raw frames: camera_matrix (not P) when D = 0
    assert (cam.width, cam.height) == (640, 480) and cam.rectification is None
    with pytest.raises(InputFileError, match="640x480"):
        cam.check_size("img.png", 320, 240)


@pytest.mark.parametrize("keys", [("K", "D", "R", "P", "width", "height"), ("k", "d", "r", "p", "width", "height")])
def test_ros_camera_info_message_yaml(tmp_path, keys):
    """`rostopic echo -n 1 /camera/color/camera_info` (ROS 1) and `ros2 topic echo` (ROS 2)."""
    k, d, r, p, w, h = keys
    doc = (f"header:\n  frame_id: camera_color_optical_frame\n{h}: 480\n{w}: 640\ndistortion_model: plumb_bob\n"
           f"{d}: [0.0, 0.0, 0.0, 0.0, 0.0]\n{k}: {K.ravel().tolist()}\n{r}: {np.eye(3).ravel().tolist()}\n"
           f"{p}: {P_RECT.ravel().tolist()}\n")
    path = tmp_path / "info.yml"
    path.write_text(doc)
    cam = read_camera_file(path)
    np.testing.assert_allclose(cam.K, K)
    assert (cam.width, cam.height) == (640, 480)


def test_ros_distortion_is_removed_as_image_proc_does(tmp_path):
    import cv2

    D = np.array([-0.28, 0.09, 0.001, -0.0005, 0.0])
    path = tmp_path / "ost.yaml"
    path.write_text(ost_yaml(D))
    cam = read_camera_file(path)
    np.testing.assert_allclose(cam.K, P_RECT[:, :3])  # rectified frames: P's left 3x3
    rect = cam.rectification
    # A raw image whose value is a linear function of the raw pixel position: after
    # rectification, pixel (u, v) must hold the value at the raw position its ray projects to.
    yy, xx = np.mgrid[0:480, 0:640].astype(np.float32)
    raw = np.dstack([xx, yy, np.zeros_like(xx)])
    out = rect.image(raw)
    for u, v in ((100, 80), (320, 240), (600, 400), (30, 450)):
        ray = np.linalg.solve(P_RECT[:, :3], [u, v, 1.0])
        expected, _ = cv2.projectPoints(ray[None], np.zeros(3), np.zeros(3), K, D)
        np.testing.assert_allclose(out[v, u, :2], expected.ravel(), atol=0.02)
    depth = np.full((480, 640), 0.7, np.float32)
    depth[:, 320:] = 0.9
    rd = rect.depth(depth)
    assert set(np.unique(rd)) <= {0.0, np.float32(0.7), np.float32(0.9)}  # nearest: no mixed depths


@pytest.mark.parametrize("doc,problem", [
    (ost_yaml((0.1, 0.01, 0.0, 0.0), model="equidistant"), "distortion_model: 'equidistant' is not supported"),
    (ost_yaml((0.1, 0.01, 0.0)), "distortion_coefficients: expected 4, 5, 8, 12 or 14 coefficients, got 3"),
    ("camera_matrix:\n  data: [1, 0, 0, 0, 1, 0, 0, 1]\n", "camera_matrix: expected 3x3 = 9 numbers, got 8"),
    ("camera_matrix: [1, 2\n  x: ]\n", "malformed YAML (line 2"),
    ("- 1\n- 2\n", "expected a YAML mapping"),
    ("image_width: 640\nD: [0.1, 0, 0, 0, 0]\n", "camera_matrix: missing field"),
])
def test_bad_ros_camera_info_names_the_problem(tmp_path, doc, problem):
    path = tmp_path / "cam.yaml"
    path.write_text(doc)
    with pytest.raises(InputFileError, match=problem.replace("(", r"\(").replace("[", r"\[")) as info:
        read_camera_file(path)
    assert "cam.yaml" in str(info.value)
