"""`dope-hope infer` on robot recordings end to end, with the shipped demo model on rendered demo
scenes: ROS 1 and ROS 2 recordings (raw and compressed, with and without depth and
camera_info, written here by rosbags' own writers) give the detections of the same frames
given as images; the poses MCAP read back with rosbags; the live Foxglove server with a
WebSocket client; hostile recordings: one line naming the topic or file, exit 2, nothing written.
"""
from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from ros_recordings import (
    COLOUR,
    DEPTH,
    FRAME_ID,
    PERIOD_NS,
    T0_NS,
    colour_message,
    write_recording,
)

from dope_hope import cli
from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.io.images import write_depth_mm, write_rgb
from dope_hope.ros.pose_messages import TOPICS

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.skipif(not DEMO_WEIGHTS.is_file(), reason="the demo model is not in this installation")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Three 320x240 renders of the demo box at 0.45-0.6 m with depth (the demo model finds it),
    their K, and the same frames as images: PNG colour, PNG depth (mm), JPEG colour, K.json."""
    import dope_hope.model  # noqa: F401 - torchvision before the GL context
    from dope_hope.demo_object import DEMO_CLASS_NAME, write_demo_object
    from dope_hope.synth import FrameGenerator
    from dope_hope.synth.settings import PLAIN_OVERRIDES

    root = tmp_path_factory.mktemp("recordings")
    mesh = write_demo_object(root / "mesh")
    still = {**PLAIN_OVERRIDES, "camera": {"focal_jitter": 0.0, "aspect_jitter": 0.0, "principal_jitter_px": 0.0}}
    with FrameGenerator(mesh, size=(320, 240), config={**still, "target": {"count": [1, 1], "distance_m": [0.45, 0.6],
                                                                          "truncation_prob": 0.0}},
                        class_name=DEMO_CLASS_NAME, depth_noise=True, seed=11) as gen:
        rendered = [gen.render_frame(i) for i in range(3)]
    frames = [(f.rgb, np.round(f.depth * 1000) / 1000) for f in rendered]
    K = rendered[0].annotation.K
    images = root / "images"
    for i, (rgb, d) in enumerate(frames):
        write_rgb(images / f"{i:06d}.png", rgb)
        write_depth_mm(images / f"{i:06d}.depth.png", d)
        _, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))  # the bytes a jpeg recording holds
        (images / f"{i:06d}.jpg").write_bytes(buf.tobytes())
    (images / "K.json").write_text(json.dumps({"K": K.tolist()}))
    return {"frames": frames, "K": K, "images": images, "mesh": mesh}


def run_cli(argv: list[str], capsys) -> tuple[int, list[dict], str]:
    code = cli.main(["infer", *map(str, argv), "--no-progress"])
    out, err = capsys.readouterr()
    return code, [json.loads(line) for line in out.splitlines() if line.startswith("{")], err


def image_detections(scenes, capsys, tmp_path, suffix: str, depth: bool) -> list[list[dict]]:
    """Per frame, the records of `infer` on the frame's image (with --depth PATH when ``depth``),
    with the settings a stream runs (``--fast``: the preset of recordings and the live node)."""
    images, per_frame = scenes["images"], []
    for i in range(len(scenes["frames"])):
        argv = [images / f"{i:06d}{suffix}", "--camera", images / "K.json", "--out", tmp_path / f"img{i}", "--fast"]
        code, recs, err = run_cli(argv + (["--depth", images / f"{i:06d}.depth.png"] if depth else []), capsys)
        assert code == 0, err
        per_frame.append(recs)
    return per_frame


def assert_same(recording: list[dict], images: list[list[dict]]) -> None:
    assert recording, "no detection on the recording"
    by_frame = {i: [r for r in recording if r["frame"] == i] for i in range(len(images))}
    for i, want in enumerate(images):
        got = by_frame[i]
        assert [r["class"] for r in got] == [r["class"] for r in want], i
        for g, w in zip(got, want):
            assert g["score"] == pytest.approx(w["score"], abs=1e-6)
            assert np.allclose(g["R"], w["R"], atol=1e-6) and np.allclose(g["t"], w["t"], atol=1e-6)
            assert g["ls_applied"] == w["ls_applied"]


VARIANTS = {  # name: (kind, write_recording options, image suffix, with depth, extra CLI flags)
    "ros1-raw-depth-info": ("ros1", {}, ".png", True, []),
    "ros2-sqlite3-bgr8-no-depth-no-info": ("ros2-sqlite3", {"depth": False, "info": False, "encoding": "bgr8"},
                                           ".png", False, ["--camera", "K"]),
    "mcap-jpeg-compressed-depth": ("mcap", {"compressed": "jpeg", "compressed_depth": True}, ".jpg", True, []),
    "ros2-mcap-32FC1-depth": ("ros2-mcap", {"depth_encoding": "32FC1"}, ".png", True, []),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_recording_gives_the_detections_of_its_frames_as_images(scenes, tmp_path, capsys, variant):
    kind, options, suffix, depth, flags = VARIANTS[variant]
    name = {"ros1": "robot.bag", "mcap": "robot.mcap"}.get(kind, "robot")
    rec = write_recording(tmp_path / name, kind, scenes["frames"], scenes["K"], **options)
    flags = [str(scenes["images"] / "K.json") if f == "K" else f for f in flags]
    code, records, err = run_cli([rec, "--out", tmp_path / "res", *flags], capsys)
    assert code == 0, err
    assert {r["stamp_ns"] for r in records} <= {T0_NS + i * PERIOD_NS for i in range(3)}
    assert all(r["frame_id"] == FRAME_ID and r["image"].startswith(f"{name}#") for r in records)
    assert "3 frame(s) read, 3 processed" in err
    assert_same(records, image_detections(scenes, capsys, tmp_path, suffix, depth))
    assert all((r["ls_reason"] != "no depth image") == depth for r in records)
    written = [json.loads(line) for line in (tmp_path / "res" / "predictions.jsonl").read_text().splitlines()]
    assert written == records


def read_bag(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    seen: dict[str, list] = {}
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            seen.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    assert types == TOPICS
    return seen


def test_poses_mcap_holds_every_frame_with_track_ids(scenes, tmp_path, capsys):
    rec = write_recording(tmp_path / "robot.bag", "ros1", scenes["frames"], scenes["K"])
    code, records, err = run_cli([rec, "--track", "--icp", "--mesh", scenes["mesh"], "--classes", "DemoBox",
                                  "--max-frames", "2", "--out", tmp_path / "res"], capsys)
    assert code == 0, err
    assert "2 frame(s) read, 2 processed" in err and f"poses MCAP {tmp_path / 'res' / 'robot_poses'}" in err
    assert records and all("track_id" in r and "icp_applied" in r for r in records)
    seen = read_bag(tmp_path / "res" / "robot_poses")
    stamps = [T0_NS, T0_NS + PERIOD_NS]
    assert all([t for t, _ in msgs] == stamps for msgs in seen.values()), {k: len(v) for k, v in seen.items()}
    for t, det in seen["/dope_hope/detections"]:
        assert det.header.frame_id == FRAME_ID and det.header.stamp.sec * 10**9 + det.header.stamp.nanosec == t
        recs = [r for r in records if r["stamp_ns"] == t]
        assert [d.results[0].hypothesis.class_id for d in det.detections] == [r["class"] for r in recs]
        assert [d.id for d in det.detections] == [str(r["track_id"]) for r in recs]
        for d, r in zip(det.detections, recs):
            p = d.results[0].pose.pose.position
            assert [p.x, p.y, p.z] == pytest.approx(r["t"]) and d.results[0].hypothesis.score == pytest.approx(r["score"])
            assert [d.bbox.size.x, d.bbox.size.y, d.bbox.size.z] == pytest.approx(r["cuboid_size_m"])
    cubes = [m for _, arr in seen["/dope_hope/markers"] for m in arr.markers if m.type == 1 and m.action == 0]
    assert {m.id for m in cubes} == {r["track_id"] for r in records}
    assert all(m.header.frame_id == FRAME_ID for m in cubes)
    tf = [x for _, msg in seen["/tf"] for x in msg.transforms]
    assert {x.child_frame_id for x in tf} == {f"DemoBox_{r['track_id']}" for r in records}
    jpeg = bytes(seen["/dope_hope/overlay/compressed"][0][1].data)
    assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (240, 320, 3)


def test_list_topics_prints_the_choice_and_stops(scenes, tmp_path, capsys):
    rec = write_recording(tmp_path / "robot", "ros2-mcap", scenes["frames"][:1], scenes["K"])
    assert cli.main(["infer", str(rec), "--list-topics", "--out", str(tmp_path / "res")]) == 0
    out = capsys.readouterr().out
    assert re.search(rf"{re.escape(COLOUR)}\s+sensor_msgs/msg/Image\s+1 message\(s\)\s+<- colour", out)
    assert re.search(rf"{re.escape(DEPTH)}\s+.*<- depth", out) and not (tmp_path / "res").exists()


# ----------------------------------------------------------------------------- live view
def receive_detection(url: str, topic: str, deadline: float) -> tuple[dict, bytes]:
    """Connect as the Foxglove app does (subprotocol foxglove.sdk.v1), subscribe to ``topic``
    when advertised, and return (its channel, the first message's payload)."""
    from websockets.sync.client import connect

    with connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
        channels: dict[str, dict] = {}
        while time.monotonic() < deadline:
            msg = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
            if isinstance(msg, str):
                data = json.loads(msg)
                if data.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in data["channels"]})
                    if topic in channels:
                        ws.send(json.dumps({"op": "subscribe",
                                            "subscriptions": [{"id": 7, "channelId": channels[topic]["id"]}]}))
            elif msg[0] == 1:  # message data: opcode, subscription id, log time, payload
                sub, _ = struct.unpack_from("<IQ", msg, 1)
                assert sub == 7
                return channels[topic], bytes(msg[13:])
    raise TimeoutError(f"no message on {topic} from {url}")


def test_foxglove_serves_the_detections_live(scenes, tmp_path):
    from dope_hope.ros.message_types import ros2_typestore

    rec = write_recording(tmp_path / "robot.mcap", "mcap", scenes["frames"], scenes["K"])
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.Popen([sys.executable, "-m", "dope_hope", "infer", str(rec), "--foxglove", "0", "--no-progress",
                             "--out", str(tmp_path / "res")], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 120
        url = None
        while url is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            assert line, "infer ended before serving"
            found = re.search(r"open connection (ws://127\.0\.0\.1:\d+)", line)
            url = found and found.group(1)
        channel, payload = receive_detection(url, "/dope_hope/detections", deadline)
        assert (channel["schemaName"], channel["encoding"], channel["schemaEncoding"]) == \
            ("vision_msgs/msg/Detection3DArray", "cdr", "ros2msg")
        msg = ros2_typestore().deserialize_cdr(payload, "vision_msgs/msg/Detection3DArray")
        assert msg.header.frame_id == FRAME_ID and msg.header.stamp.sec == T0_NS // 10**9
        assert [d.results[0].hypothesis.class_id for d in msg.detections] == ["DemoBox"]
        assert proc.wait(timeout=max(1.0, deadline - time.monotonic())) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert (tmp_path / "res" / "robot_poses" / "robot_poses.mcap").is_file()


# ----------------------------------------------------------------------------- hostile input
def one_line_error(code: int, err: str) -> str:
    """The error line: the only one, or (an error found while playing) after the model's lines."""
    lines = [line for line in err.strip().splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("dope-hope infer: error: ")]
    assert code == 2 and len(errors) == 1 and lines[-1] == errors[0], err
    assert all(not line.startswith("dope-hope infer: error") for line in lines[:-1]), err
    return errors[0]


def _second_colour(T, ros1, rgb, stamp):
    return colour_message(T, ros1, rgb, stamp)


def test_hostile_recordings_exit_2_with_one_line_and_write_nothing(scenes, tmp_path, capsys):
    frames, K = scenes["frames"][:2], scenes["K"]
    good = write_recording(tmp_path / "good.mcap", "mcap", frames, K)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size * 2 // 3])
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + os.urandom(4096))
    yuv = write_recording(tmp_path / "yuv.bag", "ros1", frames, K, encoding="yuv422")
    cases = [
        ([cut], r"cut\.mcap: not a readable ROS bag / MCAP recording"),
        ([junk], r"junk\.bag: not a readable ROS bag / MCAP recording"),
        ([good, "--image-topic", "/camera/left"], r"--image-topic /camera/left: no such topic in .*good\.mcap"),
        ([yuv], r"yuv\.bag topic /camera/color/image_raw: Image encoding 'yuv422' is not supported"),
        ([write_recording(tmp_path / "noinfo.bag", "ros1", frames, K, info=False)],
         r"noinfo\.bag: no camera_info topic for /camera/color/image_raw"),
        ([write_recording(tmp_path / "late", "ros2-sqlite3", scenes["frames"], K, depth_offset_ns=50_000_000)],
         r"late: /camera/aligned_depth_to_color/image_raw: no depth message within 15 ms"),
        ([write_recording(tmp_path / "two.bag", "ros1", frames, K, extra=[("/camera2/color/image_raw", _second_colour)])],
         r"two\.bag: several colour image topics \(/camera/color/image_raw, /camera2/color/image_raw\)"),
        ([good, "--realtime", "--depth", "x.png"], r"--depth applies to image inputs"),
        (["a.png", "--image-topic", "/c"], r"--image-topic: for a video or camera input, not images"),
    ]
    for i, (argv, pattern) in enumerate(cases):
        out = tmp_path / f"res{i}"
        code = cli.main(["infer", *map(str, argv), "--out", str(out), "--no-progress"])
        captured = capsys.readouterr()
        assert re.search(pattern, one_line_error(code, captured.err)), (pattern, captured.err)
        assert not out.exists() or not any(out.iterdir()), (argv, list(out.iterdir()))
