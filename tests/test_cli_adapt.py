"""`dope-hope adapt` end to end on a few demo frames: labels, a round of training, the adapted
model's record; a run that resumes to the same labels; bad input refused in one line with exit
status 2 and nothing written."""
from __future__ import annotations

import json
import shutil

import pytest
import torch
from adapt_frames import demo_weights, write_scene_frames
from test_cli_mistakes import run_cli

from dope_hope.model.checkpoint import load_checkpoint

FAST = ["--set", "finetune.steps=1", "finetune.rounds=1", "infer.multiscale.scales=[1]", "--no-progress"]


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("adapt")
    frames, mesh = write_scene_frames(tmp, count=3)
    return tmp, frames, mesh, demo_weights(tmp)


def test_adapt_labels_trains_and_resumes_to_the_same_result(lab, capsys, monkeypatch):
    tmp, frames, mesh, weights = lab
    out = tmp / "job"
    argv = ["adapt", frames, "--weights", weights, "--mesh", mesh, "--synthetic", frames, "--out", out, "--preview", *FAST]
    code, stdout, err = run_cli(argv, capsys)
    assert code == 0, err
    assert "adapted model:" in stdout
    labels = out / "round_1" / "labels"
    written = json.loads((labels / "000000.json").read_text())
    assert written["objects"] and written["adapt"]["labels"][0]["kept"] and "support" in written["adapt"]["labels"][0]
    counts = json.loads((labels / "summary.json").read_text())["counts"]
    assert counts["frames"] == 3 and counts["labelled_frames"] >= 2
    model = load_checkpoint(out / "adapted.pt")
    adapted = model["adapted"]
    assert adapted["frame_count"] == 3 and adapted["rounds"][0]["counts"] == counts and adapted["synthetic"]
    # the run's final weights (not a best.pt chosen on a frame or two), with the thresholds it started from
    final = load_checkpoint(out / "round_1" / "train" / "last.pt")
    assert all(torch.equal(model["model"][k], v) for k, v in final["model"].items())
    start = load_checkpoint(weights)
    assert model.get("min_score") == start.get("min_score") is not None and final.get("min_score") is None
    assert (out / "preview_round_1.png").is_file()
    first = (labels / "labels.jsonl").read_text()

    # Interrupted while labelling its second frame, its training saved: the same command goes on.
    log = out / "round_1" / "detected.jsonl"
    lines = log.read_text().splitlines()
    assert len(lines) == 3
    log.write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])
    shutil.rmtree(labels)
    (out / "round_1" / "trained.json").unlink()
    (out / "adapted.pt").unlink()

    def no_reading(*args, **kwargs):
        raise AssertionError("the frames were read again")

    monkeypatch.setattr("dope_hope.adaptation.run.open_unlabelled", no_reading)
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    assert (labels / "labels.jsonl").read_text() == first
    assert (out / "adapted.pt").is_file()

    code, _, err = run_cli([*argv, "--set", "labels.min_support=0.7"], capsys)
    assert code == 2 and "another adapt job" in err and "settings.labels.min_support" in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("case, expected", [
    ("no_weights", "--weights"),
    ("no_mesh", "--mesh"),
    ("no_depth", "no registered depth image"),
    ("video_without_depth", "a video holds no depth"),
    ("camera", "record first"),
    ("bad_setting", "labels.min_edge"),
    ("no_synthetic", "--synthetic"),
])
def test_bad_input_is_one_line_and_nothing_is_written(lab, capsys, case, expected):
    tmp, frames, mesh, weights = lab
    out = tmp / f"bad_{case}"
    inputs = [frames]
    args = ["--weights", weights, "--mesh", mesh, "--synthetic", frames]
    if case == "no_weights":
        args[1] = tmp / "missing.pt"
    elif case == "no_mesh":
        args[3] = tmp / "missing.obj"
    elif case == "no_depth":
        bare = tmp / "bare"
        bare.mkdir(exist_ok=True)
        shutil.copy(frames / "000000.png", bare / "000000.png")
        shutil.copy(frames / "000000.json", bare / "000000.json")
        inputs = [bare]
    elif case == "video_without_depth":
        inputs = [tmp / "clip.mp4"]
        (tmp / "clip.mp4").write_bytes(b"")
        k = tmp / "K.json"
        k.write_text(json.dumps({"fx": 300, "fy": 300, "cx": 159.5, "cy": 119.5}))
        args += ["--camera", k]
    elif case == "camera":
        inputs = ["0"]
    elif case == "bad_setting":
        args += ["--set", "labels.min_edge=2"]
    elif case == "no_synthetic":
        args = args[:4]
    code, _, err = run_cli(["adapt", *inputs, *args, "--out", out], capsys)
    assert code == 2, err
    assert expected in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_a_sequence_the_first_pass_confirms_nothing_in_is_labelled_again_at_the_seed_sizes(lab, capsys):
    tmp, frames, mesh, weights = lab
    argv = ["adapt", frames, "--weights", weights, "--mesh", mesh, "--synthetic", frames, "--no-progress",
            "--set", "finetune.steps=1", "finetune.rounds=1", "infer.multiscale.scales=[0.25]"]
    code, _, err = run_cli([*argv, "carry.seed_scales=null", "--out", tmp / "unseeded"], capsys)
    assert code == 2 and "confirms no label" in err  # at a quarter of its size the model finds nothing
    code, _, err = run_cli([*argv, "carry.seed_scales=[1]", "--out", tmp / "seeded"], capsys)
    assert code == 0, err
    seeded = [json.loads(line) for line in (tmp / "seeded" / "round_1" / "seeded.jsonl").read_text().splitlines()]
    assert [r["index"] for r in seeded] == [0, 1, 2] and sum(bool(r["kept"]) for r in seeded) >= 2
    counts = json.loads((tmp / "seeded" / "round_1" / "labels" / "summary.json").read_text())["counts"]
    assert counts["detected_kept"] >= 2
