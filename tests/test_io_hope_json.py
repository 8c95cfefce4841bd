"""dope_hope.io.hope_json on HOPE-Image-style files synthesized here (no sample is shipped)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from json_edit import with_field
from scipy.spatial.transform import Rotation

from dope_hope.errors import InputFileError
from dope_hope.io.hope_json import list_hope_frames, read_hope_json

K = [[1390.53, 0.0, 964.957], [0.0, 1386.99, 522.586], [0.0, 0.0, 1.0]]
R1 = Rotation.from_euler("xyz", [10, -35, 120], degrees=True).as_matrix()


def _pose(R, t_cm):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t_cm
    return T.tolist()


def _doc() -> dict:
    return {"camera": {"intrinsics": K, "width": 1920, "height": 1080,
                       "extrinsics": np.eye(4).tolist()},
            "objects": [{"class": "Ketchup", "pose": _pose(R1, [3.5, -7.25, 64.0])},
                        {"class": "Mayo", "pose": _pose(np.eye(3), [0.0, 0.0, 100.0])}]}


def _write(folder: Path, doc: dict, name: str = "0003") -> Path:
    path = folder / f"{name}.json"
    path.write_text(json.dumps(doc))
    return path


def test_values_in_metres_with_siblings(tmp_path):
    path = _write(tmp_path, _doc())
    (tmp_path / "0003_rgb.jpg").write_bytes(b"")
    (tmp_path / "0003_depth.png").write_bytes(b"")
    fr = read_hope_json(path)
    np.testing.assert_allclose(fr.K, K)
    assert (fr.width, fr.height) == (1920, 1080)
    assert fr.source == path
    assert fr.image_path == tmp_path / "0003_rgb.jpg"
    assert fr.depth_path == tmp_path / "0003_depth.png"
    assert fr.depth_scale_m == 0.001
    assert [o.class_name for o in fr.objects] == ["Ketchup", "Mayo"]
    np.testing.assert_allclose(fr.objects[0].R, R1, atol=1e-12)
    np.testing.assert_allclose(fr.objects[0].t, [0.035, -0.0725, 0.64])  # cm -> m
    np.testing.assert_allclose(fr.objects[1].t, [0.0, 0.0, 1.0])
    assert fr.objects[0].projected_cuboid is None and fr.objects[0].visibility is None


def test_missing_siblings_are_none(tmp_path):
    fr = read_hope_json(_write(tmp_path, _doc()))
    assert fr.image_path is None and fr.depth_path is None


@pytest.mark.parametrize("where, key, value, expected", [
    ("top", "depth_scale", 0.1, 1e-4),          # BOP convention: mm per unit
    ("camera", "depth_scale", 1.0, 1e-3),
    ("top", "depth_scale_m", 0.00025, 0.00025),  # explicit metres per unit
])
def test_depth_scale_from_file(tmp_path, where, key, value, expected):
    doc = _doc()
    (doc if where == "top" else doc["camera"])[key] = value
    assert read_hope_json(_write(tmp_path, doc)).depth_scale_m == pytest.approx(expected)


def test_nearly_orthonormal_pose_is_cleaned(tmp_path):
    doc = _doc()
    pose = np.array(doc["objects"][0]["pose"])
    pose[:3, :3] = np.round(pose[:3, :3], 5)  # files store rounded numbers
    doc["objects"][0]["pose"] = pose.tolist()
    R = read_hope_json(_write(tmp_path, doc)).objects[0].R
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R, R1, atol=1e-4)


@pytest.mark.parametrize("dotted, value, message", [
    ("camera", KeyError, "camera: missing field"),
    ("camera.intrinsics", KeyError, "camera.intrinsics: missing field"),
    ("camera.intrinsics", [[1, 0, 0], [0, 1, 0]], "camera.intrinsics: expected 3 rows, got 2"),
    ("camera.intrinsics", [[0, 0, 5], [0, 1, 5], [0, 0, 1]], "camera.intrinsics: expected [[fx"),
    ("camera.width", 0, "camera.width: expected a positive integer"),
    ("objects.1.pose", KeyError, "objects[1].pose: missing field"),
    ("objects.1.pose", np.eye(3).tolist(), "objects[1].pose: expected 4 rows, got 3"),
    ("objects.0.pose.3", [1, 2, 3, 1], "objects[0].pose: bottom row must be [0, 0, 0, 1]"),
    ("objects.0.pose.0", [2, 0, 0, 0], "objects[0].pose: the 3x3 block is not a rotation"),
    ("objects.0.class", 5, "objects[0].class: expected a non-empty string"),
    ("objects", "all", "objects: expected a list"),
    ("depth_scale", -1, "depth_scale: must be positive"),
])
def test_malformed_inputs_name_file_and_field(tmp_path, dotted, value, message):
    path = _write(tmp_path, with_field(_doc(), dotted, value))
    with pytest.raises(InputFileError) as err:
        read_hope_json(path)
    assert str(err.value).startswith(f"{path}: ")
    assert message in str(err.value)


@pytest.mark.parametrize("content, message", [(None, "not found"), ("{", "malformed JSON")])
def test_unreadable_file(tmp_path, content, message):
    path = tmp_path / "0000.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(InputFileError, match=message):
        read_hope_json(path)


def test_list_hope_frames(tmp_path):
    for name in ("0001.json", "0001_rgb.jpg", "0000.json", "0000_rgb.png", "0002.json",
                 "0002_depth.png"):
        (tmp_path / name).write_bytes(b"")
    assert list_hope_frames(tmp_path) == [tmp_path / "0000.json", tmp_path / "0001.json"]
    with pytest.raises(InputFileError):
        list_hope_frames(tmp_path / "missing")
