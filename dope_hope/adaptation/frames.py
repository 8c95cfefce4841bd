"""The unlabelled frames `dope-hope adapt` learns from, as a sequence of RGB-D
:class:`~dope_hope.io.streams.Frame` s: a robot recording, a video with its camera and its
depth images, or a folder (files, globs) of RGB-D frames. Each is opened the way `dope-hope
infer` opens it (:func:`dope_hope.ros.recordings.open_recording`,
:class:`dope_hope.io.streams.VideoFile`, :func:`dope_hope.io.images.collect_images` with
:func:`dope_hope.io.camera.find_image_camera`); every frame must bring depth, the teacher.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

from dope_hope.errors import CameraError, ConfigError, InputFileError
from dope_hope.io.camera import ImageCamera, camera_search_description, find_image_camera
from dope_hope.io.images import collect_images, read_depth_m, read_rgb
from dope_hope.io.streams import Frame, FrameSource, Grabbed, VideoFile, stream_kind
from dope_hope.ros.recordings import open_recording


class DepthImageFiles(FrameSource):
    """Still RGB images with registered depth, in name order: each image's camera and depth
    from its annotation (DOPE ``NNNNNN.depth.png``, HOPE, BOP), or ``camera`` for all.
    Every image is checked for its camera and depth when opened (no work before that)."""

    def __init__(self, inputs: list[str], camera: ImageCamera | None = None, depth_scale_mm: float | None = None):
        images = collect_images(inputs)
        self.name = inputs[0] if len(inputs) == 1 else "images"
        self.length = len(images)
        self.items = []
        for path, name in images:
            found = find_image_camera(path)
            cam = camera or found
            if cam is None:
                raise CameraError(f"{path}: no camera intrinsics (looked for {camera_search_description(path)}); "
                                  "give --camera K.json or --fx --fy --cx --cy")
            if found is None or found.depth_path is None:
                raise InputFileError(path, "no registered depth image beside it (DOPE NNNNNN.depth.png, HOPE "
                                           "NNNN_depth.png, BOP ../depth/): adapt learns from the depth")
            scale = depth_scale_mm * 0.001 if depth_scale_mm is not None else (found.depth_scale_m or 0.001)
            self.items.append((path, name, cam, found.depth_path, scale))

    def grab(self) -> Iterator[Grabbed]:
        for i, (path, name, cam, depth_path, scale) in enumerate(self.items):
            def load(i=i, path=path, name=name, cam=cam, depth_path=depth_path, scale=scale) -> Frame:
                rgb = read_rgb(path)
                cam.check_size(path, rgb.shape[1], rgb.shape[0])
                depth = read_depth_m(depth_path, scale)
                if depth.shape != rgb.shape[:2]:
                    raise InputFileError(depth_path, f"depth is {depth.shape[1]}x{depth.shape[0]}, the image "
                                                     f"{path.name} is {rgb.shape[1]}x{rgb.shape[0]}")
                return Frame(i, float(i), name, rgb, cam.K, depth)
            yield Grabbed(i, float(i), load)


class VideoDepthFiles(VideoFile):
    """A video file whose frame i takes the i-th depth image of a folder (name order)."""

    def __init__(self, path: str | Path, camera: ImageCamera, depth_folder: Path, depth_scale_mm: float | None = None):
        super().__init__(path, camera)
        if not depth_folder.is_dir():
            raise InputFileError(depth_folder, "--depth: not a folder of depth images")
        self.depth_files = [p for _, p in sorted((p.name, p) for p in depth_folder.iterdir()
                                                 if p.suffix.lower() in (".png", ".tif", ".tiff", ".exr"))]
        if not self.depth_files:
            raise InputFileError(depth_folder, "--depth: the folder holds no depth images (.png, .tif, .exr)")
        if self.length is not None and self.length != len(self.depth_files):
            raise InputFileError(depth_folder, f"--depth: {len(self.depth_files)} depth images for the "
                                               f"{self.length} frames of {self.name}")
        self.scale_m = (depth_scale_mm or 1.0) * 0.001

    def grab(self) -> Iterator[Grabbed]:
        for g in super().grab():
            if g.index >= len(self.depth_files):
                raise InputFileError(self.path, f"more frames than the {len(self.depth_files)} depth images")
            frame = g.load()
            depth = read_depth_m(self.depth_files[g.index], self.scale_m)
            if depth.shape != frame.rgb.shape[:2]:
                raise InputFileError(self.depth_files[g.index], f"depth is {depth.shape[1]}x{depth.shape[0]}, "
                                                                f"the video is {frame.rgb.shape[1]}x{frame.rgb.shape[0]}")
            frame.depth = depth
            yield Grabbed(g.index, g.timestamp_s, lambda frame=frame: frame)


def open_unlabelled(inputs: list[str], camera: ImageCamera | None = None, depth: Path | None = None,
                    depth_scale_mm: float | None = None, image_topic: str | None = None,
                    depth_topic: str | None = None, camera_info_topic: str | None = None,
                    warn: Callable[[str], None] | None = None) -> FrameSource:
    """The frames of ``inputs`` (module docstring): a recording (its depth topic required), a
    video (``camera`` and a ``depth`` folder required), or image files / folders / globs
    (each with its depth). ConfigError / InputFileError / CameraError, one line, otherwise."""
    if not inputs:
        raise ConfigError("no input frames: give a recording, a video or a folder of RGB-D frames")
    kinds = [stream_kind(i) for i in inputs]
    if any(k in ("camera", "realsense") for k in kinds):
        raise ConfigError(f"{inputs[kinds.index('camera') if 'camera' in kinds else kinds.index('realsense')]}: "
                          "adapt learns from recorded frames; record first (a ROS bag or MCAP), then adapt")
    if any(kinds) and len(inputs) != 1:
        raise ConfigError(f"{next(i for i, k in zip(inputs, kinds) if k)}: a recording or video must be the only input")
    if kinds[0] == "recording":
        if depth is not None:
            raise ConfigError(f"--depth: the recording {inputs[0]} brings its own depth (--depth-topic)")
        return open_recording(inputs, image_topic, depth_topic, camera_info_topic, camera, icp=True, warn=warn)
    topics = [f for f, v in (("--image-topic", image_topic), ("--depth-topic", depth_topic),
                             ("--camera-info-topic", camera_info_topic)) if v]
    if topics:
        raise ConfigError(f"{', '.join(topics)}: for a recording input, not {inputs[0]}")
    if kinds[0] == "video":
        if camera is None:
            raise CameraError(f"{inputs[0]}: no camera intrinsics for a video; give --camera K.json|camera_info.yaml "
                              "or --fx --fy --cx --cy")
        if depth is None:
            raise ConfigError(f"{inputs[0]}: a video holds no depth; give its depth images with --depth DIR "
                              "(frame i: the i-th file by name)")
        return VideoDepthFiles(inputs[0], camera, Path(depth), depth_scale_mm)
    if depth is not None:
        raise ConfigError("--depth DIR is for a video; images bring their own depth (NNNNNN.depth.png beside them)")
    return DepthImageFiles(inputs, camera, depth_scale_mm)
