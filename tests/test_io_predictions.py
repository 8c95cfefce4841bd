"""Predictions JSON lines (what `dope-hope infer` prints, what `evaluate` reads)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dope_hope.errors import InputFileError
from dope_hope.geometry import matrix_to_quaternion_xyzw
from dope_hope.io.bop_csv import BopEstimate, write_bop_csv
from dope_hope.io.predictions import (
    prediction_record,
    read_predictions,
    write_predictions_jsonl,
)


def test_round_trip_with_metadata_and_extra_keys(tmp_path):
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    recs = [prediction_record("000001.png", "Ketchup", 0.9, R, [0.01, 0.02, 0.5], ls_applied=True,
                              keypoints=np.zeros((9, 2))),
            prediction_record("000002.png", "Mustard", 0.4, np.eye(3), [0, 0, 1])]
    path = tmp_path / "p.jsonl"
    write_predictions_jsonl(path, recs, method="lite")
    preds, meta = read_predictions(path)
    assert meta["method"] == "lite"
    assert [p.class_name for p in preds] == ["Ketchup", "Mustard"]
    np.testing.assert_allclose(preds[0].R, R, atol=1e-12)
    np.testing.assert_allclose(preds[0].t, [0.01, 0.02, 0.5])
    assert preds[0].ls_applied is True and preds[1].ls_applied is None
    assert preds[0].extra["keypoints"] == np.zeros((9, 2)).tolist()
    assert preds[1].line == 3


def test_quaternion_obj_id_flat_r_comments_and_blank_lines(tmp_path):
    R = Rotation.from_euler("y", 40, degrees=True).as_matrix()
    lines = ["# produced by hand", "",
             json.dumps({"image": "a.png", "obj_id": 11, "score": 1,
                         "quaternion_xyzw": matrix_to_quaternion_xyzw(R).tolist(), "t": [0, 0, 1]}),
             json.dumps({"scene_id": 1, "im_id": 5, "class": "Milk", "score": 0.5,
                         "R": R.ravel().tolist(), "t": [0, 0, 1], "time": 0.2})]
    path = tmp_path / "p.jsonl"
    path.write_text("\n".join(lines))
    preds, _ = read_predictions(path)
    assert preds[0].class_name == "Ketchup"  # BOP obj_id 11
    np.testing.assert_allclose(preds[0].R, R, atol=1e-12)
    np.testing.assert_allclose(preds[1].R, R, atol=1e-12)
    assert (preds[1].scene_id, preds[1].im_id, preds[1].time) == (1, 5, 0.2)


@pytest.mark.parametrize("obj,problem", [
    ({"class": "Ketchup", "score": 1, "R": np.eye(3).tolist(), "t": [0, 0, 1]}, "missing field 'image'"),
    ({"image": "a", "score": 1, "R": np.eye(3).tolist(), "t": [0, 0, 1]}, "missing field 'class'"),
    ({"image": "a", "class": "K", "score": "x", "R": np.eye(3).tolist(), "t": [0, 0, 1]}, "score"),
    ({"image": "a", "class": "K", "score": 1, "t": [0, 0, 1]}, "missing field 'R'"),
    ({"image": "a", "class": "K", "score": 1, "R": (2 * np.eye(3)).tolist(), "t": [0, 0, 1]}, "R: not a rotation"),
    ({"image": "a", "class": "K", "score": 1, "R": np.eye(3).tolist(), "t": [0, 1]}, "t: expected 3"),
    ({"image": "a", "class": "K", "score": 1, "R": np.eye(3).tolist()}, "missing field 't'"),
])
def test_bad_lines_are_named(tmp_path, obj, problem):
    path = tmp_path / "p.jsonl"
    path.write_text(json.dumps({"format": "dope-hope-predictions"}) + "\n" + json.dumps(obj) + "\n")
    with pytest.raises(InputFileError, match=f"line 2: {problem}"):
        read_predictions(path)


def test_malformed_json_and_missing_file(tmp_path):
    path = tmp_path / "p.jsonl"
    path.write_text("{not json\n")
    with pytest.raises(InputFileError, match="line 1: malformed JSON"):
        read_predictions(path)
    with pytest.raises(InputFileError, match="not found"):
        read_predictions(tmp_path / "none.jsonl")


def test_bop_csv_is_read_with_class_names_and_method(tmp_path):
    path = tmp_path / "mine_hope-test.csv"
    write_bop_csv(path, [BopEstimate(3, 7, 14, 0.8, np.eye(3), np.array([0.0, 0.1, 0.9]), 0.5)])
    preds, meta = read_predictions(path)
    assert meta["method"] == "mine"
    assert preds[0].class_name == "Milk" and preds[0].image is None
    assert (preds[0].scene_id, preds[0].im_id) == (3, 7)
    np.testing.assert_allclose(preds[0].t, [0.0, 0.1, 0.9])


def _official_output(folder, objects_by_image: dict) -> None:
    """Files as NVlabs inference/inference.py writes them: OUTF/<weights>/<sub>/<stem>.json."""
    for rel, objs in objects_by_image.items():
        path = folder / f"{rel}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"camera_data": {}, "objects": objs}, indent=2))


def test_official_dope_inference_output_folder(tmp_path):
    R_leg = Rotation.from_euler("xyz", [10, -70, 35], degrees=True).as_matrix()
    q = Rotation.from_matrix(R_leg).as_quat().tolist()
    folder = tmp_path / "output" / "net_Ketchup_0060"
    _official_output(folder, {
        "scene_a/000001": [{"class": "ketchup", "location": [1.0, -2.0, 60.0], "quaternion_xyzw": q,
                            "projected_cuboid": [[0.0, 0.0]] * 9}],
        "scene_a/000002": [],
        "000003": [{"class": "Widget", "location": [0.0, 0.0, 50.0], "quaternion_xyzw": [0, 0, 0, 1],
                    "confidence": 0.4}]})
    preds, meta = read_predictions(folder)
    assert meta == {"method": "net_Ketchup_0060"}
    assert [(p.image, p.class_name, p.score, p.origin) for p in preds] == [
        ("000003", "Widget", 0.4, "cuboid"), ("scene_a/000001", "Ketchup", 1.0, "cuboid")]
    np.testing.assert_allclose(preds[1].t, [0.01, -0.02, 0.6])
    # legacy frame -> mesh frame: what NVlabs evaluate/evaluate.py does to every prediction,
    # quat * angleAxis(90 deg, x) * angleAxis(90 deg, z)
    official = R_leg @ Rotation.from_euler("x", 90, degrees=True).as_matrix() \
        @ Rotation.from_euler("z", 90, degrees=True).as_matrix()
    np.testing.assert_allclose(preds[1].R, official, atol=1e-12)
    as_is, _ = read_predictions(folder, official_frame="cuboid")
    np.testing.assert_allclose(as_is[1].R, R_leg, atol=1e-12)
    _official_output(folder, {"bad": [{"class": "Ketchup", "location": [0, 0, 1], "quaternion_xyzw": [0, 0, 0, 0]}]})
    with pytest.raises(InputFileError, match=r"bad.json: objects\[0\]\.quaternion_xyzw: zero quaternion"):
        read_predictions(folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputFileError, match="no .json files"):
        read_predictions(tmp_path / "empty")
