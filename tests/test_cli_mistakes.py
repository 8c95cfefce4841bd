"""A user's mistakes through the CLI: each ends in one line and exit 2, a refusal, or
the right result - never a traceback, a silently wrong number or a half-written folder.

In-process through ``dope_hope.cli.main`` (capfd also sees what C libraries print on file
descriptor 2); subprocesses only for signals. Simulations, each at the operating-system call:

* disk full: ``RLIMIT_FSIZE`` makes the kernel fail every write that grows a file past a few
  kB (EFBIG, "file too large"), through whatever library writes (torch, onnx, OpenCV,
  matplotlib); ENOSPC takes the same path (an OSError at the write call).
* read-only file system: ``os.statvfs`` reports ``ST_RDONLY`` for the test folder (tests run as
  root, whom a chmod does not stop; the kernel's answer is what the check reads).
* names longer than the file system allows, existing files and folders, named pipes: real.
"""
from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_training_trainer import write_frames as write_train_frames

from dope_hope import cli
from dope_hope.annotation import FrameAnnotation, ObjectAnnotation
from dope_hope.demo_object import DEMO_SIZE_M, write_demo_object
from dope_hope.geometry import cuboid_keypoints, intrinsics_matrix, project_points
from dope_hope.io.dope_json import write_dope_json
from dope_hope.io.images import write_rgb
from dope_hope.model import build_model
from dope_hope.model.checkpoint import make_object_info, save_checkpoint

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parent.parent
LITE = {"model": {"arch": "lite", "head": 50, "stages": 1,
                  "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "input": {"size": [64, 64]}}
#: `train --set` values of a tiny, fast, reproducible run (lite recipe, 64x64, batch 2).
TINY_SET = ["input.size=[64,64]", "train.batch_size=2", "train.workers=0", "train.threads=1",
            "train.log_every=1", "train.time_limit_min=null", "model.stages=1", "model.head=50",
            "model.lite.width=8", "model.lite.feature_channels=16", "model.lite.stage_channels=16"]
W, H = 80, 64


# ----------------------------------------------------------------------------- helpers
def run_cli(argv, cap) -> tuple[int, str, str]:
    """``dope-hope ARGV`` in this process: (exit status, stdout, stderr)."""
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        code = exc.code
    out, err = cap.readouterr()
    return code, out, err


def one_line_error(code: int, err: str, command: str) -> str:
    """The only stderr line of a refused command (exit 2), which names the command."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"dope-hope {command}: error: "), (code, err)
    assert "Traceback" not in err
    return lines[0]


@contextlib.contextmanager
def disk_full_after(nbytes: int):
    """Every write growing a file past ``nbytes`` fails in the kernel (RLIMIT_FSIZE: EFBIG)."""
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)


@pytest.fixture
def read_only(monkeypatch, tmp_path):
    """``tmp_path/ro`` (created) sits on a 'read-only file system' as statvfs reports it."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.statvfs

    class Flags:
        def __init__(self, st):
            self._st = st

        def __getattr__(self, name):
            return getattr(self._st, name)

        @property
        def f_flag(self):
            return self._st.f_flag | os.ST_RDONLY

    def statvfs(path):
        st = real(path)
        return Flags(st) if str(Path(path).absolute()).startswith(str(ro)) else st

    monkeypatch.setattr(os, "statvfs", statvfs)
    return ro


def no_temporaries(folder: Path) -> bool:
    return not [p for p in folder.rglob(".*") if ".tmp" in p.name]


def write_frame(folder: Path, i: int, rng, class_name: str = "DemoBox", with_object: bool = True) -> None:
    """A W x H DOPE frame: random RGB, camera, one object with its cuboid record, mm depth."""
    folder.mkdir(parents=True, exist_ok=True)
    K = intrinsics_matrix(80.0, 80.0, (W - 1) / 2, (H - 1) / 2)
    R, t = np.eye(3), np.array([0.0, 0.0, 0.6])
    objects = [ObjectAnnotation(class_name, R, t, project_points(cuboid_keypoints(DEMO_SIZE_M), K, R, t), 1.0)]
    write_rgb(folder / f"{i:06d}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    write_rgb(folder / f"{i:06d}.depth.png", np.full((H, W), 600, np.uint16))
    frame = FrameAnnotation(folder / f"{i:06d}.json", K, W, H, objects if with_object else [],
                            depth_path=folder / f"{i:06d}.depth.png")
    write_dope_json(folder / f"{i:06d}.json", frame,
                    extra={"cuboid": {"class": class_name, "size_m": list(DEMO_SIZE_M), "center_m": [0, 0, 0]}})


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("frames")
    rng = np.random.default_rng(0)
    for i in range(2):
        write_frame(folder, i, rng)
    return folder


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "demobox.pt"
    return save_checkpoint(path, build_model(LITE), LITE, make_object_info("DemoBox", DEMO_SIZE_M))


@pytest.fixture(scope="module")
def mesh(tmp_path_factory) -> Path:
    return write_demo_object(tmp_path_factory.mktemp("mesh"))


@pytest.fixture(scope="module")
def train_data(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("train")
    write_train_frames(folder, 11)  # 10 train + 1 val: 5 steps per epoch at batch 2
    return folder


@pytest.fixture(scope="module")
def predictions(tmp_path_factory) -> Path:
    """One exact detection of frame 0 (R = I, t = (0, 0, 0.6))."""
    path = tmp_path_factory.mktemp("pred") / "p.jsonl"
    path.write_text(json.dumps({"image": "000000.png", "class": "DemoBox", "score": 1.0,
                                "R": np.eye(3).tolist(), "t": [0, 0, 0.6]}) + "\n")
    return path


def command_argv(command: str, out, frames: Path, weights: Path, mesh: Path, predictions: Path,
                 train_data: Path) -> list:
    """A valid invocation of ``command`` writing to ``out``."""
    return {
        "infer": ["infer", frames / "000000.png", "--weights", weights, "--out", out, "--no-progress"],
        "evaluate": ["evaluate", "-p", predictions, "-d", frames, "--mesh", mesh, "--out", out, "--no-progress"],
        "synth": ["synth", "--mesh", mesh, "--out", out, "--count", 1, "--size", "32x32", "--no-progress"],
        "train": ["train", "--data", train_data, "--object", "Ketchup", "--out", out, "--steps", 1,
                  "--no-progress", "--set", *TINY_SET],
        "demo": ["demo", "--weights", weights, "--out", out, "--scenes", 1, "--no-onnx"],
        "export": ["export", "--weights", weights, "--out", out],
    }[command]


FOLDER_COMMANDS = ("infer", "evaluate", "synth", "train", "demo")
ALL_COMMANDS = FOLDER_COMMANDS + ("export",)


# ============================================================================= output paths
@pytest.mark.parametrize("command", ALL_COMMANDS)
def test_out_of_the_wrong_kind_is_one_line(command, frames, weights, mesh, predictions, train_data, tmp_path, capsys):
    if command == "export":
        out = tmp_path / "model.onnx"
        out.mkdir()
        expected = "is an existing folder"
    else:
        out = tmp_path / "taken"
        out.write_text("a file")
        expected = "exists and is a file, not a folder"
    argv = command_argv(command, out, frames, weights, mesh, predictions, train_data)
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert f"--out {out}: {expected}" in line


@pytest.mark.parametrize("command", ALL_COMMANDS)
def test_read_only_file_system_is_one_line(command, frames, weights, mesh, predictions, train_data, read_only, capsys):
    out = read_only / ("sub/x.onnx" if command == "export" else "sub/out")
    argv = command_argv(command, out, frames, weights, mesh, predictions, train_data)
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert f"{out}: on a read-only file system" in line
    assert not (read_only / "sub").exists()


@pytest.mark.parametrize("command", ALL_COMMANDS)
def test_name_longer_than_the_file_system_allows_is_one_line(command, frames, weights, mesh, predictions,
                                                               train_data, tmp_path, capsys):
    out = tmp_path / ("n" * 300 + (".onnx" if command == "export" else ""))
    argv = command_argv(command, out, frames, weights, mesh, predictions, train_data)
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert "longer than the file system allows" in line


def test_export_to_a_long_but_legal_name_works(weights, tmp_path, capsys):
    """The temporary name beside the target must not be what is too long."""
    out = tmp_path / ("m" * 240 + ".onnx")
    code, _, err = run_cli(["export", "--weights", weights, "--out", out], capsys)
    assert code == 0, err
    assert out.is_file() and no_temporaries(tmp_path)


def test_disk_full_export_is_one_line_and_leaves_nothing(weights, tmp_path, capfd):
    with disk_full_after(20_000):  # the .onnx of the tiny model is ~300 kB
        code, _, err = run_cli(["export", "--weights", weights, "--out", tmp_path / "m.onnx"], capfd)
    line = one_line_error(code, err, "export")
    assert "m.onnx: cannot write (file too large)" in line
    assert list(tmp_path.iterdir()) == []


def test_disk_full_evaluate_writes_all_tables_or_none(frames, mesh, predictions, tmp_path, capfd):
    out = tmp_path / "eval"
    with disk_full_after(8_000):  # the tables fit, the curves' PNG does not
        code, _, err = run_cli(["evaluate", "-p", predictions, "-d", frames, "--mesh", mesh,
                                "--out", out, "--no-progress"], capfd)
    line = one_line_error(code, err, "evaluate")
    assert "detection_rate.png: cannot write (file too large)" in line
    assert not out.exists()  # no half set of tables, no temporary files, no empty folder it made
    code, _, err = run_cli(["evaluate", "-p", predictions, "-d", frames, "--mesh", mesh, "--out", out,
                            "--no-progress"], capfd)
    assert code == 0, err
    assert {p.name for p in out.iterdir()} == {"per_object_p.md", "per_object_p.csv", "detection_rate.csv",
                                               "detection_rate.png", "summary.json"}


def test_disk_full_checkpoint_write_is_one_line(train_data, tmp_path, capfd):
    out = tmp_path / "run"
    with disk_full_after(50_000):  # metrics rows fit, the ~300 kB checkpoint does not
        code, _, err = run_cli(["train", "--data", train_data, "--object", "Ketchup", "--out", out,
                                "--steps", 2, "--no-progress", "--set", *TINY_SET], capfd)
    line = one_line_error(code, err, "train")
    assert ".pt: cannot write (file too large)" in line
    assert no_temporaries(out) and not (out / "last.pt").exists()


# ============================================================================= option values
@pytest.mark.parametrize("flags, named", [
    (["--threads", "-1"], "--threads"),
    (["--device", "bogus"], "--device"),
    (["--device", "cuda:99" if torch.cuda.is_available() else "cuda"], "--device"),
    (["--height", "100000"], "--height"),
    (["--min-score", "nan"], "--min-score"),
    (["--depth", "auto", "--depth-scale", "nan"], "--depth-scale"),
    (["--depth", "auto", "--depth-scale", "inf"], "--depth-scale"),
    (["--depth", "auto", "--depth-calibration", "0"], "--depth-calibration"),
    (["--depth", "auto", "--depth-calibration", "-1"], "--depth-calibration"),
    (["--depth", "auto", "--depth-calibration", "nan"], "--depth-calibration"),
    (["--fx", "nan", "--fy", "80", "--cx", "40", "--cy", "32"], "--fx"),
])
def test_infer_bad_values_are_refused_before_loading(flags, named, frames, tmp_path, capsys):
    # --weights names a file that does not exist: the flag must be refused before any loading
    argv = ["infer", frames / "000000.png", "--weights", tmp_path / "not_loaded.pt", "--out", tmp_path / "o", *flags]
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert f"argument {named}:" in line and "not_loaded" not in line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("flags, named", [
    (["--lr", "nan"], "argument --lr"),
    (["--lr", "-1"], "argument --lr"),
    (["--workers", "-1"], "argument --workers"),
    (["--steps", "0"], "argument --steps"),
    (["--epochs", "0"], "argument --epochs"),
    (["--time-budget", "-1"], "argument --time-budget"),
    (["--set", "train.lr=abc"], "train.lr must be a number"),
    (["--set", "train.epochs=0"], "train.epochs must be >= 1"),
    (["--set", "targets.sigam=2"], "--set targets.sigam=2: unknown setting targets.sigam (known in targets: "),
])
def test_train_bad_values_are_refused(flags, named, train_data, tmp_path, capsys):
    argv = ["train", "--data", train_data, "--object", "Ketchup", "--out", tmp_path / "run", "--no-progress",
            "--steps", "1", *flags]
    if "--set" not in flags:
        argv += ["--set", *TINY_SET]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    assert named in line
    assert not (tmp_path / "run" / "last.pt").exists()


def test_synth_refuses_an_unknown_set_key(mesh, tmp_path, capsys):
    argv = ["synth", "--mesh", mesh, "--out", tmp_path / "s", "--count", 1, "--set", "target.cuont=[1,1]"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "synth")
    assert "unknown setting target.cuont" in line and "count" in line
    cfg = tmp_path / "typo.yaml"
    cfg.write_text("target:\n  cuont: [1, 1]\n")
    line = one_line_error(*run_cli(["synth", "--mesh", mesh, "--out", tmp_path / "s", "--count", 1,
                                    "--config", cfg], capsys)[::2], "synth")
    assert "unknown setting target.cuont" in line


def test_onnx_whose_size_metadata_disagrees_with_its_graph(weights, frames, tmp_path, capsys):
    import onnx

    good = tmp_path / "m.onnx"
    assert run_cli(["export", "--weights", weights, "--out", good], capsys)[0] == 0
    model = onnx.load(str(good))
    for prop in model.metadata_props:
        if prop.key == "dope_hope.fixed_input_hw":
            prop.value = "[128, 128]"
    onnx.save(model, str(tmp_path / "bad.onnx"))
    line = one_line_error(*run_cli(["infer", frames / "000000.png", "--weights", tmp_path / "bad.onnx",
                                    "--out", tmp_path / "o"], capsys)[::2], "infer")
    assert "bad.onnx: metadata says the input is 128x128 but the graph takes 64x64" in line


# ============================================================================= silently wrong
@pytest.mark.parametrize("mesh_flags", [["--mesh-units", "mm"], ["--mesh-units", "m"], "other"])
def test_evaluate_refuses_a_mesh_that_is_not_the_datasets_object(mesh_flags, frames, mesh, predictions, tmp_path,
                                                                 capsys):
    if mesh_flags == "other":
        import trimesh

        other = tmp_path / "Other.obj"
        trimesh.creation.box(extents=[6.45, 14.86, 4.34]).export(other)  # a Ketchup-sized box, cm
        flags = ["--mesh", f"DemoBox={other}"]
    else:
        flags = ["--mesh", f"DemoBox={mesh}", *mesh_flags]
    argv = ["evaluate", "-p", predictions, "-d", frames, *flags, "--out", tmp_path / "e", "--no-progress"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "evaluate")
    if mesh_flags == ["--mesh-units", "m"]:  # a 17 m box: no object's size in metres
        assert "DemoBox.obj: mesh box 12.27 x 16.72 x 4.02 m (read in m) is too large for an object" in line
    else:
        assert "does not match the cuboid 000000.json records [12.27, 16.72, 4.02] cm for DemoBox" in line
    if mesh_flags == ["--mesh-units", "mm"]:
        assert line.endswith("(the file is likely in cm, not mm: give its unit as cm (--mesh-units cm))")
    assert not (tmp_path / "e").exists()  # nothing scored, no empty folder left


def test_same_file_names_in_two_folders_get_distinct_records(frames, weights, tmp_path, capsys):
    rng = np.random.default_rng(1)
    for sub in ("a", "b"):
        write_frame(tmp_path / sub, 0, rng)
    code, out, err = run_cli(["infer", tmp_path / "a", tmp_path / "b", "--weights", weights, "--out",
                              tmp_path / "o", "--no-progress", "--min-score", "-1"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "o").glob("*.overlay.png")) == ["a__000000.overlay.png",
                                                                               "b__000000.overlay.png"]
    assert (tmp_path / "o" / "predictions.jsonl").is_file()
    names = {json.loads(line)["image"] for line in out.splitlines()}
    assert names <= {"a/000000.png", "b/000000.png"}


@pytest.fixture
def truncated_jpeg(frames, tmp_path) -> Path:
    data = cv2.imencode(".jpg", cv2.imread(str(frames / "000000.png")))[1].tobytes()
    path = tmp_path / "cut.jpg"
    path.write_bytes(data[: len(data) // 2])
    return path


def test_truncated_jpeg_is_refused_without_libjpeg_noise(truncated_jpeg, weights, tmp_path, capfd):
    argv = ["infer", truncated_jpeg, "--weights", weights, "--fx", 80, "--fy", 80, "--cx", 40, "--cy", 32,
            "--out", tmp_path / "o"]
    line = one_line_error(*run_cli(argv, capfd)[::2], "infer")
    assert "cut.jpg: truncated or corrupt image (Premature end of JPEG file)" in line


def test_corrupt_png_is_one_line_without_libpng_noise(frames, weights, tmp_path, capfd):
    data = bytearray((frames / "000000.png").read_bytes())
    data[len(data) // 2] ^= 0xFF  # a flipped bit inside the image data: libpng prints a warning and an error
    bad = tmp_path / "flipped.png"
    bad.write_bytes(bytes(data))
    argv = ["infer", bad, "--weights", weights, "--fx", 80, "--fy", 80, "--cx", 40, "--cy", 32, "--out", tmp_path / "o"]
    line = one_line_error(*run_cli(argv, capfd)[::2], "infer")
    assert "flipped.png: not a readable image (libpng error: IDAT: CRC error)" in line


def test_one_unreadable_image_in_a_folder_is_skipped_and_reported(frames, weights, truncated_jpeg, tmp_path, capfd):
    folder = tmp_path / "mixed"
    rng = np.random.default_rng(2)
    write_frame(folder, 0, rng)
    write_frame(folder, 1, rng)
    (folder / "000000.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(50))  # unreadable
    out = tmp_path / "o"
    out.mkdir()
    (out / "predictions.jsonl").write_text('{"stale": true}\n')  # an earlier run's
    code, stdout, err = run_cli(["infer", folder, "--weights", weights, "--out", out, "--no-progress",
                                 "--min-score", "-1"], capfd)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and "Traceback" not in err and "libpng" not in err.replace("(libpng", "")
    assert lines[0].startswith("dope-hope infer: warning: ") and "000000.png" in lines[0]
    assert lines[-1].startswith("dope-hope infer: error: 1 of 2 image(s) skipped")
    assert sorted(p.name for p in out.glob("*.overlay.png")) == ["000001.overlay.png"]
    records = [json.loads(ln) for ln in (out / "predictions.jsonl").read_text().splitlines()]
    assert records == [json.loads(ln) for ln in stdout.splitlines()]
    assert all(r["image"] == "000001.png" for r in records)


# ============================================================================= accepted silently
def test_bad_depth_inputs_are_refused(frames, weights, tmp_path, capsys):
    rng = np.random.default_rng(3)
    folder = tmp_path / "d"
    write_frame(folder, 0, rng)
    doc = json.loads((folder / "000000.json").read_text())
    doc["depth_scale_m"] = -0.001
    (folder / "000000.json").write_text(json.dumps(doc))
    argv = ["infer", folder / "000000.png", "--weights", weights, "--depth", "auto", "--out", tmp_path / "o"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
    assert "000000.json: depth_scale_m: must be positive" in line

    rgb_depth = tmp_path / "rgb_depth.png"
    write_rgb(rgb_depth, rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    gray8 = tmp_path / "gray8.png"
    write_rgb(gray8, rng.integers(0, 255, (H, W), dtype=np.uint8))
    for depth, problem in ((rgb_depth, "8-bit image, not a depth map"), (gray8, "8-bit image, not a depth map")):
        argv = ["infer", frames / "000000.png", "--weights", weights, "--depth", depth, "--out", tmp_path / "o"]
        line = one_line_error(*run_cli(argv, capsys)[::2], "infer")
        assert f"{depth.name}: an {problem}" in line
    rgb16 = tmp_path / "rgb16.png"
    write_rgb(rgb16, np.full((H, W, 3), 600, np.uint16))
    argv = ["infer", frames / "000000.png", "--weights", weights, "--depth", rgb16, "--out", tmp_path / "o"]
    assert "rgb16.png: a 3-channel image, not a depth map" in one_line_error(*run_cli(argv, capsys)[::2], "infer")


def test_nan_weights_are_warned_about(frames, tmp_path, capsys):
    model = build_model(LITE)
    with torch.no_grad():
        next(model.parameters()).fill_(float("nan"))
    path = save_checkpoint(tmp_path / "nan.pt", model, LITE, make_object_info("DemoBox", DEMO_SIZE_M))
    code, _, err = run_cli(["infer", frames / "000000.png", "--weights", path, "--out", tmp_path / "o",
                            "--no-progress"], capsys)
    warning = [ln for ln in err.splitlines() if ": warning: " in ln]
    assert code == 0 and len(warning) == 1
    assert warning[0].startswith("dope-hope infer: warning: ") and "nan.pt: 1 of" in warning[0]
    assert "NaN or infinity" in warning[0]


def test_predictions_whose_r_and_quaternion_disagree_are_refused(frames, mesh, tmp_path, capsys):
    pred = tmp_path / "p.jsonl"
    pred.write_text(json.dumps({"image": "000000.png", "class": "DemoBox", "score": 1.0, "R": np.eye(3).tolist(),
                                "quaternion_xyzw": [0, 0, 0.7071068, 0.7071068], "t": [0, 0, 0.6]}) + "\n")
    argv = ["evaluate", "-p", pred, "-d", frames, "--mesh", mesh, "--out", tmp_path / "e", "--no-progress"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "evaluate")
    assert "p.jsonl: line 1: R and quaternion_xyzw disagree (by 90 deg)" in line


def test_resume_with_init_is_refused_or_says_which_wins(train_data, weights, tmp_path, capsys, caplog):
    out = tmp_path / "run"
    base = ["train", "--data", train_data, "--object", "Ketchup", "--out", out, "--no-progress"]
    assert run_cli([*base, "--steps", 1, "--set", *TINY_SET], capsys)[0] == 0
    line = one_line_error(*run_cli([*base, "--resume", out / "last.pt", "--init", weights], capsys)[::2], "train")
    assert "--resume PATH continues a run" in line and "--init" in line
    caplog.set_level("WARNING", "dope_hope.training")
    code, _, err = run_cli([*base, "--resume", "--init", weights], capsys)
    assert code == 0, err
    assert any("--init" in r.message and "ignored" in r.message for r in caplog.records)


# ============================================================================= misleading messages
def test_weights_messages_say_what_the_file_is(frames, weights, tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    line = one_line_error(*run_cli(["infer", frames / "000000.png", "--weights", junk], capsys)[::2], "infer")
    assert "junk.pt: not a torch weights file" in line and "pickles" not in line

    line = one_line_error(*run_cli(["infer", frames / "000000.png", "--weights", weights, "--backend", "onnx"],
                                   capsys)[::2], "infer")
    assert "a PyTorch checkpoint, not an ONNX model" in line and "corrupt" not in line

    pipe = tmp_path / "pipe.pt"
    os.mkfifo(pipe)
    line = one_line_error(*run_cli(["infer", frames / "000000.png", "--weights", pipe], capsys)[::2], "infer")
    assert "pipe.pt: weights file is a named pipe, not a regular file" in line
    image_pipe = tmp_path / "pipe.png"
    os.mkfifo(image_pipe)
    line = one_line_error(*run_cli(["infer", image_pipe, "--weights", weights], capsys)[::2], "infer")
    assert "pipe.png: image file is a named pipe, not a regular file" in line


# ============================================================================= leftovers
def test_training_cleans_stale_temporaries_and_keeps_validation_on_a_completed_resume(train_data, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    stale = out / ".last.k3j9x0_q.tmp.pt"  # what a process killed inside torch.save leaves
    stale.write_bytes(b"PK\x03\x04 half")
    base = ["train", "--data", train_data, "--object", "Ketchup", "--out", out, "--no-progress"]
    assert run_cli([*base, "--steps", 2, "--set", *TINY_SET], capsys)[0] == 0
    assert not stale.exists() and no_temporaries(out)
    first = json.loads((out / "summary.json").read_text())
    rows = (out / "metrics.csv").read_text()
    assert run_cli([*base, "--resume"], capsys)[0] == 0  # nothing left to do
    again = json.loads((out / "summary.json").read_text())
    for key in ("status", "step", "val_loss", "val_kp_acc", "val_kp_acc_decoded", "val_frames"):
        assert again[key] == first[key], key
    assert (out / "metrics.csv").read_text() == rows


def test_demo_writes_nothing_when_its_weights_do_not_load(tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not weights")
    line = one_line_error(*run_cli(["demo", "--weights", junk, "--out", tmp_path / "o", "--no-onnx"],
                                   capsys)[::2], "demo")
    assert "junk.pt" in line
    assert not (tmp_path / "o").exists()  # the folder it made for --out is taken back


def test_bad_input_found_after_out_was_made_leaves_no_empty_folder(mesh, tmp_path, capsys):
    """--out is checked (and made) first; an input refused after that takes the new, still
    empty folders back, parents included, and never a folder that was there or holds a file."""
    argv = ["synth", "--mesh", mesh, "--count", 1, "--backgrounds", tmp_path / "no_such_photos"]
    line = one_line_error(*run_cli(argv + ["--out", tmp_path / "new" / "deeper" / "s"], capsys)[::2], "synth")
    assert "no_such_photos" in line
    assert not (tmp_path / "new").exists()
    (tmp_path / "kept").mkdir()
    one_line_error(*run_cli(argv + ["--out", tmp_path / "kept"], capsys)[::2], "synth")
    assert (tmp_path / "kept").is_dir()


def test_evaluate_without_ground_truth_prints_no_matplotlib_warning(mesh, predictions, tmp_path, capfd):
    folder = tmp_path / "nogt"
    write_frame(folder, 0, np.random.default_rng(4), with_object=False)
    code, _, err = run_cli(["evaluate", "-p", predictions, "-d", folder, "--mesh", f"DemoBox={mesh}",
                            "--out", tmp_path / "e", "--no-progress"], capfd)
    assert code == 0 and err.strip() == "", err


# ============================================================================= signals
def _synth_process(out: Path, mesh: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "dope_hope.cli", "synth", "--mesh", str(mesh), "--out", str(out), "--count", "400",
         "--size", "32x32", "--workers", "2", "--no-progress"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        # as from a shell: Ctrl-C not ignored (a child inherits SIG_IGN, and Python keeps it)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


@pytest.mark.parametrize("how", ["SIGTERM to the main process", "Ctrl-C to the process group"])
def test_synth_workers_stop_quietly(how, mesh, tmp_path):
    out = tmp_path / "s"
    proc = _synth_process(out, mesh)
    deadline = time.monotonic() + 180
    while not list(out.glob("0*.json")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)  # the workers run
    if how.startswith("SIGTERM"):
        os.kill(proc.pid, signal.SIGTERM)
        expected = (143, "dope-hope synth: terminated")
    else:
        os.killpg(proc.pid, signal.SIGINT)
        expected = (130, "dope-hope synth: interrupted")
    _, err = proc.communicate(timeout=120)
    assert (proc.returncode, err.strip()) == expected
    assert no_temporaries(out)
    deadline = time.monotonic() + 10  # the workers are gone; multiprocessing's resource tracker follows
    while subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True).returncode == 0:
        assert time.monotonic() < deadline, "a process of the synth run outlived it"
        time.sleep(0.1)
