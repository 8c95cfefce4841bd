"""Test helper (not a test file): a lite model briefly fitted so that its maps detect a box.

Untrained networks output near-zero maps: nothing decodes, so comparing the detections of two
backends would compare empty lists. Here a lite network is fitted for a few dozen Adam steps
to the belief/affinity targets of ONE synthetic image (a drawn box whose cuboid keypoints are
known), which is enough for its maps to hold one clean instance at that image. The fit is
deterministic (seeded, one thread) and takes a few seconds.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

IMAGE_HW = (96, 128)
CLASS_NAME = "Ketchup"
K = np.array([[110.0, 0.0, 63.5], [0.0, 110.0, 47.5], [0.0, 0.0, 1.0]])


def scene() -> tuple[np.ndarray, np.ndarray]:
    """(rgb (96, 128, 3) uint8, keypoints (9, 2) image px) of the Ketchup box at a fixed pose."""
    from scipy.spatial.transform import Rotation

    from dope_hope.catalog import get_object
    from dope_hope.geometry import CUBOID_EDGES, cuboid_keypoints, project_points

    size = get_object(CLASS_NAME).size_array
    R = Rotation.from_euler("xyz", [25, -35, 10], degrees=True).as_matrix()
    t = np.array([0.0, 0.0, 0.42])
    kp = project_points(cuboid_keypoints(size), K, R, t)
    rgb = np.full(IMAGE_HW + (3,), 90, np.uint8)
    rgb[::8] = 60  # some background texture
    hull = cv2.convexHull(np.round(kp[:8]).astype(np.int32))
    cv2.fillConvexPoly(rgb, hull, (200, 40, 40))
    for a, b in CUBOID_EDGES:
        cv2.line(rgb, tuple(int(v) for v in np.round(kp[a])), tuple(int(v) for v in np.round(kp[b])),
                 (250, 250, 250), 1)
    for k, p in enumerate(kp[:8]):  # a distinct colour per corner: corner identity is visible
        cv2.circle(rgb, tuple(int(v) for v in np.round(p)), 2, (30 * k, 255 - 30 * k, 120), -1)
    return rgb, kp


def fit_lite_checkpoint(path: Path, steps: int = 60) -> Path:
    """Fit a lite network to :func:`scene`'s targets and save it as a dope-hope checkpoint."""
    import torch

    from dope_hope.config import load_config
    from dope_hope.model.checkpoint import save_checkpoint
    from dope_hope.model.network import build_model, normalize_image
    from dope_hope.targets import make_targets

    torch.manual_seed(0)
    torch.set_num_threads(1)
    cfg = load_config("lite")
    cfg["input"]["size"] = list(IMAGE_HW)
    model = build_model(cfg)
    rgb, kp = scene()
    belief, affinity = make_targets(kp[None], IMAGE_HW, model.stride, sigma=1.0, radius=1.0)
    x = normalize_image(rgb)[None]
    tb, ta = torch.from_numpy(belief)[None], torch.from_numpy(affinity)[None]
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    model.train()
    for _ in range(steps):
        loss = sum(((b - tb) ** 2).mean() + ((a - ta) ** 2).mean() for b, a in model(x))
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    save_checkpoint(path, model, cfg, {"class_name": CLASS_NAME})
    return path
