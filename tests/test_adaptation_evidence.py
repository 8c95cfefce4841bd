"""The depth's verdict on a pose (dope_hope.adaptation.evidence): the true pose of a box in front of a
table is kept, also where the sensor dropped half of its depth; the same pose 3 cm farther, 3 cm
to the side, against a depth that disagrees or over nothing but holes is rejected, each for its own
reason."""
from __future__ import annotations

import numpy as np
import pytest
from box_depth import box_surface_points, render_box_depth
from scipy.spatial.transform import Rotation

from dope_hope.adaptation.evidence import pose_evidence, rejection
from dope_hope.adaptation.settings import AdaptConfig, LabelSettings
from dope_hope.config import load_settings
from dope_hope.errors import ConfigError
from dope_hope.refine.depth import DepthImage

BOX = np.array([0.06, 0.10, 0.04])
HW = (240, 320)
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
R = Rotation.from_euler("xyz", [20, -30, 10], degrees=True).as_matrix()
T = np.array([0.02, -0.01, 0.55])
POINTS = box_surface_points(BOX)


def scene_depth(noise_m: float = 0.0015, seed: int = 0) -> DepthImage:
    """The box at (R, T) before a wall at 0.8 m, with sensor noise."""
    d = render_box_depth(BOX, R, T, K, HW)
    d = np.where(d > 0, d, 0.8) + np.random.default_rng(seed).normal(0, noise_m, HW)
    return DepthImage.from_raw(d.astype(np.float32), K)


def test_the_true_pose_is_kept():
    ev = pose_evidence(R, T, POINTS, scene_depth(), 0.9, LabelSettings())
    assert ev.kept and ev.reason == "ok"
    assert ev.support > 0.8 and ev.residual_m < 0.003 and ev.edge > 0.8


def test_holes_in_the_depth_say_nothing_against_the_true_pose():
    d = scene_depth()
    box = render_box_depth(BOX, R, T, K, HW) > 0
    holes = box & (np.random.default_rng(1).random(HW) < 0.5)  # a dark surface: half its pixels dropped
    ev = pose_evidence(R, T, POINTS, DepthImage.from_raw(np.where(holes, np.nan, d.metres).astype(np.float32), K),
                       0.9, LabelSettings())
    assert ev.kept and 0.4 < ev.measured < 0.7 and ev.support > 0.8


def test_a_pose_over_nothing_but_holes_is_rejected():
    box = render_box_depth(BOX, R, T, K, HW) > 0
    d = DepthImage.from_raw(np.where(box, np.nan, scene_depth().metres).astype(np.float32), K)
    ev = pose_evidence(R, T, POINTS, d, 0.9, LabelSettings())
    assert not ev.kept and ev.measured < 0.3 and "labels.min_measured" in ev.reason  # the outline sees the wall


def test_a_pose_3cm_farther_is_rejected_by_its_depth_support():
    t = T * (1 + 0.03 / np.linalg.norm(T))
    ev = pose_evidence(R, t, POINTS, scene_depth(), 0.9, LabelSettings())
    assert not ev.kept and ("labels.min_support" in ev.reason or "labels.min_points" in ev.reason)


def test_a_pose_3cm_to_the_side_is_rejected():
    ev = pose_evidence(R, T + [0.03, 0, 0], POINTS, scene_depth(), 0.9, LabelSettings())
    assert not ev.kept
    assert ev.edge < 0.5  # its outline left the box's depth edges


def test_a_depth_that_disagrees_rejects_the_true_pose():
    flat = DepthImage.from_raw(np.full(HW, 0.8, np.float32), K)  # the box is not there: the wall behind
    ev = pose_evidence(R, T, POINTS, flat, 0.9, LabelSettings())
    assert not ev.kept and "labels.min_support" in ev.reason and ev.residual_m > 0.2
    board = DepthImage.from_raw(np.full(HW, 0.3, np.float32), K)  # a board in front hides it all
    ev = pose_evidence(R, T, POINTS, board, 0.9, LabelSettings())
    assert not ev.kept and "labels.min_points" in ev.reason


def test_a_low_score_is_rejected_whatever_the_depth():
    ev = pose_evidence(R, T, POINTS, scene_depth(), 0.1, LabelSettings())
    assert not ev.kept and "labels.min_score" in ev.reason
    ev.score = 0.9
    assert rejection(ev, LabelSettings()) is None


def test_evidence_is_plain_json():
    rec = pose_evidence(R, T, POINTS, scene_depth(), 0.9, LabelSettings()).to_json()
    assert set(rec) >= {"score", "support", "measured", "residual_m", "edge", "points", "source", "kept", "reason"}
    assert rec["icp_fit"] is None and rec["source"] == "detected"


def test_settings_are_checked_with_their_section_names():
    cfg = load_settings(AdaptConfig, None, ["labels.min_support=0.7", "infer.multiscale.scales=[1]"])
    assert cfg.labels.min_support == 0.7 and cfg.infer.icp and cfg.infer.given() == {"icp": True}
    assert AdaptConfig().infer.multiscale.scales == (1.0, 0.75, 1.33)
    with pytest.raises(ConfigError, match="labels.min_support"):
        load_settings(AdaptConfig, None, ["labels.min_support=2"])
    with pytest.raises(ConfigError, match="finetune.rounds"):
        load_settings(AdaptConfig, None, ["finetune.rounds=0"])
