"""Where a belief-map cell sits in the image: the one shared map <-> image convention.

A head with stride ``s`` (8 for DOPE-DR-50, 1 for DOPE-DR-400) has map cell ``j`` cover image
pixels ``j*s .. j*s + s - 1``; with pixel centres at integer coordinates its centre is at
image coordinate ``j*s + (s - 1) / 2``. ``targets`` encodes with :func:`image_to_map` and
``decode`` decodes with :func:`map_to_image`, so encoding and decoding cannot drift apart.
"""
from __future__ import annotations

import numpy as np


def map_offset(stride: int) -> float:
    """Image coordinate of map cell 0's centre, pixels."""
    return (stride - 1) / 2.0


def image_to_map(uv: np.ndarray, stride: int) -> np.ndarray:
    """Image pixel coordinates (..., 2) -> continuous map coordinates (..., 2)."""
    return (np.asarray(uv, dtype=np.float64) - map_offset(stride)) / stride


def map_to_image(xy: np.ndarray, stride: int) -> np.ndarray:
    """Continuous map coordinates (..., 2) -> image pixel coordinates (..., 2)."""
    return np.asarray(xy, dtype=np.float64) * stride + map_offset(stride)


def map_size(image_hw: tuple[int, int], stride: int) -> tuple[int, int]:
    """(h, w) of the maps for an input of (H, W); the network needs H, W divisible by 8."""
    return image_hw[0] // stride, image_hw[1] // stride
