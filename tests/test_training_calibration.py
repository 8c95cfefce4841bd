"""A run's end: each object's own score threshold chosen on its validation frames and recorded
in its chosen checkpoint (training/calibration.py), inside the time budget."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from test_multi_object_model import POSES, MultiTargetsBackend, lite_config, objects
from test_training_trainer import TINY, write_frames

from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.cli import main
from dope_hope.config import load_config
from dope_hope.geometry import KEYPOINT_ORDER, cuboid_keypoints, project_points
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_rgb
from dope_hope.model.checkpoint import load_checkpoint, save_checkpoint
from dope_hope.model.info import ModelInfo
from dope_hope.model.network import build_model
from dope_hope.training.budget import BudgetPlan
from dope_hope.training.calibration import calibrate_run
from dope_hope.training.objects import run_objects
from dope_hope.training.settings import TrainJob
from dope_hope.training.sources import scan_training_data
from dope_hope.training.trainer import train

torch.set_num_threads(1)
K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])


def _frames(folder: Path, ketchup_moved: bool) -> None:
    """Two 640x480 frames holding the instances of POSES (Ketchup's moved 30 cm in the second
    when ``ketchup_moved``: an estimate there is false)."""
    from dope_hope.catalog import get_object

    folder.mkdir(parents=True)
    for k in range(2):
        anns = []
        for name, poses in POSES.items():
            for R, t in poses:
                t = t + (np.array([0.3, 0, 0]) if ketchup_moved and k == 1 and name == "Ketchup" else 0)
                kp = project_points(cuboid_keypoints(get_object(name).size_array), K, R, t)
                anns.append(ObjectAnnotation(name.lower() if k else name, R, t, kp, 1.0))
        write_rgb(folder / f"{k:06d}.png", np.zeros((480, 640, 3), np.uint8))
        write_dope_json(folder / f"{k:06d}.json", FrameAnnotation(folder / f"{k:06d}.json", K, 640, 480, anns))


def test_the_chosen_checkpoint_records_each_objects_threshold(tmp_path, monkeypatch, caplog):
    # a network whose maps are those of POSES, in every frame: each of its estimates scores ~1
    backend = MultiTargetsBackend(("Ketchup", "Mustard"), POSES)
    monkeypatch.setattr("dope_hope.inference.predictor.open_backend", lambda *a, **kw: backend)
    torch.manual_seed(0)
    cfg = lite_config(2)
    weights = save_checkpoint(tmp_path / "best.pt", build_model(cfg), cfg, objects(2))
    data = tmp_path / "val"
    _frames(data, ketchup_moved=True)
    job = TrainJob([data], "Ketchup", tmp_path, objects=["Ketchup", "Mustard"], progress=False)
    records, _ = scan_training_data([data], job.class_names, KEYPOINT_ORDER)
    caplog.set_level(logging.INFO, logger="dope_hope")
    found = calibrate_run(weights, job, records, run_objects(job, records), min_instances=2)
    # Mustard: every estimate true at every threshold (ties: the highest); Ketchup: one of two true
    assert found["min_scores"] == {"Ketchup": 0.95, "Mustard": 0.95} and found["min_score_frames"] == 2
    assert [o.min_score for o in ModelInfo.from_checkpoint(load_checkpoint(weights)).objects] == [0.95, 0.95]
    assert "Ketchup 0.95 (F1 0.500; 0.5: 0.500)" in caplog.text  # the frames' own spelling, 'ketchup', matched
    assert load_checkpoint(weights)["optimizer"] is None  # the file rewritten as it was, thresholds added


def test_an_object_without_a_true_estimate_keeps_its_threshold(tmp_path, monkeypatch, caplog):
    backend = MultiTargetsBackend(("Ketchup", "Mustard"), {"Mustard": POSES["Mustard"]})  # no Ketchup found
    monkeypatch.setattr("dope_hope.inference.predictor.open_backend", lambda *a, **kw: backend)
    cfg = lite_config(2)
    weights = save_checkpoint(tmp_path / "best.pt", build_model(cfg), cfg, objects(2))
    _frames(tmp_path / "val", ketchup_moved=False)
    job = TrainJob([tmp_path / "val"], "Ketchup", tmp_path, objects=["Ketchup", "Mustard"], progress=False)
    records, _ = scan_training_data(job.data, job.class_names, KEYPOINT_ORDER)
    caplog.set_level(logging.INFO, logger="dope_hope")
    assert calibrate_run(weights, job, records, run_objects(job, records), min_instances=2)["min_scores"] == \
        {"Mustard": 0.95}
    assert "Ketchup: no estimate on the frames; its threshold stays 0.5" in caplog.text
    assert [o.min_score for o in ModelInfo.from_checkpoint(load_checkpoint(weights)).objects] == [None, 0.95]
    # too few instances to choose from (the run's default asks 20): every threshold stays
    assert calibrate_run(weights, job, records, run_objects(job, records))["min_scores"] == {}
    assert "Mustard: 4 labelled instance(s) on the frames, fewer than the 20 a choice needs" in caplog.text


@pytest.mark.parametrize("calibrate", [True, False])
def test_a_run_ends_by_choosing_on_its_validation_frames_unless_told_not_to(tmp_path, calibrate, caplog):
    write_frames(tmp_path / "d", 11)
    overrides = json.loads(json.dumps(TINY))
    overrides["train"].update(steps=3, calibrate_thresholds=calibrate)
    caplog.set_level(logging.INFO, logger="dope_hope")
    summary = train(TrainJob([tmp_path / "d"], "Ketchup", tmp_path / "run", progress=False, overrides=overrides),
                    load_config("lite"))
    assert summary["status"] == "completed"
    if calibrate:  # one bottle to choose on: the threshold stays, and the summary says on what it was chosen
        assert summary["min_scores"] == {} and summary["min_score_frames"] == 1 and summary["calibration_s"] >= 0
        assert "thresholds: Ketchup: 1 labelled instance(s) on the frames, fewer than the 20" in caplog.text
    else:
        assert "min_scores" not in summary and "thresholds:" not in caplog.text


def test_the_budget_keeps_the_thresholds_choice_inside_it():
    plan = BudgetPlan(limit_s=100.0)
    # 1 s steps, a validation of 2 s every 10 steps: the choice's 8 s move the end 8 steps earlier
    free = plan.budget_steps(0, 0.0, 1.0, 2.0, 10)
    kept = plan.budget_steps(0, 0.0, 1.0, 2.0, 10, after_s=8.0)
    assert BudgetPlan.run_cost(0, kept, 1.0, 2.0, 10, after_s=8.0) <= 100.0 * (1 - 0.015)
    assert kept < free and BudgetPlan.run_cost(0, kept + 1, 1.0, 2.0, 10, after_s=8.0) > 100.0 * (1 - 0.015)


def test_the_train_command_says_which_file_records_the_thresholds(tmp_path, monkeypatch, capsys):
    write_frames(tmp_path / "d", 11)
    chosen = {"min_scores": {"Ketchup": 0.35}, "min_scores_file": str(tmp_path / "run" / "best.pt"),
              "min_score_frames": 1, "calibration_s": 0.1}
    monkeypatch.setattr("dope_hope.training.calibration.calibrate_run", lambda *a, **kw: chosen)
    assert main(["train", "--data", str(tmp_path / "d"), "--object", "Ketchup", "--out", str(tmp_path / "run"),
                 "--init", "none", "--steps", "2", "--batch-size", "2", "--workers", "0", "--no-progress",
                 "--set", "input.size=[64,64]", "train.plots=false", "train.threads=1"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("completed: step 2") and out.rstrip().endswith(
        f"each object's own score threshold, chosen on the validation frames, recorded in {tmp_path}/run/best.pt: "
        "Ketchup 0.35"), out
