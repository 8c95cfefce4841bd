"""Camera intrinsics of synthetic frames: a reference camera scaled to the size, jittered."""
from __future__ import annotations

import numpy as np

from dope_hope.config import SectionSettings
from dope_hope.geometry import intrinsics_matrix


def reference_intrinsics(size: tuple[int, int], cam: SectionSettings) -> np.ndarray:
    """(3, 3) K of the reference camera at ``size`` = (W, H), without jitter (``cam``: the synth
    settings' ``camera`` section).

    The reference image is centre-cropped to the new aspect ratio and resized: focal lengths
    scale by ``max(W / W_ref, H / H_ref)``, the principal point follows the image centre
    ((W - 1) / 2, (H - 1) / 2 under the pixel-centre convention) plus the configured offset.
    """
    W, H = size
    W_ref, H_ref = cam.reference_size
    s = max(W / W_ref, H / H_ref)
    ox, oy = cam.principal_offset_px
    return intrinsics_matrix(cam.fx * s, cam.fy * s, (W - 1) / 2.0 + s * ox, (H - 1) / 2.0 + s * oy)


def sample_intrinsics(rng: np.random.Generator, size: tuple[int, int], cam: SectionSettings) -> np.ndarray:
    """Reference intrinsics with uniform focal, aspect and principal-point jitter. -> (3, 3)."""
    K = reference_intrinsics(size, cam)
    W_ref, H_ref = cam.reference_size
    s = max(size[0] / W_ref, size[1] / H_ref)
    fx = K[0, 0] * (1.0 + rng.uniform(-cam.focal_jitter, cam.focal_jitter))
    fy = fx * (K[1, 1] / K[0, 0]) * (1.0 + rng.uniform(-cam.aspect_jitter, cam.aspect_jitter))
    j = cam.principal_jitter_px * s
    cx = K[0, 2] + rng.uniform(-j, j)
    cy = K[1, 2] + rng.uniform(-j, j)
    return intrinsics_matrix(fx, fy, cx, cy)
