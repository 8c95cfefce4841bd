"""`dope-hope demo` end to end: scenes rendered, PyTorch and ONNX run, errors printed, overlays,
DOPE frames that `dope-hope infer` reads by itself, the ONNX cache, and the one-line errors.

The checkpoint is a lite network fitted in a few seconds to the first demo scene of SEED
(tests/fitted_model.py; the demo renders exactly that scene again), so the demo has a real
detection to score and to compare between the two backends.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from fitted_model import DEMO_INPUT_HW, fit_demo_checkpoint

from dope_hope import cli
from dope_hope.commands import demo as demo_cmd
from dope_hope.commands import infer as infer_cmd

torch.set_num_threads(1)
SEED = 11


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(argv)
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    return fit_demo_checkpoint(tmp_path_factory.mktemp("demo_ckpt") / "demo_fit.pt", SEED)


@pytest.fixture(scope="module")
def demo_run(ckpt, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("demo") / "demo_out"
    rc, stdout, stderr = _run(["demo", "--scenes", "2", "--seed", str(SEED), "--weights", str(ckpt),
                               "--out", str(out), "--threads", "1"])
    assert rc == 0, stderr
    # what evaluate reads, kept apart from the later run into the same folder
    shutil.copytree(out, out.parent / "first_run", ignore=shutil.ignore_patterns("*.overlay.png", "overview.png", "*.onnx"))
    return out, stdout


def test_demo_prints_errors_summary_and_backend_agreement(demo_run):
    out, stdout = demo_run
    assert f"seed {SEED}" in stdout.splitlines()[0]
    m = re.search(r"^found (\d)/2 scenes with ADD-H < 2 cm \(with -LS; without -LS: (\d)/2; "
                  r"with -LS \+ ICP: (\d)/2\)$", stdout, re.M)
    assert m, stdout
    # Scene 1 is the scene the network was fitted to: detected, scored against its GT, with
    # both the plain PnP and the -LS pose, and the same keypoints from onnxruntime.
    scene1 = stdout.split("[1/2] 000000.png: ", 1)[1].split("[2/2]", 1)[0]
    assert re.match(r"[1-9]\d* detection\(s\)", scene1), scene1
    errors = [float(v) for v in re.findall(r"ADD-H +([\d.]+) cm", scene1)]
    assert len(errors) == 3  # PnP, PnP+LS and +ICP
    assert re.search(r"\+ICP .* OK  \(ICP applied\)", scene1), scene1
    # The errors are against the rendered ground truth: a fitted scene must come out right
    # (this fails if the demo's frames, K, poses or metrics disagree on any convention).
    assert max(errors) < 2.0, scene1
    assert "OK" in scene1 and int(m.group(1)) >= 1 and int(m.group(2)) >= 1 and int(m.group(3)) >= 1
    diff = float(re.search(r"ONNX keypoints within ([\d.]+) px of PyTorch", scene1).group(1))
    assert diff < 0.5
    assert re.search(r"ONNX vs PyTorch: same objects in \d/2 scenes", stdout)


def test_demo_writes_overlays_frames_onnx_and_predictions(demo_run, ckpt):
    from dope_hope.io.dope_json import read_dope_json
    from dope_hope.io.images import read_depth_m, read_rgb
    from dope_hope.io.predictions import read_predictions

    out, _ = demo_run
    for i in range(2):
        img = read_rgb(out / f"{i:06d}.overlay.png")
        assert img.shape == (480, 640, 3)
        frame = read_dope_json(out / "frames" / f"{i:06d}.json")
        assert frame.objects[0].class_name == "DemoBox" and frame.width == 640
        assert 0.45 <= frame.objects[0].t[2] <= 0.9 + 0.1  # the demo's distance range (box centre)
        depth = read_depth_m(out / "frames" / f"{i:06d}.depth.png")
        assert depth.shape == (480, 640) and np.any(depth > 0)
    assert (out / "overview.png").is_file()
    assert (out / "mesh" / "DemoBox.obj").is_file()
    onnx_path = out / f"{ckpt.stem}.onnx"
    stamp = json.loads((out / f"{ckpt.stem}.onnx.json").read_text())
    assert onnx_path.is_file() and stamp["input_hw"] == list(DEMO_INPUT_HW)
    preds, _ = read_predictions(out / "predictions.jsonl")
    assert preds and all(p.class_name == "DemoBox" for p in preds)


def test_evaluate_on_the_demo_predictions_reports_what_the_demo_found(demo_run, tmp_path):
    """`dope-hope evaluate` on the demo's own output (the command the demo prints) counts the
    same true positives at 2 cm ADD-H as the demo's "found", and with the box's symmetries
    (model_info.json beside the mesh) the same MeanSSD errors."""
    out, stdout = demo_run
    first = out.parent / "first_run"
    rc, _, stderr = _run(["evaluate", "-p", str(first / "predictions.jsonl"), "-d", str(first / "frames"),
                               "--mesh", str(first / "mesh" / "DemoBox.obj"), "--metric", "addh,meanssd",
                               "--out", str(tmp_path / "eval"), "--no-progress"])
    assert rc == 0, stderr
    found = int(re.search(r"^found (\d)/2 scenes with ADD-H < 2 cm", stdout, re.M).group(1))
    hint = re.search(r"reports recall ([\d.]+) at 2 cm ADD-H: the (\d) of (\d) instances", stdout)
    assert hint and int(hint.group(2)) == found and int(hint.group(3)) == 2, stdout
    with open(tmp_path / "eval" / "detection_rate.csv", newline="") as f:
        at_2cm = {r["metric"]: r for r in csv.DictReader(f) if r["group"] == "overall" and r["threshold_cm"] == "2"}
    assert int(at_2cm["addh"]["true_positives"]) == found and int(at_2cm["addh"]["gt_instances"]) == 2
    assert f"{float(at_2cm['addh']['detection_rate']):.3f}" == hint.group(1)
    # the errors themselves agree: MeanSSD (symmetry-aware) of the -LS poses the demo printed
    meanssd = [float(v) for v in re.findall(r"PnP\+LS .* MeanSSD +([\d.]+) cm", stdout)]
    assert int(at_2cm["meanssd"]["true_positives"]) == sum(v < 2.0 for v in meanssd)
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["models"]["DemoBox"].endswith("model_info.json")
    addh = [float(v) for v in re.findall(r"PnP\+LS .* ADD-H +([\d.]+) cm", stdout)]
    within = sorted(v for v in addh if v < 10.0)
    if within:
        assert summary["methods"]["predictions"]["overall"]["median_tp_error_cm"] == pytest.approx(
            float(np.median(within)), abs=0.006)


def test_infer_on_a_demo_frame_uses_sibling_camera_and_default_weights(demo_run, ckpt, tmp_path, monkeypatch):
    out, _ = demo_run
    monkeypatch.setattr(infer_cmd, "DEMO_WEIGHTS", ckpt)  # what the installation ships
    rc, stdout, stderr = _run(["infer", str(out / "frames" / "000000.png"), "--depth", "auto",
                               "--out", str(tmp_path / "inf"), "--no-progress"])
    assert rc == 0, stderr
    recs = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    assert recs and recs[0]["class"] == "DemoBox" and recs[0]["image"] == "000000.png"
    # The demo printed the same detection: its -LS translation matches infer's (same maps, same K).
    demo_preds = [json.loads(line) for line in (out / "predictions.jsonl").read_text().splitlines()
                  if line.startswith("{") and '"000000.png"' in line]
    assert np.allclose(recs[0]["t"], demo_preds[0]["t"], atol=2e-3)


def test_demo_reuses_the_onnx_export_and_replaces_old_frames(demo_run, ckpt):
    out, _ = demo_run
    onnx_path = out / f"{ckpt.stem}.onnx"
    mtime = onnx_path.stat().st_mtime_ns
    rc, stdout, stderr = _run(["demo", "--scenes", "1", "--seed", "5", "--weights", str(ckpt),
                               "--out", str(out), "--threads", "1"])
    assert rc == 0, stderr
    assert "(cached)" in stdout.splitlines()[0] and onnx_path.stat().st_mtime_ns == mtime
    assert re.search(r"^found \d/1 scenes with ADD-H < 2 cm", stdout, re.M)
    assert sorted(p.name for p in (out / "frames").glob("*.json")) == ["000000.json"]
    assert sorted(p.name for p in out.glob("*.overlay.png")) == ["000000.overlay.png"]


def test_missing_weights_fail_with_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr(demo_cmd, "DEMO_WEIGHTS", tmp_path / "assets" / "demo_lite.pt")
    rc, stdout, stderr = _run(["demo", "--out", str(tmp_path / "o")])
    assert rc == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "demo model not found" in lines[0] and "configs/demo.yaml" in lines[0]
    rc, _, stderr = _run(["demo", "--weights", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "nope.pt: weights file not found" in stderr and len(stderr.strip().splitlines()) == 1


def test_a_model_of_another_object_is_refused(tmp_path):
    from dope_hope.model import build_model
    from dope_hope.model.checkpoint import make_object_info, save_checkpoint

    cfg = {"model": {"arch": "lite", "head": 50, "stages": 1,
                     "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
           "input": {"size": [64, 64]}}
    path = save_checkpoint(tmp_path / "ketchup.pt", build_model(cfg), cfg, make_object_info("Ketchup"))
    rc, _, stderr = _run(["demo", "--weights", str(path), "--out", str(tmp_path / "o"), "--no-onnx"])
    assert rc == 2 and "a model of 'Ketchup'" in stderr
