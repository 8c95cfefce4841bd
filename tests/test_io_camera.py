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
