"""Test helper (not a test file): small video files written and read back with OpenCV."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import pytest


def write_video(path: Path, frames: Sequence[np.ndarray], fps: float = 10.0) -> Path:
    """RGB ``frames`` as ``path`` with suffix .mp4 (mp4v), or .avi (MJPG) where this OpenCV
    lacks mp4v; skips the test when it writes neither. Returns the file written."""
    h, w = frames[0].shape[:2]
    for suffix, fourcc in ((".mp4", "mp4v"), (".avi", "MJPG")):
        out = path.with_suffix(suffix)
        writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
        if writer.isOpened():
            for f in frames:
                writer.write(cv2.cvtColor(np.ascontiguousarray(f, np.uint8), cv2.COLOR_RGB2BGR))
            writer.release()
            return out
    pytest.skip("this OpenCV writes neither mp4v nor MJPG")


def read_video(path: Path) -> list[np.ndarray]:
    """Every frame of a video file (BGR, as OpenCV decodes it)."""
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            return out
        out.append(img)
