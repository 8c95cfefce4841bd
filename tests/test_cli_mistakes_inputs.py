"""More of a user's inputs through the CLI: a camera index OpenCV cannot take, NDDS camera
settings of the wrong shape, a negative diameter, a models folder without the object, a
video that ends before its stated length, Isaac ROS flags that do not apply, Ctrl-C while
synth's workers start. Each ends in one line and exit 2, or (the video) the right result
with a warning; nothing half-written.
"""
from __future__ import annotations

import json
import multiprocessing
import os
import re
import signal
from pathlib import Path

import numpy as np
import pytest
import trimesh
from test_cli_mistakes import (  # noqa: F401 - fixtures
    H,
    W,
    frames,
    mesh,
    no_temporaries,
    one_line_error,
    predictions,
    run_cli,
    weights,
)
from video_files import read_video, write_video

from dope_hope.demo_object import demo_object_mesh
from dope_hope.geometry import intrinsics_matrix
from dope_hope.io.images import read_rgb


def k_json(path: Path) -> Path:
    """A K.json for the W x H frames of test_cli_mistakes."""
    K = intrinsics_matrix(80.0, 80.0, (W - 1) / 2, (H - 1) / 2)
    path.write_text(json.dumps({"K": K.tolist(), "width": W, "height": H}))
    return path


# ----------------------------------------------------------------------------- sources
def test_camera_index_too_large_for_opencv_is_one_line(weights, tmp_path, capsys):
    index = "99999999999999999999999"
    argv = ["infer", index, "--camera", k_json(tmp_path / "K.json"), "--weights", weights, "--out", tmp_path / "o"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert f"camera {index}: camera index out of range" in line
    assert not (tmp_path / "o").exists()


def test_video_that_ends_before_its_stated_length_says_so(frames, weights, tmp_path, capfd):
    rgb = read_rgb(frames / "000000.png")
    rng = np.random.default_rng(5)
    clip = write_video(tmp_path / "clip", [np.clip(rgb.astype(int) + rng.integers(-40, 40, rgb.shape), 0, 255)
                                           for _ in range(10)])
    data = bytearray(clip.read_bytes())
    data[int(len(data) * 0.45): len(data) - 2000] = bytes(len(data) - 2000 - int(len(data) * 0.45))
    clip.write_bytes(bytes(data))  # frames after the first few are zeros; the index still says 10
    decodable = len(read_video(clip))
    assert 0 < decodable < 10
    out = tmp_path / "o"
    code, stdout, err = run_cli(["infer", clip, "--camera", k_json(tmp_path / "K.json"), "--weights", weights,
                                 "--out", out, "--no-progress", "--min-score", "-1"], capfd)
    assert code == 0, err
    warnings = [ln for ln in err.splitlines() if ": warning: " in ln]
    assert len(warnings) == 1 and "Traceback" not in err
    assert f"{clip.name}: the stream ended early: {decodable} of the 10 frames the file states" in warnings[0]
    summary = err.strip().splitlines()[-1]
    assert re.search(rf"{decodable} frame\(s\) read, {decodable} processed, 0 dropped; .*"
                     rf"\(ended early: {decodable} of the 10 frames the file states\)", summary), summary
    records = [json.loads(ln) for ln in (out / "predictions.jsonl").read_text().splitlines()]
    assert records == [json.loads(ln) for ln in stdout.splitlines()]
    assert {r["frame"] for r in records} <= set(range(decodable))
    assert len(read_video(out / f"clip.overlay{clip.suffix}")) == decodable
    assert no_temporaries(out)


# ----------------------------------------------------------------------------- NDDS camera settings
@pytest.fixture
def ndds_frame(shared_data, tmp_path) -> Path:
    """An NDDS frame (no intrinsics in its JSON) copied into its own folder; returns the folder."""
    folder = tmp_path / "ndds"
    folder.mkdir()
    for name in ("000030.json", "000030.png"):
        (folder / name).write_bytes((shared_data / "dope_format_samples" / "ndds" / name).read_bytes())
    return folder


def write_camera_settings(folder: Path, size) -> None:
    (folder / "_camera_settings.json").write_text(json.dumps({"camera_settings": [{
        "name": "Viewpoint", "intrinsic_settings": {"fx": 768.16, "fy": 768.16, "cx": 256, "cy": 256, "s": 0},
        "captured_image_size": size}]}))


@pytest.mark.parametrize("size, problem", [
    ([512, 512], 'captured_image_size: expected an object {"width": W, "height": H}, got list'),
    ({"width": "512", "height": 512}, "captured_image_size.width: expected a positive integer, got '512'"),
    ({"width": 512, "height": -512}, "captured_image_size.height: expected a positive integer, got -512"),
    ({"width": 512.5, "height": 512}, "captured_image_size.width: expected a positive integer, got 512.5"),
])
@pytest.mark.parametrize("command", ["infer", "evaluate"])
def test_ndds_camera_settings_of_the_wrong_shape_are_refused(command, size, problem, ndds_frame, weights, mesh,
                                                             tmp_path, capsys):
    write_camera_settings(ndds_frame, size)
    if command == "infer":
        argv = ["infer", ndds_frame / "000030.png", "--weights", weights, "--out", tmp_path / "o"]
    else:
        pred = tmp_path / "p.jsonl"
        pred.write_text(json.dumps({"image": "000030.png", "class": "DemoBox", "score": 1.0,
                                    "R": np.eye(3).tolist(), "t": [0, 0, 0.6]}) + "\n")
        argv = ["evaluate", "-p", pred, "-d", ndds_frame, "--mesh", mesh, "--out", tmp_path / "o", "--no-progress"]
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert f"_camera_settings.json: camera_settings[0].{problem}" in line
    assert not (tmp_path / "o").exists()


def test_ndds_camera_settings_with_a_valid_size_still_work(ndds_frame, weights, tmp_path, capsys):
    write_camera_settings(ndds_frame, {"width": 512, "height": 512})
    code, _, err = run_cli(["infer", ndds_frame / "000030.png", "--weights", weights, "--out", tmp_path / "o",
                            "--no-progress"], capsys)
    assert code == 0, err


# ----------------------------------------------------------------------------- models
def test_models_info_with_a_negative_diameter_is_refused(frames, predictions, tmp_path, capsys):
    models = tmp_path / "models"
    models.mkdir()
    box = demo_object_mesh()
    box.apply_scale(1000.0)  # BOP: millimetres
    trimesh.Trimesh(box.vertices, box.faces).export(models / "obj_000001.ply")
    (models / "models_info.json").write_text(json.dumps({"1": {"diameter": -5.0, "min_x": 0, "min_y": 0,
                                                                 "min_z": 0}}))
    argv = ["evaluate", "-p", predictions, "-d", frames, "--mesh", f"DemoBox={models / 'obj_000001.ply'}",
            "--bop-ar", "--out", tmp_path / "e", "--no-progress"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "evaluate")
    assert "models_info.json: 1.diameter: must be positive, got -5.0" in line
    assert not (tmp_path / "e").exists()


def test_models_dir_without_the_object_is_refused_not_replaced_by_a_cuboid(frames, predictions, tmp_path, capsys):
    models = tmp_path / "models_eval"
    models.mkdir()
    trimesh.creation.box(extents=[50, 60, 70]).export(models / "obj_000002.ply")  # another object's
    argv = ["evaluate", "-p", predictions, "-d", frames, "--models-dir", models, "--out", tmp_path / "e",
            "--no-progress"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "evaluate")
    assert f"{models}: no mesh for DemoBox (looked for " in line
    assert not (tmp_path / "e").exists()


# ----------------------------------------------------------------------------- export flags
@pytest.mark.parametrize("flags, expected", [
    (["--layout", "isaac-ros", "--isaac-ros-version", "99.9"],
     "--isaac-ros-version 99.9: newer than the newest known release 4.0"),
    (["--layout", "isaac-ros", "--isaac-ros-version", "4.1"],
     "--isaac-ros-version 4.1: newer than the newest known release 4.0"),
    (["--isaac-ros-version", "3.1"], "--isaac-ros-version applies only to --layout isaac-ros"),
    (["--layout", "native", "--isaac-normalization", "half"],
     "--isaac-normalization applies only to --layout isaac-ros"),
])
def test_isaac_ros_flags_that_cannot_apply_are_refused(flags, expected, weights, tmp_path, capsys):
    argv = ["export", "--weights", weights, "--out", tmp_path / "m.onnx", *flags]
    line = one_line_error(*run_cli(argv, capsys)[::2], "export")
    assert expected in line
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- signals
@pytest.fixture
def ctrl_c_armed():
    """Ctrl-C handled as in a terminal for the test: a shell starts a background job (``pytest
    &``) with SIGINT ignored, and Python keeps that, so no interrupt would ever come."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_while_synth_workers_start_stops_the_run(ctrl_c_armed, mesh, tmp_path, monkeypatch, capsys):
    """A real SIGINT to this process while ``Pool()`` starts the workers (the moment it used to
    be ignored in) ends the run like any Ctrl-C: exit 130, the workers gone, nothing left."""
    spawn = type(multiprocessing.get_context("spawn"))
    real_pool = spawn.Pool
    started = []

    def pool_then_ctrl_c(self, *args, **kwargs):
        pool = real_pool(self, *args, **kwargs)
        started.append(pool)
        os.kill(os.getpid(), signal.SIGINT)
        return pool

    monkeypatch.setattr(spawn, "Pool", pool_then_ctrl_c)
    out = tmp_path / "s"
    code, _, err = run_cli(["synth", "--mesh", mesh, "--out", out, "--count", 6, "--size", "32x32",
                            "--workers", 2, "--no-progress"], capsys)
    assert started, "the worker pool was not started"
    assert (code, err.strip()) == (130, "dope-hope synth: interrupted")
    assert multiprocessing.active_children() == []
    assert no_temporaries(out) and not list(out.glob("0*.json"))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())
