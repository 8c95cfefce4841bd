"""Labels of frames with known truth (dope_hope.adaptation.labelling): the model's confirmed
detection is kept and lies on the truth; a frame whose colour shows nothing (the detector
misses) gets the pose the tracker carries from its neighbour, re-fitted against its depth, and a
run of such frames longer than ``carry.max_frames`` is crossed by chaining, never from one input
folder's sequence into another's."""
from __future__ import annotations

import numpy as np
import pytest
from adapt_frames import demo_weights, write_scene_frames

from dope_hope.adaptation.labelling import DepthLabeller, LabelledFrame, frame_depth, sequences, unseeded
from dope_hope.adaptation.settings import AdaptConfig
from dope_hope.inference.predictor import DopePredictor
from dope_hope.io.dope_json import read_dope_json
from dope_hope.io.images import read_depth_m, read_rgb
from dope_hope.io.streams import Frame


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("labelling")
    frames, mesh = write_scene_frames(tmp, count=1)
    cfg = AdaptConfig.from_mapping({"infer": {"multiscale": {"scales": [1.0]}}})
    predictor = DopePredictor(demo_weights(tmp), mesh=mesh, options=cfg.infer.given())
    truth = read_dope_json(frames / "000000.json")
    frame = Frame(0, 0.0, "000000.png", read_rgb(frames / "000000.png"), truth.K,
                  read_depth_m(frames / "000000.depth.png"))
    return DepthLabeller(predictor, cfg), frame, truth.objects[0]


def test_the_confirmed_detection_is_kept_on_the_truth(scene):
    labeller, frame, truth = scene
    lf = labeller.label_frame(frame)
    assert len(lf.kept) == 1 and lf.detected
    lab = lf.kept[0]
    assert lab.evidence.source == "detected" and lab.evidence.reason == "ok"
    assert np.linalg.norm(lab.t - truth.t) < 0.02
    assert lab.evidence.support >= 0.6 and lab.evidence.edge >= 0.5


def test_a_missed_frame_gets_a_carried_label(scene):
    labeller, frame, truth = scene
    blind = Frame(1, 1.0, "blind.png", np.full_like(frame.rgb, 127), frame.K, frame.depth)  # the colour shows nothing
    frames = [labeller.label_frame(frame), labeller.label_frame(blind), labeller.label_frame(frame)]
    assert not frames[1].kept and not frames[1].detected  # the detector missed it
    depth = frame_depth(frame)
    assert labeller.carry(frames, lambda i: depth) == 1
    (lab,) = frames[1].kept
    assert lab.evidence.source == "carried" and lab.detection is None
    assert np.linalg.norm(lab.t - truth.t) < 0.02
    assert [len(f.kept) for f in frames] == [1, 1, 1]  # the detected frames get nothing carried


def test_a_carried_pose_the_depth_denies_is_rejected(scene):
    labeller, frame, _ = scene
    wall = Frame(1, 1.0, "wall.png", np.full_like(frame.rgb, 127), frame.K,
                 np.full(frame.depth.shape, 1.5, np.float32))  # the object is gone
    frames = [labeller.label_frame(frame), labeller.label_frame(wall)]
    walls = frame_depth(wall)
    assert labeller.carry(frames, lambda i: frame_depth(frame) if i == 0 else walls) == 0
    assert not frames[1].kept
    assert frames[1].rejected and frames[1].rejected[0].evidence.source == "carried"


@pytest.mark.parametrize("chain, carried", [(False, 1), (True, 3)])
def test_a_long_run_of_missed_frames_is_crossed_by_chaining(scene, chain, carried):
    labeller, frame, truth = scene
    cfg = AdaptConfig.from_mapping({"infer": {"multiscale": {"scales": [1.0]}},
                                    "carry": {"max_frames": 1, "chain": chain}})
    chained = DepthLabeller(labeller.predictor, cfg)
    blind = Frame(1, 1.0, "blind.png", np.full_like(frame.rgb, 127), frame.K, frame.depth)
    frames = [chained.label_frame(frame)] + [chained.label_frame(blind) for _ in range(3)]
    depth = frame_depth(frame)
    assert chained.carry(frames, lambda i: depth) == carried  # one frame from the detection, or all three
    assert [len(f.kept) for f in frames] == [1] * (carried + 1) + [0] * (3 - carried)
    assert all(np.linalg.norm(f.kept[0].t - truth.t) < 0.02 for f in frames[1:carried + 1])
    assert all(len(f.rejected) <= 1 for f in frames)  # a frame's rejected carried pose recorded once


def test_the_input_folders_are_sequences_of_their_own(scene):
    labeller, frame, _ = scene
    named = [LabelledFrame(i, n, frame.K, (4, 4)) for i, n in enumerate(["a/0.png", "a/1.png", "b/0.png", "0.png"])]
    assert sequences(named) == [range(0, 2), range(2, 3), range(3, 4)]
    named[1].kept.append(labeller.label_frame(frame).kept[0])  # a confirmed detection in a/
    assert unseeded(named) == [2, 3]  # b/ and the top folder's frame: nothing to carry there
    first = labeller.label_frame(Frame(0, 0.0, "seq_00/000019.png", frame.rgb, frame.K, frame.depth))
    blind = labeller.label_frame(Frame(1, 1.0, "seq_01/000000.png", np.full_like(frame.rgb, 127), frame.K, frame.depth))
    depth = frame_depth(frame)
    assert labeller.carry([first, blind], lambda i: depth) == 0  # the same depth, but another sequence
    assert not blind.kept and not blind.rejected
