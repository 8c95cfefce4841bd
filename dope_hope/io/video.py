"""Frames out: an overlay video file (``cv2.VideoWriter``, written atomically) and a live window.

:class:`OverlayVideo` writes ``PATH.mp4`` with the ``mp4v`` codec, or ``PATH.avi`` with
``MJPG`` when this OpenCV build cannot write the first; frames go to a temporary file beside
it, renamed when the video is closed, so an interrupted run leaves no half-written video.

:class:`LiveWindow` shows frames with ``cv2.imshow`` where a display exists
(:func:`display_problem` says why not: no ``DISPLAY`` / ``WAYLAND_DISPLAY`` on Linux, or an
OpenCV without GUI support such as ``opencv-python-headless``).
"""
from __future__ import annotations

import os
import re
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from dope_hope.errors import ConfigError

#: (suffix, FourCC) tried in order.
VIDEO_CODECS = ((".mp4", "mp4v"), (".avi", "MJPG"))
#: Keys that close the live window (q, Esc).
QUIT_KEYS = (ord("q"), 27)


class OverlayVideo:
    """A video of RGB frames written to ``stem`` + the first suffix this OpenCV can encode.

    Args:
        stem: output path without suffix (``OUT/clip.overlay``).
        fps: frames per second of the video.

    The writer opens at the first frame (its size fixes the video's); ``close()`` renames the
    temporary file to :attr:`path` (None until then); ``discard()`` removes it.
    """

    def __init__(self, stem: str | os.PathLike, fps: float):
        self.stem = Path(stem)
        self.fps = float(fps)
        self.path: Path | None = None
        self.frames = 0
        self._writer = None
        self._tmp: Path | None = None
        self._final: Path | None = None
        self._last: np.ndarray | None = None

    def _open(self, width: int, height: int) -> None:

        self.stem.parent.mkdir(parents=True, exist_ok=True)
        for suffix, fourcc in VIDEO_CODECS:
            fd, tmp = tempfile.mkstemp(prefix=f".{self.stem.name}.", suffix=f".tmp{suffix}", dir=self.stem.parent)
            os.close(fd)
            writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*fourcc), self.fps, (width, height))
            if writer.isOpened():
                self._writer, self._tmp = writer, Path(tmp)
                self._final = self.stem.with_name(self.stem.name + suffix)
                return
            writer.release()
            Path(tmp).unlink(missing_ok=True)
        raise ConfigError("this OpenCV build writes no mp4v / MJPG video; pass --no-overlay")

    def write(self, rgb: np.ndarray, repeat: int = 1) -> None:
        """Append ``rgb`` (H, W, 3) uint8 ``repeat`` times (same size as the first frame)."""
        if self._writer is None:
            self._open(rgb.shape[1], rgb.shape[0])
        bgr = cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)
        for _ in range(max(0, int(repeat))):
            self._writer.write(bgr)
            self.frames += 1
        self._last = rgb

    def repeat_last(self, n: int) -> None:
        """Append the last frame ``n`` more times (it stands in for dropped frames)."""
        if self._last is not None and n > 0:
            self.write(self._last, n)

    def close(self) -> Path | None:
        """Finish the file and move it to its final name; the path, or None without frames."""
        if self._writer is None:
            return None
        self._writer.release()
        self._writer = None
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(self._tmp, 0o666 & ~umask)
        os.replace(self._tmp, self._final)
        self.path = self._final
        return self.path

    def discard(self) -> None:
        """Drop the unfinished video (after an error)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
            self._tmp.unlink(missing_ok=True)


def display_problem() -> str | None:
    """Why no window can be shown here, or None when one can."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY / WAYLAND_DISPLAY unset)"
    if re.search(r"^\s*GUI:\s*NONE\s*$", cv2.getBuildInformation(), re.MULTILINE):
        return "this OpenCV has no GUI support (opencv-python-headless)"
    return None


class LiveWindow:
    """A ``cv2.imshow`` window; :meth:`show` returns False once q / Esc is pressed or the
    window is closed."""

    def __init__(self, title: str):
        self.title = title
        self._opened = False

    def show(self, rgb: np.ndarray) -> bool:

        if self._opened and cv2.getWindowProperty(self.title, cv2.WND_PROP_VISIBLE) < 1:
            return False  # closed by the user
        cv2.imshow(self.title, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        self._opened = True
        return (cv2.waitKey(1) & 0xFF) not in QUIT_KEYS

    def close(self) -> None:
        if self._opened:

            cv2.destroyWindow(self.title)
            self._opened = False
