"""A stand-in for Intel's ``pyrealsense2`` with the calls dope_hope.io.streams makes, checked
against pyrealsense2 2.59 (names, signatures, units): ``pipeline`` (``start(config)``,
``wait_for_frames(timeout_ms)``, ``stop()``), ``config`` (``enable_device``,
``enable_stream(stream, w, h, format, fps)``), the profile's ``get_device().first_depth_sensor()
.get_depth_scale()`` and ``get_stream(stream.color).as_video_stream_profile().get_intrinsics()``
(``fx, fy, ppx, ppy, width, height, model, coeffs``), ``align(stream.color).process(frames)``,
frames' ``get_color_frame()``, ``get_depth_frame()``, ``get_data()``, ``get_timestamp()`` (ms).

The device plays a list of (rgb uint8, depth in metres) frames registered to colour. Like a
real D4xx, the depth stream it delivers *before* alignment is in the depth camera's own frame:
here it is shifted by :data:`UNALIGNED_SHIFT_PX` pixels, so that a reader skipping
``align.process`` gets depth that disagrees with the colour image. Install with
``install(monkeypatch, frames, ...)``; the returned module records what was asked of it.
"""
from __future__ import annotations

import enum
import sys
import types

import numpy as np

UNALIGNED_SHIFT_PX = 17


class stream(enum.Enum):  # noqa: N801 - pyrealsense2's names
    color = 2
    depth = 1


class format(enum.Enum):  # noqa: N801, A001
    rgb8 = 5
    z16 = 1


class distortion(enum.Enum):  # noqa: N801
    none = 0
    modified_brown_conrady = 1
    inverse_brown_conrady = 2
    ftheta = 3
    brown_conrady = 4
    kannala_brandt4 = 5


class intrinsics:  # noqa: N801
    def __init__(self, K, width, height, model=distortion.inverse_brown_conrady, coeffs=(0.0,) * 5):
        self.fx, self.fy, self.ppx, self.ppy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        self.width, self.height, self.model, self.coeffs = int(width), int(height), model, list(coeffs)


class _Frame:
    def __init__(self, data: np.ndarray, timestamp_ms: float, aligned: bool):
        self._data, self._ts, self.aligned = data, timestamp_ms, aligned

    def get_data(self):
        return memoryview(self._data)  # the real get_data() is a buffer too

    def get_timestamp(self) -> float:
        return self._ts

    def __bool__(self) -> bool:
        return True


class composite_frame:  # noqa: N801
    def __init__(self, color: _Frame, depth: _Frame):
        self._color, self._depth = color, depth

    def get_color_frame(self) -> _Frame:
        return self._color

    def get_depth_frame(self) -> _Frame:
        return self._depth

    def get_timestamp(self) -> float:
        return self._color.get_timestamp()


class align:  # noqa: N801
    def __init__(self, align_to):
        MODULE.calls.append(("align", align_to))
        self.align_to = align_to

    def process(self, frames: composite_frame) -> composite_frame:
        assert self.align_to == stream.color, "depth must be aligned to colour"
        MODULE.calls.append(("align.process",))
        depth = frames.get_depth_frame()
        return composite_frame(frames.get_color_frame(),
                               _Frame(np.roll(depth._data, -UNALIGNED_SHIFT_PX, axis=1), depth._ts, True))


class config:  # noqa: N801
    def __init__(self):
        self.streams, self.serial = [], None

    def enable_device(self, serial: str) -> None:
        self.serial = serial

    def enable_stream(self, stream_type, width, height, fmt, framerate) -> None:
        self.streams.append((stream_type, width, height, fmt, framerate))


class _Sensor:
    def get_depth_scale(self) -> float:
        return MODULE.depth_scale


class _Device:
    def first_depth_sensor(self) -> _Sensor:
        return _Sensor()


class _VideoProfile:
    def get_intrinsics(self) -> intrinsics:
        return MODULE.color_intrinsics


class _StreamProfile:
    def as_video_stream_profile(self) -> _VideoProfile:
        return _VideoProfile()


class pipeline_profile:  # noqa: N801
    def get_device(self) -> _Device:
        return _Device()

    def get_stream(self, stream_type) -> _StreamProfile:
        assert stream_type == stream.color
        return _StreamProfile()


class pipeline:  # noqa: N801
    def __init__(self):
        self.started, self.index = False, 0

    def start(self, cfg: config) -> pipeline_profile:
        if MODULE.connected is False:
            raise RuntimeError("No device connected")
        MODULE.calls.append(("start", cfg.serial, list(cfg.streams)))
        self.started = True
        return pipeline_profile()

    def wait_for_frames(self, timeout_ms: int = 5000) -> composite_frame:
        assert self.started
        if self.index >= len(MODULE.frames):
            raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
        rgb, depth_m = MODULE.frames[self.index]
        units = np.round(np.asarray(depth_m, np.float64) / MODULE.depth_scale).astype(np.uint16)
        ts = 1.0e6 + 1000.0 * self.index / MODULE.fps  # device clock, ms
        self.index += 1
        return composite_frame(_Frame(np.ascontiguousarray(rgb, np.uint8), ts, False),
                               _Frame(np.roll(units, UNALIGNED_SHIFT_PX, axis=1), ts, False))

    def stop(self) -> None:
        MODULE.calls.append(("stop",))
        self.started = False


MODULE = types.ModuleType("pyrealsense2")


def install(monkeypatch, frames, K, depth_scale: float = 0.001, fps: float = 30.0, connected: bool = True,
            model=distortion.inverse_brown_conrady, coeffs=(0.0,) * 5) -> types.ModuleType:
    """Make ``import pyrealsense2`` give this fake, playing ``frames`` [(rgb, depth_m), ...]."""
    h, w = frames[0][0].shape[:2] if frames else (480, 640)
    for name in ("stream", "format", "distortion", "intrinsics", "composite_frame", "align", "config",
                 "pipeline_profile", "pipeline"):
        setattr(MODULE, name, globals()[name])
    MODULE.frames, MODULE.depth_scale, MODULE.fps, MODULE.connected = list(frames), depth_scale, fps, connected
    MODULE.color_intrinsics = intrinsics(np.asarray(K, np.float64), w, h, model, coeffs)
    MODULE.calls = []
    monkeypatch.setitem(sys.modules, "pyrealsense2", MODULE)
    return MODULE
