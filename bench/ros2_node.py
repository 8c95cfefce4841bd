"""The live ROS 2 node (`dope-hope ros2`) against `dope-hope infer` on a recording of the same frames.

    python bench/ros2_node.py [--frames 30] [--repeats 2] [--threads 2] [--live-seconds 20]

Renders ``--frames`` demo scenes at 640x480 with depth, one box (bench/stream.py's
:func:`render`), and writes them as a ROS 2 MCAP bag (bench/recordings.py's :func:`write_bag`:
rgb8 Image, 16UC1 aligned depth, CameraInfo on RealSense's topics). Then, alternating
``--repeats`` times, with the shipped demo model through PyTorch (``--threads``) in both:

* **infer**: `dope-hope infer robot_bag/` as a subprocess (reading, pairing, decoding, network,
  PnP, -LS, the poses MCAP with the JPEG overlay), every frame: the frames/s end to end it prints;
* **node**: `dope-hope ros2` as a subprocess on a ROS domain of its own (loopback only; its
  default sensor-data QoS, both processes with docs/ros2/fastdds_large_shm.xml so that the
  raw frames go through shared memory); this process publishes the bag's messages, as
  recorded (serialized), to its topics:

  - *closed loop*: a frame (camera info, depth, then the image), then wait for its PoseArray
    before the next: frames/s, and per frame the round trip (image published -> its poses
    received here) against the node's own ``processing_time_ms`` (the image's arrival ->
    its poses published): their difference is what the ROS transport adds (the image to the
    node, the poses back);
  - *live*: the frames at the bag's 30 frames/s for ``--live-seconds`` (fresh stamps, the
    frames repeated), as a camera would: frames/s the node processes (the newest frame wins,
    the others dropped), the publisher sharing the cores.

Prints every run, then the best of each with the ratios node / infer, the medians of the
latency figures, and the CPU (``dope_hope.devices.cpu_line``). Targets: node frames/s >= 0.9x
infer's; the transport's added latency < 5 ms median.
"""
from __future__ import annotations

import argparse
import os
import random
import re
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from recordings import write_bag
from stream import render

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo.scenes import IMAGE_SIZE
from dope_hope.devices import cpu_line

REPO = Path(__file__).resolve().parent.parent
TOPICS = {"/camera/color/image_raw": "image", "/camera/aligned_depth_to_color/image_raw": "depth",
          "/camera/color/camera_info": "info"}
LIVE_PERIOD_S = 1 / 30
T0_NS = 1_700_000_000_000_000_000
#: Shared memory segments large enough for a raw 640x480 frame, in both processes (docs/commands/ros2.md).
FASTDDS_PROFILE = REPO / "docs" / "ros2" / "fastdds_large_shm.xml"


def recorded_frames(bag: Path) -> list[dict[str, bytes]]:
    """Per frame, {"info", "depth", "image": the serialized message as recorded}."""
    from rosbags.highlevel import AnyReader

    by_stamp: dict[int, dict[str, bytes]] = {}
    with AnyReader([bag]) as reader:
        for conn, stamp, raw in reader.messages():
            by_stamp.setdefault(stamp, {})[TOPICS[conn.topic]] = bytes(raw)
    return [by_stamp[s] for s in sorted(by_stamp)]


def restamped(raw: bytes, stamp_ns: int) -> bytes:
    """A serialized message whose first field is a Header, on another stamp (CDR little-endian)."""
    out = bytearray(raw)
    struct.pack_into("<iI", out, 4, stamp_ns // 10**9, stamp_ns % 10**9)
    return bytes(out)


class Peer:
    """This process's ROS node: publishes the recorded messages, notes when the poses come back."""

    def __init__(self, domain: int):
        import rclpy
        from geometry_msgs.msg import PoseArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import CameraInfo, Image
        from std_msgs.msg import Float64

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("dope_hope_bench_peer", context=self.context)
        types = {"image": Image, "depth": Image, "info": CameraInfo}
        self.pubs = {key: self.node.create_publisher(types[key], topic, 10) for topic, key in TOPICS.items()}
        self.poses: dict[int, float] = {}  # stamp -> perf_counter when received
        self.times: list[float] = []  # the node's processing_time_ms, in order
        self.cond = threading.Condition()
        self.node.create_subscription(PoseArray, "/dope_hope/poses", self._on_poses, 10)
        self.node.create_subscription(Float64, "/dope_hope/processing_time_ms", self._on_time, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on_poses(self, msg) -> None:
        with self.cond:
            self.poses[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = time.perf_counter()
            self.cond.notify_all()

    def _on_time(self, msg) -> None:
        with self.cond:
            self.times.append(msg.data)
            self.cond.notify_all()

    def wait(self, check, timeout: float) -> bool:
        """Whether ``check()`` came true within ``timeout`` s (looked at on each message and every 50 ms)."""
        end = time.perf_counter() + timeout
        with self.cond:
            while not check():
                left = end - time.perf_counter()
                if left <= 0:
                    return False
                self.cond.wait(min(left, 0.05))
            return True

    def send(self, frame: dict[str, bytes], stamp_ns: int) -> float:
        """The frame's camera info, depth and image on ``stamp_ns``; the time the image went out."""
        for key in ("info", "depth", "image"):
            if key == "image":
                sent = time.perf_counter()
            self.pubs[key].publish(restamped(frame[key], stamp_ns))
        return sent

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def closed_loop(peer: Peer, frames: list[dict[str, bytes]], t0_ns: int) -> tuple[float, list[float], list[float]]:
    """(frames/s, round trips ms, the node's processing times ms): a frame, its poses, the next."""
    trips, node_ms = [], []
    start = time.perf_counter()
    for i, frame in enumerate(frames):
        stamp = t0_ns + i * 33_333_333
        with peer.cond:
            times_before = len(peer.times)
        sent = peer.send(frame, stamp)
        assert peer.wait(lambda: stamp in peer.poses and len(peer.times) > times_before, 60.0), \
            f"no poses for frame {i}"
        trips.append((peer.poses[stamp] - sent) * 1000)
        node_ms.append(peer.times[times_before])
    return len(frames) / (time.perf_counter() - start), trips, node_ms


def live(peer: Peer, frames: list[dict[str, bytes]], t0_ns: int, seconds: float) -> tuple[float, int, int]:
    """(frames/s processed, frames sent, frames processed): the frames at 30 frames/s, repeated."""
    sent_stamps = []
    start = time.perf_counter()
    i = 0
    while time.perf_counter() - start < seconds:
        stamp = t0_ns + i * 33_333_333
        peer.send(frames[i % len(frames)], stamp)
        sent_stamps.append(stamp)
        i += 1
        time.sleep(max(0.0, start + i * LIVE_PERIOD_S - time.perf_counter()))
    peer.wait(lambda: sent_stamps[-1] in peer.poses, 10.0)  # the last frame is the newest: it is processed
    with peer.cond:
        done = [peer.poses[s] for s in sent_stamps if s in peer.poses]
    return len(done) / (max(done) - start), len(sent_stamps), len(done)


def start_node(threads: int, env: dict[str, str], log: Path) -> subprocess.Popen:
    with open(log, "w") as out:
        return subprocess.Popen([sys.executable, "-m", "dope_hope.cli", "ros2", "--ros-args", "-p",
                                 f"threads:={threads}"],
                                stdout=out, stderr=subprocess.STDOUT, env=env)


def run_infer(bag: Path, threads: int, env: dict[str, str], out: Path) -> tuple[float, str]:
    """(frames/s end to end, its summary line) of `dope-hope infer` on the recording."""
    proc = subprocess.run([sys.executable, "-m", "dope_hope.cli", "infer", str(bag), "--threads", str(threads),
                           "--out", str(out), "--no-progress"], capture_output=True, text=True, env=env, timeout=1800)
    summary = proc.stderr.strip().splitlines()[-1]
    found = re.search(r"([0-9.]+) frames/s end to end", summary)
    assert proc.returncode == 0 and found, summary
    return float(found.group(1)), summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--live-seconds", type=float, default=20.0)
    args = ap.parse_args()

    domain = random.randint(100, 200)
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "FASTDDS_DEFAULT_PROFILES_FILE": str(FASTDDS_PROFILE),
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                           "FASTDDS_DEFAULT_PROFILES_FILE")})
    with tempfile.TemporaryDirectory(prefix="bench-ros2-") as tmpdir:
        tmp = Path(tmpdir)
        video, K, depths = render(tmp, args.frames)
        bag = write_bag(tmp / "robot", video, K, depths)
        frames = recorded_frames(bag)
        print(f"{cpu_line()}, {os.cpu_count()} CPUs, {args.threads} threads; {len(frames)} frames "
              f"{IMAGE_SIZE[0]}x{IMAGE_SIZE[1]} with depth, one box; PyTorch, {DEMO_WEIGHTS.name}; ROS domain {domain}; "
              f"load average {os.getloadavg()[0]:.2f}", flush=True)
        node = start_node(args.threads, env, tmp / "node.log")
        peer = Peer(domain)
        try:
            connected = peer.wait(lambda: all(p.get_subscription_count() > 0 for p in peer.pubs.values())
                                  and peer.node.count_publishers("/dope_hope/poses") > 0, 120.0)
            assert connected, "the node did not connect: " + (tmp / "node.log").read_text()[-2000:]
            time.sleep(1.0)  # both ends of every topic matched
            try:
                closed_loop(peer, frames[:3], T0_NS)  # warm-up, as infer's below
            except AssertionError:
                print((tmp / "node.log").read_text()[-3000:], file=sys.stderr)
                raise
            fps: dict[str, list[float]] = {"infer": [], "node closed loop": [], "node live": []}
            trips: list[float] = []
            node_ms: list[float] = []
            for r in range(args.repeats):
                rate, summary = run_infer(bag, args.threads, env, tmp / f"infer_{r}")
                fps["infer"].append(rate)
                print(f"infer            run {r + 1}: {summary}; load average {os.getloadavg()[0]:.2f}", flush=True)
                rate, t, n = closed_loop(peer, frames, T0_NS + (r + 1) * 10**14)
                fps["node closed loop"].append(rate)
                trips += t
                node_ms += n
                print(f"node closed loop run {r + 1}: {rate:.2f} frames/s; round trip median {np.median(t):.1f} ms, "
                      f"the node's arrival-to-poses median {np.median(n):.1f} ms, the transport "
                      f"{np.median(np.subtract(t, n)):.1f} ms; load average {os.getloadavg()[0]:.2f}", flush=True)
                rate, sent, done = live(peer, frames, T0_NS + (r + 1) * 10**14 + 5 * 10**13, args.live_seconds)
                fps["node live"].append(rate)
                print(f"node live        run {r + 1}: {sent} frames sent at 30 frames/s, {done} processed "
                      f"({sent - done} dropped): {rate:.2f} frames/s; load average {os.getloadavg()[0]:.2f}", flush=True)
        finally:
            peer.close()
            node.send_signal(signal.SIGINT)
            try:
                node.wait(timeout=30)
            except subprocess.TimeoutExpired:
                node.kill()
                node.wait()
        print((tmp / "node.log").read_text().strip().splitlines()[-1])
    best = {k: max(v) for k, v in fps.items()}
    added = np.subtract(trips, node_ms)
    print(f"best of {args.repeats}: infer {best['infer']:.2f} frames/s; node closed loop {best['node closed loop']:.2f} "
          f"({best['node closed loop'] / best['infer']:.2f}x infer), live at 30 frames/s {best['node live']:.2f} "
          f"({best['node live'] / best['infer']:.2f}x infer); medians {np.median(fps['infer']):.2f}, "
          f"{np.median(fps['node closed loop']):.2f}, {np.median(fps['node live']):.2f}")
    print(f"latency over {len(trips)} closed-loop frames: the node's arrival to poses published median "
          f"{np.median(node_ms):.1f} ms; round trip (image published -> poses received) median {np.median(trips):.1f} ms; "
          f"added by the ROS transport median {np.median(added):.2f} ms (p90 {np.percentile(added, 90):.2f} ms)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
