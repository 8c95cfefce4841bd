"""Decoded training frames kept in memory shared with the DataLoader workers.

Decoding a 256x192 PNG costs about as much as augmenting it and building its targets (about
0.9 ms of the ~3.7 ms of one lite training item, one core); a 30-minute run reads each frame
ten times or more. :class:`FrameCache` keeps the first decode of each frame in an anonymous
shared memory map (``mmap.mmap(-1, n)``: ``MAP_SHARED | MAP_ANONYMOUS``, not a ``/dev/shm``
file, so a container's small ``/dev/shm`` does not limit it). Forked workers inherit the map:
what one worker decodes in one epoch, every later worker reads. A frame is written once,
then its flag set; a reader that sees the flag reads the finished pixels (both are stores to
the same shared pages, in program order). The cached pixels are the decoded ones, so a run
gives the same result with the cache or without it.

Only frames of the first frame's size are kept, and only as many as ``budget_mb`` holds (the
first indices); the rest are decoded each time. Pages are taken from the system as frames
are written, not when the map is made.
"""
from __future__ import annotations

import mmap

import numpy as np


class FrameCache:
    """Up to ``budget_mb`` of (H, W, 3) uint8 frames, by dataset index.

    Args:
        count: frames in the dataset (indices 0 .. count - 1).
        frame_hw: (H, W) of the frames kept; a frame of another size is never kept.
        budget_mb: memory for the pixels, MiB (2**20 bytes); 0 keeps nothing.
    """

    def __init__(self, count: int, frame_hw: tuple[int, int], budget_mb: float):
        self.frame_hw = (int(frame_hw[0]), int(frame_hw[1]))
        frame_bytes = self.frame_hw[0] * self.frame_hw[1] * 3
        self.capacity = max(0, min(int(count), int(float(budget_mb) * 2**20) // frame_bytes))
        self._map = mmap.mmap(-1, max(1, self.capacity * (frame_bytes + 1)))
        self._pixels = np.frombuffer(self._map, np.uint8, self.capacity * frame_bytes).reshape(
            self.capacity, *self.frame_hw, 3)
        self._filled = np.frombuffer(self._map, np.uint8, self.capacity, offset=self.capacity * frame_bytes)

    def __getstate__(self) -> dict:
        # A spawned worker cannot share an anonymous map: it gets an empty cache of its own.
        return {"frame_hw": self.frame_hw, "capacity": 0}

    def __setstate__(self, state: dict) -> None:
        self.__init__(0, state["frame_hw"], 0)

    def get(self, index: int) -> np.ndarray | None:
        """A copy of frame ``index`` (H, W, 3) uint8, or None when it is not kept yet."""
        if 0 <= index < self.capacity and self._filled[index]:
            return self._pixels[index].copy()
        return None

    def put(self, index: int, rgb: np.ndarray) -> None:
        """Keep frame ``index`` when it fits (its size, the budget) and is not kept yet."""
        if 0 <= index < self.capacity and not self._filled[index] and rgb.shape[:2] == self.frame_hw \
                and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3:
            self._pixels[index] = rgb
            self._filled[index] = 1

    @property
    def reserved_mb(self) -> float:
        """Memory reserved for the frames (``capacity`` of them, taken as they are kept), MiB."""
        return self._pixels.nbytes / 2**20

    @property
    def kept(self) -> int:
        """Frames kept so far."""
        return int(self._filled.sum()) if self.capacity else 0
