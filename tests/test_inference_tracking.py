"""Tracking: association, the SE(3) filter with symmetries, coasting, settings, `infer --track`."""
from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dope_hope.demo_object import DEMO_SIZE_M, demo_symmetries
from dope_hope.errors import ConfigError
from dope_hope.geometry import cuboid_keypoints, project_points, projected_bbox, rotation_error_deg
from dope_hope.inference.detection import Detection
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.pose_filter import PoseFilter, closest_equivalent
from dope_hope.inference.tracking import PoseTracker, TrackingSettings
from dope_hope.io.predictions import read_predictions
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.line_search import LineSearchSettings
from dope_hope.symmetry.transforms import declaration_transforms

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
HW = (480, 640)
CUBOID = cuboid_keypoints(DEMO_SIZE_M)
R0 = Rotation.from_euler("xyz", [20, 30, 10], degrees=True).as_matrix()
FLIP_Y = Rotation.from_euler("y", 180, degrees=True).as_matrix()


def fake_predictor(**tracking):
    """What the tracker reads of a DopePredictor: its classes, each object's box and surface
    points (``objects``), options."""
    box = SimpleNamespace(class_name="DemoBox", cuboid_size_m=DEMO_SIZE_M, cuboid_center_m=np.zeros(3),
                          cuboid_mesh=CUBOID, bbox_points=CUBOID[:8], model_points=CUBOID)
    return SimpleNamespace(class_names=("DemoBox",), objects=[box],
                           options=SimpleNamespace(line_search=LineSearchSettings(), icp=False,
                                                   tracking=tracking))


def detection(R, t, score=0.9) -> Detection:
    t = np.asarray(t, dtype=np.float64)
    uv = project_points(CUBOID, K, R, t)
    return Detection("DemoBox", score, R, t, uv, np.ones(9), np.ones(9, bool), uv, 0.5, DEMO_SIZE_M,
                     bbox_2d=projected_bbox(CUBOID[:8], K, R, t, HW))


def make_filter(R=R0, t=(0.0, 0.0, 0.6), **kw) -> PoseFilter:
    return PoseFilter(R, np.asarray(t), declaration_transforms(demo_symmetries()), TrackingSettings(**kw))


# ----------------------------------------------------------------------------- filter
def test_a_flip_between_symmetric_poses_is_no_motion():
    f = make_filter()
    for _ in range(5):
        f.predict()
        f.update(R0, [0.0, 0.0, 0.6])
    f.predict()
    R, t = f.update(R0 @ FLIP_Y, [0.0, 0.0, 0.6])  # the box turned 180 deg: the same box
    assert rotation_error_deg(R, R0) < 1e-3
    np.testing.assert_allclose(t, [0.0, 0.0, 0.6], atol=1e-9)
    R_eq, _, angle = closest_equivalent(R0 @ FLIP_Y, np.zeros(3), R0, declaration_transforms(demo_symmetries()))
    assert angle < 1e-3 and rotation_error_deg(R_eq, R0) < 1e-3


def test_a_turn_that_is_no_symmetry_is_motion():
    f = make_filter(rotation_gate_deg=180.0)
    f.predict()
    R, _ = f.update(Rotation.from_euler("y", 20, degrees=True).as_matrix() @ R0, [0.0, 0.0, 0.6])
    assert rotation_error_deg(R, R0) > 5.0


def test_constant_velocity_lags_at_most_one_frame():
    """Noisy measurements of a box moving at 0.5 m/s (30 frames/s) and turning 30 deg/s."""
    rng = np.random.default_rng(0)
    f, v, w = None, np.array([0.0167, 0.0, 0.0]), np.radians(1.0)  # per frame
    lags, errs = [], []
    for k in range(60):
        R_true = Rotation.from_euler("y", w * k).as_matrix() @ R0
        t_true = np.array([-0.4, 0.0, 0.6]) + v * k
        R_m = Rotation.from_rotvec(rng.normal(0, np.radians(1.0), 3)).as_matrix() @ R_true
        t_m = t_true + rng.normal(0, 0.002, 3)
        if f is None:
            f = make_filter(R_m, t_m)
            continue
        f.predict()
        R, t = f.update(R_m, t_m)
        if k >= 10:
            lags.append(-(t - t_true) @ v / (v @ v))
            errs.append(rotation_error_deg(R, R_true))
    assert abs(np.mean(lags)) < 0.5 and max(abs(x) for x in lags) < 1.0
    assert np.mean(errs) < 1.0


def test_smoothing_reduces_jitter_at_rest():
    rng = np.random.default_rng(1)
    t_true = np.array([0.0, 0.0, 0.6])
    f, raw, out = None, [], []
    for _ in range(80):
        t_m = t_true + rng.normal(0, 0.002, 3)
        if f is None:
            f = make_filter(R0, t_m)
            continue
        f.predict()
        out.append(f.update(R0, t_m)[1] - t_true)
        raw.append(t_m - t_true)
    steps_out, steps_raw = np.diff(out[20:], axis=0), np.diff(raw[20:], axis=0)  # frame-to-frame jitter
    assert np.std(steps_out) < np.std(steps_raw) / 3 and np.std(out[20:]) < np.std(raw[20:]) / 2


def test_an_outlying_translation_is_ignored_and_a_real_jump_restarts():
    f = make_filter()
    for _ in range(10):
        f.predict()
        f.update(R0, [0.0, 0.0, 0.6])
    f.predict()
    _, t = f.update(R0, [0.0, 0.0, 0.55])  # a line search fooled by something in front
    np.testing.assert_allclose(t, [0.0, 0.0, 0.6], atol=1e-3)
    for _ in range(3):  # the object really is there now
        f.predict()
        _, t = f.update(R0, [0.03, 0.0, 0.6])
    np.testing.assert_allclose(t, [0.03, 0.0, 0.6], atol=3e-3)


def test_a_poorly_fitting_detection_moves_the_track_less():
    """reprojection_px: a detection with a large reprojection error counts as noisier."""
    moved = {}
    for ref in (0.0, 1.0):
        tracker = PoseTracker(fake_predictor(), settings={"reprojection_px": ref, "reprojection_power": 2.0})
        for k in range(5):
            tracker.update([detection(R0, [0.0, 0.0, 0.6])], K, frame=k, image_hw=HW)
        det = detection(R0, [0.004, 0.0, 0.6])
        det.reprojection_error_px = 4.0
        (o,) = tracker.update([det], K, frame=5, image_hw=HW)
        moved[ref] = o.t[0]
    assert 0 < moved[1.0] < moved[0.0] / 3


# ----------------------------------------------------------------------------- tracker
def test_two_crossing_boxes_keep_their_ids():
    tracker = PoseTracker(fake_predictor())
    ids = {}
    for k in range(40):
        u = (k - 20) * 0.005  # they pass at frame 20, 10 cm apart in depth
        dets = [detection(R0, [u, 0.0, 0.55]), detection(R0 @ FLIP_Y, [-u, 0.0, 0.65], score=0.8)]
        for o in tracker.update(dets, K, frame=k, image_hw=HW):
            which = "near" if o.t[2] < 0.6 else "far"
            ids.setdefault(which, set()).add(o.track_id)
            assert o.tracked == "detected"
    assert ids == {"near": {1}, "far": {2}}


def test_a_missed_frame_is_coasted_at_most_max_coast_frames():
    tracker = PoseTracker(fake_predictor(), settings={"confirm_hits": 3, "max_coast": 2, "max_misses": 4})
    v = np.array([0.01, 0.0, 0.0])
    for k in range(5):
        (o,) = tracker.update([detection(R0, [0.0, 0.0, 0.6] + v * k)], K, frame=k, image_hw=HW)
        assert (o.track_id, o.tracked) == (1, "detected") and o.confirmed == (k >= 2)
    coasted = [tracker.update([], K, frame=k, image_hw=HW) for k in range(5, 9)]
    assert [len(c) for c in coasted] == [1, 1, 0, 0]
    o = coasted[0][0]
    assert (o.track_id, o.tracked, o.detection) == (1, "coasted", None)
    np.testing.assert_allclose(o.t, [0.05, 0.0, 0.6], atol=1e-3)  # predicted along its motion
    rec = o.to_json("clip#000005", frame=5)
    assert rec["R_detected"] is None and rec["t_detected"] is None and rec["tracked"] == "coasted"
    # back within max_misses: the same track; after it: a new one
    (o,) = tracker.update([detection(R0, [0.09, 0.0, 0.6])], K, frame=9, image_hw=HW)
    assert o.track_id == 1
    for k in range(10, 15):
        tracker.update([], K, frame=k, image_hw=HW)
    (o,) = tracker.update([detection(R0, [0.15, 0.0, 0.6])], K, frame=15, image_hw=HW)
    assert o.track_id == 2


def test_tentative_tracks_are_not_coasted():
    tracker = PoseTracker(fake_predictor())
    tracker.update([detection(R0, [0.0, 0.0, 0.6])], K, frame=0, image_hw=HW)
    assert tracker.update([], K, frame=1, image_hw=HW) == []


def test_coasting_refines_the_prediction_against_the_depth():
    from box_depth import box_surface_points, render_box_depth

    pred = fake_predictor()
    pred.objects[0].model_points = box_surface_points(DEMO_SIZE_M, spacing=0.01)
    tracker = PoseTracker(pred)
    for k in range(4):
        tracker.update([detection(R0, [0.0, 0.0, 0.6])], K, frame=k, image_hw=HW)
    depth_m = render_box_depth(DEMO_SIZE_M, R0, np.array([0.0, 0.0, 0.62]), K, HW)
    (o,) = tracker.update([], K, DepthImage.from_raw(depth_m.astype(np.float32), K), frame=4)
    assert o.tracked == "coasted" and o.ls_applied
    assert abs(o.t[2] - 0.62) < 0.004


def test_record_carries_both_poses_and_evaluate_reads_it(tmp_path):
    tracker = PoseTracker(fake_predictor())
    det = detection(R0 @ FLIP_Y, [0.0, 0.0, 0.6])
    tracker.update([detection(R0, [0.0, 0.0, 0.6])], K, frame=0, image_hw=HW)
    (o,) = tracker.update([det], K, frame=1, image_hw=HW)
    rec = o.to_json("clip.mp4#000001", frame=1)
    assert rotation_error_deg(np.array(rec["R"]), R0) < 1e-3  # the track's pose, not the flip
    assert rotation_error_deg(np.array(rec["R_detected"]), R0 @ FLIP_Y) < 1e-3
    assert (rec["track_id"], rec["tracked"]) == (1, "detected")
    path = tmp_path / "p.jsonl"
    path.write_text(json.dumps(rec) + "\n")
    (p,), _ = read_predictions(path)  # R and quaternion_xyzw agree
    assert rotation_error_deg(p.R, R0) < 1e-4 and p.extra["track_id"] == 1


# ----------------------------------------------------------------------------- settings
def test_settings_are_checked_with_the_inference_options():
    assert InferenceOptions.from_mapping({"tracking": {"max_coast": 2}}).tracking == TrackingSettings(max_coast=2)
    for bad, words in (({"foo": 1}, "foo"), ({"max_coast": 20}, "max_coast"), ({"gate_m": 0}, "gate_m"),
                       ({"confirm_hits": 1.5}, "confirm_hits"), ({"coast_search": [1.1, 1.2]}, "coast_search"),
                       ({"coast_refine": "yes"}, "coast_refine")):
        with pytest.raises(ConfigError, match=words):
            InferenceOptions.from_mapping({"tracking": bad})


# ----------------------------------------------------------------------------- command line
def test_infer_track_on_a_video_writes_tracked_records(tmp_path, monkeypatch, capsys):
    """A 160x120 clip of one still box (perfect maps: tests/_targets_backend.py), missed by the
    network in frames 4 and 5: ids, both poses, and coasted records for the missed frames."""
    from _targets_backend import TargetsBackend
    from video_files import write_video

    from dope_hope import cli

    Ks = np.array([[150.0, 0.0, 80.0], [0.0, 150.0, 60.0], [0.0, 0.0, 1.0]])
    pose = (R0, np.array([0.0, 0.0, 0.5]))

    class Blinking(TargetsBackend):
        def run(self, batch):
            belief, affinity = super().run(batch)
            if len(self.calls) in (5, 6):  # frames 4 and 5: nothing found
                belief = np.zeros_like(belief)
            return belief, affinity

    monkeypatch.setattr("dope_hope.inference.backends.open_backend",
                        lambda *a, **k: Blinking("DemoBox", DEMO_SIZE_M, [pose], Ks, (120, 160)))
    video = write_video(tmp_path / "clip", [np.full((120, 160, 3), 128, np.uint8)] * 8, fps=10.0)
    out = tmp_path / "out"
    code = cli.main(["infer", str(video), "--weights", "w.pt", "--fx", "150", "--fy", "150", "--cx", "80",
                     "--cy", "60", "--track", "--out", str(out), "--no-progress"])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    records = [json.loads(line) for line in stdout.splitlines() if line.strip()]
    assert [r["frame"] for r in records] == list(range(8))
    assert [r["tracked"] for r in records] == ["detected"] * 4 + ["coasted"] * 2 + ["detected"] * 2
    assert {r["track_id"] for r in records} == {1}
    for r in records:
        assert rotation_error_deg(np.array(r["R"]), R0) < 1.0 and np.linalg.norm(np.array(r["t"]) - pose[1]) < 0.01
        assert (r["R_detected"] is None) == (r["tracked"] == "coasted")
    preds, _ = read_predictions(out / "predictions.jsonl")
    assert len(preds) == 8 and preds[4].extra["tracked"] == "coasted"


def test_track_is_for_streams_only(tmp_path, capsys):
    from dope_hope import cli
    from dope_hope.io.images import write_rgb

    write_rgb(tmp_path / "a.png", np.zeros((32, 32, 3), np.uint8))
    code = cli.main(["infer", str(tmp_path / "a.png"), "--track", "--fx", "30", "--fy", "30", "--cx", "16",
                     "--cy", "16", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--track" in err[0]


def test_tracker_takes_the_symmetries_the_model_records():
    """Without a mesh the tracker uses the model's object list (a multi-object checkpoint records
    each object's symmetries, e.g. found on its mesh); given ones win; else the catalog's."""
    predictor = fake_predictor()
    predictor.objects[0].symmetries = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    tracker = PoseTracker(predictor)
    assert len(tracker.symmetries["DemoBox"]) == 360 // 5  # continuous about z every 5 degrees
    turn = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    assert closest_equivalent(R0 @ turn, np.zeros(3), R0, tracker.symmetries["DemoBox"])[2] < 1e-3
    given = PoseTracker(predictor, symmetries={"DemoBox": np.eye(4)[None]})
    assert len(given.symmetries["DemoBox"]) == 1
    assert len(PoseTracker(fake_predictor()).symmetries["DemoBox"]) == 4  # the demo box's own flips
