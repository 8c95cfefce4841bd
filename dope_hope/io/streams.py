"""Where ``dope-hope infer`` gets the frames of a stream: a video file, a camera, a RealSense.

:func:`stream_kind` tells a stream input from an image input (image files, folders and
globs stay with ``dope_hope.commands.infer``); :func:`open_stream` opens one:

* a video file (:data:`VIDEO_SUFFIXES`): :class:`VideoFile`, decoded by OpenCV (FFmpeg);
* a camera index (``0``): :class:`CameraDevice`, ``cv2.VideoCapture(0)``;
* ``realsense`` or ``realsense:SERIAL``: :class:`RealSenseCamera`, an Intel RealSense through
  the vendor's ``pyrealsense2`` (``pip install "dope-hope[realsense]"``): colour, depth aligned
  to colour (``rs.align``), intrinsics and depth scale read from the device.

A digit string is always a camera index and ``realsense[:SERIAL]`` always the device: a file
or folder of that name is given as ``./0`` or ``realsense/``.

A source yields :class:`Grabbed` items (index, timestamp and a ``load()`` that makes the
:class:`Frame`): grabbing runs in the stream loop's reader thread
(:mod:`dope_hope.inference.frame_loop`) and stays cheap; the costly part (RealSense alignment,
colour conversion and undistortion of a camera frame) runs in ``load()``, only for the frames
the loop processes (a video file's frames are decoded in the reader thread, ahead of the loop).
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dope_hope.errors import CameraError, ConfigError, DeviceError, InputFileError
from dope_hope.geometry import intrinsics_matrix
from dope_hope.io.camera import ImageCamera, Rectification
from dope_hope.io.images import GLOB_CHARS

#: File suffixes read as videos.
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv")
#: File suffixes of robot recordings (ROS 1 bag, ROS 2 MCAP / sqlite3; :mod:`dope_hope.ros.recordings`).
RECORDING_SUFFIXES = (".bag", ".mcap", ".db3")
#: Colour and depth resolution (W, H) and frame rate asked of a RealSense by default.
REALSENSE_DEFAULT_SIZE = (640, 480)
REALSENSE_DEFAULT_FPS = 30
#: How long a RealSense read may wait for a frame set, milliseconds.
REALSENSE_TIMEOUT_MS = 5000
#: Largest camera index OpenCV takes (a C int).
MAX_CAMERA_INDEX = 2**31 - 1
_REALSENSE = "realsense"


@dataclass
class Frame:
    """One frame for the predictors.

    index: position in its source, 0-based (a camera's count of captured frames).
    timestamp_s: seconds since the source's first frame (a video's presentation time; a
        camera's capture time).
    name: the records' ``image`` ("clip.mp4#000012", "camera0#000012").
    rgb: (H, W, 3) uint8. K: (3, 3) intrinsics of ``rgb``.
    depth: (H, W) float32 metres registered to ``rgb`` (0 = no measurement), or None.
    stamp_ns, frame_id: a recorded image's header stamp (ns since the epoch) and frame_id
        (:mod:`dope_hope.ros.recordings`), else None.
    """

    index: int
    timestamp_s: float
    name: str
    rgb: np.ndarray
    K: np.ndarray
    depth: np.ndarray | None = None
    stamp_ns: int | None = None
    frame_id: str | None = None


@dataclass
class Grabbed:
    """A frame taken from its source but not yet made (``load()`` makes it)."""

    index: int
    timestamp_s: float
    load: Callable[[], Frame]


class FrameSource:
    """Base of the sources: ``grab()`` yields :class:`Grabbed` items, ``close()`` releases.

    name: short name for outputs ("clip.mp4", "camera0", "realsense"). live: frames arrive in
    real time whether or not they are taken (a camera). fps: nominal frames per second, or
    None. length: number of frames when known (a video file's frame count), else None.
    """

    name: str = ""
    live: bool = False
    fps: float | None = None
    length: int | None = None

    def grab(self) -> Iterator[Grabbed]:
        raise NotImplementedError

    def close(self) -> None:
        """Release the file or device (idempotent)."""


def _rectify(rect: Rectification | None, rgb: np.ndarray, depth: np.ndarray | None):
    if rect is None:
        return rgb, depth
    return rect.image(rgb), None if depth is None else rect.depth(depth)


# ----------------------------------------------------------------------------- OpenCV captures
def open_capture(target: int | str):
    """``cv2.VideoCapture`` of a file path or camera index, OpenCV's and FFmpeg's own log lines
    silenced (a failure becomes one error line of ours)."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # read when FFmpeg is first used
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        return cv2.VideoCapture(target)
    finally:
        cv2.utils.logging.setLogLevel(level)


class _Capture(FrameSource):
    """Frames of a ``cv2.VideoCapture`` (BGR converted to RGB) with a fixed camera."""

    def __init__(self, capture, camera: ImageCamera):
        self.capture = capture
        self.camera = camera

    def _frame(self, index: int, timestamp_s: float, bgr: np.ndarray) -> Frame:
        if bgr.ndim == 2:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)
        else:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGRA2RGB if bgr.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        name = f"{self.name}#{index:06d}"
        self.camera.check_size(name, rgb.shape[1], rgb.shape[0])
        rgb, _ = _rectify(self.camera.rectification, rgb, None)
        return Frame(index=index, timestamp_s=timestamp_s, name=name, rgb=rgb, K=self.camera.K)

    def close(self) -> None:
        self.capture.release()


class VideoFile(_Capture):
    """A video file decoded by OpenCV; timestamps are the file's presentation times."""

    def __init__(self, path: str | os.PathLike, camera: ImageCamera):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputFileError(self.path, "video file not found")
        super().__init__(open_capture(str(self.path)), camera)
        if not self.capture.isOpened():
            raise InputFileError(self.path, "not a readable video (OpenCV / FFmpeg cannot open it)")
        self.name = self.path.name
        fps = float(self.capture.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = fps if np.isfinite(fps) and fps > 0 else None
        count = int(self.capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self.length = count if count > 0 else None

    def grab(self) -> Iterator[Grabbed]:
        index = 0
        while True:
            ok, bgr = self.capture.read()
            if not ok or bgr is None:
                break
            ms = float(self.capture.get(cv2.CAP_PROP_POS_MSEC))
            ts = ms / 1000.0 if (ms > 0 or index == 0) else (index / self.fps if self.fps else float(index))
            frame = self._frame(index, ts, bgr)  # decoded here, in the reader thread
            yield Grabbed(index, ts, lambda frame=frame: frame)
            index += 1
        if index == 0:
            raise InputFileError(self.path, "no frame could be decoded")


class CameraDevice(_Capture):
    """A camera by its OpenCV index; timestamps are capture times since the first frame."""

    live = True

    def __init__(self, index: int, camera: ImageCamera, size: tuple[int, int] | None = None,
                 fps: float | None = None):
        if not 0 <= index <= MAX_CAMERA_INDEX:
            raise DeviceError(f"camera {index}: camera index out of range (OpenCV takes 0 to {MAX_CAMERA_INDEX})")
        capture = open_capture(index)
        if not capture.isOpened():
            raise DeviceError(f"camera {index}: cannot be opened (no such device, or in use)")
        super().__init__(capture, camera)
        self.name = f"camera{index}"
        size = size or ((camera.width, camera.height) if camera.width and camera.height else None)
        if size is not None:
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        if fps:
            capture.set(cv2.CAP_PROP_FPS, fps)
        reported = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = reported if np.isfinite(reported) and reported > 0 else None

    def grab(self) -> Iterator[Grabbed]:
        index, t0 = 0, None
        while True:
            ok, bgr = self.capture.read()
            now = time.monotonic()
            if not ok or bgr is None:
                if index == 0:
                    raise DeviceError(f"{self.name}: opened but delivers no frames")
                raise DeviceError(f"{self.name}: stopped delivering frames after {index}")
            t0 = now if t0 is None else t0
            yield Grabbed(index, now - t0, lambda i=index, ts=now - t0, bgr=bgr: self._frame(i, ts, bgr))
            index += 1


# ----------------------------------------------------------------------------- RealSense
def _import_realsense():
    try:
        import pyrealsense2  # noqa: PLC0415 (pyrealsense2 is the optional realsense extra)
    except ModuleNotFoundError as exc:
        if exc.name != "pyrealsense2":
            raise
        raise ConfigError("realsense: needs Intel's pyrealsense2 package: "
                          "pip install \"dope-hope[realsense]\"") from None
    return pyrealsense2


class RealSenseCamera(FrameSource):
    """An Intel RealSense through ``pyrealsense2``: RGB colour, depth aligned to it.

    K comes from the colour stream's intrinsics and the depth scale (metres per unit) from the
    device's depth sensor; depth frames are aligned to colour with ``rs.align(rs.stream.color)``
    (in ``load()``, only for processed frames) and returned in metres. A colour stream with
    Brown-Conrady distortion is undistorted (image and aligned depth, K kept); other non-zero
    distortion models are reported once as a warning and left as they are.

    Args:
        serial: the device's serial number, or None for the first one found.
        size: (W, H) of both streams. fps: frames per second of both streams.
        warn: called with one line per warning.
    """

    live = True

    def __init__(self, serial: str | None = None, size: tuple[int, int] | None = None,
                 fps: float | None = None, warn: Callable[[str], None] | None = None):
        rs = _import_realsense()
        self.rs = rs
        self.name = _REALSENSE if serial is None else f"{_REALSENSE}-{serial}"
        w, h = size or REALSENSE_DEFAULT_SIZE
        self.fps = float(fps or REALSENSE_DEFAULT_FPS)
        config = rs.config()
        if serial is not None:
            config.enable_device(str(serial))
        config.enable_stream(rs.stream.color, int(w), int(h), rs.format.rgb8, int(self.fps))
        config.enable_stream(rs.stream.depth, int(w), int(h), rs.format.z16, int(self.fps))
        self.pipeline = rs.pipeline()
        try:
            profile = self.pipeline.start(config)
        except RuntimeError as exc:
            raise DeviceError(f"{self.name}: cannot start the colour + depth streams at {w}x{h}, "
                              f"{self.fps:g} fps ({exc})") from None
        self._started = True
        try:
            self.depth_scale_m = float(profile.get_device().first_depth_sensor().get_depth_scale())
            intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        except RuntimeError as exc:
            self.close()
            raise DeviceError(f"{self.name}: cannot read the intrinsics / depth scale ({exc})") from None

        self.K = intrinsics_matrix(float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy))
        self.size = (int(intr.width), int(intr.height))
        self.rectification = None
        coeffs = np.asarray(list(intr.coeffs), dtype=np.float64)
        if np.any(coeffs):
            if intr.model == rs.distortion.brown_conrady:
                self.rectification = Rectification(K_raw=self.K, D=coeffs[:5], R=np.eye(3), K_new=self.K)
            elif warn is not None:
                warn(f"{self.name}: colour distortion {intr.model} {coeffs.round(4).tolist()} is not corrected")
        self.align = rs.align(rs.stream.color)

    def grab(self) -> Iterator[Grabbed]:
        index, t0 = 0, None
        while True:
            try:
                frames = self.pipeline.wait_for_frames(REALSENSE_TIMEOUT_MS)
            except RuntimeError as exc:
                raise DeviceError(f"{self.name}: no frames after {index} ({exc})") from None
            ms = float(frames.get_timestamp())
            t0 = ms if t0 is None else t0
            ts = (ms - t0) / 1000.0
            yield Grabbed(index, ts, lambda i=index, ts=ts, fs=frames: self._load(i, ts, fs))
            index += 1

    def _load(self, index: int, timestamp_s: float, frames) -> Frame:
        aligned = self.align.process(frames)
        color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
        name = f"{self.name}#{index:06d}"
        if not color or not depth:
            raise DeviceError(f"{name}: a frame set without colour or depth")
        rgb = np.array(np.asanyarray(color.get_data()), dtype=np.uint8, copy=True)
        d = np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(self.depth_scale_m)
        if rgb.shape[:2] != d.shape or rgb.shape[1::-1] != self.size:
            raise DeviceError(f"{name}: colour {rgb.shape[1]}x{rgb.shape[0]} and aligned depth "
                              f"{d.shape[1]}x{d.shape[0]} differ from the intrinsics' {self.size[0]}x{self.size[1]}")
        rgb, d = _rectify(self.rectification, rgb, d)
        return Frame(index=index, timestamp_s=timestamp_s, name=name, rgb=rgb, K=self.K, depth=d)

    def close(self) -> None:
        if getattr(self, "_started", False):
            self._started = False
            try:
                self.pipeline.stop()
            except RuntimeError:
                pass


# ----------------------------------------------------------------------------- dispatch
#: Bytes of a folder's metadata.yaml searched for the ROS 2 bag key (it is the file's first key).
ROS2_METADATA_HEAD = 4096


def is_recording(item: str) -> bool:
    """True for a ROS 1 bag, a ROS 2 MCAP / sqlite3 file or a ROS 2 bag folder (a
    metadata.yaml that describes a bag: its ``rosbag2_bagfile_information`` key; an image
    folder's own metadata.yaml does not make it a bag)."""
    path = Path(item)
    if path.suffix.lower() in RECORDING_SUFFIXES and not (GLOB_CHARS & set(item)):
        return True
    metadata = path / "metadata.yaml"
    if not (path.is_dir() and metadata.is_file()):
        return False
    try:
        with open(metadata, "rb") as f:
            return b"rosbag2_bagfile_information" in f.read(ROS2_METADATA_HEAD)
    except OSError:
        return True  # unreadable: the recording reader says why


def stream_kind(item: str) -> str | None:
    """"camera", "realsense", "video" or "recording" (:mod:`dope_hope.ros.recordings`, opened
    by its ``RecordingSource``) for an input naming a stream, else None (images)."""
    if is_recording(item):
        return "recording"
    if item.isdigit():
        return "camera"
    if item == _REALSENSE or item.startswith(_REALSENSE + ":"):
        return "realsense"
    if Path(item).suffix.lower() in VIDEO_SUFFIXES and not (GLOB_CHARS & set(item)):
        return "video"
    return None


def open_stream(inputs: list[str], camera: ImageCamera | None = None, depth: str | None = None,
                capture_size: tuple[int, int] | None = None, capture_fps: float | None = None,
                warn: Callable[[str], None] | None = None) -> FrameSource:
    """The one video / camera / RealSense the inputs name (module docstring).

    ``camera`` is required for a video or camera index (CameraError otherwise) and refused for
    a RealSense (its intrinsics come from the device); ``depth`` (``--depth``) is refused:
    only a RealSense streams depth.
    """
    kinds = [stream_kind(i) for i in inputs]
    stream = next((i for i, k in zip(inputs, kinds) if k), None)
    if stream is None:
        raise ConfigError(f"no video, camera or RealSense among the inputs {inputs}")
    if len(inputs) != 1:
        raise ConfigError(f"{stream}: a video, camera or RealSense input must be the only input")
    item, kind = inputs[0], kinds[0]
    if kind == "recording":
        raise ConfigError(f"{item}: a recording is opened by dope_hope.ros.recordings.RecordingSource")
    if depth is not None:
        raise ConfigError(f"--depth applies to image inputs; {item} has none"
                          + (" (a RealSense brings its own)" if kind == "realsense" else ""))
    if kind == "realsense":
        if camera is not None:
            raise ConfigError("a RealSense's intrinsics are read from the device; drop --camera / --fx ...")
        serial = item.partition(":")[2] or None
        return RealSenseCamera(serial, capture_size, capture_fps, warn)
    if camera is None:
        raise CameraError(f"{item}: no camera intrinsics for a video or camera; give --camera "
                          "K.json|camera_info.yaml or --fx --fy --cx --cy")
    if kind == "camera":
        return CameraDevice(int(item), camera, capture_size, capture_fps)
    return VideoFile(item, camera)
