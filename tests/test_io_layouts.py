"""dope_hope.io.layouts: one layout detector for infer (an image's camera) and evaluate (a folder)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dope_hope.errors import InputFileError
from dope_hope.evaluation.datasets import load_dataset
from dope_hope.io.camera import find_image_camera
from dope_hope.io.layouts import annotation_file, dataset_layout, image_layout

K = [[615.0, 0.0, 319.5], [0.0, 615.0, 239.5], [0.0, 0.0, 1.0]]


def _hope_folder(root):
    """One HOPE-Image-style frame: 0000_rgb.png + 0000.json (Ketchup 64 cm away)."""
    scene = root / "scene_0000"
    scene.mkdir(parents=True)
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 64.0]  # cm
    (scene / "0000.json").write_text(json.dumps({
        "camera": {"intrinsics": K, "width": 640, "height": 480, "extrinsics": np.eye(4).tolist()},
        "objects": [{"class": "Ketchup", "pose": pose.tolist()}]}))
    (scene / "0000_rgb.png").write_bytes(b"")
    return scene


def test_a_hope_folder_is_recognised_by_infer_and_evaluate_alike(tmp_path):
    scene = _hope_folder(tmp_path / "hope")
    image = scene / "0000_rgb.png"
    assert image_layout(image) == "hope" and annotation_file(image, "hope") == scene / "0000.json"
    assert find_image_camera(image).source == scene / "0000.json"  # infer's camera lookup
    assert dataset_layout(tmp_path / "hope") == "hope"
    ds = load_dataset(tmp_path / "hope")  # evaluate's default: auto
    assert ds.fmt == "hope" and len(ds.frames) == 1 and ds.frames[0].objects[0].class_name == "Ketchup"


def test_dope_and_bop_layouts_and_nothing(tmp_path):
    (tmp_path / "dope").mkdir()
    (tmp_path / "dope" / "000000.png").write_bytes(b"")
    (tmp_path / "dope" / "000000.depth.png").write_bytes(b"")  # auxiliary: not a frame
    (tmp_path / "dope" / "000000.json").write_text("{}")
    assert dataset_layout(tmp_path / "dope") == "dope"
    rgb = tmp_path / "bop" / "test" / "000001" / "rgb"
    rgb.mkdir(parents=True)
    (rgb / "000000.png").write_bytes(b"")
    (rgb.parent / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": np.ravel(K).tolist()}}))
    assert image_layout(rgb / "000000.png") == "bop"
    assert dataset_layout(tmp_path / "bop") == "bop" and dataset_layout(tmp_path / "bop" / "test") == "bop"
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "photo.jpg").write_bytes(b"")
    with pytest.raises(InputFileError, match="no annotated frames found"):
        dataset_layout(tmp_path / "empty")
    with pytest.raises(ValueError, match="unknown layout"):
        annotation_file(rgb / "000000.png", "ndds")
