"""Each object's own score threshold: the F1 choice, its record in checkpoints and ONNX files,
the predictor using it (an explicit min_score still wins), and `dope-hope calibrate`."""
from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from test_multi_object_model import K640, POSES, MultiTargetsBackend, lite_config, objects, white

from dope_hope import cli
from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.evaluation.thresholds import best_f1_threshold
from dope_hope.export.pipeline import export_checkpoint
from dope_hope.inference.onnx_backend import OnnxBackend
from dope_hope.inference.predictor import DopePredictor
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_rgb
from dope_hope.io.predictions import prediction_record, write_predictions_jsonl
from dope_hope.model.checkpoint import load_checkpoint, save_checkpoint, save_inference_checkpoint
from dope_hope.model.info import ModelInfo, ObjectInfo
from dope_hope.model.network import build_model

torch.set_num_threads(1)


def test_the_threshold_of_highest_f1_is_chosen_and_ties_go_to_the_higher_one():
    # three of four instances found at >= 0.35; 0.3 and 0.2 are false detections
    c = best_f1_threshold("Can", np.array([0.9, 0.8, 0.35, 0.3, 0.2]), np.array([1, 1, 1, 0, 0], bool), 4)
    assert (c.min_score, c.true, c.false, c.missed, c.instances) == (0.35, 3, 0, 1, 4)
    assert math.isclose(c.f1, 6 / 7)
    # every threshold up to 0.9 keeps the one true estimate: the highest wins
    assert best_f1_threshold("Can", np.array([0.9]), np.array([True]), 1).min_score == 0.9
    # nothing estimated: F1 0 everywhere, the highest candidate
    none = best_f1_threshold("Can", np.zeros(0), np.zeros(0, bool), 3)
    assert none.f1 == 0.0 and none.missed == 3 and none.min_score == 0.95


def test_the_predictor_uses_each_objects_own_threshold_unless_one_is_given():
    backend = MultiTargetsBackend(("Ketchup", "Mustard"), POSES)
    ketchup, mustard = backend.info.objects
    # Mustard's own threshold above any score (perfect maps score 1): its detections dropped
    backend.info.objects = (ketchup, ObjectInfo(mustard.class_name, mustard.size_m, min_score=1.01))
    p = DopePredictor(backend, height=400)
    assert [o.min_score for o in p.objects] == [0.5, 1.01]
    assert {d.class_name for d in p.predict(white(), K640)} == {"Ketchup"}
    given = DopePredictor(backend, height=400, min_score=0.4)
    assert [o.min_score for o in given.objects] == [0.4, 0.4]
    assert sorted(d.class_name for d in given.predict(white(), K640)) == ["Ketchup", "Mustard", "Mustard"]


@pytest.fixture(scope="module")
def two_objects(tmp_path_factory) -> Path:
    torch.manual_seed(2)
    cfg = lite_config(2)
    return save_checkpoint(tmp_path_factory.mktemp("thr") / "two.pt", build_model(cfg), cfg, objects(2))


def test_thresholds_are_recorded_in_the_checkpoint_and_its_onnx_export(two_objects, tmp_path):
    out = save_inference_checkpoint(two_objects, tmp_path / "cal.pt", object_min_scores={"Mustard": 0.3})
    info = ModelInfo.from_checkpoint(load_checkpoint(out), out)
    assert [o.min_score for o in info.objects] == [None, 0.3] and info.min_score is None
    export_checkpoint(out, tmp_path / "cal.onnx")
    assert [o.min_score for o in OnnxBackend(tmp_path / "cal.onnx").info.objects] == [None, 0.3]
    with pytest.raises(ConfigError, match="'Soup' is not an object of"):
        save_inference_checkpoint(two_objects, tmp_path / "bad.pt", object_min_scores={"Soup": 0.3})
    assert not (tmp_path / "bad.pt").exists()
    ckpt = load_checkpoint(out)
    ckpt["objects"][1]["min_score"] = float("nan")
    with pytest.raises(ModelFileError, match=r"objects\[1\]\.min_score must be a finite number >= 0"):
        ModelInfo.from_checkpoint(ckpt, out)


K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
GT = {0: [("Ketchup", [0.1, 0.0, 0.7]), ("Mustard", [-0.1, 0.05, 0.8])],
      1: [("Ketchup", [-0.05, 0.02, 0.6]), ("Mustard", [0.12, -0.03, 0.9])]}
R0 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()


def write_frames(folder: Path) -> Path:
    folder.mkdir(parents=True)
    for k, objs in GT.items():
        write_rgb(folder / f"{k:06d}.png", np.zeros((480, 640, 3), np.uint8))
        anns = [ObjectAnnotation(c, R0, np.array(t)) for c, t in objs]
        write_dope_json(folder / f"{k:06d}.json", FrameAnnotation(folder / f"{k:06d}.json", K, 640, 480, anns))
    return folder


def estimate(frame: int, i: int, score: float, shift=(0.0, 0.0, 0.0)) -> dict:
    c, t = GT[frame][i]
    return prediction_record(f"{frame:06d}.png", c, score, R0, np.array(t) + np.array(shift))


def _cli(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


def test_calibrate_records_each_objects_f1_threshold(two_objects, tmp_path):
    data = write_frames(tmp_path / "calib")
    preds = tmp_path / "preds.jsonl"
    write_predictions_jsonl(preds, [
        estimate(0, 0, 0.9), estimate(1, 0, 0.8), estimate(1, 0, 0.3, shift=(0.3, 0, 0)),   # Ketchup: false at 0.3
        estimate(0, 1, 0.3), estimate(1, 1, 0.25), estimate(0, 1, 0.2, shift=(0, 0.4, 0)),  # Mustard scores low
    ])
    out = tmp_path / "cal.pt"
    rc, text, err = _cli(["calibrate", "-p", preds, "-d", data, "--weights", two_objects, "--out", out,
                          "--no-progress"])
    assert rc == 0, err
    assert "| Ketchup | **0.8** | 2 / 0 / 0 of 2 | 1.000 | 0.5: 2 / 0 / 0, 1.000 |" in text
    assert "| Mustard | **0.25** | 2 / 0 / 0 of 2 | 1.000 | 0.5: 0 / 0 / 2, 0.000 |" in text
    assert [o.min_score for o in DopePredictor(out).objects] == [0.8, 0.25]
    assert [o.min_score for o in DopePredictor(out, min_score=0.4).objects] == [0.4, 0.4]
    rc, _, err = _cli(["infer", data / "000000.png", "--weights", out, "--no-overlay", "--out", tmp_path / "res"])
    assert rc == 0 and "min score Ketchup 0.8, Mustard 0.25, the model's own" in err, err

    # an object with no estimate keeps its threshold, and says so
    write_predictions_jsonl(tmp_path / "ketchup.jsonl", [estimate(0, 0, 0.9)])
    rc, text, err = _cli(["calibrate", "-p", tmp_path / "ketchup.jsonl", "-d", data, "--weights", two_objects,
                          "--out", tmp_path / "ketchup.pt", "--no-progress"])
    assert rc == 0, err
    assert "Mustard: no estimate on" in text and "its threshold stays 0.5" in text
    info = ModelInfo.from_checkpoint(load_checkpoint(tmp_path / "ketchup.pt"))
    assert [o.min_score for o in info.objects] == [0.9, None]

    # an object whose estimates are all false keeps its threshold too
    write_predictions_jsonl(tmp_path / "false.jsonl", [estimate(0, 0, 0.9), estimate(0, 1, 0.7, shift=(0, 0.5, 0))])
    rc, text, err = _cli(["calibrate", "-p", tmp_path / "false.jsonl", "-d", data, "--weights", two_objects,
                          "--out", tmp_path / "false.pt", "--no-progress"])
    assert rc == 0 and "Mustard: none of its 1 estimates is within 10 cm of an instance" in text, err
    assert [o.min_score for o in ModelInfo.from_checkpoint(load_checkpoint(tmp_path / "false.pt")).objects] == [0.9, None]

    # frames without a Mustard: a flag naming it (one command line for several calibrations) is no mistake
    only = tmp_path / "only_ketchup"
    only.mkdir()
    for k in GT:
        write_rgb(only / f"{k:06d}.png", np.zeros((480, 640, 3), np.uint8))
        ann = ObjectAnnotation("Ketchup", R0, np.array(GT[k][0][1]))
        write_dope_json(only / f"{k:06d}.json", FrameAnnotation(only / f"{k:06d}.json", K, 640, 480, [ann]))
    rc, text, err = _cli(["calibrate", "-p", preds, "-d", only, "--weights", two_objects, "--out", tmp_path / "k.pt",
                          "--mesh-units", "Mustard=cm", "--no-progress"])
    assert rc == 0 and "Mustard: no labelled instance in" in text, err

    # mistakes: one line, exit status 2, nothing written
    write_predictions_jsonl(tmp_path / "soup.jsonl", [prediction_record("000000.png", "Soup", 0.9, R0, [0, 0, 1.0])])
    for argv, message in [
        (["-p", tmp_path / "soup.jsonl", "-d", data, "--weights", two_objects, "--out", tmp_path / "x.pt"],
         "no estimate of Ketchup, Mustard (the objects of"),
        (["-p", preds, "-d", data, "--weights", two_objects, "--out", tmp_path / "x.onnx"],
         "give a checkpoint (.pt)"),
        (["-p", preds, "-d", data, "--weights", two_objects, "--out", tmp_path / "x.pt", "--within-cm", "0"],
         "--within-cm must be a positive distance"),
        (["-p", preds, "-d", data, "--weights", two_objects, "--out", two_objects], "is --weights"),
    ]:
        rc, _, err = _cli(["calibrate", *argv])
        assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "x.pt").exists() and not (tmp_path / "x.onnx").exists()
