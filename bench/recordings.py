"""Frames/s of `dope-hope infer` on a robot recording with depth against the same frames as a video.

    python bench/recordings.py [--frames 30] [--repeats 2] [--threads 2] [--weights dope_hope/assets/demo_lite.pt]

Renders ``--frames`` demo scenes at 640x480 with depth (bench/stream.py's :func:`render`: one
fixed camera, RealSense-like depth noise) and stores them twice:

* as a ROS 2 bag with MCAP storage, written by rosbags (:class:`~dope_hope.ros.recording_writer.RecordingWriter`):
  ``sensor_msgs/Image`` rgb8 colour, 16UC1 depth (mm) aligned to it, ``CameraInfo``, on
  RealSense's topic names, 30 frames/s stamps;
* as the video of bench/stream.py (mp4v) with each frame's depth attached (``VideoWithDepth``,
  bench/video_with_depth.py).

Then, in this process, alternating ``--repeats`` times after a 3-frame warm-up of each, the
loop of `dope-hope infer` runs over each with the same PyTorch predictor (``--threads``):

* recording: :class:`~dope_hope.ros.recordings.RecordingSource` (reading, deserialising, depth
  paired by stamp, decoding) -> ``predict_stream`` (network, PnP, -LS, the JSON records) ->
  :class:`~dope_hope.ros.outputs.RosOutputs` writing the poses MCAP (Detection3DArray,
  PoseArray, MarkerArray, ImageAnnotations, tf and the JPEG overlay);
* video: bench/stream.py's :func:`run_loop` (OpenCV decoding, the same predictor, the overlay
  video written).

Prints frames/s end to end of every run (run_stream's count), the load average, and the best
of each with the ratio recording / video (and the medians'). Because the network dominates both loops and the
CPU may be shared, it also times the input/output alone, per frame, median of the repeats:
reading a frame (recording: deserialise, pair, decode colour and depth; video: OpenCV decoding)
and writing its outputs with no detection (recording: the overlay JPEG and the poses MCAP's
messages; video: the overlay and its mp4v frame).
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from stream import render, run_loop
from video_with_depth import VideoWithDepth

from dope_hope.assets import DEMO_WEIGHTS
from dope_hope.demo.scenes import IMAGE_SIZE
from dope_hope.demo_object import demo_object_mesh
from dope_hope.devices import cpu_line
from dope_hope.inference.frame_loop import passive_openmp

FRAME_ID = "camera_color_optical_frame"
PERIOD_NS = 33_333_333
T0_NS = 1_700_000_000_000_000_000


def write_bag(path: Path, video: Path, K: np.ndarray, depths: list) -> Path:
    """The rendered frames (decoded back from ``video``, as the video run sees them) with their
    depth and K as a ROS 2 MCAP bag on RealSense's topics; returns the bag folder."""
    import cv2

    from dope_hope.ros.message_types import ros2_typestore
    from dope_hope.ros.recording_writer import RecordingWriter

    T = ros2_typestore().types
    writer = RecordingWriter(path)
    capture = cv2.VideoCapture(str(video))
    for i, depth in enumerate(depths):
        ok, bgr = capture.read()
        assert ok, f"{video}: frame {i} missing"
        stamp = T0_NS + i * PERIOD_NS
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9,
                                                                                  nanosec=stamp % 10**9),
                                          frame_id=FRAME_ID)
        rgb = np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        mm = np.round(depth * 1000).astype(np.uint16)
        h, w = mm.shape
        writer.write("/camera/color/image_raw", stamp, T["sensor_msgs/msg/Image"](
            header=header, height=h, width=w, encoding="rgb8", is_bigendian=0, step=w * 3, data=rgb.reshape(-1)))
        writer.write("/camera/aligned_depth_to_color/image_raw", stamp, T["sensor_msgs/msg/Image"](
            header=header, height=h, width=w, encoding="16UC1", is_bigendian=0, step=w * 2,
            data=mm.reshape(-1).view(np.uint8)))
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        writer.write("/camera/color/camera_info", stamp, T["sensor_msgs/msg/CameraInfo"](
            header=header, height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5), k=K.ravel(),
            r=np.eye(3).ravel(), p=np.hstack([K, np.zeros((3, 1))]).ravel(), binning_x=0, binning_y=0, roi=roi))
    capture.release()
    return writer.close()


def run_recording(predictor, bag: Path, out: Path, max_frames: int | None = None):
    """The `dope-hope infer robot_bag/` loop: (StreamStats, detections, detections refined by -LS)."""
    from dope_hope.inference.stream_inference import StreamSinks, predict_stream
    from dope_hope.ros.outputs import RosOutputs
    from dope_hope.ros.recording_writer import RecordingWriter
    from dope_hope.ros.recordings import RecordingSource

    source = RecordingSource(bag)
    outputs = RosOutputs(RecordingWriter(out), None, overlays=True)
    lines: list[str] = []
    result = predict_stream(source, [predictor], StreamSinks(on_record=lambda rec: lines.append(json.dumps(rec)),
                                                             on_frame=outputs.on_frame), max_frames=max_frames)
    outputs.close()
    return result.stats, len(lines), sum(r["ls_applied"] for r in result.records)


def io_only(bag: Path, video: Path, K: np.ndarray, depths: list, out: Path) -> dict[str, tuple[float, float]]:
    """{"recording" | "video": (ms per frame read, ms per frame written)}, no network (module docstring)."""
    from dope_hope.io.camera import ImageCamera
    from dope_hope.io.video import OverlayVideo
    from dope_hope.ros.outputs import RosOutputs
    from dope_hope.ros.recording_writer import RecordingWriter
    from dope_hope.ros.recordings import RecordingSource
    from dope_hope.viz import overlay_detections

    def timed(source, write) -> tuple[float, float]:
        t_read = t_write = 0.0
        n = 0
        grabbed = source.grab()
        while True:
            t0 = time.perf_counter()
            item = next(grabbed, None)
            if item is None:
                break
            frame = item.load()
            t1 = time.perf_counter()
            write(frame)
            t_read, t_write, n = t_read + t1 - t0, t_write + time.perf_counter() - t1, n + 1
        source.close()
        return 1000 * t_read / n, 1000 * t_write / n

    ros = RosOutputs(RecordingWriter(out / "io_poses"), None, overlays=True)
    rec = timed(RecordingSource(bag), lambda f: ros.on_frame(f, []))
    ros.close()
    camera = ImageCamera(K=K, width=IMAGE_SIZE[0], height=IMAGE_SIZE[1], source=Path("bench"))
    overlay = OverlayVideo(out / "io_overlay", 30.0)
    vid = timed(VideoWithDepth(video, camera, depths), lambda f: overlay.write(overlay_detections(f.rgb, [], f.K)))
    overlay.close()
    return {"recording": rec, "video": vid}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--weights", type=Path, default=DEMO_WEIGHTS)
    args = ap.parse_args()

    passive_openmp()  # as `dope-hope infer` does for a stream, before torch is imported
    from dope_hope.inference.backends import open_backend
    from dope_hope.inference.predictor import DopePredictor

    # the network backend before any rendering: importing torch after the GL context crashes here
    predictor = DopePredictor(open_backend(args.weights, "torch", threads=args.threads), mesh=demo_object_mesh())
    with tempfile.TemporaryDirectory(prefix="bench-recordings-") as tmpdir:
        tmp = Path(tmpdir)
        t0 = time.perf_counter()
        video, K, depths = render(tmp, args.frames)
        bag = write_bag(tmp / "robot", video, K, depths)
        size_mb = sum(p.stat().st_size for p in bag.iterdir()) / 1e6
        print(f"{cpu_line()}, {os.cpu_count()} CPUs, {args.threads} threads; {args.frames} frames "
              f"{IMAGE_SIZE[0]}x{IMAGE_SIZE[1]} with depth rendered and written in {time.perf_counter() - t0:.1f} s: "
              f"{video.name} and a ROS 2 MCAP bag of {size_mb:.1f} MB; PyTorch, {args.weights.name}; "
              f"load average {os.getloadavg()[0]:.2f}", flush=True)
        runs = (("recording", lambda out, n=None: run_recording(predictor, bag, out, n)),
                ("video", lambda out, n=None: run_loop(predictor, video, K, depths, out, n)))
        for name, run in runs:  # warm-up
            run(tmp / f"warm_{name}", 3)
        best: dict[str, float] = {}
        fps: dict[str, list] = {"recording": [], "video": []}
        io_times: dict[str, list] = {"recording": [], "video": []}
        for r in range(args.repeats):
            for name, run in runs:
                stats, n_det, n_ls = run(tmp / f"{name}_{r}")
                best[name] = max(best.get(name, 0.0), stats.fps)
                fps[name].append(stats.fps)
                print(f"{name:9s} run {r + 1}: {stats.summary()}; {n_det} detection(s), {n_ls} refined by -LS; "
                      f"load average {os.getloadavg()[0]:.2f}", flush=True)
            for name, times in io_only(bag, video, K, depths, tmp / f"io_{r}").items():
                io_times[name].append(times)
    med = {name: np.median(np.array(t), axis=0) for name, t in io_times.items()}
    for name, (read_ms, write_ms) in med.items():
        print(f"{name:9s} input/output alone (median of {args.repeats}): read {read_ms:.1f} ms/frame, "
              f"outputs written {write_ms:.1f} ms/frame")
    rec, vid = best["recording"], best["video"]
    print(f"best of {args.repeats}: recording {rec:.1f} frames/s (reading + the poses MCAP), video {vid:.1f} frames/s "
          f"(decoding + the overlay video); recording / video {rec / vid:.2f}x end to end; medians "
          f"{np.median(fps['recording']):.1f} and {np.median(fps['video']):.1f} frames/s "
          f"({np.median(fps['recording']) / np.median(fps['video']):.2f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
