"""Bench helper (not a benchmark): a rendered clip as a stream source with its depth.

The stream, tracking and recordings benches render clips of the demo box with their depth
and run them through the video loop; a video container cannot hold the depth, so each
frame i gets ``depths[i]`` here. Not shipped: `dope-hope infer` streams depth from a
RealSense or a recording only.
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dope_hope.io.camera import ImageCamera
from dope_hope.io.streams import Grabbed, VideoFile


class VideoWithDepth(VideoFile):
    """A video file whose frame i carries ``depths[i]`` ((H, W) metres)."""

    def __init__(self, path: Path, camera: ImageCamera, depths: list[np.ndarray]):
        super().__init__(path, camera)
        self.depths = depths

    def grab(self) -> Iterator[Grabbed]:
        for g in super().grab():
            frame = g.load()
            frame.depth = self.depths[g.index]
            yield Grabbed(g.index, g.timestamp_s, lambda frame=frame: frame)
