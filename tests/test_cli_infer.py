"""`dope-hope infer` end to end on generated frames: JSON lines, overlays, belief montages, errors.

Detections are checked for exact poses with ``TargetsBackend`` (perfect maps of the frame's
ground truth) patched in place of the weights loader; the real torch path runs a tiny random
lite checkpoint. Errors must exit with status 2 and print one line.
"""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from _targets_backend import TargetsBackend
from video_files import read_video, write_video

from dope_hope import cli
from dope_hope.geometry import rotation_error_deg
from dope_hope.io.dope_json import read_dope_json
from dope_hope.io.images import write_rgb
from dope_hope.io.predictions import read_predictions
from dope_hope.model import build_model
from dope_hope.model.checkpoint import make_object_info, save_checkpoint

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parent.parent
LITE = {"model": {"arch": "lite", "head": 50, "stages": 1,
                  "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "input": {"size": [64, 64]}}
SIZE = (160, 120)  # W, H of the generated frames


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    """Two 160x120 synthetic frames of the demo box (one instance, no occluders), with depth."""
    from dope_hope.demo_object import write_demo_object
    from dope_hope.synth.generate import SynthJob
    from dope_hope.synth.to_disk import generate_dataset

    root = tmp_path_factory.mktemp("infer")
    mesh = write_demo_object(root / "mesh")
    cfg = {"target": {"count": [1, 1], "truncation_prob": 0.0, "distance_m": [0.45, 0.55]},
           "distractors": {"count": [0, 0], "occluder_prob": 0.0}}
    generate_dataset(root / "data", SynthJob(mesh, size=SIZE, config=cfg), 2, progress=False)
    return root / "data"


@pytest.fixture(scope="module")
def lite_weights(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "demobox_lite.pt"
    save_checkpoint(path, build_model(LITE), LITE, make_object_info("DemoBox", [0.1227, 0.1672, 0.0402]))
    return path


def gt_backends(monkeypatch, frame_json: Path, distance_factor: float = 1.0,
                turn_deg: float = 0.0) -> list[TargetsBackend]:
    """Patch the weights loader: every --weights opens a TargetsBackend of this frame's GT
    (optionally too far by ``distance_factor`` and turned ``turn_deg`` about the object's y)."""
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_euler("y", turn_deg, degrees=True).as_matrix()
    frame = read_dope_json(frame_json)
    made = []

    def fake_open_backend(weights, backend="auto", device="cpu", threads=None):
        b = TargetsBackend("DemoBox", [0.1227, 0.1672, 0.0402],
                           [(o.R @ turn, o.t * distance_factor) for o in frame.objects], frame.K,
                           (frame.height, frame.width))
        made.append(b)
        return b

    monkeypatch.setattr("dope_hope.inference.backends.open_backend", fake_open_backend)
    return made


def run_cli(argv, capsys):
    code = cli.main(["infer", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, [json.loads(line) for line in out.splitlines() if line.strip()], err


def test_single_frame_prints_gt_poses_and_writes_overlay(frames, tmp_path, monkeypatch, capsys):
    gt_backends(monkeypatch, frames / "000000.json")
    out = tmp_path / "out"
    code, records, err = run_cli([frames / "000000.png", "--weights", "w.pt", "--out", out], capsys)
    assert code == 0, err
    (gt,) = read_dope_json(frames / "000000.json").objects
    (rec,) = records
    assert rec["image"] == "000000.png" and rec["class"] == "DemoBox"
    assert rotation_error_deg(np.array(rec["R"]), gt.R) < 0.1
    assert np.linalg.norm(np.array(rec["t"]) - gt.t) < 1e-3
    kp = np.array(rec["keypoints_2d"], dtype=float)
    assert np.abs(kp - gt.projected_cuboid).max() < 0.05  # original-image pixels
    assert rec["ls_applied"] is False and rec["time"] >= 0
    overlay = cv2.imread(str(out / "000000.overlay.png"), cv2.IMREAD_UNCHANGED)
    assert overlay is not None and overlay.shape == (SIZE[1], SIZE[0], 3)
    assert (out / "000000.overlay.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    preds, _ = read_predictions(out / "predictions.jsonl")  # the evaluate reader accepts it
    assert len(preds) == 1 and preds[0].image == "000000.png"
    np.testing.assert_allclose(preds[0].t, rec["t"])
    # the cuboid is drawn in the class colour along its edges (edge 0-1 midpoint)
    from dope_hope.viz import class_color

    rgb = cv2.cvtColor(overlay, cv2.COLOR_BGR2RGB).astype(int)
    u, v = np.round(gt.projected_cuboid[[0, 1]].mean(0)).astype(int)
    patch = rgb[v - 1:v + 2, u - 1:u + 2].reshape(-1, 3)
    assert (np.abs(patch - np.array(class_color("DemoBox"))).sum(1) < 60).any()


def test_pose_search_flag_reaches_the_predictor(frames, tmp_path, monkeypatch, capsys):
    """--pose-search, and the same option through --set, reach the predictor's options."""
    from dope_hope.inference.predictor import DopePredictor

    searches = []
    init = DopePredictor.__init__

    def spy(self, *a, **kw):
        init(self, *a, **kw)
        searches.append(self.options.pose_search)

    monkeypatch.setattr(DopePredictor, "__init__", spy)
    gt_backends(monkeypatch, frames / "000000.json")
    (gt,) = read_dope_json(frames / "000000.json").objects
    for flag, expected in (([], "hypotheses"), (["--pose-search", "groups"], "groups"),
                           (["--set", "pose_search=groups"], "groups")):
        code, (rec,), err = run_cli([frames / "000000.png", "--weights", "w.pt", "--out", tmp_path / "o",
                                     "--no-overlay", *flag], capsys)
        assert code == 0, err
        assert searches[-1] == expected
        assert rotation_error_deg(np.array(rec["R"]), gt.R) < 0.1  # perfect maps: both exact


def test_depth_auto_applies_the_line_search(frames, tmp_path, monkeypatch, capsys):
    gt_backends(monkeypatch, frames / "000000.json", distance_factor=1.06)
    code, records, err = run_cli([frames / "000000.png", "--weights", "w.pt", "--depth", "auto",
                                  "--mesh", frames.parent / "mesh" / "DemoBox.obj",
                                  "--out", tmp_path / "o", "--no-overlay"], capsys)
    assert code == 0, err
    (gt,) = read_dope_json(frames / "000000.json").objects
    (rec,) = records
    assert rec["ls_applied"] is True, rec["ls_reason"]
    assert rec["ls_scale"] == pytest.approx(1 / 1.06, abs=0.01)
    assert np.linalg.norm(np.array(rec["t"]) - gt.t) < 0.006
    assert not (tmp_path / "o" / "000000.overlay.png").exists()


def test_folder_with_real_lite_model_and_belief(frames, lite_weights, tmp_path, capsys):
    out = tmp_path / "out"
    code, records, err = run_cli([frames, "--weights", lite_weights, "--out", out, "--belief",
                                  "--no-progress"], capsys)
    assert code == 0, err
    for stem in ("000000", "000001"):
        img = cv2.imread(str(out / f"{stem}.overlay.png"))
        assert img is not None and img.shape == (SIZE[1], SIZE[0], 3)
        montage = cv2.imread(str(out / f"{stem}.belief.DemoBox.png"))
        assert montage is not None and montage.shape[0] > 50 and montage.shape[1] > montage.shape[0]
    assert not list(out.glob("*.depth.overlay.png")) and not list(out.glob("*seg*"))
    preds, _ = read_predictions(out / "predictions.jsonl")
    assert len(preds) == len(records)
    assert "2 image(s)" in err.splitlines()[-1]


def test_glob_names_are_relative_and_camera_flags(frames, tmp_path, monkeypatch, capsys):
    gt_backends(monkeypatch, frames / "000001.json")
    K = read_dope_json(frames / "000001.json").K
    code, records, err = run_cli([str(frames.parent / "*" / "000001.png"), "--weights", "w.pt",
                                  "--fx", K[0, 0], "--fy", K[1, 1], "--cx", K[0, 2], "--cy", K[1, 2],
                                  "--out", tmp_path / "o"], capsys)
    assert code == 0, err
    assert [r["image"] for r in records] == ["data/000001.png"]
    assert (tmp_path / "o" / "data__000001.overlay.png").is_file()


def one_line_error(code, err):
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dope-hope infer: error:"), err
    return lines[0]


def test_icp_flag_refines_the_rotation_against_the_depth(frames, tmp_path, monkeypatch, capsys):
    gt_backends(monkeypatch, frames / "000000.json", distance_factor=1.06, turn_deg=20.0)
    (gt,) = read_dope_json(frames / "000000.json").objects
    base = [frames / "000000.png", "--weights", "w.pt", "--depth", "auto",
            "--mesh", frames.parent / "mesh" / "DemoBox.obj", "--out", tmp_path / "o", "--no-overlay"]
    code, (ls,), err = run_cli(base + ["--fast"], capsys)  # the packaged defaults: -LS alone
    assert code == 0, err
    assert "icp_applied" not in ls and rotation_error_deg(np.array(ls["R"]), gt.R) > 15
    for flags in (["--fast", "--icp"], []):  # an image's default (the accurate preset) runs ICP too
        code, (rec,), err = run_cli(base + flags, capsys)
        assert code == 0, err
        assert rec["ls_applied"] is True and rec["icp_applied"] is True, rec["icp_reason"]
        assert rotation_error_deg(np.array(rec["R"]), gt.R) < 2.0
        assert np.linalg.norm(np.array(rec["t"]) - gt.t) < 0.005
    code, (mono,), err = run_cli(base[:3] + base[5:], capsys)  # no depth: no ICP, no error
    assert code == 0, err
    assert mono["ls_applied"] is False and mono["icp_applied"] is False and mono["icp_reason"] == "no depth image"
    line = one_line_error(*run_cli(base[:3] + ["--icp"], capsys)[::2])
    assert "--icp" in line and "--depth" in line
    with pytest.raises(SystemExit) as exc:
        run_cli(base + ["--fast", "--accurate"], capsys)
    assert exc.value.code == 2 and "--accurate: not allowed with argument --fast" in capsys.readouterr().err


def test_errors_exit_2_with_one_line(frames, lite_weights, tmp_path, capsys):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(200)))
    line = one_line_error(*run_cli([bad, "--weights", lite_weights, "--fx", 100, "--fy", 100,
                                    "--cx", 50, "--cy", 50], capsys)[::2])
    assert "broken.png" in line and "not a readable image" in line

    lonely = tmp_path / "lonely.png"
    write_rgb(lonely, np.zeros((32, 48, 3), np.uint8))
    line = one_line_error(*run_cli([lonely, "--weights", lite_weights, "--out", tmp_path / "o"], capsys)[::2])
    assert "lonely.png" in line and "no camera intrinsics" in line and "--camera" in line

    other = tmp_path / "other_arch.pt"
    save_checkpoint(other, build_model(LITE), LITE, make_object_info("DemoBox", [0.1, 0.1, 0.1]))
    ckpt = torch.load(other, weights_only=True)
    ckpt["model"] = torch.nn.Conv2d(3, 8, 3).state_dict()
    torch.save(ckpt, other)
    line = one_line_error(*run_cli([frames / "000000.png", "--weights", other], capsys)[::2])
    assert "other_arch.pt" in line and "another architecture" in line

    junk = tmp_path / "junk.pt"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    line = one_line_error(*run_cli([frames / "000000.png", "--weights", junk], capsys)[::2])
    assert "junk.pt" in line

    wrong_cam = tmp_path / "K.json"
    wrong_cam.write_text(json.dumps({"fx": 100, "fy": 100, "cx": 50, "cy": 50, "width": 640, "height": 480}))
    line = one_line_error(*run_cli([frames / "000000.png", "--weights", lite_weights,
                                    "--camera", wrong_cam], capsys)[::2])
    assert "640x480" in line and "160x120" in line

    line = one_line_error(*run_cli([frames / "000000.png", "--weights", lite_weights, "--fx", 100], capsys)[::2])
    assert "together" in line


def test_weights_required_without_demo_model(frames, monkeypatch, tmp_path, capsys):
    import dope_hope.commands.infer as infer_cmd

    monkeypatch.setattr(infer_cmd, "DEMO_WEIGHTS", tmp_path / "absent.pt")
    line = one_line_error(*run_cli([frames / "000000.png"], capsys)[::2])
    assert "--weights is required" in line


def test_demo_model_is_the_default_when_present(frames, lite_weights, monkeypatch, tmp_path, capsys):
    import dope_hope.commands.infer as infer_cmd

    monkeypatch.setattr(infer_cmd, "DEMO_WEIGHTS", lite_weights)
    code, _, err = run_cli([frames / "000000.png", "--out", tmp_path / "o"], capsys)
    assert code == 0, err
    assert (tmp_path / "o" / "000000.overlay.png").is_file()


def test_top_level_infer_py_forwards_and_fails_cleanly(lite_weights, tmp_path):
    bad = tmp_path / "x.png"
    bad.write_bytes(b"not an image")
    proc = subprocess.run([sys.executable, str(REPO / "infer.py"), str(bad), "--weights", str(lite_weights),
                           "--fx", "1", "--fy", "1", "--cx", "0", "--cy", "0"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0, proc.stderr
    assert "x.png" in proc.stderr and "not a readable image" in proc.stderr


# ----------------------------------------------------------------------------- video and cameras
def ros_camera_yaml(path: Path, K: np.ndarray, width: int, height: int) -> Path:
    """A camera_calibration ost.yaml without distortion."""
    path.write_text(f"image_width: {width}\nimage_height: {height}\ncamera_name: cam\n"
                    f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {K.ravel().tolist()}\n"
                    "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n"
                    "  data: [0, 0, 0, 0, 0]\n")
    return path


def test_video_file_records_frames_timestamps_boxes_and_overlay_video(frames, tmp_path, monkeypatch, capsys):
    from dope_hope.io.images import read_rgb

    gt_backends(monkeypatch, frames / "000000.json")
    ann = read_dope_json(frames / "000000.json")
    video = write_video(tmp_path / "clip", [read_rgb(frames / "000000.png")] * 5, fps=10.0)
    cam = ros_camera_yaml(tmp_path / "ost.yaml", ann.K, SIZE[0], SIZE[1])
    out = tmp_path / "out"
    code, records, err = run_cli([video, "--weights", "w.pt", "--camera", cam, "--out", out, "--no-progress"], capsys)
    assert code == 0, err
    (gt,) = ann.objects
    assert [r["frame"] for r in records] == [0, 1, 2, 3, 4]
    np.testing.assert_allclose([r["timestamp_s"] for r in records], [0, 0.1, 0.2, 0.3, 0.4], atol=1e-4)
    assert [r["image"] for r in records] == [f"{video.name}#{i:06d}" for i in range(5)]
    corners = gt.projected_cuboid[:8]
    box = np.concatenate([np.maximum(corners.min(0), 0), np.minimum(corners.max(0), [SIZE[0] - 1, SIZE[1] - 1])])
    for rec in records:
        assert rotation_error_deg(np.array(rec["R"]), gt.R) < 0.5
        assert np.linalg.norm(np.array(rec["t"]) - gt.t) < 3e-3
        np.testing.assert_allclose(rec["bbox_2d"], box, atol=0.5)  # the projected cuboid's box
    preds, _ = read_predictions(out / "predictions.jsonl")
    assert len(preds) == 5 and preds[2].extra["frame"] == 2
    overlay = read_video(out / f"clip.overlay{video.suffix}")
    assert len(overlay) == 5 and overlay[0].shape == (SIZE[1], SIZE[0], 3)
    assert not list(out.glob(".*tmp*"))  # the temporary video was renamed
    summary = err.strip().splitlines()[-1]
    assert re.search(rf"{video.name}: 5 frame\(s\) read, 5 processed, 0 dropped; [\d.]+ frames/s end to end", summary)


def test_camera_index_keeps_the_newest_frame(frames, tmp_path, monkeypatch, capsys):
    from dope_hope.io.images import read_rgb

    gt_backends(monkeypatch, frames / "000000.json")
    ann = read_dope_json(frames / "000000.json")
    video = write_video(tmp_path / "camera", [read_rgb(frames / "000000.png")] * 12, fps=30.0)
    opened = []

    def fake_camera(target):  # camera 2 "captures" the frames of the video, as fast as it can
        opened.append(target)
        return cv2.VideoCapture(str(video))

    monkeypatch.setattr("dope_hope.io.streams.open_capture", fake_camera)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    (tmp_path / "K.json").write_text(json.dumps({"K": ann.K.tolist(), "width": SIZE[0], "height": SIZE[1]}))
    out = tmp_path / "out"
    code, records, err = run_cli(["2", "--weights", "w.pt", "--camera", tmp_path / "K.json", "--max-frames", "8",
                                  "--show", "--out", out], capsys)
    assert code == 0, err
    assert opened == [2]
    assert "warning: --show ignored: no display" in err
    m = re.search(r"camera2: 8 frame\(s\) read, (\d+) processed, (\d+) dropped", err)
    assert m and int(m.group(1)) + int(m.group(2)) == 8 and int(m.group(1)) == len(records)
    idx = [r["frame"] for r in records]
    assert idx == sorted(set(idx)) and all(r["image"] == f"camera2#{i:06d}" for r, i in zip(records, idx))
    # one overlay frame per camera frame from the first processed on: dropped ones repeat the last
    assert len(read_video(out / f"camera2.overlay{video.suffix}")) == idx[-1] - idx[0] + 1


def test_realsense_stream_refines_with_its_aligned_depth(frames, tmp_path, monkeypatch, capsys):
    import fake_realsense

    from dope_hope.io.images import read_depth_m, read_rgb

    gt_backends(monkeypatch, frames / "000000.json", distance_factor=1.06)
    ann = read_dope_json(frames / "000000.json")
    rgb, depth = read_rgb(frames / "000000.png"), read_depth_m(frames / "000000.depth.png")
    rs = fake_realsense.install(monkeypatch, [(rgb, depth)] * 4, ann.K, depth_scale=0.0001)
    code, records, err = run_cli(["realsense:817612070", "--weights", "w.pt", "--icp", "--max-frames", "4",
                                  "--mesh", frames.parent / "mesh" / "DemoBox.obj", "--out", tmp_path / "o",
                                  "--capture-size", "160x120", "--capture-fps", "15"], capsys)
    assert code == 0, err
    (gt,) = ann.objects
    assert records and all(r["image"].startswith("realsense-817612070#") for r in records)
    for rec in records:
        assert rec["ls_applied"] is True and "icp_applied" in rec
        assert np.linalg.norm(np.array(rec["t"]) - gt.t) < 0.006  # 6 % too far before -LS
    start = next(c for c in rs.calls if c[0] == "start")
    assert start[1] == "817612070" and (rs.stream.depth, 160, 120, rs.format.z16, 15) in start[2]
    assert ("stop",) in rs.calls
    assert "realsense-817612070: 4 frame(s) read" in err


def test_stream_errors_exit_2_with_one_line(frames, lite_weights, tmp_path, monkeypatch, capsys):
    from dope_hope.io.images import read_rgb

    video = write_video(tmp_path / "clip", [read_rgb(frames / "000000.png")] * 2)
    line = one_line_error(*run_cli([video, "--weights", lite_weights], capsys)[::2])
    assert video.name in line and "no camera intrinsics" in line and "camera_info.yaml" in line
    line = one_line_error(*run_cli([tmp_path / "missing.mp4", "--weights", lite_weights, "--fx", 100, "--fy", 100,
                                    "--cx", 50, "--cy", 50], capsys)[::2])
    assert "missing.mp4: video file not found" in line
    line = one_line_error(*run_cli([frames / "000000.png", "--weights", lite_weights, "--realtime"], capsys)[::2])
    assert "--realtime" in line
    line = one_line_error(*run_cli([video, "--weights", lite_weights, "--fx", 100, "--fy", 100, "--cx", 50,
                                    "--cy", 50, "--depth", "auto"], capsys)[::2])
    assert "--depth applies to image inputs" in line
    monkeypatch.setattr("dope_hope.io.streams.open_capture", lambda target: cv2.VideoCapture(str(tmp_path / "no.mp4")))
    line = one_line_error(*run_cli(["0", "--weights", lite_weights, "--fx", 100, "--fy", 100, "--cx", 50,
                                    "--cy", 50], capsys)[::2])
    assert "camera 0: cannot be opened" in line


def test_help_states_the_default_min_score(capsys):
    from dope_hope.inference.options import InferenceOptions

    default = InferenceOptions.from_mapping().min_score
    assert default == 0.5  # chosen by bench/min_score.py (bench/RESULTS.md "Default --min-score")
    with pytest.raises(SystemExit):
        cli.main(["infer", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: each object's own threshold when its file records one (train, dope-hope calibrate), else the " \
           "model's own" in text
    assert f"else {default:g} from dope_hope/configs/infer.yaml" in text
