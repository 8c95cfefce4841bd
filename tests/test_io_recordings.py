"""Recordings in and poses out, as a library: message decoding, topic choice, depth pairing,
the recorded camera, the MCAP writer and the pose messages (dope_hope/ros/recordings.py,
recording_writer.py, pose_messages.py, message_types.py in dope_hope/ros/). Recordings are written here by rosbags'
own writers (tests/ros_recordings.py) from small synthetic images."""
from __future__ import annotations

import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from ros_recordings import (
    COLOUR,
    DEPTH,
    FRAME_ID,
    INFO,
    PERIOD_NS,
    T0_NS,
    colour_message,
    depth_message,
    info_message,
    write_recording,
)

from dope_hope.errors import CameraError, ConfigError, InputFileError
from dope_hope.io.streams import is_recording, stream_kind
from dope_hope.ros.message_types import ros1_typestore, ros2_typestore
from dope_hope.ros.pose_messages import TOPICS, PosedObject, PoseMessages
from dope_hope.ros.recording_writer import RecordingWriter
from dope_hope.ros.recordings import (
    RecordingSource,
    TopicInfo,
    camera_from_info,
    choose_topics,
    decode_depth,
    decode_image,
    topic_table,
)

W, H = 32, 24
K = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
T2 = ros2_typestore().types


def _frames(n: int = 3) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(0)
    return [(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), rng.uniform(0.3, 2.0, (H, W)).astype(np.float32))
            for _ in range(n)]


def _grab_all(source: RecordingSource):
    return [g.load() for g in source.grab()]


# ----------------------------------------------------------------------------- decoding
@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_raw_colour_encodings_decode_to_rgb(encoding):
    rgb = _frames(1)[0][0]
    out = decode_image(colour_message(T2, False, rgb, T0_NS, encoding=encoding), "rec topic /c")
    want = cv2.cvtColor(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB) if encoding == "mono8" else rgb
    assert out.shape == (H, W, 3) and out.dtype == np.uint8 and np.array_equal(out, want)


def test_padded_rows_and_compressed_colour():
    rgb = _frames(1)[0][0]
    padded = np.zeros((H, W * 3 + 4), np.uint8)
    padded[:, : W * 3] = rgb.reshape(H, -1)
    msg = T2["sensor_msgs/msg/Image"](header=colour_message(T2, False, rgb, T0_NS).header, height=H, width=W,
                                      encoding="rgb8", is_bigendian=0, step=W * 3 + 4, data=padded.ravel())
    assert np.array_equal(decode_image(msg, "x"), rgb)
    assert np.array_equal(decode_image(colour_message(T2, False, rgb, T0_NS, compressed="png"), "x"), rgb)
    msg = colour_message(T2, False, rgb, T0_NS, compressed="jpeg")
    bgr = cv2.imdecode(np.asarray(msg.data), cv2.IMREAD_COLOR)
    assert np.array_equal(decode_image(msg, "x"), bgr[..., ::-1])


def test_unsupported_encodings_name_the_topic():
    rgb = _frames(1)[0][0]
    msg = colour_message(T2, False, rgb, T0_NS)
    msg.encoding = "yuv422"
    with pytest.raises(InputFileError, match=r"rec\.mcap topic /c: Image encoding 'yuv422' is not supported"):
        decode_image(msg, "rec.mcap topic /c")
    depth = depth_message(T2, False, _frames(1)[0][1], T0_NS)
    depth.encoding = "8UC1"
    with pytest.raises(InputFileError, match="not supported for depth"):
        decode_depth(depth, "rec.mcap topic /d")
    with pytest.raises(InputFileError, match="not a colour image"):
        decode_image(depth_message(T2, False, _frames(1)[0][1], T0_NS, compressed=True), "x")
    short = colour_message(T2, False, rgb, T0_NS)
    short.data = short.data[:100]
    with pytest.raises(InputFileError, match="truncated or malformed"):
        decode_image(short, "x")


def test_depth_encodings_are_metres():
    d = _frames(1)[0][1]
    mm = np.round(d * 1000) / 1000
    assert np.allclose(decode_depth(depth_message(T2, False, d, T0_NS), "x"), mm, atol=1e-6)
    assert np.allclose(decode_depth(depth_message(T2, False, d, T0_NS, compressed=True), "x"), mm, atol=1e-6)
    d_nan = d.copy()
    d_nan[0, 0] = np.nan
    f = decode_depth(depth_message(T2, False, d_nan, T0_NS, encoding="32FC1"), "x")
    assert f[0, 0] == 0 and np.allclose(f[1:], d[1:])
    # image_transport's compressedDepth of 32FC1: inverse depth quantised (value = A / z + B,
    # A = q (q + 1), B = 1 - A / max depth; q = 100, max depth 10 m as the plugin's defaults)
    a = np.float32(100.0 * 101.0)
    b = np.float32(1.0 - a / 10.0)
    q = np.round(a / d + b).astype(np.uint16)
    q[0, 0] = 0
    data = np.concatenate([np.frombuffer(np.int32(0).tobytes() + a.tobytes() + b.tobytes(), np.uint8),
                           cv2.imencode(".png", q)[1].ravel()])
    msg = T2["sensor_msgs/msg/CompressedImage"](header=depth_message(T2, False, d, T0_NS).header,
                                                format="32FC1; compressedDepth png", data=data)
    out = decode_depth(msg, "x")
    assert out[0, 0] == 0 and np.allclose(out[1:], d[1:], rtol=0.02)


# ----------------------------------------------------------------------------- topics
def _infos(*pairs):
    return {n: TopicInfo(n, t, 3) for n, t in pairs}


IMG, CMP, CI = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"


def test_realsense_names_are_chosen_and_the_raw_twin_preferred():
    topics = _infos((COLOUR, IMG), (COLOUR + "/compressed", CMP), (DEPTH, IMG), ("/camera/depth/image_rect_raw", IMG),
                    (INFO, CI), ("/camera/depth/camera_info", CI), ("/camera/infra1/image_rect_raw", IMG))
    chosen = choose_topics("rec.bag", topics)
    assert (chosen.image, chosen.depth, chosen.camera_info) == (COLOUR, DEPTH, INFO)
    assert choose_topics("rec.bag", topics, depth="none").depth is None
    only_compressed = _infos((COLOUR + "/compressed", CMP), (INFO, CI))
    assert choose_topics("rec.bag", only_compressed).image == COLOUR + "/compressed"


def test_ambiguous_or_missing_topics_name_the_flag_and_the_topics():
    two = _infos(("/left/image_raw", IMG), ("/right/image_raw", IMG), (INFO, CI))
    with pytest.raises(ConfigError, match=r"rec\.bag: several colour image topics \(/left/image_raw, "
                                          r"/right/image_raw\); name one with --image-topic"):
        choose_topics("rec.bag", two)
    assert choose_topics("rec.bag", two, image="/right/image_raw").image == "/right/image_raw"
    with pytest.raises(ConfigError, match=r"--image-topic /nope: no such topic in rec\.bag \(its topics: "):
        choose_topics("rec.bag", two, image="/nope")
    with pytest.raises(ConfigError, match=r"--camera-info-topic /left/image_raw: a sensor_msgs/msg/Image topic"):
        choose_topics("rec.bag", two, image="/left/image_raw", camera_info="/left/image_raw")
    with pytest.raises(ConfigError, match="no colour image topic"):
        choose_topics("rec.bag", _infos((INFO, CI)))


def test_topic_table_lists_even_what_cannot_be_played(tmp_path):
    def second(T, ros1, rgb, stamp):
        return colour_message(T, ros1, rgb, stamp)

    path = write_recording(tmp_path / "two.bag", "ros1", _frames(2), K, info=False, extra=[("/cam2/image_raw", second)])
    lines = topic_table(path).splitlines()
    assert lines[0] == f"{path}: 3 topic(s)" and "<-" not in "".join(lines)
    assert lines[-1].startswith("  no choice: ") and "several colour image topics" in lines[-1]
    marked = topic_table(path, image_topic="/cam2/image_raw")
    assert re.search(r"/cam2/image_raw +sensor_msgs/msg/Image  2 message\(s\)  <- colour", marked)
    assert "<- depth" in marked


def test_recording_inputs_are_streams(tmp_path):
    folder = tmp_path / "bag2"
    folder.mkdir()
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 9\n")
    assert [stream_kind(p) for p in ("a.bag", "a.MCAP", "a.db3", str(folder), "a.png")] == \
        ["recording"] * 4 + [None]
    assert not is_recording(str(tmp_path))
    (tmp_path / "metadata.yaml").write_text("camera: kitchen\n")  # an image folder's own file
    assert not is_recording(str(tmp_path))


# ----------------------------------------------------------------------------- the source
@pytest.mark.parametrize("kind", ["ros1", "ros2-sqlite3", "ros2-mcap", "mcap"])
def test_frames_carry_stamp_frame_id_depth_and_camera(tmp_path, kind):
    frames = _frames(3)
    path = write_recording(tmp_path / ("rec.bag" if kind == "ros1" else "rec.mcap" if kind == "mcap" else "rec"),
                           kind, frames, K)
    source = RecordingSource(path)
    assert source.length == 3 and source.chosen.depth == DEPTH
    out = _grab_all(source)
    source.close()
    assert [f.stamp_ns for f in out] == [T0_NS + i * PERIOD_NS for i in range(3)]
    assert [f.timestamp_s for f in out] == pytest.approx([0.0, 0.1, 0.2])
    assert all(f.frame_id == FRAME_ID for f in out) and out[1].name == f"{path.name}#000001"
    for f, (rgb, d) in zip(out, frames):
        assert np.array_equal(f.rgb, rgb) and np.allclose(f.depth, np.round(d * 1000) / 1000, atol=1e-6)
        assert np.allclose(f.K, K)


def test_depth_pairing_tolerance_edges_and_gaps(tmp_path):
    frames = _frames(4)
    late = write_recording(tmp_path / "late.bag", "ros1", frames, K, depth_offset_ns=40_000_000)
    with pytest.raises(InputFileError, match=r"late\.bag: /camera/aligned_depth_to_color/image_raw: no depth "
                                             r"message within 15 ms of the /camera/color/image_raw frame"):
        _grab_all(RecordingSource(late))
    warned = []
    out = _grab_all(RecordingSource(late, tolerance_s=0.05, warn=warned.append))
    assert all(f.depth is not None for f in out) and not warned
    # depth starting one frame late: the first colour frame is processed without depth, and said so
    T = ros2_typestore().types
    path = tmp_path / "start.mcap"
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = ros2_typestore()
    with Writer(tmp_path / "start", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection(COLOUR, IMG, typestore=store)
        d = w.add_connection(DEPTH, IMG, typestore=store)
        i_ = w.add_connection(INFO, CI, typestore=store)
        for i, (rgb, dep) in enumerate(frames):
            stamp = T0_NS + i * PERIOD_NS
            w.write(i_, stamp, store.serialize_cdr(info_message(T, False, K, (W, H), stamp), CI))
            w.write(c, stamp, store.serialize_cdr(colour_message(T, False, rgb, stamp), IMG))
            if i:
                w.write(d, stamp, store.serialize_cdr(depth_message(T, False, dep, stamp), IMG))
    (tmp_path / "start" / "start.mcap").rename(path)
    warned = []
    out = _grab_all(RecordingSource(path, warn=warned.append))
    assert [f.depth is None for f in out] == [True, False, False, False]
    assert warned == [f"{path}: 1 colour frame(s) before the first or after the last {DEPTH} message were "
                      "processed without depth"]


def test_camera_info_missing_distorted_and_unsupported(tmp_path):
    frames = _frames(2)
    path = write_recording(tmp_path / "noinfo.bag", "ros1", frames, K, info=False)
    with pytest.raises(CameraError, match=r"noinfo\.bag: no camera_info topic for /camera/color/image_raw"):
        RecordingSource(path)
    from dope_hope.io.camera import ImageCamera

    given = ImageCamera(K=K, width=W, height=H, source=Path("K.json"))
    assert np.allclose(_grab_all(RecordingSource(path, camera=given))[0].K, K)
    T1 = ros1_typestore().types
    distorted = info_message(T1, True, K, (W, H), T0_NS, D=(-0.2, 0.05, 0.0, 0.0, 0.0))
    K_new, w, h, rect = camera_from_info(distorted, "rec.bag topic /ci")
    assert rect is not None and (w, h) == (W, H) and np.allclose(K_new, K)
    rgb = frames[0][0]
    assert not np.array_equal(rect.image(rgb), rgb)
    fisheye = info_message(T2, False, K, (W, H), T0_NS, D=(0.1, 0.0, 0.0, 0.0), model="equidistant")
    with pytest.raises(InputFileError, match=r"rec\.mcap topic /ci: distortion_model: 'equidistant' is not supported"):
        camera_from_info(fisheye, "rec.mcap topic /ci")


def test_corrupt_and_truncated_recordings_are_named(tmp_path):
    good = write_recording(tmp_path / "good.mcap", "mcap", _frames(2), K)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 8)
    for path in (cut, junk):
        with pytest.raises(InputFileError, match=rf"^{path}: not a readable ROS bag / MCAP recording \("):
            RecordingSource(path)


def test_missing_extra_says_which_to_install(monkeypatch):
    from dope_hope.ros.foxglove_live import FoxgloveLive
    from dope_hope.ros.message_types import require_rosbags

    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(ConfigError, match=r'rosbags package: pip install "dope-hope\[ros\]"'):
        require_rosbags()
    monkeypatch.setitem(sys.modules, "foxglove", None)
    with pytest.raises(ConfigError, match=r'^--foxglove needs the foxglove-sdk package: pip install "dope-hope\[ros\]"'):
        FoxgloveLive(0)


# ----------------------------------------------------------------------------- poses out
def _objects():
    R = cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0]
    return [PosedObject("DemoBox", 0.9, R, np.array([0.01, -0.02, 0.5]), np.array([0.12, 0.16, 0.04]),
                        np.array([0.0, 0.01, 0.0]), track_id=3, color_rgb=(255, 0, 0)),
            PosedObject("Ketchup", 0.7, np.eye(3), np.array([0.1, 0.0, 0.6]), np.array([0.06, 0.19, 0.04]),
                        np.zeros(3))]


def test_writer_round_trip_types_stamps_frame_ids_and_fields(tmp_path):
    from rosbags.highlevel import AnyReader

    msgs = PoseMessages()
    path = tmp_path / "out" / "rec_poses"
    path.mkdir(parents=True)
    (path / "metadata.yaml").write_text("old run")  # an earlier run's bag: replaced whole on close
    (path / "rec_poses.mcap").write_text("old run")
    writer = RecordingWriter(path)
    for i in range(2):
        for topic, msg in msgs.frame(T0_NS + i * PERIOD_NS, FRAME_ID, _objects(), K, b"\xff\xd8jpeg"):
            writer.write(topic, T0_NS + i * PERIOD_NS, msg)
    assert writer.close() == path and sorted(p.name for p in path.iterdir()) == ["metadata.yaml", "rec_poses.mcap"]
    assert [p.name for p in path.parent.iterdir()] == ["rec_poses"]
    with AnyReader([path]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == TOPICS
        seen = {}
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            seen.setdefault(conn.topic, []).append((t, msg))
    assert all(len(v) == 2 and [t for t, _ in v] == [T0_NS, T0_NS + PERIOD_NS] for v in seen.values())
    det = seen["/dope_hope/detections"][0][1]
    assert det.header.frame_id == FRAME_ID and det.header.stamp.sec == T0_NS // 10**9
    assert det.header.stamp.nanosec == T0_NS % 10**9
    d0 = det.detections[0]
    assert d0.results[0].hypothesis.class_id == "DemoBox" and d0.results[0].hypothesis.score == pytest.approx(0.9)
    assert d0.id == "3" and det.detections[1].id == ""
    assert [d0.bbox.size.x, d0.bbox.size.y, d0.bbox.size.z] == pytest.approx([0.12, 0.16, 0.04])
    centre = _objects()[0].R @ np.array([0.0, 0.01, 0.0]) + np.array([0.01, -0.02, 0.5])
    assert [d0.bbox.center.position.x, d0.bbox.center.position.y, d0.bbox.center.position.z] == pytest.approx(centre)
    assert d0.results[0].pose.pose.position.z == pytest.approx(0.5)
    poses = seen["/dope_hope/poses"][0][1]
    assert len(poses.poses) == 2 and poses.header.frame_id == FRAME_ID
    markers = seen["/dope_hope/markers"][0][1].markers
    assert markers[0].action == 3 and [(m.ns, m.id, m.type) for m in markers[1:]] == [
        ("DemoBox", 3, 1), ("DemoBox/label", 3, 9), ("Ketchup", 2, 1), ("Ketchup/label", 2, 9)]
    assert markers[2].text == "DemoBox #3 0.90"
    tf = seen["/tf"][0][1].transforms
    assert [x.child_frame_id for x in tf] == ["DemoBox_3", "Ketchup_2"] and tf[0].header.frame_id == FRAME_ID
    ann = seen["/dope_hope/annotations"][0][1]
    assert [len(p.points) for p in ann.points] == [24, 24] and ann.texts[1].text == "Ketchup 0.70"
    assert bytes(seen["/dope_hope/overlay/compressed"][0][1].data) == b"\xff\xd8jpeg"


def test_writer_discard_leaves_nothing(tmp_path):
    writer = RecordingWriter(tmp_path / "rec_poses")
    for topic, msg in PoseMessages().frame(T0_NS, FRAME_ID, _objects(), K):
        writer.write(topic, T0_NS, msg)
    writer.discard()
    assert list(tmp_path.iterdir()) == []
