"""Frame sources (video file, camera index, RealSense through a fake pyrealsense2) and the stream
loop that drops the frames it cannot process (dope_hope.io.streams, dope_hope.inference.frame_loop)."""
from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import fake_realsense
import numpy as np
import pytest
from video_files import write_video

from dope_hope.errors import CameraError, ConfigError, DeviceError, InputFileError
from dope_hope.geometry import intrinsics_matrix
from dope_hope.inference.frame_loop import FrameFeed, run_stream
from dope_hope.io.camera import ImageCamera
from dope_hope.io.streams import (
    CameraDevice,
    FrameSource,
    Grabbed,
    RealSenseCamera,
    VideoFile,
    open_stream,
    stream_kind,
)

K = intrinsics_matrix(300.0, 301.0, 159.5, 119.5)
W, H = 320, 240


def camera(width=None, height=None) -> ImageCamera:
    return ImageCamera(K=K, width=width, height=height, source=Path("K.json"))


def pattern(i: int) -> np.ndarray:
    """(H, W, 3) uint8 frame i: a flat grey level that survives video compression, and a
    block whose position encodes i."""
    img = np.full((H, W, 3), 40 + 20 * i, np.uint8)
    img[20:60, 20 + 25 * i: 60 + 25 * i] = (250, 30, 30)
    return img


def write_clip(path: Path, n: int, fps: float = 10.0) -> Path:
    """An n-frame video of :func:`pattern`."""
    return write_video(path, [pattern(i) for i in range(n)], fps)


def test_video_file_frames_timestamps_and_names(tmp_path):
    video = write_clip(tmp_path / "clip", 6, fps=12.5)
    src = VideoFile(video, camera(W, H))
    assert (src.fps, src.length, src.live) == (12.5, 6, False)
    frames = [g.load() for g in src.grab()]
    src.close()
    assert [f.index for f in frames] == list(range(6))
    np.testing.assert_allclose([f.timestamp_s for f in frames], np.arange(6) / 12.5, atol=1e-6)
    assert frames[3].name == f"{video.name}#000003"
    for i, f in enumerate(frames):  # decoded RGB (not BGR), the right frame
        assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8 and f.depth is None
        assert abs(float(np.median(f.rgb[120:, :, 1])) - (40 + 20 * i)) < 6
        block = f.rgb[25:55, 25 + 25 * i: 55 + 25 * i].reshape(-1, 3).mean(0)
        assert block[0] > 200 and block[2] < 80
        np.testing.assert_array_equal(f.K, K)


def test_video_errors_are_one_line(tmp_path):
    with pytest.raises(InputFileError, match="video file not found"):
        VideoFile(tmp_path / "missing.mp4", camera())
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(InputFileError, match="bad.mp4: not a readable video"):
        VideoFile(bad, camera())
    video = write_clip(tmp_path / "clip", 2)
    src = VideoFile(video, camera(640, 480))
    with pytest.raises(InputFileError, match="camera is for 640x480 images.*320x240"):
        next(src.grab())
    with pytest.raises(CameraError, match="no camera intrinsics"):
        open_stream([str(video)])
    with pytest.raises(ConfigError, match="must be the only input"):
        open_stream([str(video), "x.png"], camera())
    with pytest.raises(ConfigError, match="--depth applies to image inputs"):
        open_stream([str(video)], camera(), depth="auto")


def test_stream_kinds():
    assert [stream_kind(s) for s in ("0", "12", "realsense", "realsense:0123", "a/clip.MP4", "x.avi",
                                     "img.png", "scene/", "realsense/", "*.mp4")] == \
        ["camera", "camera", "realsense", "realsense", "video", "video", None, None, None, None]


def test_camera_index_reads_through_opencv(tmp_path, monkeypatch):
    video = write_clip(tmp_path / "cam", 4)
    opened = []

    def fake_open(target):
        opened.append(target)
        return cv2.VideoCapture(str(video)) if target == 3 else cv2.VideoCapture(str(tmp_path / "none.mp4"))

    monkeypatch.setattr("dope_hope.io.streams.open_capture", fake_open)
    src = CameraDevice(3, camera(W, H))
    assert src.live and src.name == "camera3" and opened == [3]
    items = []
    with pytest.raises(DeviceError, match="camera3: stopped delivering frames after 4"):
        for g in src.grab():
            items.append(g.load())
    assert [f.index for f in items] == [0, 1, 2, 3] and items[0].timestamp_s == 0.0
    assert all(b.timestamp_s >= a.timestamp_s for a, b in zip(items, items[1:]))
    assert items[2].name == "camera3#000002"
    with pytest.raises(DeviceError, match="camera 5: cannot be opened"):
        CameraDevice(5, camera())


# ----------------------------------------------------------------------------- RealSense
def rs_frames(n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    yy, xx = np.mgrid[0:H, 0:W]
    return [(pattern(i), (0.5 + 0.001 * xx + 0.0001 * yy + 0.01 * i).astype(np.float32)) for i in range(n)]


def test_realsense_frames_depth_aligned_intrinsics_and_scale(monkeypatch):
    frames = rs_frames(3)
    rs = fake_realsense.install(monkeypatch, frames, K, depth_scale=0.00025, fps=15.0)
    src = RealSenseCamera(serial="0123", size=(W, H), fps=15)
    assert src.live and src.name == "realsense-0123" and src.depth_scale_m == 0.00025
    start = next(c for c in rs.calls if c[0] == "start")
    assert start[1] == "0123"
    assert (rs.stream.color, W, H, rs.format.rgb8, 15) in start[2]
    assert (rs.stream.depth, W, H, rs.format.z16, 15) in start[2]
    assert ("align", rs.stream.color) in rs.calls
    grabbed = []
    with pytest.raises(DeviceError, match="no frames after 3"):
        for g in src.grab():
            grabbed.append(g)
    assert ("align.process",) not in rs.calls  # grabbing is cheap: alignment happens in load()
    out = [g.load() for g in grabbed]
    assert [f.index for f in out] == [0, 1, 2]
    np.testing.assert_allclose([f.timestamp_s for f in out], [0, 1 / 15, 2 / 15], atol=1e-9)
    for f, (rgb, depth) in zip(out, frames):
        np.testing.assert_array_equal(f.rgb, rgb)
        np.testing.assert_array_equal(f.K, K)
        assert f.depth.dtype == np.float32 and f.depth.shape == (H, W)
        np.testing.assert_allclose(f.depth, depth, atol=0.00025 / 2 + 1e-6)  # aligned, in metres
    src.close()
    src.close()
    assert rs.calls.count(("stop",)) == 1


def test_realsense_brown_conrady_colour_is_undistorted(monkeypatch):
    coeffs = (0.12, -0.05, 0.0, 0.0, 0.0)
    fake_realsense.install(monkeypatch, rs_frames(1), K, model=fake_realsense.distortion.brown_conrady,
                           coeffs=coeffs)
    src = RealSenseCamera()
    assert src.name == "realsense" and src.rectification is not None
    np.testing.assert_allclose(src.rectification.D, coeffs)
    warned = []
    fake_realsense.install(monkeypatch, rs_frames(1), K, model=fake_realsense.distortion.ftheta, coeffs=coeffs)
    assert RealSenseCamera(warn=warned.append).rectification is None
    assert len(warned) == 1 and "not corrected" in warned[0]


def test_realsense_missing_package_or_device(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails like a missing package
    with pytest.raises(ConfigError, match=r'pip install "dope-hope\[realsense\]"'):
        open_stream(["realsense"])
    fake_realsense.install(monkeypatch, rs_frames(1), K, connected=False)
    with pytest.raises(DeviceError, match="realsense: cannot start.*No device connected"):
        open_stream(["realsense"])
    fake_realsense.install(monkeypatch, rs_frames(1), K)
    with pytest.raises(ConfigError, match="read from the device"):
        open_stream(["realsense"], camera())


# ----------------------------------------------------------------------------- the loop
class Ticker(FrameSource):
    """``n`` frames, one every ``period`` s of wall time (live: whether or not the loop takes
    them), stamped ``i * stamp`` s; ``load()`` gives the index."""

    name = "ticker"

    def __init__(self, n: int, period: float, live: bool, fail_after: int | None = None,
                 stamp: float | None = None):
        self.n, self.period, self.live, self.fail_after = n, period, live, fail_after
        self.stamp = period if stamp is None else stamp
        self.closed = threading.Event()

    def grab(self):
        for i in range(self.n):
            if self.fail_after is not None and i == self.fail_after:
                raise DeviceError(f"ticker: unplugged after {i}")
            time.sleep(self.period)
            yield Grabbed(i, i * self.stamp, lambda i=i: i)

    def close(self):
        self.closed.set()


def test_live_source_keeps_the_newest_frame_and_counts_drops():
    src = Ticker(30, 0.005, live=True)
    seen = []
    stats = run_stream(src, lambda i: seen.append(i) or time.sleep(0.03))
    assert stats.read == 30 and stats.processed == len(seen)
    assert stats.dropped > 0 and stats.processed + stats.dropped == stats.read  # dropped, not queued
    assert seen == sorted(seen) and seen[-1] == 29  # always the newest; the last one is processed
    assert stats.fps > 0 and stats.seconds > 0 and src.closed.is_set()
    assert "30 frame(s) read" in stats.summary() and f"{stats.dropped} dropped" in stats.summary()


def test_file_source_processes_every_frame_in_order():
    src = Ticker(12, 0.0, live=False)
    seen = []
    stats = run_stream(src, lambda i: seen.append(i) or time.sleep(0.01))
    assert seen == list(range(12)) and (stats.read, stats.processed, stats.dropped) == (12, 12, 0)


def test_paced_file_plays_at_its_frame_rate_and_drops_behind():
    src = Ticker(10, 0.0, live=False, stamp=0.05)  # decoded at once, stamped 0, 0.05 .. 0.45 s
    t0 = time.perf_counter()
    seen = []
    stats = run_stream(src, lambda i: seen.append(i) or time.sleep(0.12), pace=True)
    assert time.perf_counter() - t0 >= 0.45  # not faster than the file's frame rate
    assert stats.dropped > 0 and stats.processed + stats.dropped == 10 and seen[-1] == 9


def test_max_frames_callback_stop_and_ctrl_c():
    stats = run_stream(Ticker(50, 0.0, live=False), lambda i: None, max_frames=7)
    assert (stats.read, stats.processed, stats.stopped) == (7, 7, "max frames")
    stats = run_stream(Ticker(50, 0.0, live=False), lambda i: i < 3)
    assert (stats.processed, stats.stopped) == (4, "stopped by the callback")
    src = Ticker(50, 0.001, live=True)

    def interrupt(i):
        if i >= 2:
            raise KeyboardInterrupt

    stats = run_stream(src, interrupt)
    assert stats.stopped == "interrupted" and src.closed.is_set()



def test_source_errors_reach_the_caller_after_the_frames_before_them():
    seen = []
    with pytest.raises(DeviceError, match="unplugged after 3"):
        run_stream(Ticker(10, 0.0, live=False, fail_after=3), seen.append)
    assert seen == [0, 1, 2]
    stats = run_stream(Ticker(10, 0.0, live=False, fail_after=3), lambda i: None, on_source_error=lambda e: True)
    assert stats.processed == 3 and "unplugged" in stats.stopped
    with pytest.raises(ValueError, match="boom"):  # the callback's own errors are never swallowed
        run_stream(Ticker(3, 0.0, live=False), lambda i: (_ for _ in ()).throw(ValueError("boom")),
                   on_source_error=lambda e: True)


def test_feed_prefetch_is_bounded():
    src = Ticker(20, 0.0, live=False)
    feed = FrameFeed(src, latest=False)
    time.sleep(0.2)
    assert feed.read <= 2  # the reader waits for the loop instead of queueing the file
    assert [g.index for g in feed] == list(range(20))
    feed.close()


def test_passive_openmp_only_before_torch_and_never_over_the_user(tmp_path):
    import os
    import subprocess
    import sys

    code = ("import os\nfrom dope_hope.inference.frame_loop import passive_openmp\n"
            "print(passive_openmp(), os.environ.get('OMP_WAIT_POLICY'))\nimport torch\nprint(passive_openmp())\n")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    repo = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join([repo, env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.stdout.split() == ["True", "PASSIVE", "False"], out.stderr
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env=dict(env, OMP_WAIT_POLICY="ACTIVE"))
    assert out.stdout.split() == ["False", "ACTIVE", "False"], out.stderr
