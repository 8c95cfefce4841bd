"""The stream sink of ROS 2 messages (dope_hope/ros/outputs.py): detections and tracked
objects become the poses MCAP's messages, on the recorded stamp and frame_id, or, for a video /
camera frame, on the wall clock of the stream's start plus the frame's timestamp and ``camera``."""
from __future__ import annotations

import time
from types import SimpleNamespace

import cv2
import numpy as np
from rosbags.highlevel import AnyReader

from dope_hope.io.streams import Frame
from dope_hope.ros.outputs import RosOutputs, posed_objects
from dope_hope.ros.recording_writer import RecordingWriter

K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])


def _det(track_id=None):
    fields = {"class_name": "DemoBox", "score": 0.8, "R": np.eye(3), "t": np.array([0.0, 0.0, 0.5]),
              "cuboid_size_m": np.array([0.1, 0.2, 0.05]), "cuboid_center_m": np.zeros(3)}
    return SimpleNamespace(**fields, **({} if track_id is None else {"track_id": track_id}))


def _read(path):
    with AnyReader([path]) as reader:
        return [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def test_video_frames_are_stamped_from_the_wall_clock_and_named_camera(tmp_path):
    rgb = np.full((48, 64, 3), 90, np.uint8)
    before = time.time_ns()
    outputs = RosOutputs(RecordingWriter(tmp_path / "clip_poses"), None, overlays=True)
    for i, ts in enumerate((0.0, 0.5)):
        outputs.on_frame(Frame(index=i, timestamp_s=ts, name=f"clip.mp4#{i:06d}", rgb=rgb, K=K), [_det()])
    after = time.time_ns()
    msgs = _read(outputs.close())
    dets = [(t, m) for topic, t, m in msgs if topic == "/dope_hope/detections"]
    assert before <= dets[0][0] <= after and dets[1][0] - dets[0][0] == 500_000_000
    assert all(m.header.frame_id == "camera" for _, m in dets)
    overlay = next(m for topic, _, m in msgs if topic == "/dope_hope/overlay/compressed")
    assert cv2.imdecode(np.asarray(overlay.data), cv2.IMREAD_COLOR).shape == (48, 64, 3)


def test_recorded_frames_keep_their_stamp_and_tracks_their_id(tmp_path):
    outputs = RosOutputs(RecordingWriter(tmp_path / "rec_poses"), None, overlays=False)
    frame = Frame(index=0, timestamp_s=0.0, name="rec.bag#000000", rgb=np.zeros((48, 64, 3), np.uint8), K=K,
                  stamp_ns=1_700_000_000_000_000_007, frame_id="cam_optical")
    outputs.on_frame(frame, [_det(track_id=4)])
    msgs = _read(outputs.close())
    assert {t for _, t, _ in msgs} == {1_700_000_000_000_000_007}
    assert "/dope_hope/overlay/compressed" not in {topic for topic, _, _ in msgs}
    tf = next(m for topic, _, m in msgs if topic == "/tf")
    assert tf.transforms[0].header.frame_id == "cam_optical" and tf.transforms[0].child_frame_id == "DemoBox_4"
    assert posed_objects([_det(track_id=4)])[0].track_id == 4 and posed_objects([_det()])[0].track_id is None
