"""`dope-hope ros2` with real ROS 2 (the pip wheels), loopback only: the node runs as a
subprocess on a ROS domain of this test session's own; a test node publishes the demo's
rendered frames (colour, camera info, aligned depth) and reads what comes back. The poses
equal `dope-hope infer` on the same frames; stamps and frame ids are carried; parameter
changes take effect on the next frame and bad values are refused with the node serving on;
a bad camera info or image is logged and skipped; Ctrl-C ends the node cleanly.
"""
from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_cli_recordings import image_detections, scenes  # noqa: F401 - the demo frames fixture

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.geometry import quaternion_xyzw_to_matrix

rclpy = pytest.importorskip("rclpy", reason='the ROS 2 wheels are not installed: pip install "dope-hope[ros2]"')
try:
    from rclpy.impl.implementation_singleton import rclpy_implementation  # noqa: F401 - its C libraries
except ImportError as exc:  # pragma: no cover - depends on the installation
    pytest.skip(f"rclpy cannot load its libraries ({exc})", allow_module_level=True)
from geometry_msgs.msg import PoseArray, PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

pytestmark = pytest.mark.skipif(not DEMO_WEIGHTS.is_file(), reason="the demo model is not in this installation")
REPO = Path(__file__).resolve().parent.parent
FRAME_ID = "camera_color_optical_frame"
T0_NS = 1_700_000_000_000_000_000
WAIT_S = 60.0  # the node's start (torch, the model) on a loaded 2-core machine


def _header(stamp_ns: int, frame_id: str = FRAME_ID):
    from std_msgs.msg import Header

    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = stamp_ns // 10**9, stamp_ns % 10**9
    return h


def image_msg(rgb: np.ndarray, stamp_ns: int, encoding: str = "rgb8") -> Image:
    h, w = rgb.shape[:2]
    return Image(header=_header(stamp_ns), height=h, width=w, encoding=encoding, is_bigendian=0, step=w * 3,
                 data=np.ascontiguousarray(rgb).tobytes())


def depth_msg(depth_m: np.ndarray, stamp_ns: int) -> Image:
    mm = np.round(np.nan_to_num(depth_m) * 1000).astype(np.uint16)
    h, w = mm.shape
    return Image(header=_header(stamp_ns), height=h, width=w, encoding="16UC1", is_bigendian=0, step=w * 2,
                 data=mm.tobytes())


def info_msg(K: np.ndarray, size: tuple[int, int], stamp_ns: int, model: str = "plumb_bob") -> CameraInfo:
    return CameraInfo(header=_header(stamp_ns), width=size[0], height=size[1], distortion_model=model,
                      d=[0.0] * 5, k=np.asarray(K, float).ravel(), r=np.eye(3).ravel(),
                      p=np.hstack([K, np.zeros((3, 1))]).ravel())


class Peer:
    """The test's own ROS node: publishes camera frames, collects the node's outputs by stamp."""

    def __init__(self, domain: int):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("dope_hope_test_peer", context=self.context)
        self.pubs = {"image": self.node.create_publisher(Image, "/camera/color/image_raw", 10),
                     "info": self.node.create_publisher(CameraInfo, "/camera/color/camera_info", 10),
                     "depth": self.node.create_publisher(Image, "/camera/aligned_depth_to_color/image_raw", 10)}
        self.got: dict[str, list] = {k: [] for k in ("poses", "pose", "markers", "overlay", "time")}
        self.lock = threading.Lock()
        for key, cls, topic in (("poses", PoseArray, "/dope_hope/poses"),
                                ("pose", PoseStamped, "/dope_hope/pose_DemoBox"),
                                ("markers", MarkerArray, "/dope_hope/markers"),
                                ("overlay", Image, "/dope_hope/overlay"),
                                ("time", Float64, "/dope_hope/processing_time_ms")):
            self.node.create_subscription(cls, topic, lambda msg, key=key: self._keep(key, msg), 10)
        self.params = AsyncParameterClient(self.node, "dope_hope")
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _keep(self, key: str, msg) -> None:
        with self.lock:
            self.got[key].append(msg)

    def wait_for(self, check, what: str, timeout: float = WAIT_S):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                value = check()
            if value:
                return value
            time.sleep(0.02)
        raise AssertionError(f"timed out waiting for {what}")

    def connected(self, node_proc: subprocess.Popen) -> None:
        def ready():
            assert node_proc.poll() is None, "the node ended"
            return (all(p.get_subscription_count() > 0 for p in self.pubs.values())
                    and self.node.count_publishers("/dope_hope/poses") > 0)
        self.wait_for(ready, "the node's topics")

    def send(self, rgb, depth_m, K, stamp_ns: int, info_size=None, encoding="rgb8") -> None:
        h, w = rgb.shape[:2]
        self.pubs["info"].publish(info_msg(K, info_size or (w, h), stamp_ns))
        if depth_m is not None:
            self.pubs["depth"].publish(depth_msg(depth_m, stamp_ns))
        self.pubs["image"].publish(image_msg(rgb, stamp_ns, encoding))

    def poses_of(self, stamp_ns: int, timeout: float = WAIT_S) -> PoseArray:
        def found():
            return next((m for m in self.got["poses"]
                         if m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == stamp_ns), None)
        return self.wait_for(found, f"the poses of stamp {stamp_ns}", timeout)

    def set(self, name: str, value) -> tuple[bool, str]:
        param = Parameter(name, value=value) if value is not None else Parameter(name, Parameter.Type.NOT_SET)
        future = self.params.set_parameters([param])
        self.wait_for(future.done, f"the answer to setting {name}", 20.0)
        result = future.result().results[0]
        return result.successful, result.reason

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.thread.join(timeout=5)


@pytest.fixture(scope="module")
def ros_env():
    """A ROS domain of this session's own (others may run ROS tests on this machine), loopback only."""
    env = {"ROS_DOMAIN_ID": str(random.randint(100, 200)), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOCALHOST_ONLY": "1"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    yield env
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="module")
def node_process(ros_env, tmp_path_factory):
    """The node: a `dope-hope ros2` subprocess on the demo model (starting while the frames
    render), in an environment whose library path was reset after the wheels' bootstrapper
    ran (as sudo or ``env -u`` leave it): the command finds the wheels' libraries itself."""
    log = tmp_path_factory.mktemp("ros2") / "node.log"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
           "LD_LIBRARY_PATH": "", "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1"}
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "dope_hope.cli", "ros2", "--ros-args", "--params-file",
                                 str(REPO / "docs" / "ros2" / "dope_hope_params.yaml"), "-p", "threads:=1",
                                 "-p", "depth_wait_ms:=2000.0"], stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        yield proc, log
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture(scope="module")
def live(ros_env, node_process, scenes):  # noqa: F811
    """(the test's peer node, the node's process, its log), the two connected."""
    proc, log = node_process
    peer = Peer(int(ros_env["ROS_DOMAIN_ID"]))
    try:
        peer.connected(proc)
        yield peer, proc, log
    finally:
        peer.close()


def _pose_matrix(pose) -> tuple[np.ndarray, np.ndarray]:
    q = pose.orientation
    return quaternion_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([pose.position.x, pose.position.y,
                                                                                pose.position.z])


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1.0, 1.0))))


def test_node_poses_equal_infer_on_the_same_frames(live, scenes, tmp_path, capsys):  # noqa: F811
    peer, proc, log = live
    want = image_detections(scenes, capsys, tmp_path, ".png", True)
    assert any(want), "infer found nothing on the demo frames"
    for i, (rgb, depth) in enumerate(scenes["frames"]):
        stamp = T0_NS + i * 100_000_000
        peer.send(rgb, depth, scenes["K"], stamp)
        got = peer.poses_of(stamp)
        assert got.header.frame_id == FRAME_ID
        assert len(got.poses) == len(want[i]), (i, log.read_text()[-2000:])
        for pose, rec in zip(got.poses, want[i]):
            R, t = _pose_matrix(pose)
            assert np.linalg.norm(t - np.asarray(rec["t"])) < 0.001
            assert _angle_deg(R, np.asarray(rec["R"])) < 0.1
    stamps = {T0_NS + i * 100_000_000 for i, w in enumerate(want) if w}
    peer.wait_for(lambda: {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in peer.got["pose"]} >= stamps,
                  "pose_DemoBox of every frame with a detection", 10.0)
    peer.wait_for(lambda: len(peer.got["time"]) >= 3 and len(peer.got["overlay"]) >= 3, "times and overlays", 10.0)
    with peer.lock:
        overlay = peer.got["overlay"][-1]
        assert (overlay.width, overlay.height, overlay.encoding) == (320, 240, "rgb8")
        assert overlay.header.frame_id == FRAME_ID
        assert all(0 < m.data < 60_000 for m in peer.got["time"])
        markers = peer.got["markers"][-1].markers
        assert markers[0].action == 3 and any(m.ns == "DemoBox" for m in markers)  # DELETEALL, then the cuboid


def test_parameters_change_on_the_next_frame_and_bad_values_are_refused(live, scenes):  # noqa: F811
    peer, proc, _ = live
    rgb, depth = scenes["frames"][0]
    assert peer.set("min_score", 2.0) == (True, "")
    peer.send(rgb, depth, scenes["K"], T0_NS + 10**9)
    assert len(peer.poses_of(T0_NS + 10**9).poses) == 0  # no pose scores 2
    ok, reason = peer.set("min_score", "high")
    assert not ok and "min_score must be a number" in reason
    ok, reason = peer.set("classes", ["Ketchup"])
    assert not ok and "'Ketchup' is not an object this node detects (known: DemoBox)" in reason
    ok, reason = peer.set("height", 400)
    assert not ok and "height is read at start" in reason
    assert peer.set("min_score", None) == (True, "")  # unset: the model's own threshold again
    peer.send(rgb, depth, scenes["K"], T0_NS + 2 * 10**9)
    assert len(peer.poses_of(T0_NS + 2 * 10**9).poses) >= 1
    assert proc.poll() is None


def test_each_frame_uses_the_camera_info_of_its_own_stamp(live, scenes):  # noqa: F811
    peer, _, _ = live
    rgb, depth = scenes["frames"][0]
    wide = scenes["K"] * np.array([[1.5], [1.5], [1.0]])  # another focal length on one frame only
    poses = []
    for i, K in enumerate((scenes["K"], wide, scenes["K"])):
        stamp = T0_NS + 6 * 10**9 + i * 10**8
        peer.send(rgb, depth, K, stamp)
        got = peer.poses_of(stamp)
        assert len(got.poses) >= 1
        poses.append(_pose_matrix(got.poses[0])[1])
    assert np.linalg.norm(poses[1] - poses[0]) > 0.01 and np.allclose(poses[2], poses[0], atol=1e-6)


def test_bad_camera_info_or_image_is_logged_and_skipped(live, scenes):  # noqa: F811
    peer, proc, log = live
    rgb, depth = scenes["frames"][1]
    bad = {T0_NS + 3 * 10**9: ({"info_size": (640, 480)}, "camera info for 640x480, the image is 320x240"),
           T0_NS + 4 * 10**9: ({"encoding": "32FC3"}, "Image encoding '32FC3' is not supported for colour")}
    for stamp, (how, message) in bad.items():
        peer.send(rgb, depth, scenes["K"], stamp, **how)
        peer.wait_for(lambda message=message: message in log.read_text(), f"the log line {message!r}", 20.0)
    good = T0_NS + 5 * 10**9
    peer.send(rgb, depth, scenes["K"], good)
    assert len(peer.poses_of(good).poses) >= 1
    with peer.lock:
        assert not {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in peer.got["poses"]} & set(bad)
    assert proc.poll() is None


def test_sigint_ends_the_node_cleanly(live):
    peer, proc, log = live
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=30) == 0
    last = log.read_text().strip().splitlines()[-1]
    assert re.fullmatch(r"dope-hope ros2: \d+ image\(s\) received, \d+ processed, .* \d+ skipped, .*", last), last


def test_the_node_class_composes_and_refuses_a_bad_parameter_in_one_line(ros_env):
    from dope_hope.errors import ConfigError
    from dope_hope.ros.node import DopeHopeNode

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    try:
        for override, message in ((Parameter("decode.threshold", value="high"), "decode.threshold must be a number"),
                                  (Parameter("image_transport", value="theora"), "image_transport must be one of")):
            with pytest.raises(ConfigError, match=message):
                DopeHopeNode("dope_hope_composed", context=context, parameter_overrides=[override])
    finally:
        rclpy.try_shutdown(context=context)
