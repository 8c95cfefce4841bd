"""Exact depth of a box by ray casting (slab test; no GL): ground truth for depth refinement.

Checks of the "-LS" line search and ICP (tests, ``bench/postprocess.py``) compare against it,
and :func:`box_surface_points` gives model points on the same box.
"""
from __future__ import annotations

import numpy as np


def render_box_depth(size: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                     hw: tuple[int, int]) -> np.ndarray:
    """(H, W) metres: depth of a box (size (3,) m, centred and axis-aligned in its frame) under
    (R, t), camera K (3, 3), image ``hw`` = (H, W); 0 where a ray misses."""
    H, W = hw
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1: t_hit = depth
    origin = -R.T @ t
    d = rays @ R  # ray directions in the box frame
    half = np.asarray(size) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - origin) / d, (half - origin) / d
    near = np.nanmax(np.minimum(t1, t2), axis=-1)
    far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((near <= far) & (near > 0), near, 0.0)


def box_surface_points(size: np.ndarray, spacing: float = 0.004) -> np.ndarray:
    """(N, 3) points on a grid (``spacing`` m) over the six faces of the box, metres."""
    half = np.asarray(size) / 2
    pts = []
    for ax in range(3):
        a, b = [i for i in range(3) if i != ax]
        A, B = np.meshgrid(np.arange(-half[a], half[a] + 1e-9, spacing),
                           np.arange(-half[b], half[b] + 1e-9, spacing))
        for sign in (-1, 1):
            p = np.zeros((A.size, 3))
            p[:, a], p[:, b], p[:, ax] = A.ravel(), B.ravel(), sign * half[ax]
            pts.append(p)
    return np.vstack(pts)
