"""Test helper (not a test file): an exact depth image of a box and points on its surface.

Depth is ray-cast analytically (slab test, no GL needed), so depth-based refinement can be
checked against exact ground truth. Also used by bench/postprocess.py.
"""
from __future__ import annotations

import numpy as np


def render_box_depth(size, R, t, K, hw):
    """(H, W) metres: depth of a box (centred, axis-aligned in its frame) under (R, t); 0 = miss."""
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


def box_surface_points(size, spacing=0.004):
    """(N, 3) points on a grid over the six faces of the box, metres."""
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
