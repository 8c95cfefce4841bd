"""The README's task sections, run: every ```bash block whose first line is
``# tested: tests/test_readme.py`` is parsed (backslash continuations joined, comments
dropped) and its commands run in README order in a sandbox folder, shrunk for speed:

* ``dope-hope synth``: ``--count 3 --size 160x120 --workers 1``;
* ``dope-hope train``: ``--steps 1 --batch-size 1 --workers 0 --set input.size=[64,64]``
  (a resumed run: ``--steps 2``);
* ``dope-hope demo``: ``--scenes 2``; ``dope-hope export --int8``: ``--calibration-images 2``;
* ``torchrun``: ``--nproc_per_node 1`` plus the train shrinking, as a subprocess
  (tests/test_training_trainer.py runs two processes);
* ``dope-hope infer ... --max-frames N``: ``--max-frames 6``;
* ``dope-hope adapt``: ``--max-frames 3 --set finetune.steps=1 finetune.rounds=1
  infer.multiscale.scales=[1]``;
* every other command exactly as written. ``dope-hope`` commands run in-process (cli.main).

The sandbox holds what a user downloads: ``hope/meshes/full/Ketchup/`` (links to the shared
HOPE Ketchup files), a BOP folder ``bop/hope`` (the mesh as ``obj_000011.ply`` in mm, in
``models/`` and ``models_eval/``, and a two-image test split rendered here), ``photos/`` (the shared backgrounds), ``grocery/`` (the shared grocery meshes, metres), ``realsense/``
(colour, aligned depth and K.json of a rendered frame) and ``weights/Ketchup.pth`` (a stand-in
for NVIDIA's weights: the importer's DR-50 architecture is swapped for a tiny lite network,
as in tests/test_cli_import_official.py). The demo runs the shipped model when the installation
has it, else a checkpoint fitted in seconds (tests/fitted_model.py).

The recording section runs in its own sandbox too (:func:`test_recording_section`):
``robot.bag`` (ROS 1) and ``robot_ros2/`` (ROS 2, MCAP storage, JPEG CompressedImage) of
rendered demo scenes, written by rosbags' writers (tests/ros_recordings.py).

The adapt section runs in its own sandbox too (:func:`test_adapt_section`): ``lab/`` (a ROS 2
bag, MCAP storage) of rendered demo scenes, the shipped demo model as ``runs/ketchup/best.pt``,
the demo box's mesh as ``hope/meshes/full/Ketchup/textured.obj`` and three synthetic frames of
it as ``data/ketchup``.

The video section runs in its own sandbox (:func:`test_video_section`): ``clip.mp4`` and
``camera_info.yaml`` of rendered demo scenes, camera 0 an OpenCV capture of that clip, and
``realsense`` a stand-in for ``pyrealsense2`` playing the same scenes with their depth
(tests/fake_realsense.py): no physical camera is needed or used.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dope_hope import cli
from dope_hope.model.checkpoint import load_checkpoint

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parent.parent
MARK = "# tested: tests/test_readme.py"
TINY = {"model": {"arch": "lite", "head": 50, "stages": 1,
                  "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "input": {"size": [64, 64]}}
TASKS = ["See it work: `dope-hope demo`", "Generate training data for a HOPE object", "Train on your own mesh",
         "Many objects in one network", "Infer on a RealSense image with depth", "Pose a new object with no training",
         "Infer on a video, a webcam or a live RealSense", "Infer on a robot recording, view it in Foxglove",
         "Teach a model your lab: record, adapt, infer", "Use NVIDIA's published DOPE weights for the HOPE objects",
         "Export to ONNX for CPU inference or Isaac ROS", "Evaluate, and submit to the BOP challenge",
         "Train on many GPUs with torchrun"]
VIDEO_TASK = "Infer on a video, a webcam or a live RealSense"
RECORDING_TASK = "Infer on a robot recording, view it in Foxglove"
ADAPT_TASK = "Teach a model your lab: record, adapt, infer"


# ----------------------------------------------------------------------------- parsing
def readme_blocks(path: Path = REPO / "README.md") -> list[tuple[str, list[list[str]]]]:
    """(section heading, commands as argv lists) of each marked bash block, in README order."""
    blocks, heading, lines, inside = [], "", None, False
    for raw in path.read_text(encoding="utf-8").splitlines():
        if not inside and raw.startswith("#"):
            heading = raw.lstrip("#").strip()
        if raw.strip() == "```bash" and not inside:
            inside, lines = True, []
        elif raw.strip() == "```" and inside:
            inside = False
            if lines and lines[0].strip() == MARK:
                text = "\n".join(lines[1:]).replace("\\\n", " ")
                cmds = [shlex.split(line, comments=True) for line in text.splitlines()]
                blocks.append((heading, [c for c in cmds if c]))
        elif inside:
            lines.append(raw)
    return blocks


def _set(argv: list[str], option: str, value: str) -> list[str]:
    """argv with ``option value`` (replaced when present, appended otherwise)."""
    argv = list(argv)
    if option in argv:
        argv[argv.index(option) + 1] = value
    else:
        argv += [option, value]
    return argv


def _shrink_train(argv: list[str]) -> list[str]:
    if "--data" not in argv:  # a resumed run: one more step
        return _set(_set(argv, "--steps", "2"), "--workers", "0")
    for opt, val in (("--steps", "1"), ("--batch-size", "1"), ("--workers", "0")):
        argv = _set(argv, opt, val)
    if "--set" in argv:  # one --set option: argparse keeps only the last one given
        i = argv.index("--set") + 1
        return argv[:i] + ["input.size=[64,64]"] + argv[i:]
    return argv + ["--set", "input.size=[64,64]"]


def shrink(argv: list[str]) -> list[str]:
    """The small version of one README command (see the module docstring)."""
    prog, args = argv[0], list(argv[1:])
    if prog == "torchrun":
        args = _set(args, "--nproc_per_node", "1")
        i = args.index("train.py")
        return ["torchrun", *args[:i], str(REPO / "train.py"), *_shrink_train(args[i + 1:])]
    assert prog == "dope-hope", f"README command of an unknown program: {argv}"
    sub = args[0]
    if sub == "synth":
        args = _set(_set(_set(args, "--count", "3"), "--size", "160x120"), "--workers", "1")
    elif sub == "train":
        args = _shrink_train(args)
    elif sub == "demo":
        args = _set(args, "--scenes", "2")
    elif sub == "export" and "--int8" in args:
        args = _set(args, "--calibration-images", "2")
    elif sub == "infer" and "--max-frames" in args:
        args = _set(args, "--max-frames", "6")
    elif sub == "adapt":
        args = _set(args, "--max-frames", "3") + ["--set", "finetune.steps=1", "finetune.rounds=1",
                                                   "infer.multiscale.scales=[1]"]
    return [prog, *args]


def run_command(argv: list[str], cwd: Path) -> str:
    """Run one (shrunk) README command; returns its stdout; fails the test on non-zero status."""
    if argv[0] == "dope-hope":
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = cli.main(argv[1:])
        assert rc == 0, f"{shlex.join(argv)} -> status {rc}: {err.getvalue()[-1500:]}"
        return out.getvalue()
    cmd = [sys.executable, "-m", "torch.distributed.run", *argv[1:]]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=240, env=env)
    assert proc.returncode == 0, f"{shlex.join(argv)}: {proc.stdout[-1000:]}{proc.stderr[-1500:]}"
    return proc.stdout


# ----------------------------------------------------------------------------- tests
def test_readme_has_every_task_section_and_the_commands_parse():
    blocks = readme_blocks()
    assert [h for h, _ in blocks] == TASKS
    parser = cli.build_parser()
    for heading, cmds in blocks:
        assert cmds, heading
        for argv in cmds:
            small = shrink(argv)
            if small[0] == "dope-hope":
                parser.parse_args(small[1:])  # argparse exits (SystemExit) on an unknown option
            else:
                i = small.index(str(REPO / "train.py"))
                parser.parse_args(["train", *small[i + 1:]])
    assert shrink(["dope-hope", "synth", "--count", "4000", "--out", "d"]) == \
        ["dope-hope", "synth", "--count", "3", "--out", "d", "--size", "160x120", "--workers", "1"]


def test_demo_section(tmp_path, monkeypatch):
    from fitted_model import fit_demo_checkpoint

    from dope_hope.commands import demo as demo_cmd
    from dope_hope.commands import infer as infer_cmd

    if not demo_cmd.DEMO_WEIGHTS.is_file():  # not shipped yet: a quickly fitted stand-in
        weights = fit_demo_checkpoint(tmp_path / "fit" / "demo_lite.pt", seed=7)
        monkeypatch.setattr(demo_cmd, "DEMO_WEIGHTS", weights)
        monkeypatch.setattr(infer_cmd, "DEMO_WEIGHTS", weights)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    (heading, cmds), = [b for b in readme_blocks() if b[0] == TASKS[0]]
    outputs = [run_command(shrink(argv), work) for argv in cmds]
    assert re.search(r"^found \d/2 scenes with ADD-H < 2 cm", outputs[0], re.M)
    assert (work / "demo_out" / "000001.overlay.png").is_file()
    assert (work / "demo_out" / "demo_lite.onnx").is_file()
    assert (work / "demo_out" / "infer" / "predictions.jsonl").is_file()
    assert (work / "demo_out" / "eval" / "summary.json").is_file()


@pytest.fixture
def sandbox(shared_data, tmp_path, monkeypatch) -> Path:
    """The files a user brings (see the module docstring); cwd is the sandbox."""
    import cv2

    from dope_hope.demo_object import write_demo_object
    from dope_hope.io.meshes import load_mesh
    from dope_hope.model import build_model
    from dope_hope.synth import FrameGenerator

    box = tmp_path / "sandbox"
    ketchup = box / "hope" / "meshes" / "full" / "Ketchup"
    ketchup.mkdir(parents=True)
    for f in (shared_data / "hope_ketchup").iterdir():
        (ketchup / f.name).symlink_to(f)
    write_demo_object(box / "hope" / "meshes" / "full" / "DemoBox")  # another object (distractor)
    (box / "photos").symlink_to(shared_data / "backgrounds")
    (box / "grocery").symlink_to(shared_data / "grocery_objects")
    models = box / "bop" / "hope" / "models"
    models.mkdir(parents=True)
    mesh_mm = load_mesh(ketchup / "textured.obj")
    mesh_mm.apply_scale(1000.0)
    mesh_mm.export(models / "obj_000011.ply")
    (box / "bop" / "hope" / "models_eval").symlink_to(models)  # the BOP19 scoring models
    one = {"target": {"count": [1, 1], "truncation_prob": 0.0}, "distractors": {"occluder_prob": 0.0}}
    with FrameGenerator(ketchup / "textured.obj", size=(160, 120), config=one, seed=77) as gen:
        frames = [gen.render_frame(i) for i in range(3)]
    scene = box / "bop" / "hope" / "test" / "000001"
    (scene / "rgb").mkdir(parents=True)
    (scene / "depth").mkdir()
    cams, gts, targets = {}, {}, []
    for i, f in enumerate(frames[:2]):
        cv2.imwrite(str(scene / "rgb" / f"{i:06d}.png"), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(scene / "depth" / f"{i:06d}.png"), np.round(f.depth * 1000).astype(np.uint16))
        o = f.annotation.objects[0]
        cams[str(i)] = {"cam_K": f.annotation.K.ravel().tolist(), "depth_scale": 1.0}
        gts[str(i)] = [{"obj_id": 11, "cam_R_m2c": o.R.ravel().tolist(), "cam_t_m2c": (1000 * o.t).tolist()}]
        targets.append({"scene_id": 1, "im_id": i, "obj_id": 11, "inst_count": 1})
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    (scene / "scene_gt.json").write_text(json.dumps(gts))
    (box / "bop" / "hope" / "test_targets_bop19.json").write_text(json.dumps(targets))
    rs = box / "realsense"
    rs.mkdir()
    f = frames[2]
    cv2.imwrite(str(rs / "color.png"), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(rs / "depth.png"), np.round(f.depth * 1000).astype(np.uint16))
    K = f.annotation.K
    (rs / "K.json").write_text(json.dumps({"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
                                           "width": 160, "height": 120}))
    (box / "weights").mkdir()
    torch.save({f"module.{k}": v for k, v in build_model(TINY).state_dict().items()},
               box / "weights" / "Ketchup.pth")
    monkeypatch.setattr("dope_hope.model.checkpoint.load_config", lambda name: json.loads(json.dumps(TINY)))
    monkeypatch.chdir(box)
    return box


def test_task_sections_run_in_order(sandbox):
    for _heading, cmds in [b for b in readme_blocks()[1:] if b[0] not in (VIDEO_TASK, RECORDING_TASK, ADAPT_TASK)]:
        for argv in cmds:
            run_command(shrink(argv), sandbox)
    # What each section promises a user, checked on the files it left.
    assert len(list((sandbox / "data" / "ketchup").glob("0*.json"))) == 3
    assert (sandbox / "data" / "ketchup" / "preview.png").is_file()
    assert sorted(p.name for p in (sandbox / "data" / "ketchup_bop").glob("0*.json")) == ["000000.json", "000002.json"]
    assert (sandbox / "runs" / "ketchup" / "last.pt").is_file()
    shelf = load_checkpoint(sandbox / "runs" / "shelf" / "last.pt")
    assert [o["class_name"] for o in shelf["objects"]] == ["Bread", "Can", "Cereal", "Lemon", "Milk"]
    assert {json.loads(line)["class"] for line in (sandbox / "res" / "shelf" / "predictions.jsonl").read_text()
            .splitlines()} <= {"Can", "Lemon"}
    assert (sandbox / "shelf.onnx").is_file() and (sandbox / "can_isaac.onnx").is_file()
    assert json.loads((sandbox / "eval" / "shelf" / "summary.json").read_text())["gt_instances"] >= 1
    assert (sandbox / "res" / "realsense" / "color.overlay.png").is_file()
    assert (sandbox / "res" / "realsense" / "predictions.jsonl").is_file()
    for line in (sandbox / "res" / "new_object" / "predictions.jsonl").read_text().splitlines():
        rec = json.loads(line)  # the pretrained start on the Ketchup's cuboid, untrained
        assert rec["class"] == "Ketchup" and len(rec["cuboid_symmetries"]) == 3 and "pose_ambiguity" in rec
    assert (sandbox / "imported" / "Ketchup.pt").is_file()
    for name in ("ketchup.onnx", "ketchup_int8.onnx", "ketchup_isaac.onnx"):
        assert (sandbox / name).is_file()
    summary = json.loads((sandbox / "eval" / "ketchup" / "summary.json").read_text())
    assert summary["gt_instances"] >= 3
    csv = (sandbox / "dopehope-lite_hope-test.csv").read_text().splitlines()
    assert csv[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert (sandbox / "runs" / "ketchup_dr50" / "last.pt").is_file()


def test_video_section(tmp_path, monkeypatch):
    """The video / webcam / RealSense block on rendered demo scenes (module docstring)."""
    import cv2
    import fake_realsense
    from fitted_model import fit_demo_checkpoint
    from video_files import read_video, write_video

    from dope_hope.commands import infer as infer_cmd
    from dope_hope.demo_object import DEMO_CLASS_NAME, write_demo_object

    if not infer_cmd.DEMO_WEIGHTS.is_file():  # not shipped yet: a quickly fitted stand-in
        monkeypatch.setattr(infer_cmd, "DEMO_WEIGHTS", fit_demo_checkpoint(tmp_path / "fit" / "demo_lite.pt", seed=7))
    import dope_hope.model  # noqa: F401 - torchvision before the GL context (importing it after crashes)
    from dope_hope.synth import FrameGenerator

    work = tmp_path / "work"
    mesh = write_demo_object(work / "demo_out" / "mesh")
    from dope_hope.synth.settings import PLAIN_OVERRIDES

    # the demo's own scenes: no clutter, hard negatives or sensor artefacts (configs/demo.yaml), the box
    # at 0.45-0.6 m: inside the demo model's 0.45-0.9 m (at 320x240 its input sees it as at 640x480)
    still = {**PLAIN_OVERRIDES, "camera": {"focal_jitter": 0.0, "aspect_jitter": 0.0, "principal_jitter_px": 0.0}}
    with FrameGenerator(mesh, size=(320, 240), config={**still, "target": {"count": [1, 1], "distance_m": [0.45, 0.6],
                                                                          "truncation_prob": 0.0}},
                        class_name=DEMO_CLASS_NAME, depth_noise=True, seed=11) as gen:
        frames = [gen.render_frame(i) for i in range(8)]
    if write_video(work / "clip.mp4", [f.rgb for f in frames]).suffix != ".mp4":
        pytest.skip("this OpenCV cannot write mp4v (the README's clip.mp4)")
    K = frames[0].annotation.K
    (work / "camera_info.yaml").write_text(
        f"image_width: 320\nimage_height: 240\ncamera_name: webcam\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        f"  data: {K.ravel().tolist()}\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n"
        "  cols: 5\n  data: [0, 0, 0, 0, 0]\n")
    monkeypatch.setattr("dope_hope.io.streams.open_capture",
                        lambda target: cv2.VideoCapture(str(work / "clip.mp4") if target == 0 else target))
    rs = fake_realsense.install(monkeypatch, [(f.rgb, f.depth) for f in frames], K)
    monkeypatch.chdir(work)
    (heading, cmds), = [b for b in readme_blocks() if b[0] == VIDEO_TASK]
    for argv in cmds:
        run_command(shrink(argv), work)
    records = [json.loads(line) for line in (work / "res" / "clip" / "predictions.jsonl").read_text().splitlines()]
    assert records and all({"frame", "timestamp_s", "bbox_2d"} <= set(r) for r in records)
    assert {r["frame"] for r in records} <= set(range(8)) and len({r["frame"] for r in records}) >= 4
    tracked = [json.loads(line) for line in (work / "res" / "clip_tracked" / "predictions.jsonl").read_text().splitlines()]
    assert tracked and all({"track_id", "tracked", "R_detected", "t_detected"} <= set(r) for r in tracked)
    for out, n in (("res/clip/clip.overlay.mp4", 8), ("res/clip_live/clip.overlay.mp4", None),
                   ("res/webcam/camera0.overlay.mp4", None), ("res/rs/realsense.overlay.mp4", None)):
        count = len(read_video(work / out))
        assert count >= 1 and (n is None or count == n), (out, count)
    live = [json.loads(line) for line in (work / "res" / "rs" / "predictions.jsonl").read_text().splitlines()]
    assert live and all(r["ls_applied"] and "icp_applied" in r for r in live)
    assert ("align", rs.stream.color) in rs.calls and ("stop",) in rs.calls


def test_recording_section(tmp_path, monkeypatch):
    """The robot recording block on rendered demo scenes (module docstring)."""
    from fitted_model import fit_demo_checkpoint
    from ros_recordings import write_recording

    from dope_hope.commands import infer as infer_cmd
    from dope_hope.demo_object import DEMO_CLASS_NAME, write_demo_object

    if not infer_cmd.DEMO_WEIGHTS.is_file():  # not shipped yet: a quickly fitted stand-in
        monkeypatch.setattr(infer_cmd, "DEMO_WEIGHTS", fit_demo_checkpoint(tmp_path / "fit" / "demo_lite.pt", seed=7))
    import dope_hope.model  # noqa: F401 - torchvision before the GL context
    from dope_hope.synth import FrameGenerator
    from dope_hope.synth.settings import PLAIN_OVERRIDES

    work = tmp_path / "work"
    still = {**PLAIN_OVERRIDES, "camera": {"focal_jitter": 0.0, "aspect_jitter": 0.0, "principal_jitter_px": 0.0}}
    with FrameGenerator(write_demo_object(tmp_path / "mesh"), size=(320, 240),
                        config={**still, "target": {"count": [1, 1], "distance_m": [0.45, 0.6], "truncation_prob": 0.0}},
                        class_name=DEMO_CLASS_NAME, depth_noise=True, seed=11) as gen:
        rendered = [gen.render_frame(i) for i in range(3)]
    frames, K = [(f.rgb, f.depth) for f in rendered], rendered[0].annotation.K
    work.mkdir()
    write_recording(work / "robot.bag", "ros1", frames, K)
    write_recording(work / "robot_ros2", "ros2-mcap", frames, K, compressed="jpeg")
    monkeypatch.chdir(work)
    (heading, cmds), = [b for b in readme_blocks() if b[0] == RECORDING_TASK]
    outputs = [run_command(shrink(argv), work) for argv in cmds]
    assert "<- colour" in outputs[0] and "<- depth" in outputs[0]
    for res, name in (("robot", "robot"), ("robot2", "robot_ros2")):
        records = [json.loads(line) for line in (work / "res" / res / "predictions.jsonl").read_text().splitlines()]
        assert records and all({"stamp_ns", "frame_id"} <= set(r) for r in records)
        assert (work / "res" / res / f"{name}_poses" / f"{name}_poses.mcap").is_file()
    assert all("track_id" in json.loads(line) for line in (work / "res" / "robot" / "predictions.jsonl").open())


def test_adapt_section(tmp_path, monkeypatch):
    """The record, adapt, infer block on a recording of rendered demo scenes (module docstring)."""
    import shutil

    from fitted_model import fit_demo_checkpoint
    from ros_recordings import write_recording

    from dope_hope.assets import DEMO_WEIGHTS
    from dope_hope.demo_object import DEMO_CLASS_NAME, write_demo_object

    work = tmp_path / "work"
    mesh = write_demo_object(work / "hope" / "meshes" / "full" / "Ketchup")
    for f in list(mesh.parent.iterdir()):  # the demo box under the block's mesh path
        if f.suffix == ".obj":
            f.rename(f.with_name("textured.obj"))
    (work / "runs" / "ketchup").mkdir(parents=True)
    weights = DEMO_WEIGHTS if DEMO_WEIGHTS.is_file() else fit_demo_checkpoint(tmp_path / "fit" / "demo.pt", seed=7)
    shutil.copy(weights, work / "runs" / "ketchup" / "best.pt")
    import dope_hope.model  # noqa: F401 - torchvision before the GL context
    from dope_hope.synth import FrameGenerator
    from dope_hope.synth.settings import PLAIN_OVERRIDES

    still = {**PLAIN_OVERRIDES, "camera": {"focal_jitter": 0.0, "aspect_jitter": 0.0, "principal_jitter_px": 0.0}}
    with FrameGenerator(work / "hope" / "meshes" / "full" / "Ketchup" / "textured.obj", size=(320, 240),
                        config={**still, "target": {"count": [1, 1], "distance_m": [0.4, 0.5], "truncation_prob": 0.0}},
                        class_name=DEMO_CLASS_NAME, depth_noise=True, seed=11) as gen:
        rendered = [gen.render_frame(i) for i in range(3)]
        for i in range(3):
            gen.write_frame(work / "data" / "ketchup", 10 + i)
    write_recording(work / "lab", "ros2-mcap", [(f.rgb, f.depth) for f in rendered], rendered[0].annotation.K)
    monkeypatch.chdir(work)
    (heading, cmds), = [b for b in readme_blocks() if b[0] == ADAPT_TASK]
    outputs = [run_command(shrink(argv), work) for argv in cmds]
    assert "adapted model:" in outputs[0]
    adapted = load_checkpoint(work / "adapt" / "ketchup" / "adapted.pt")
    assert adapted["adapted"]["frame_count"] == 3 and adapted["adapted"]["rounds"][0]["counts"]["labelled_frames"] >= 1
    assert (work / "adapt" / "ketchup" / "preview_round_1.png").is_file()
    assert (work / "res" / "lab" / "predictions.jsonl").is_file()
